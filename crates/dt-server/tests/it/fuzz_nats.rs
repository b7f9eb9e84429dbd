//! Fuzzing the NATS telemetry payload decoder (`TelemetryBatch::decode`, what
//! any vehicle or MQTT client on the bus reaches), from mutations of a valid
//! batch (pretty JSON: values and keys replaced by interesting JSON, lines
//! removed, duplicated, swapped or inserted, bits flipped, non-UTF-8 bytes,
//! truncation) and from arbitrary bytes, each on a right and a wrong subject
//! token.
//!
//! Asserted: no panic or hang; a refusal has a kind and a reason; an accepted
//! batch gives its samples in time order and survives an encode/decode round
//! trip unchanged (NaN as NaN).

use dt_core::log::Sample;
use dt_server::nats::payload::{subject_token, TelemetryBatch};
use proptest::prelude::*;

use crate::fuzz_config::{mutate, text_mutation, TextMutation};
use crate::fuzz_driver::fuzz;

fn seed_batch() -> Vec<u8> {
    let mut b = TelemetryBatch {
        v: 1,
        asset_id: "bus.7".into(),
        run_id: "r-1".into(),
        batch: 3,
        end: false,
        ..TelemetryBatch::default()
    };
    b.meta.insert("charge_pressure_bar".into(), "12".into());
    b.meta.insert("excitation".into(), "road".into());
    let t0 = 1_700_000_000_000_000_000_i64;
    for i in 0..6 {
        let t = t0 + i * 10_000_000;
        b.push(&Sample::Position {
            t_ns: t,
            position_m: 0.01 * i as f64,
        });
        b.push(&Sample::Acceleration {
            t_ns: t,
            a1_mps2: 0.3,
            a2_mps2: if i == 2 { f64::NAN } else { -0.1 },
        });
        b.push(&Sample::Force {
            t_ns: t + 3_000_000,
            force_n: -400.0,
        });
    }
    b.push(&Sample::TempShock {
        t_ns: t0,
        temperature_c: 25.0,
    });
    serde_json::to_vec_pretty(&b).unwrap()
}

fn json_value() -> impl Strategy<Value = String> + Clone {
    prop::sample::select(vec![
        "null",
        "0",
        "-1",
        "1e309",
        "-1e309",
        "1e-320",
        "18446744073709551616",
        "-9223372036854775809",
        "9223372036854775807",
        "true",
        "\"\"",
        "\"x\"",
        "[]",
        "{}",
        "[[]]",
        "[[1]]",
        "[[1, 2, 3, 4]]",
        "[[\"1\", 2]]",
        "[[1.5, 2]]",
        "\"\\uD800\"",
        "\"bad id\"",
        "\"a.b\"",
        "2",
        "[[[[[[[[[[1]]]]]]]]]]",
        "\"\\u0000\"",
        "{\"v\":1}",
    ])
    .prop_map(str::to_owned)
}

#[derive(Debug, Clone)]
struct Case {
    mutations: Vec<TextMutation>,
    raw: Option<Vec<u8>>,
    right_token: bool,
}

fn case() -> impl Strategy<Value = Case> {
    let line = json_value().prop_map(|v| format!("\"position\": {v},"));
    (
        prop::collection::vec(text_mutation(json_value(), line), 0..6),
        prop::option::weighted(0.15, prop::collection::vec(any::<u8>(), 0..256)),
        any::<bool>(),
    )
        .prop_map(|(mutations, raw, right_token)| Case {
            mutations,
            raw,
            right_token,
        })
}

fn check(case: &Case) {
    let bytes = match &case.raw {
        Some(raw) => raw.clone(),
        None => mutate(&seed_batch(), &case.mutations, b':'),
    };
    let token = if case.right_token {
        subject_token("bus.7")
    } else {
        "bus.7".to_owned()
    };
    match TelemetryBatch::decode(&token, &bytes) {
        Err(e) => {
            assert!(!e.kind().is_empty());
            assert!(!e.to_string().is_empty());
        }
        Ok(b) => {
            let samples = b.samples();
            assert_eq!(samples.len(), b.len());
            assert!(samples.windows(2).all(|w| w[0].t_ns() <= w[1].t_ns()));
            let _ = b.metadata();
            let again = serde_json::to_vec(&b).unwrap();
            let back = TelemetryBatch::decode(&subject_token(&b.asset_id), &again).unwrap();
            assert_eq!(serde_json::to_vec(&back).unwrap(), again, "round trip");
        }
    }
}

#[test]
fn fuzz_nats_payload() {
    assert!(TelemetryBatch::decode("bus~7", &seed_batch()).is_ok());
    fuzz("nats/payload", 2000, &case(), check);
}
