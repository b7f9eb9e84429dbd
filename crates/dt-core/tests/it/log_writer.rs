//! The writer, checked with the `mcap` crate's own reader (an independent
//! decoding path from ours).

use std::io::Cursor;

use dt_core::log::{
    Compression, LogError, LogWriter, RunMetadata, Sample, WriteOptions, RUN_METADATA_NAME,
};

pub fn meta() -> RunMetadata {
    RunMetadata {
        asset_id: "shock-001".into(),
        run_id: "run_7.a".into(),
        charge_pressure_bar: Some(12.5),
        excitation: Some("sine 2 Hz 80 mm p-p".into()),
        frequency_hz: Some(2.0),
        stroke_pp_m: Some(0.08),
        extra: [("operator".to_string(), "bench 3".to_string())].into(),
    }
}

/// A few samples of every topic, in time order.
pub fn samples() -> Vec<Sample> {
    let mut out = Vec::new();
    for i in 0..200_i64 {
        let t_ns = 1_000_000 * i;
        let x = i as f64 * 0.001;
        out.push(Sample::Acceleration {
            t_ns,
            a1_mps2: x.sin(),
            a2_mps2: -x,
        });
        if i % 10 == 0 {
            out.push(Sample::Position {
                t_ns,
                position_m: 0.04 * x.cos(),
            });
        }
        if i % 20 == 0 {
            out.push(Sample::Force {
                t_ns,
                force_n: 1e3 * x - 7.25e-9,
            });
        }
        if i % 100 == 0 {
            out.push(Sample::TempShock {
                t_ns,
                temperature_c: 25.0 + x,
            });
            out.push(Sample::TempAmbient {
                t_ns,
                temperature_c: 21.5,
            });
            out.push(Sample::TruthPressure {
                t_ns,
                static_bar: 12.0 + x,
            });
        }
        if i % 10 == 0 {
            // simulator truth at the /position instants, last at equal times (rank 6)
            out.push(Sample::TruthVelocity {
                t_ns,
                velocity_mps: -0.04 * x.sin() - 3.5e-7,
            });
        }
    }
    out
}

pub fn write_bytes(samples: &[Sample], options: WriteOptions) -> Vec<u8> {
    let mut w = LogWriter::new(Cursor::new(Vec::new()), &meta(), options).unwrap();
    for s in samples {
        w.write_sample(s).unwrap();
    }
    w.finish().unwrap().into_inner()
}

fn all_options() -> Vec<WriteOptions> {
    let mut out = Vec::new();
    for compression in [Compression::Zstd, Compression::Lz4, Compression::None] {
        for chunk_size in [Some(1 << 20), Some(512), None] {
            out.push(WriteOptions {
                compression,
                chunk_size,
            });
        }
    }
    out
}

#[test]
fn mcap_crate_reads_back_every_message_with_schema_and_time() {
    let samples = samples();
    for options in all_options() {
        let bytes = write_bytes(&samples, options);
        let messages: Vec<_> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(messages.len(), samples.len(), "{options:?}");
        for (m, s) in messages.iter().zip(&samples) {
            assert_eq!(m.channel.topic, s.topic());
            assert_eq!(m.channel.message_encoding, "json");
            let schema = m.channel.schema.as_ref().unwrap();
            assert_eq!(schema.encoding, "jsonschema");
            let schema: serde_json::Value = serde_json::from_slice(&schema.data).unwrap();
            assert_eq!(m.log_time, s.t_ns() as u64);
            assert_eq!(m.publish_time, m.log_time);
            let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            let fields: Vec<(&str, f64)> = match *s {
                Sample::Acceleration {
                    a1_mps2, a2_mps2, ..
                } => {
                    vec![("a1_mps2", a1_mps2), ("a2_mps2", a2_mps2)]
                }
                Sample::Position { position_m, .. } => vec![("position_m", position_m)],
                Sample::Force { force_n, .. } => vec![("force_n", force_n)],
                Sample::TempShock { temperature_c, .. }
                | Sample::TempAmbient { temperature_c, .. } => {
                    vec![("temperature_c", temperature_c)]
                }
                Sample::TruthPressure { static_bar, .. } => vec![("static_bar", static_bar)],
                Sample::TruthVelocity { velocity_mps, .. } => {
                    vec![("velocity_mps", velocity_mps)]
                }
            };
            assert_eq!(v.as_object().unwrap().len(), fields.len());
            for (name, value) in fields {
                // exact: the writer's float text must round-trip
                assert_eq!(
                    v[name].as_f64().unwrap().to_bits(),
                    value.to_bits(),
                    "{name}"
                );
                assert!(schema["required"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|f| f == name));
                assert!(schema["properties"][name].is_object());
            }
        }
        // sequence numbers count per channel
        let seqs: Vec<u32> = messages
            .iter()
            .filter(|m| m.channel.topic == "/force")
            .map(|m| m.sequence)
            .collect();
        assert_eq!(seqs, (0..seqs.len() as u32).collect::<Vec<_>>());
    }
}

