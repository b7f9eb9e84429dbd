//! `shocktwin inspect FILE`.

use crate::cli::InspectArgs;

/// Runs `shocktwin inspect`; the exit code follows SPEC §7.
pub fn run(args: &InspectArgs) -> anyhow::Result<std::process::ExitCode> {
    let _ = args;
    anyhow::bail!("inspect: not implemented yet")
}
