//! The whole-file reader and the incremental decoder: round trips, NaN,
//! validation (fatal errors and problems), truncation and absurd lengths.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::time::Instant;

use dt_core::log::{
    read_log, read_log_bytes, Compression, LogDecoder, LogError, LogEvent, LogWriter, RunLog,
    Sample, WriteOptions, RUN_METADATA_NAME,
};

use crate::log_writer::{meta, samples, write_bytes};

/// Decodes `bytes` fed in pieces of `piece` bytes; returns the samples, the
/// non-fatal errors and `finish()`'s result.
fn decode_pieces(
    bytes: &[u8],
    piece: usize,
) -> (Vec<LogEvent>, Vec<LogError>, Result<(), LogError>) {
    let mut decoder = LogDecoder::new("stream");
    let mut events = Vec::new();
    let mut errors = Vec::new();
    for chunk in bytes.chunks(piece) {
        decoder.feed(chunk);
        while let Some(e) = decoder.next_event() {
            match e {
                Ok(e) => events.push(e),
                Err(e) => errors.push(e),
            }
        }
    }
    (events, errors, decoder.finish())
}

fn samples_of(events: &[LogEvent]) -> Vec<Sample> {
    events
        .iter()
        .filter_map(|e| match e {
            LogEvent::Sample(s) => Some(*s),
            _ => None,
        })
        .collect()
}

#[test]
fn whole_file_and_stream_readers_round_trip_every_layout() {
    let written = samples();
    for compression in [Compression::Zstd, Compression::Lz4, Compression::None] {
        for chunk_size in [Some(1 << 20), Some(300), None] {
            let options = WriteOptions {
                compression,
                chunk_size,
            };
            let bytes = write_bytes(&written, options);
            let log = read_log_bytes("mem", &bytes).unwrap();
            assert_eq!(log.metadata, meta(), "{options:?}");
            assert!(log.problems.is_empty(), "{:?}", log.problems);
            // written in time order with acceleration first: the sort is the identity
            assert_eq!(log.samples_sorted(), written, "{options:?}");
            let truth: Vec<(i64, f64)> = written
                .iter()
                .filter_map(|s| match *s {
                    Sample::TruthVelocity { t_ns, velocity_mps } => Some((t_ns, velocity_mps)),
                    _ => None,
                })
                .collect();
            assert_eq!(truth.len(), 20);
            assert_eq!(log.truth_velocity, truth, "{options:?}");
            assert_eq!(log.t0_ns(), Some(0));

            for piece in [1, 7, 4096, bytes.len()] {
                let (events, errors, end) = decode_pieces(&bytes, piece);
                assert!(errors.is_empty(), "{errors:?}");
                end.unwrap();
                assert_eq!(events.first(), Some(&LogEvent::Metadata(meta())));
                assert_eq!(events.last(), Some(&LogEvent::End));
                assert_eq!(samples_of(&events), written, "{options:?} piece {piece}");
            }
        }
    }
}

#[test]
fn read_log_reads_a_file_and_names_a_missing_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let mut w = LogWriter::create(&path, &meta(), WriteOptions::default()).unwrap();
    for s in samples() {
        w.write_sample(&s).unwrap();
    }
    w.finish().unwrap();
    let log = read_log(&path).unwrap();
    assert_eq!(log.samples_sorted(), samples());
    let missing = dir.path().join("nope.mcap");
    let err = read_log(&missing).unwrap_err();
    assert!(err.to_string().contains("nope.mcap"), "{err}");
}

/// Ctrl-C in the bindings sets the call's flag ([`dt_core::cancel`]): the
/// reader stops taking messages (its caller drops the log); without the flag,
/// or with it unset, it reads them all.
#[test]
fn read_log_stops_when_its_call_is_cancelled() {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;
    let bytes = write_bytes(&samples(), WriteOptions::default());
    let read = |set: bool| {
        dt_core::cancel::with_flag(Arc::new(AtomicBool::new(set)), || {
            read_log_bytes("mem", &bytes).unwrap()
        })
    };
    assert_eq!(read(false).samples_sorted(), samples());
    let stopped = read(true);
    assert_eq!(
        stopped.metadata,
        meta(),
        "the metadata comes before any message"
    );
    assert_eq!(
        stopped.sample_count(),
        0,
        "no message read once the flag is set"
    );
}

