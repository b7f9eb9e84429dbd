//! `shocktwin inspect FILE`: channels, message counts and rates, duration,
//! metadata, and what the file lacks to be a shocktwin log
//! ([`dt_core::log::inspect`]).
//!
//! Exit status 0 for any valid MCAP file, shocktwin log or not; for a broken
//! or non-MCAP file an error whose one-line message names the file (printed
//! by `main` as `shocktwin: <file>: <reason>`, exit status 1).

use std::process::ExitCode;

use crate::cli::InspectArgs;

/// Runs `shocktwin inspect`; the exit code follows SPEC §7.
pub fn run(args: &InspectArgs) -> anyhow::Result<ExitCode> {
    // The error's own message already names the file and the reason; turn it
    // into a message-only error so that it prints as one line.
    let report = dt_core::log::inspect(&args.file).map_err(|err| anyhow::anyhow!("{err}"))?;
    if args.json {
        crate::outln!("{}", report.to_json());
    } else {
        crate::out!("{report}");
    }
    Ok(ExitCode::SUCCESS)
}
