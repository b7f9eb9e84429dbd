//! The `shocktwin` binary: parses arguments, sets up logging, dispatches.

use std::process::ExitCode;

use clap::Parser;
use dt_server::cli::{Cli, Command};

fn main() -> ExitCode {
    let cli = Cli::parse();
    // The NATS client logs each of its events (a reconnection attempt a
    // second per part while the server is away, a refused connection at
    // error every few seconds); the daemon says the ones that matter itself
    // (`nats::LastError`), so the client's own lines are off by default.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info,async_nats=off"));
    // Structured (JSON) logs: `serve --log-format json` or SHOCKTWIN_LOG_FORMAT=json.
    let json_logs = match &cli.command {
        Command::Serve(args) if args.log_format.is_some() => {
            args.log_format == Some(dt_server::cli::LogFormat::Json)
        }
        _ => std::env::var("SHOCKTWIN_LOG_FORMAT").is_ok_and(|v| v == "json"),
    };
    if json_logs {
        tracing_subscriber::fmt()
            .json()
            .with_env_filter(filter)
            .with_writer(std::io::stderr)
            .init();
    } else {
        tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .with_writer(std::io::stderr)
            .init();
    }
    let result = match &cli.command {
        Command::Simulate(args) => dt_server::cmd_simulate::run(args).map(|()| ExitCode::SUCCESS),
        Command::Inspect(args) => dt_server::cmd_inspect::run(args),
        Command::Import(args) => dt_server::cmd_import::run(args),
        Command::Replay(args) => dt_server::cmd_replay::run(args),
        Command::Road(args) => dt_server::cmd_road::run(args),
        Command::Serve(args) => dt_server::cmd_serve::run(args).map(|()| ExitCode::SUCCESS),
        Command::Publish(args) => dt_server::nats::publish::run(args),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("shocktwin: {err:#}");
            ExitCode::FAILURE
        }
    }
}