#[test]
fn samples_sorted_orders_equal_times_by_topic_rank() {
    let mut log = RunLog::default();
    log.push(Sample::TempAmbient {
        t_ns: 10,
        temperature_c: 20.0,
    });
    log.push(Sample::Position {
        t_ns: 10,
        position_m: 0.1,
    });
    log.push(Sample::Position {
        t_ns: 5,
        position_m: 0.0,
    });
    log.push(Sample::Acceleration {
        t_ns: 10,
        a1_mps2: 1.0,
        a2_mps2: 0.0,
    });
    log.push(Sample::Force {
        t_ns: 10,
        force_n: 3.0,
    });
    log.push(Sample::TruthVelocity {
        t_ns: 10,
        velocity_mps: 0.3,
    });
    log.push(Sample::TruthVelocity {
        t_ns: 7,
        velocity_mps: 0.2,
    });
    log.push(Sample::TruthPressure {
        t_ns: 7,
        static_bar: 12.0,
    });
    let topics: Vec<(i64, &str)> = log
        .samples_sorted()
        .iter()
        .map(|s| (s.t_ns(), s.topic()))
        .collect();
    assert_eq!(
        topics,
        [
            (5, "/position"),
            (7, "/truth/gas_pressure"),
            (7, "/truth/velocity"),
            (10, "/acceleration"),
            (10, "/position"),
            (10, "/force"),
            (10, "/temperature/ambient"),
            (10, "/truth/velocity"),
        ]
    );
    assert_eq!(log.t0_ns(), Some(5));
    assert_eq!(RunLog::default().t0_ns(), None);
}

/// Writes a file with the `mcap` crate directly, for content our writer refuses.
struct Raw {
    w: mcap::Writer<Cursor<Vec<u8>>>,
}

impl Raw {
    fn new(options: mcap::WriteOptions) -> Self {
        Raw {
            w: options.create(Cursor::new(Vec::new())).unwrap(),
        }
    }
    fn metadata(&mut self, map: &[(&str, &str)]) -> &mut Self {
        let metadata = map
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        self.w
            .write_metadata(&mcap::records::Metadata {
                name: RUN_METADATA_NAME.into(),
                metadata,
            })
            .unwrap();
        self
    }
    fn channel(&mut self, topic: &str, encoding: &str, schema: Option<&str>) -> u16 {
        self.channel_encoded(topic, encoding, schema.map(|s| ("jsonschema", s)))
    }
    fn channel_encoded(
        &mut self,
        topic: &str,
        encoding: &str,
        schema: Option<(&str, &str)>,
    ) -> u16 {
        let schema_id = match schema {
            Some((how, s)) => self.w.add_schema("s", how, s.as_bytes()).unwrap(),
            None => 0,
        };
        self.w
            .add_channel(schema_id, topic, encoding, &BTreeMap::new())
            .unwrap()
    }
    fn message(&mut self, channel_id: u16, t_ns: u64, data: &str) -> &mut Self {
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: 0,
            log_time: t_ns,
            publish_time: t_ns,
        };
        self.w
            .write_to_known_channel(&header, data.as_bytes())
            .unwrap();
        self
    }
    fn finish(mut self) -> Vec<u8> {
        self.w.finish().unwrap();
        self.w.into_inner().into_inner()
    }
}

const IDS: [(&str, &str); 2] = [("asset_id", "A1"), ("run_id", "r1")];

