//! `shocktwin serve`: resolves the configuration (defaults < TOML file <
//! `SHOCKTWIN_*` environment < flags), binds the listeners and runs
//! [`crate::server::run`] until SIGTERM or Ctrl-C, then drains and flushes.

use std::sync::Arc;

use anyhow::Context;

use crate::cli::ServeArgs;
use crate::server::{
    self, Config, ConfigOverrides, EstimatorFactory, Listeners, TickCounterFactory, TwinFactory,
};

/// Runs `shocktwin serve`.
pub fn run(args: &ServeArgs) -> anyhow::Result<()> {
    let overrides = ConfigOverrides {
        listen: args.listen,
        http: args.http,
        model: args.model.clone(),
        road: args.road.clone(),
        inbox: args.inbox.clone(),
        record_dir: args.record_dir.clone(),
        db: args.db.clone(),
        nats: args.nats.clone(),
    };
    let mut config = Config::load(
        args.config.as_deref(),
        &|var| std::env::var(var).ok(),
        &overrides,
    )?;
    config.insecure = args.insecure;
    if args.no_db {
        config.store.path = None;
    } else if config.store.path.is_none() {
        config.store.path = default_db();
    }
    let twins = twin_factory(&config)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("shocktwin-serve")
        .build()
        .context("cannot start the tokio runtime")?;
    runtime.block_on(async move {
        let shutdown = shutdown_signal();
        let listeners = Listeners::bind(&config).await?;
        let per_connection = config.limits.connection_memory_bound();
        tracing::info!(
            per_connection_mib = per_connection >> 20,
            max_connections = config.limits.max_connections,
            total_mib = (per_connection.saturating_mul(config.limits.max_connections as u64)) >> 20,
            "ingest decoding memory bound (limits.max_record_bytes + max_chunk_uncompressed_bytes per connection)"
        );
        server::run(config, listeners, twins, shutdown).await?;
        Ok(())
    })
}

/// `<state dir>/fleet.sqlite` (see `--db`); none without a home directory.
fn default_db() -> Option<std::path::PathBuf> {
    let var = |k: &str| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(std::path::PathBuf::from)
    };
    let dir = var("SHOCKTWIN_STATE_DIR")
        .or_else(|| var("STATE_DIRECTORY")) // systemd's StateDirectory=
        .or_else(|| var("XDG_STATE_HOME").map(|d| d.join("shocktwin")))
        .or_else(|| var("HOME").map(|h| h.join(".local/state/shocktwin")))?;
    Some(dir.join("fleet.sqlite"))
}

/// The estimator behind the daemon: the model bundle's, or without one the
/// placeholder (50 Hz clock only), said loudly.
fn twin_factory(config: &Config) -> anyhow::Result<Arc<dyn TwinFactory>> {
    if let Some(bundle) = &config.model.bundle {
        return Ok(Arc::new(EstimatorFactory::load(
            bundle,
            config.model.road.as_deref(),
        )?));
    }
    tracing::warn!(
        "no model bundle (--model, [model] bundle, SHOCKTWIN_MODEL): serving with the \
         placeholder twin; estimates carry NaN pressure and health `unknown`"
    );
    Ok(Arc::new(TickCounterFactory))
}

/// Resolves on SIGTERM or Ctrl-C. The handlers are installed when this is
/// called (not when the future is first polled), so that a signal arriving
/// while the daemon is still starting is not lost to its default action.
/// SIGHUP, which operators send after rotating certificates or tokens, is
/// said and survived: its default action ended the daemon without a word,
/// a drain or a report to its clients, and systemd's `Restart=on-failure`
/// takes such an end for a clean one (a helper's trial). Nothing is
/// reloaded: the log says to restart.
fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    #[cfg(unix)]
    let (term, int, hup) = {
        use tokio::signal::unix::{signal, SignalKind};
        (
            signal(SignalKind::terminate()),
            signal(SignalKind::interrupt()),
            signal(SignalKind::hangup()),
        )
    };
    async move {
        #[cfg(unix)]
        {
            let wait = |s: std::io::Result<tokio::signal::unix::Signal>, name: &'static str| async move {
                match s {
                    Ok(mut s) => {
                        s.recv().await;
                        tracing::info!("{name} received");
                    }
                    Err(e) => {
                        tracing::error!("cannot listen for {name}: {e}");
                        std::future::pending::<()>().await;
                    }
                }
            };
            let hups = async move {
                match hup {
                    Ok(mut s) => {
                        while s.recv().await.is_some() {
                            tracing::warn!(
                                "SIGHUP received: the daemon reloads nothing (its configuration, \
                                 certificates, tokens and model are read at start) and goes on; \
                                 restart it to take new ones (`systemctl restart shocktwin`)"
                            );
                        }
                    }
                    Err(e) => tracing::error!("cannot listen for SIGHUP: {e}"),
                }
                std::future::pending::<()>().await;
            };
            tokio::select! {
                () = wait(term, "SIGTERM") => {}
                () = wait(int, "Ctrl-C") => {}
                () = hups => {}
            }
        }
        #[cfg(not(unix))]
        {
            if let Err(e) = tokio::signal::ctrl_c().await {
                tracing::error!("cannot listen for Ctrl-C: {e}");
                std::future::pending::<()>().await;
            }
            tracing::info!("Ctrl-C received");
        }
    }
}
