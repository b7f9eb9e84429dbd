//! Shutdown (the tests' SIGTERM) drains the runs in progress and flushes
//! the rotating MCAP recorder.

use dt_core::log::Sample;

use crate::common::{
    chunked, files_in, meta, read_estimates, run_samples, test_config, wait_until, write_stream,
    Daemon, TICK_NS,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_runs_and_finishes_rotating_recordings() {
    let record = tempfile::tempdir().unwrap();
    let mut config = test_config();
    config.server.record_dir = Some(record.path().to_owned());
    config.record.max_file_s = 1.0;
    let d = Daemon::start(config).await;

    // 3.5 s of data; the last sample lands exactly on a tick, which only the
    // end of the run (here: shutdown) can emit.
    let t0 = 100_000_000_000;
    let mut samples = run_samples(t0, 3500);
    samples.push(Sample::Position {
        t_ns: t0 + 3_500_000_000,
        position_m: 0.0,
    });
    let s = write_stream(&meta("rig-9", "long"), &samples, chunked());
    assert_eq!(s.ticks, 175);
    // Send the whole file but its footer (29 bytes, which would end the run)
    // and end magic (8), and keep the connection open.
    let mut c = TcpStream::connect(d.ingest).await.unwrap();
    c.write_all(&s.bytes[..s.bytes.len() - 37]).await.unwrap();
    wait_until("the data to be processed", || async {
        d.asset_ticks("rig-9").await == s.ticks - 1
    })
    .await;

    let reply = tokio::spawn(async move {
        let mut reply = String::new();
        c.read_to_string(&mut reply).await.unwrap();
        reply
    });
    d.stop().await;
    let r: serde_json::Value = serde_json::from_str(reply.await.unwrap().trim()).unwrap();
    assert_eq!(r["status"], "interrupted", "{r}");
    assert_eq!(
        r["ticks"], s.ticks,
        "the last tick was emitted at shutdown: {r}"
    );
    assert_eq!(r["flushed"], true);

    // Rotated every second of estimate time; every part finished and renamed.
    let dir = record.path().join("rig-9");
    let files = files_in(&dir);
    let names: Vec<_> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names,
        [
            "long.0000.mcap",
            "long.0001.mcap",
            "long.0002.mcap",
            "long.0003.mcap"
        ],
        "no .part left behind"
    );
    let mut all = Vec::new();
    for f in &files {
        let part = read_estimates(f);
        let span = part.last().unwrap().t_ns - part[0].t_ns;
        assert!(span < 1_000_000_000, "{}: span {span} ns", f.display());
        all.extend(part);
    }
    assert_eq!(all.len() as u64, s.ticks);
    for (k, e) in all.iter().enumerate() {
        assert_eq!(e.t_ns, t0 + (k as i64 + 1) * TICK_NS);
        assert!((e.expected_bar - 12.0).abs() < 1e-12);
    }
}
