//! `shocktwin publish --nats URL FILE.mcap... [--realtime] [--batch-ms 100]`:
//! sends runs as vehicles would, to `shocktwin.telemetry.<asset>` (stream
//! `SHOCKTWIN_TELEMETRY`), one task per file, batches of `--batch-ms` of
//! samples (see [`super::payload`]). Every batch carries the message id
//! `<asset>/<run>/<batch>`, so a publisher that retries after a lost ack
//! never stores a batch twice.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use async_nats::jetstream::{self, message::PublishMessage as Publish};
use dt_core::log::{read_log, Sample};

use super::payload::{subject_token, TelemetryBatch, PAYLOAD_VERSION};
use super::{connect, ensure_topology, NatsConfig};
use crate::cli::PublishArgs;

/// Runs `shocktwin publish`.
pub fn run(args: &PublishArgs) -> Result<std::process::ExitCode> {
    if args.batch_ms == 0 {
        bail!("--batch-ms must be at least 1");
    }
    if args.speed.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        bail!("--speed must be a positive number");
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("tokio runtime")?;
    rt.block_on(publish_all(args))
}

async fn publish_all(args: &PublishArgs) -> Result<std::process::ExitCode> {
    let cfg = NatsConfig {
        url: Some(args.nats.clone()),
        ca_file: args.nats_ca.clone(),
        cert_file: args.nats_cert.clone(),
        key_file: args.nats_key.clone(),
        token_file: args.nats_token_file.clone(),
        ..NatsConfig::default()
    };
    if let Err((_, why)) = cfg.check_settings() {
        bail!("--nats {why}");
    }
    if let Some(prefix) = &args.rename_assets {
        // the longest id it makes: the charset and length are all that vary
        // (a helper's trial: `x*` published 701 batches a run, every one
        // dead-lettered by the workers; `Bad Id-` was retried for a minute)
        let longest = format!("{prefix}{}", args.files.len().saturating_sub(1));
        if !dt_core::log::is_valid_id(&longest) {
            bail!(
                "--rename-assets {prefix:?}: makes asset ids such as {longest:?}, not {}",
                dt_core::log::ID_FORMAT
            );
        }
    }
    if let Err((key, why)) = cfg.check_files() {
        let flag = match key {
            "nats.ca_file" => "--nats-ca",
            "nats.cert_file" => "--nats-cert",
            "nats.key_file" => "--nats-key",
            _ => "--nats-token-file",
        };
        bail!("{flag}: {why}");
    }
    let client = connect(&cfg, "shocktwin publish").await?;
    let js = jetstream::new(client);
    ensure_topology(&js, &cfg).await?;
    let js = Arc::new(js);
    let (done_tx, mut done_rx) = tokio::sync::mpsc::unbounded_channel();
    let mut tasks = tokio::task::JoinSet::new();
    for group in by_asset(args).await {
        let js = Arc::clone(&js);
        let (tx, opts) = (done_tx.clone(), group);
        tasks.spawn(async move {
            // one asset's runs one after another, in the order given
            for (file, opts) in opts {
                let r = publish_file(&js, &file, &opts).await;
                let _ = tx.send((file, r));
            }
        });
    }
    drop(done_tx);
    let mut failed = 0;
    while let Some((file, r)) = done_rx.recv().await {
        match r {
            Ok(p) => eprintln!(
                "published {}: asset {} run {}, {} batches, {} samples{}",
                file.display(),
                p.asset,
                p.run,
                p.batches,
                p.samples,
                // a helper's trial: publishing a run again said nothing of it
                match p.duplicates {
                    0 => String::new(),
                    d if d == p.batches => {
                        "; every batch was already in the stream (this run was published before): stored once, nothing new".into()
                    }
                    d => format!("; {d} of them already in the stream (published before, or a retried batch): stored once"),
                }
            ),
            Err(e) => {
                failed += 1;
                let (name, msg) = (file.display().to_string(), format!("{e:#}"));
                if msg.starts_with(&name) {
                    eprintln!("shocktwin: {msg}");
                } else {
                    eprintln!("shocktwin: {name}: {msg}");
                }
            }
        }
    }
    while let Some(joined) = tasks.join_next().await {
        joined.context("publish task")?;
    }
    Ok(if failed > 0 {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    })
}

/// The files with their options, grouped by the asset they are published
/// as: the groups go side by side, a group's files one after another in the
/// order given. Before, every file went at once, and several runs of one
/// asset (`publish leak/*.mcap`, a unit's daily runs) were interleaved: the
/// workers ended all but one as interrupted (a helper's trial). Without
/// `--rename-assets` each file's asset id is read first (a second read of
/// the file; one that cannot be read goes alone and fails as before).
async fn by_asset(args: &PublishArgs) -> Vec<Vec<(PathBuf, FileOptions)>> {
    let mut groups: Vec<Vec<(PathBuf, FileOptions)>> = Vec::new();
    let mut group_of: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    for (i, file) in args.files.iter().enumerate() {
        let opts = FileOptions {
            batch_ns: i64::from(args.batch_ms) * 1_000_000,
            speed: if args.realtime { Some(1.0) } else { args.speed },
            asset: args.rename_assets.as_ref().map(|p| format!("{p}{i}")),
        };
        let asset = if let Some(a) = &opts.asset {
            Some(a.clone())
        } else {
            let path = file.clone();
            tokio::task::spawn_blocking(move || read_log(&path).ok())
                .await
                .ok()
                .flatten()
                .map(|log| log.metadata.asset_id)
        };
        match asset.map(|a| group_of.get(&a).copied().ok_or(a)) {
            Some(Ok(g)) => groups[g].push((file.clone(), opts)),
            Some(Err(a)) => {
                group_of.insert(a, groups.len());
                groups.push(vec![(file.clone(), opts)]);
            }
            None => groups.push(vec![(file.clone(), opts)]),
        }
    }
    groups
}