#[test]
fn python_nan_tokens_and_null_read_as_nan() {
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&IDS);
    let acc = raw.channel("/acceleration", "json", None);
    raw.message(acc, 1, r#"{"a1_mps2": NaN, "a2_mps2": Infinity}"#);
    raw.message(acc, 2, r#"{"a1_mps2": null, "a2_mps2": -Infinity}"#);
    raw.message(
        acc,
        3,
        r#"{"a1_mps2": 1.25, "a2_mps2": -0.5, "extra": "ignored"}"#,
    );
    let log = read_log_bytes("py.mcap", &raw.finish()).unwrap();
    assert!(log.problems.is_empty(), "{:?}", log.problems);
    assert_eq!(log.acceleration.len(), 3);
    for &(_, a1, a2) in &log.acceleration[..2] {
        assert!(a1.is_nan() && a2.is_nan());
    }
    assert_eq!(log.acceleration[2], (3, 1.25, -0.5));
}

#[test]
fn a_bad_message_is_skipped_and_named_and_its_neighbours_kept() {
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&IDS);
    let force = raw.channel("/force", "json", None);
    let est = raw.channel("/estimate", "json", None);
    raw.message(force, 1, r#"{"force_n": 1.0}"#);
    raw.message(force, 2, r#"{"force": 2.0}"#); // wrong field name
    raw.message(force, 3, r#"{"force_n": "3"}"#); // a string
    raw.message(force, 4, r#"{"force_n": 4.0"#); // broken JSON
    raw.message(force, 5, r#"{"force_n": 5.0}"#);
    raw.message(est, 5, r#"{"pressure_bar": 5.0}"#);
    raw.message(est, 6, r#"{"pressure_bar": 5.0}"#);
    let bytes = raw.finish();
    let log = read_log_bytes("bad.mcap", &bytes).unwrap();
    assert_eq!(log.force, [(1, 1.0), (5, 5.0)]);
    assert_eq!(log.unknown_topics["/estimate"], 2);
    let text = log.problems.join("\n");
    assert!(
        text.contains("/force") && text.contains("`force_n`") && text.contains("missing"),
        "{text}"
    );
    assert!(text.contains("not a number"), "{text}");
    assert!(
        text.contains("ignored topic /estimate (2 messages)"),
        "{text}"
    );

    // the decoder reports the same three messages and goes on
    let (events, errors, end) = decode_pieces(&bytes, 5);
    end.unwrap();
    assert_eq!(errors.len(), 3, "{errors:?}");
    assert!(errors
        .iter()
        .all(|e| !e.is_fatal() && !e.to_string().contains("bad.mcap")));
    assert!(
        errors[0]
            .to_string()
            .contains("stream: topic `/force` message at t_ns=2: field `force_n`"),
        "{}",
        errors[0]
    );
    assert_eq!(samples_of(&events).len(), 2);
    assert_eq!(
        events
            .iter()
            .filter(|e| matches!(e, LogEvent::Unknown { topic, .. } if topic == "/estimate"))
            .count(),
        2
    );
}

/// `finish()`'s result as an item of [`one_by_one`]'s list: `End` when the
/// stream ended well.
fn finished(decoder: LogDecoder) -> Result<LogEvent, String> {
    decoder
        .finish()
        .map(|()| LogEvent::End)
        .map_err(|e| e.to_string())
}

/// What the decoder makes of `bytes` fed in pieces of `piece` bytes, one
/// event at a time: the events, errors as text, then `finish()`'s result.
fn one_by_one(bytes: &[u8], piece: usize) -> Vec<Result<LogEvent, String>> {
    let mut decoder = LogDecoder::new("stream");
    let mut out = Vec::new();
    for chunk in bytes.chunks(piece) {
        decoder.feed(chunk);
        while let Some(event) = decoder.next_event() {
            out.push(event.map_err(|e| e.to_string()));
        }
    }
    out.push(finished(decoder));
    out
}

/// The same, read from a reader `piece` bytes at a time
/// (`LogDecoder::feed_from`) and decoded in runs of at most `max` samples
/// (`LogDecoder::next_samples`).
fn in_runs(bytes: &[u8], piece: usize, max: usize) -> Vec<Result<LogEvent, String>> {
    let mut decoder = LogDecoder::new("stream");
    let mut source = Cursor::new(bytes);
    let mut samples = Vec::new();
    let mut out = Vec::new();
    loop {
        loop {
            let next = decoder.next_samples(&mut samples, max);
            assert!(samples.len() <= max);
            let full = samples.len() == max;
            out.extend(samples.drain(..).map(|s| Ok(LogEvent::Sample(s))));
            match next {
                Some(event) => out.push(event.map_err(|e| e.to_string())),
                None if full => {}
                None => break,
            }
        }
        if decoder.feed_from(&mut source, piece).unwrap() == 0 {
            break;
        }
    }
    out.push(finished(decoder));
    out
}

#[test]
fn samples_decoded_in_runs_are_the_events_one_by_one() {
    // good and bad messages, an unknown topic, a file that ends cleanly
    let mut raw = Raw::new(mcap::WriteOptions::new().chunk_size(Some(200)));
    raw.metadata(&IDS);
    let force = raw.channel("/force", "json", None);
    let est = raw.channel("/estimate", "json", None);
    let position = raw.channel("/position", "json", None);
    for t in 0..40_u64 {
        raw.message(force, t, &format!(r#"{{"force_n": {t}.5}}"#));
        raw.message(position, t, r#"{"position_m": 0.01}"#);
        if t % 7 == 3 {
            raw.message(force, t, r#"{"force": 2.0}"#); // wrong field name
            raw.message(est, t, r#"{"pressure_bar": 5.0}"#);
        }
    }
    let mixed = raw.finish();
    // a fatal error after some samples: a known topic in another encoding
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&IDS);
    let force = raw.channel("/force", "json", None);
    raw.message(force, 1, r#"{"force_n": 1.0}"#);
    raw.channel("/position", "cbor", None);
    raw.message(force, 2, r#"{"force_n": 2.0}"#);
    let fatal = raw.finish();
    let written = write_bytes(
        &samples(),
        WriteOptions {
            compression: Compression::Zstd,
            chunk_size: Some(300),
        },
    );
    for (name, bytes) in [("mixed", &mixed), ("fatal", &fatal), ("written", &written)] {
        for piece in [1, 5, 64, 4096, bytes.len()] {
            let want = one_by_one(bytes, piece);
            assert!(want.len() > 3, "{name}: {want:?}");
            for max in [1, 2, 3, 1000] {
                assert_eq!(
                    in_runs(bytes, piece, max),
                    want,
                    "{name}, piece {piece}, max {max}"
                );
            }
        }
    }
    let errors = |events: &[Result<LogEvent, String>]| events.iter().filter(|e| e.is_err()).count();
    assert_eq!(errors(&one_by_one(&mixed, 64)), 6);
    assert!(one_by_one(&fatal, 64).last().unwrap().is_err());
}

#[test]
fn fatal_validation_errors_name_file_topic_and_field() {
    // no metadata
    let mut raw = Raw::new(mcap::WriteOptions::new());
    let c = raw.channel("/position", "json", None);
    raw.message(c, 1, r#"{"position_m": 1}"#);
    let bytes = raw.finish();
    let err = read_log_bytes("f1.mcap", &bytes).unwrap_err();
    assert!(matches!(err, LogError::MissingMetadata { .. }), "{err}");
    assert!(err.to_string().contains("f1.mcap") && err.to_string().contains("shocktwin.run"));
    let (_, errors, _) = decode_pieces(&bytes, 64);
    assert!(
        matches!(errors[0], LogError::MissingMetadata { .. }),
        "{errors:?}"
    );

    // bad run_id charset
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&[("asset_id", "A1"), ("run_id", "run/1")]);
    let err = read_log_bytes("f2.mcap", &raw.finish()).unwrap_err();
    assert!(
        err.to_string().contains("f2.mcap") && err.to_string().contains("run_id"),
        "{err}"
    );

    // missing asset_id
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&[("run_id", "r")]);
    let err = read_log_bytes("f3.mcap", &raw.finish()).unwrap_err();
    assert!(err.to_string().contains("asset_id"), "{err}");

    // a known topic in another encoding
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&IDS);
    raw.channel("/force", "cbor", None);
    let err = read_log_bytes("f4.mcap", &raw.finish()).unwrap_err();
    assert!(
        matches!(err, LogError::Encoding { ref topic, .. } if topic == "/force"),
        "{err}"
    );

    // a schema lacking a field
    let mut raw = Raw::new(mcap::WriteOptions::new());
    raw.metadata(&IDS);
    raw.channel(
        "/acceleration",
        "json",
        Some(r#"{"type":"object","properties":{"a1_mps2":{"type":"number"}}}"#),
    );
    let bytes = raw.finish();
    let err = read_log_bytes("f5.mcap", &bytes).unwrap_err();
    let text = err.to_string();
    assert!(
        text.contains("f5.mcap") && text.contains("/acceleration") && text.contains("a2_mps2"),
        "{text}"
    );
    let (_, errors, end) = decode_pieces(&bytes, 3);
    assert!(matches!(errors[0], LogError::Schema { .. }), "{errors:?}");
    assert!(end.is_err());

    // a schema that declares a field other than a number, or is not
    // jsonschema (a helper's audit of SPEC §2: both were read as if right)
    for (name, how, schema, field, says) in [
        (
            "f6.mcap",
            "jsonschema",
            r#"{"properties":{"position_m":{"type":"string"}}}"#,
            "position_m",
            "declares it `\"string\"`",
        ),
        (
            "f7.mcap",
            "jsonschema",
            r#"{"properties":{"position_m":{"type":["string","null"]}}}"#,
            "position_m",
            "not a number",
        ),
        (
            "f8.mcap",
            "protobuf",
            "message Position { double position_m = 1; }",
            "position_m",
            "encoded `protobuf`, not `jsonschema`",
        ),
    ] {
        let mut raw = Raw::new(mcap::WriteOptions::new());
        raw.metadata(&IDS);
        let c = raw.channel_encoded("/position", "json", Some((how, schema)));
        raw.message(c, 1, r#"{"position_m": 0.01}"#);
        let bytes = raw.finish();
        let text = read_log_bytes(name, &bytes).unwrap_err().to_string();
        assert!(
            text.contains(name) && text.contains("/position") && text.contains(field),
            "{text}"
        );
        assert!(text.contains(says), "{text}");
        let (events, errors, _) = decode_pieces(&bytes, 7);
        assert!(matches!(errors[0], LogError::Schema { .. }), "{errors:?}");
        assert!(samples_of(&events).is_empty(), "{events:?}");
    }
    // what a writer may declare instead of a bare number, and no type at all
    for schema in [
        r#"{"properties":{"position_m":{"type":["number","null"]}}}"#,
        r#"{"properties":{"position_m":{"type":"integer"}}}"#,
        r#"{"properties":{"position_m":{}}}"#,
    ] {
        let mut raw = Raw::new(mcap::WriteOptions::new());
        raw.metadata(&IDS);
        let c = raw.channel("/position", "json", Some(schema));
        raw.message(c, 1, r#"{"position_m": 0.01}"#);
        let log = read_log_bytes("ok.mcap", &raw.finish()).unwrap();
        assert_eq!(log.position, vec![(1, 0.01)], "{schema}");
    }
}

#[test]
fn truncated_files_and_streams_are_errors() {
    let bytes = write_bytes(&samples(), WriteOptions::default());
    for cut in [0, 5, 8, 20, bytes.len() / 2, bytes.len() - 1] {
        let err = read_log_bytes("cut.mcap", &bytes[..cut]).unwrap_err();
        assert!(err.to_string().contains("cut.mcap"), "{err}");
    }
    // a stream stopping in the middle of a record
    let (_, _, end) = decode_pieces(&bytes[..bytes.len() / 2], 100);
    let err = end.unwrap_err();
    assert!(matches!(err, LogError::Truncated { .. }), "{err}");
    // a stream stopping between records (no footer yet) is fine
    let unchunked = write_bytes(
        &samples(),
        WriteOptions {
            compression: Compression::None,
            chunk_size: None,
        },
    );
    let full = read_raw_boundaries(&unchunked);
    let (events, errors, end) = decode_pieces(&unchunked[..full], 10);
    assert!(errors.is_empty());
    end.unwrap();
    assert!(!samples_of(&events).is_empty());
}

/// Offset of the start of the last message record of an unchunked file.
fn read_raw_boundaries(bytes: &[u8]) -> usize {
    let mut pos = 8;
    let mut last_message_end = 0;
    while pos + 9 <= bytes.len() {
        let opcode = bytes[pos];
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        pos += 9 + len;
        if opcode == 0x05 {
            last_message_end = pos;
        }
        if opcode == 0x0F {
            break;
        }
    }
    last_message_end
}

/// A file whose record declares `len` bytes; the rest of the file is short.
fn absurd_record(opcode: u8, len: u64) -> Vec<u8> {
    let mut bytes = write_bytes(
        &[],
        WriteOptions {
            compression: Compression::None,
            chunk_size: None,
        },
    );
    // keep magic + header + metadata, then the absurd record
    let cut = read_until_data_end(&bytes);
    bytes.truncate(cut);
    bytes.push(opcode);
    bytes.extend_from_slice(&len.to_le_bytes());
    bytes.extend_from_slice(&[0_u8; 64]);
    bytes
}

fn read_until_data_end(bytes: &[u8]) -> usize {
    let mut pos = 8;
    loop {
        let opcode = bytes[pos];
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        if opcode == 0x0F {
            return pos;
        }
        pos += 9 + len;
    }
}

#[test]
fn an_absurd_declared_length_is_refused_quickly_without_allocating_it() {
    let huge = 1_u64 << 62;
    for opcode in [0x05_u8, 0x06, 0x0C, 0x03, 0x80] {
        let bytes = absurd_record(opcode, huge);
        let start = Instant::now();
        let err = read_log_bytes("huge.mcap", &bytes).unwrap_err();
        assert!(start.elapsed().as_secs_f64() < 1.0);
        match &err {
            LogError::TooLarge { file, len, .. } => {
                assert_eq!(file, "huge.mcap");
                assert_eq!(*len, huge);
            }
            other => panic!("opcode {opcode:#x}: {other}"),
        }
        let (_, errors, _) = decode_pieces(&bytes, 3);
        assert!(
            matches!(errors.last(), Some(LogError::TooLarge { .. })),
            "{errors:?}"
        );
    }
    // a chunk whose header declares an absurd uncompressed size
    let mut bytes = absurd_record(0x06, 200);
    let at = bytes.len() - 64;
    bytes[at + 16..at + 24].copy_from_slice(&huge.to_le_bytes());
    let err = read_log_bytes("bomb.mcap", &bytes).unwrap_err();
    assert!(
        matches!(err, LogError::TooLarge { ref what, .. } if what.contains("uncompressed")),
        "{err}"
    );
}

#[test]
fn a_record_inside_a_chunk_with_an_absurd_length_is_refused() {
    // an uncompressed chunk holding one record that declares 2^62 bytes
    let mut inner = vec![0x05_u8];
    inner.extend_from_slice(&(1_u64 << 62).to_le_bytes());
    inner.extend_from_slice(&[0; 30]);
    let mut chunk = Vec::new();
    chunk.extend_from_slice(&0_u64.to_le_bytes()); // start
    chunk.extend_from_slice(&0_u64.to_le_bytes()); // end
    chunk.extend_from_slice(&(inner.len() as u64).to_le_bytes()); // uncompressed size
    chunk.extend_from_slice(&0_u32.to_le_bytes()); // crc (0: not checked)
    chunk.extend_from_slice(&0_u32.to_le_bytes()); // compression ""
    chunk.extend_from_slice(&(inner.len() as u64).to_le_bytes()); // compressed size
    chunk.extend_from_slice(&inner);
    let mut bytes = absurd_record(0x06, chunk.len() as u64);
    bytes.truncate(bytes.len() - 64);
    bytes.extend_from_slice(&chunk);
    let err = read_log_bytes("inner.mcap", &bytes).unwrap_err();
    assert!(
        matches!(err, LogError::TooLarge { len, .. } if len == 1 << 62),
        "{err}"
    );
}

#[test]
fn not_mcap_is_an_error_naming_the_file() {
    let err = read_log_bytes("notes.txt", b"hello, this is not an MCAP file at all").unwrap_err();
    assert!(err.to_string().starts_with("notes.txt: "), "{err}");
    // a flipped byte in a chunk fails its CRC
    let mut bytes = write_bytes(
        &samples(),
        WriteOptions {
            compression: Compression::None,
            chunk_size: Some(1 << 20),
        },
    );
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x55;
    assert!(read_log_bytes("flip.mcap", &bytes).is_err());
}

/// `inspect` says what `read_log` says (a helper's audit): metadata after
/// the first message is a problem, and a bad channel's problem is said once
/// though its record comes again in the summary.
#[test]
fn inspect_names_late_metadata_and_a_bad_schema_once() {
    let mut raw = Raw::new(mcap::WriteOptions::new());
    let c = raw.channel(
        "/force",
        "json",
        Some(r#"{"type":"object","properties":{"f":{"type":"number"}}}"#),
    );
    raw.message(c, 1, r#"{"force_n": 1}"#);
    raw.metadata(&IDS);
    let bytes = raw.finish();
    let read = read_log_bytes("late.mcap", &bytes);
    let report = dt_core::log::inspect_bytes("late.mcap", &bytes).unwrap();
    let said = |what: &str| report.problems.iter().filter(|p| p.contains(what)).count();
    assert_eq!(
        said("comes after the first message"),
        1,
        "{:?}",
        report.problems
    );
    assert_eq!(said("schema field `force_n`"), 1, "{:?}", report.problems);
    // the whole-file reader refuses the schema outright
    assert!(read.is_err());
    // the metadata alone late: read_log and inspect both say so
    let mut raw = Raw::new(mcap::WriteOptions::new());
    let c = raw.channel("/position", "json", None);
    raw.message(c, 1, r#"{"position_m": 0.01}"#);
    raw.metadata(&IDS);
    let bytes = raw.finish();
    let log = read_log_bytes("late.mcap", &bytes).unwrap();
    let report = dt_core::log::inspect_bytes("late.mcap", &bytes).unwrap();
    for problems in [&log.problems, &report.problems] {
        assert!(
            problems
                .iter()
                .any(|p| p.contains("comes after the first message")),
            "{problems:?}"
        );
    }
}

#[test]
fn inspect_reports_counts_rates_and_a_complete_log() {
    let bytes = write_bytes(&samples(), WriteOptions::default());
    let report = dt_core::log::inspect_bytes("run.mcap", &bytes).unwrap();
    assert!(report.problems.is_empty(), "{:?}", report.problems);
    assert_eq!(report.count("/acceleration"), 200);
    assert_eq!(report.count("/position"), 20);
    assert_eq!(report.count("/truth/velocity"), 20);
    let truth = report
        .channels
        .iter()
        .find(|c| c.topic == "/truth/velocity")
        .unwrap();
    assert_eq!(truth.schema_name, "shocktwin.TruthVelocity");
    assert!((truth.rate_hz().unwrap() - 100.0).abs() < 1e-9);
    assert_eq!(report.chunks.keys().collect::<Vec<_>>(), ["zstd"]);
    let acc = report
        .channels
        .iter()
        .find(|c| c.topic == "/acceleration")
        .unwrap();
    assert!((acc.rate_hz().unwrap() - 1000.0).abs() < 1e-9);
    assert!((report.duration_s() - 0.199).abs() < 1e-12);
    assert_eq!(report.run.as_ref(), Some(&meta()));
    let text = report.to_string();
    assert!(text.contains("problems:  none"), "{text}");

    // a log without /force and with an unknown topic: listed, not fatal
    let only_position: Vec<Sample> = samples()
        .into_iter()
        .filter(|s| matches!(s, Sample::Position { .. }))
        .collect();
    let mut w = LogWriter::new(Cursor::new(Vec::new()), &meta(), WriteOptions::default()).unwrap();
    for s in &only_position {
        w.write_sample(s).unwrap();
    }
    w.write_json(
        "/estimate",
        "{}",
        5,
        &serde_json::json!({"pressure_bar": 1.0}),
    )
    .unwrap();
    let bytes = w.finish().unwrap().into_inner();
    let report = dt_core::log::inspect_bytes("partial.mcap", &bytes).unwrap();
    let problems = report.problems.join("\n");
    for needle in [
        "/force",
        "/acceleration",
        "ignored topic /estimate (1 messages)",
    ] {
        assert!(problems.contains(needle), "{needle}: {problems}");
    }
    assert!(!problems.contains("/position"), "{problems}");
    // the simulator-truth topics are optional: their absence is no problem
    assert!(!problems.contains("/truth/"), "{problems}");
}

/// A gap in a channel is named with its length: a 3 s gap in a 100 Hz
/// channel read as a rate of 96 Hz and nothing else (a helper's trial).
#[test]
fn inspect_names_a_channels_gaps() {
    let shifted: Vec<Sample> = samples()
        .into_iter()
        .map(|s| match s {
            Sample::Position { t_ns, position_m } if t_ns >= 100_000_000 => Sample::Position {
                t_ns: t_ns + 3_000_000_000,
                position_m,
            },
            other => other,
        })
        .collect();
    let bytes = write_bytes(&shifted, WriteOptions::default());
    let report = dt_core::log::inspect_bytes("gap.mcap", &bytes).unwrap();
    let problems = report.problems.join("\n");
    assert!(
        problems.contains("/position: 1 gap(s) longer than 1 s (the longest 3.010 s)"),
        "{problems}"
    );
    assert_eq!(problems.lines().count(), 1, "{problems}");
    let position = report
        .channels
        .iter()
        .find(|c| c.topic == "/position")
        .unwrap();
    assert_eq!(position.largest_interval_ns, 3_010_000_000);
    assert!(report.to_string().contains("gap(s) longer than"));
}

/// Bytes after the end magic are not read, whatever pieces they come in: the
/// whole file and the file fed byte by byte give the same events and the same
/// end (the fuzzer found a file whose split changed `finish` from `Ok` to
/// "truncated": the whole input fed the reader past the magic, the pieces
/// did not).
#[test]
fn bytes_after_the_end_magic_do_not_depend_on_the_pieces() {
    let clean = write_bytes(&samples(), WriteOptions::default());
    for tail in [&b"x"[..], b"xyz", &[0u8; 100]] {
        let mut bytes = clean.clone();
        bytes.extend_from_slice(tail);
        let (whole, whole_errors, whole_end) = decode_pieces(&bytes, bytes.len());
        for piece in [1, 7, 4096] {
            let (events, errors, end) = decode_pieces(&bytes, piece);
            assert_eq!(
                events.len(),
                whole.len(),
                "tail {} B, pieces of {piece}",
                tail.len()
            );
            assert_eq!(errors.len(), whole_errors.len());
            assert_eq!(
                end.is_ok(),
                whole_end.is_ok(),
                "tail {} B, pieces of {piece}: {end:?}",
                tail.len()
            );
        }
    }
}