#[test]
fn metadata_is_written_before_the_first_message() {
    let bytes = write_bytes(&samples(), WriteOptions::default());
    let mut saw_metadata = false;
    for record in mcap::read::LinearReader::new(&bytes).unwrap() {
        match record.unwrap() {
            mcap::records::Record::Metadata(m) => {
                assert_eq!(m.name, RUN_METADATA_NAME);
                assert_eq!(m.metadata, meta().to_map());
                assert_eq!(m.metadata["charge_pressure_bar"], "12.5");
                assert_eq!(m.metadata["operator"], "bench 3");
                saw_metadata = true;
            }
            mcap::records::Record::Message { .. } | mcap::records::Record::Chunk { .. } => {
                assert!(saw_metadata, "a message came before the metadata");
            }
            _ => {}
        }
    }
    assert!(saw_metadata);
}

#[test]
fn the_simulated_key_is_read_only_when_it_says_true_or_false() {
    let with = |v: Option<&str>| {
        let mut m = meta();
        if let Some(v) = v {
            m.extra.insert("simulated".into(), v.into());
        }
        RunMetadata::from_map("x.mcap", &m.to_map())
            .unwrap()
            .simulated()
    };
    assert_eq!(with(Some("true")), Some(true));
    assert_eq!(with(Some("false")), Some(false));
    assert_eq!(with(Some("yes")), None);
    assert_eq!(with(None), None);
}

#[test]
fn nan_is_written_as_null() {
    let bytes = write_bytes(
        &[Sample::Force {
            t_ns: 5,
            force_n: f64::NAN,
        }],
        WriteOptions::default(),
    );
    let m = mcap::MessageStream::new(&bytes)
        .unwrap()
        .next()
        .unwrap()
        .unwrap();
    assert_eq!(&*m.data, br#"{"force_n":null}"#);
}

#[test]
fn write_json_uses_one_channel_per_topic() {
    let mut w = LogWriter::new(Cursor::new(Vec::new()), &meta(), WriteOptions::default()).unwrap();
    let schema = r#"{"type":"object","properties":{"pressure_bar":{"type":"number"}}}"#;
    for i in 0..3 {
        w.write_json(
            "/estimate",
            schema,
            20_000_000 * i,
            &serde_json::json!({"pressure_bar": 11.5}),
        )
        .unwrap();
    }
    let bytes = w.finish().unwrap().into_inner();
    let messages: Vec<_> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(messages.len(), 3);
    assert!(messages
        .iter()
        .all(|m| m.channel.id == messages[0].channel.id));
    assert_eq!(messages[2].sequence, 2);
    assert_eq!(
        &messages[0].channel.schema.as_ref().unwrap().data[..],
        schema.as_bytes()
    );
}

#[test]
fn invalid_ids_and_negative_times_are_refused() {
    let mut bad = meta();
    bad.run_id = "run 1".into();
    let err = LogWriter::new(Cursor::new(Vec::new()), &bad, WriteOptions::default())
        .err()
        .unwrap();
    assert!(
        matches!(err, LogError::InvalidMetadata { ref key, .. } if key == "run_id"),
        "{err}"
    );
    // `.` and `..` name directories: an asset `..` recorded outside the
    // daemon's record_dir (sixty-second session)
    for (key, id) in [("asset_id", ".."), ("run_id", "."), ("run_id", "..")] {
        let mut bad = meta();
        if key == "asset_id" {
            bad.asset_id = id.into();
        } else {
            bad.run_id = id.into();
        }
        let err = LogWriter::new(Cursor::new(Vec::new()), &bad, WriteOptions::default())
            .err()
            .unwrap();
        assert!(
            err.to_string()
                .contains(r#"not [A-Za-z0-9._-]{1,64}, not "." or "..""#),
            "{err}"
        );
    }
    assert!(dt_core::log::is_valid_id("...") && dt_core::log::is_valid_id(".a"));
    // a log another writer made is refused as it is read, by key
    let mut map = meta().to_map();
    map.insert("asset_id".into(), "..".into());
    let err = RunMetadata::from_map("x.mcap", &map).unwrap_err();
    assert!(
        matches!(err, LogError::InvalidMetadata { ref key, .. } if key == "asset_id"),
        "{err}"
    );

    let mut w = LogWriter::new(Cursor::new(Vec::new()), &meta(), WriteOptions::default()).unwrap();
    let err = w
        .write_sample(&Sample::Position {
            t_ns: -1,
            position_m: 0.0,
        })
        .unwrap_err();
    assert!(err.to_string().contains("/position"), "{err}");
}
