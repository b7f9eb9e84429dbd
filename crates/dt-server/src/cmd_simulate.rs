//! `shocktwin simulate`.

use crate::cli::SimulateArgs;

/// Runs `shocktwin simulate`.
pub fn run(args: &SimulateArgs) -> anyhow::Result<()> {
    let _ = args;
    anyhow::bail!("simulate: not implemented yet")
}