struct FileOptions {
    batch_ns: i64,
    /// Pacing: this many times real time (none: as fast as acknowledged).
    speed: Option<f64>,
    asset: Option<String>,
}

/// Publishes one run; returns asset, run, batches and samples sent.
async fn publish_file(
    js: &jetstream::Context,
    file: &Path,
    opts: &FileOptions,
) -> Result<Published> {
    let path = PathBuf::from(file);
    // the reader's error names the file and says its cause already: one
    // message, not its chain (a helper's trial: "f: f: No such file …: No
    // such file …")
    let log = tokio::task::spawn_blocking(move || read_log(&path))
        .await
        .context("reader task")?
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut meta = log.metadata.clone();
    if let Some(a) = &opts.asset {
        meta.asset_id.clone_from(a);
    }
    let samples = log.samples_sorted();
    let subject = format!("shocktwin.telemetry.{}", subject_token(&meta.asset_id));
    let mut map = meta.to_map();
    map.remove("asset_id");
    map.remove("run_id");
    let t0 = samples.first().map_or(0, Sample::t_ns);
    let started = tokio::time::Instant::now();
    let (mut batch_no, mut duplicates) = (0u64, 0u64);
    let mut i = 0;
    loop {
        let end_t = t0 + (batch_no as i64 + 1) * opts.batch_ns;
        let mut b = TelemetryBatch {
            v: PAYLOAD_VERSION,
            asset_id: meta.asset_id.clone(),
            run_id: meta.run_id.clone(),
            batch: batch_no,
            ..TelemetryBatch::default()
        };
        if batch_no == 0 {
            b.meta.clone_from(&map);
        }
        while i < samples.len() && samples[i].t_ns() < end_t {
            b.push(&samples[i]);
            i += 1;
        }
        b.end = i == samples.len();
        if let Some(speed) = opts.speed {
            let due = Duration::from_secs_f64((end_t - t0).max(0) as f64 / 1e9 / speed);
            tokio::time::sleep_until(started + due).await;
        }
        let payload: bytes::Bytes = serde_json::to_vec(&b)?.into();
        let most = js.client().server_info().max_payload;
        if most > 0 && payload.len() > most {
            // refused by the client at every retry (a helper's trial: a minute's silence)
            bail!(
                "batch {batch_no} is {} bytes, over the server's max_payload of {most}: \
                 use a shorter --batch-ms (now {} ms)",
                payload.len(),
                opts.batch_ns / 1_000_000
            );
        }
        let id = format!("{}/{}/{}", meta.asset_id, meta.run_id, batch_no);
        if send_with_retry(js, &subject, &payload, &id)
            .await
            .with_context(|| format!("batch {batch_no} on {subject}"))?
        {
            duplicates += 1;
        }
        batch_no += 1;
        if b.end {
            break;
        }
    }
    Ok(Published {
        asset: meta.asset_id,
        run: meta.run_id,
        batches: batch_no,
        duplicates,
        samples: samples.len(),
    })
}

/// What one file's publish sent.
struct Published {
    asset: String,
    run: String,
    batches: u64,
    /// Batches the stream already held (same message id): stored once.
    duplicates: u64,
    samples: usize,
}

/// How long a batch is retried while the server is away (a restart).
const RETRY_FOR: Duration = Duration::from_secs(60);

/// Publishes one batch and waits for its acknowledgement, retrying (same
/// message id: stored once) until [`RETRY_FOR`] has passed. Returns whether
/// the stream already held it (`JetStream`'s `duplicate`).
async fn send_with_retry(
    js: &jetstream::Context,
    subject: &str,
    payload: &bytes::Bytes,
    id: &str,
) -> Result<bool> {
    let deadline = tokio::time::Instant::now() + RETRY_FOR;
    let mut wait = Duration::from_millis(50);
    loop {
        let attempt = async {
            js.send_publish(
                subject.to_owned(),
                Publish::build().payload(payload.clone()).message_id(id),
            )
            .await
            .map_err(anyhow::Error::from)?
            .await
            .map_err(anyhow::Error::from)
        };
        match attempt.await {
            Ok(ack) => return Ok(ack.duplicate),
            Err(e) if tokio::time::Instant::now() >= deadline => {
                return Err(e.context(format!("no acknowledgement for {} s", RETRY_FOR.as_secs())));
            }
            Err(e) => {
                tracing::debug!(subject, "publish retried: {e}");
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(Duration::from_secs(1));
            }
        }
    }
}
