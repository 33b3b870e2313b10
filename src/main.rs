use clap::Parser;

/// Exit codes (docs/runs.md): 0 done, 1 a check failed, 2 an error at run time (bad input, I/O,
/// a refused run folder, divergence), 64 a usage error (unknown flag, bad value: sysexits'
/// EX_USAGE), 130 stopped by a signal with a checkpoint written, 3 stopped by a signal with nothing
/// saved.
fn main() -> std::process::ExitCode {
    ignore_file_size_signal();
    let cli = match xscale::cli::Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            // --help and --version are not errors.
            return std::process::ExitCode::from(if e.use_stderr() { 64 } else { 0 });
        }
    };
    match xscale::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            // Not `eprintln!`, which panics when stderr is a closed pipe.
            use std::io::Write;
            let mut err = std::io::stderr();
            let _ = writeln!(err, "error: {e:#}");
            if hit_file_size_limit(&e) {
                let _ = writeln!(
                    err,
                    "hint: the process has a file-size limit (`ulimit -f` shows it); raise it or write \
                     to a folder without one"
                );
            }
            std::process::ExitCode::from(2)
        }
    }
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

/// EFBIG anywhere in the error: as an `io::Error` in the chain, or in the text where a writer
/// (the PNG encoder, safetensors) kept only the message, which ends in "(os error 27)" on Linux.
fn hit_file_size_limit(e: &anyhow::Error) -> bool {
    let kind = e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::FileTooLarge)
    });
    #[cfg(unix)]
    let text = format!("{e:#}").contains(&format!("(os error {})", libc::EFBIG));
    #[cfg(not(unix))]
    let text = false;
    kind || text
}
