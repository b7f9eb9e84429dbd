//! The `shocktwin` binary: parses arguments, sets up logging, dispatches.

use std::process::ExitCode;

use clap::Parser;
use dt_server::cli::{Cli, Command};

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Simulate(args) => dt_server::cmd_simulate::run(args).map(|()| ExitCode::SUCCESS),
        Command::Inspect(args) => dt_server::cmd_inspect::run(args),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("shocktwin: {err:#}");
            ExitCode::FAILURE
        }
    }
}
