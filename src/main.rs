/// Exit codes (docs/runs.md): 0 done, 1 a check failed, 2 an error at run time (bad input, I/O,
/// a refused run folder, divergence), 64 a usage error (unknown flag, bad value: sysexits'
/// EX_USAGE), 130 stopped by a signal with a checkpoint written, 3 stopped by a signal with nothing
/// saved.
fn main() -> std::process::ExitCode {
    ignore_file_size_signal();
    xscale::cli::main_with(std::env::args_os())
}

/// A file-size limit (`ulimit -f`, RLIMIT_FSIZE) sends SIGXFSZ on the write that crosses it, and
/// that signal's default action kills the process without a word. Ignored, the write fails with
/// EFBIG instead and the error names the file like any other I/O error.
fn ignore_file_size_signal() {
    #[cfg(unix)]
    // SAFETY: setting a signal's disposition to SIG_IGN before any other thread exists; no
    // handler code runs.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}
