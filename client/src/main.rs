use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    match scnerf_client::cli::run(scnerf_client::args::Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
