//! `dt-server` owns the `shocktwin` command line and the fleet-gateway
//! daemon; every model and format lives in `dt-core`, the simulator in
//! `dt-sim`. Each subcommand has its own module; `src/bin/shocktwin.rs` only
//! parses arguments and dispatches.

pub mod cli;
pub mod cmd_import;
pub mod cmd_inspect;
pub mod cmd_replay;
pub mod cmd_road;
pub mod cmd_serve;
pub mod cmd_simulate;
pub mod nats;
pub mod progress;
pub mod server;
pub mod stdout;
