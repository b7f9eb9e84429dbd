//! `dt-server` owns the `shocktwin` command line and the fleet-gateway
//! daemon; every model and format lives in `dt-core`.
