use clap::Parser;

fn main() -> std::process::ExitCode {
    let cli = xscale::cli::Cli::parse();
    match xscale::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(2)
        }
    }
}
