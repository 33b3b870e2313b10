use clap::Parser;

/// Exit codes (docs/runs.md): 0 done, 1 a check failed, 2 an error at run time (bad input, I/O,
/// a refused run folder, divergence), 64 a usage error (unknown flag, bad value: sysexits'
/// EX_USAGE), 130 stopped by a signal with a checkpoint written.
fn main() -> std::process::ExitCode {
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
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(2)
        }
    }
}
