//! The HTTP API read with a real HTTP client: the live event stream.

use crate::common::{
    chunked, good_stream, meta, run_samples, send, test_config, write_stream, Daemon, WAIT,
};

/// One parsed Server-Sent Event.
#[derive(Debug)]
struct SseEvent {
    name: String,
    data: serde_json::Value,
}

/// Parses complete events out of `buf` (leaves a partial one in it).
fn parse_events(buf: &mut String) -> Vec<SseEvent> {
    let mut out = Vec::new();
    while let Some(end) = buf.find("\n\n") {
        let block: String = buf.drain(..end + 2).collect();
        let mut name = String::from("message");
        let mut data = String::new();
        for line in block.lines() {
            if let Some(v) = line.strip_prefix("event:") {
                v.trim().clone_into(&mut name);
            } else if let Some(v) = line.strip_prefix("data:") {
                data.push_str(v.trim_start());
            }
        }
        if !data.is_empty() {
            out.push(SseEvent {
                name,
                data: serde_json::from_str(&data).unwrap_or(serde_json::Value::String(data)),
            });
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn event_stream_carries_every_estimate_and_the_run_lifecycle() {
    let mut config = test_config();
    config.limits.queue_depth = 256;
    let d = Daemon::start(config).await;
    assert_eq!(d.get("/healthz").await.text().await.unwrap().trim(), "ok");
    let ready = d.get("/readyz").await;
    assert_eq!(ready.status(), 200);

    let mut events = d.get("/v1/events").await;
    assert_eq!(events.status(), 200);
    assert!(events.headers()["content-type"]
        .to_str()
        .unwrap()
        .starts_with("text/event-stream"));

    // A log that says it is simulated, as `shocktwin simulate` writes them.
    let mut m = meta("sse-1", "r7");
    m.extra.insert("simulated".into(), "true".into());
    let s = write_stream(&m, &run_samples(40_000_000_000, 1000), chunked());
    let addr = d.ingest;
    let bytes = s.bytes.clone();
    let sender = tokio::spawn(async move { send(addr, &bytes, 1200).await });

    let mut buf = String::new();
    let mut seen = Vec::new();
    let collect = async {
        loop {
            let chunk = events.chunk().await.unwrap().expect("stream ended early");
            buf.push_str(std::str::from_utf8(&chunk).unwrap());
            for e in parse_events(&mut buf) {
                let done = e.name == "run" && e.data["status"] == "completed";
                seen.push(e);
                if done {
                    return;
                }
            }
        }
    };
    tokio::time::timeout(WAIT, collect)
        .await
        .expect("events in time");
    let report = sender.await.unwrap();
    assert_eq!(report["status"], "completed");

    assert_eq!(seen[0].name, "run");
    assert_eq!(seen[0].data["status"], "started");
    assert_eq!(seen[0].data["asset_id"], "sse-1");
    let ends: Vec<_> = seen.iter().filter(|e| e.name == "run").collect();
    assert!(ends.iter().all(|e| e.data["simulated"] == true), "{ends:?}");
    let estimates: Vec<_> = seen.iter().filter(|e| e.name == "estimate").collect();
    assert_eq!(estimates.len() as u64, s.ticks, "one event per tick");
    for (k, e) in estimates.iter().enumerate() {
        assert_eq!(e.data["asset_id"], "sse-1");
        assert_eq!(e.data["run_id"], "r7");
        assert_eq!(
            e.data["t_ns"].as_i64().unwrap(),
            s.t0_ns + (k as i64 + 1) * 20_000_000
        );
        assert_eq!(e.data["health"], "unknown");
        assert!(e.data["pressure_bar"].is_null());
    }
    // The placeholder's health never leaves `unknown`: no health events.
    assert!(seen.iter().all(|e| e.name != "health"));
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn delay_histogram_counts_every_estimate_of_each_asset() {
    let d = Daemon::start(test_config()).await;
    let a = good_stream("delay-a", "r1", 10_000_000_000, 700);
    let b = good_stream("delay-b", "r1", 20_000_000_000, 300);
    let (ra, rb) = tokio::join!(send(d.ingest, &a.bytes, 500), send(d.ingest, &b.bytes, 700));
    assert_eq!(ra["status"], "completed");
    assert_eq!(rb["status"], "completed");
    let text = d.metrics().await;
    for asset in ["delay-a", "delay-b"] {
        // the health state set: the placeholder's `unknown`, and no charge to show
        for (state, want) in [("ok", 0.0), ("low", 0.0), ("leak", 0.0), ("unknown", 1.0)] {
            let series = format!("shocktwin_asset_health{{asset=\"{asset}\",health=\"{state}\"}}");
            assert_eq!(
                crate::common::metric(&text, &series),
                Some(want),
                "{series}\n{text}"
            );
        }
        assert!(!text.contains(&format!(
            "shocktwin_asset_pressure_bar{{asset=\"{asset}\"}}"
        )));
    }
    for (asset, s) in [("delay-a", &a), ("delay-b", &b)] {
        let count = crate::common::metric(
            &text,
            &format!("shocktwin_estimate_delay_seconds_count{{asset=\"{asset}\"}}"),
        );
        assert_eq!(
            count,
            Some(s.ticks as f64),
            "{asset}: one observation per estimate"
        );
        // Every estimate is under the largest finite bound (5 s) on loopback.
        let le5 = crate::common::metric(
            &text,
            &format!("shocktwin_estimate_delay_seconds_bucket{{le=\"5.0\",asset=\"{asset}\"}}"),
        );
        assert_eq!(le5, Some(s.ticks as f64), "{asset}:\n{text}");
        let sum = crate::common::metric(
            &text,
            &format!("shocktwin_estimate_delay_seconds_sum{{asset=\"{asset}\"}}"),
        )
        .unwrap();
        assert!(sum >= 0.0 && sum.is_finite(), "{asset}: sum {sum}");
    }
    d.stop().await;
}
