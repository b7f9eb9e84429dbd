//! Logs written by Python's `mcap` package (`fixtures/python_mcap`, made by
//! `make_fixtures.py` there): zstd, lz4 and uncompressed chunks, unchunked,
//! and a file without indexes or summary.

use std::path::PathBuf;

use dt_core::log::raw::read_raw;
use dt_core::log::{read_log, LogDecoder, LogEvent, Sample};

const T0_NS: i64 = 1_700_000_000_000_000_000;
const MS: i64 = 1_000_000;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/python_mcap")
        .join(name)
}

/// (file, compression of its chunks: `None` for an unchunked file)
const FILES: [(&str, Option<&str>); 5] = [
    ("zstd.mcap", Some("zstd")),
    ("lz4.mcap", Some("lz4")),
    ("none_chunked.mcap", Some("")),
    ("unchunked.mcap", None),
    ("zstd_no_index.mcap", Some("zstd")),
];

#[test]
#[allow(clippy::float_cmp)] // exact: the values are k/1024
fn python_written_logs_read_with_exact_values() {
    for (name, compression) in FILES {
        let path = fixture(name);
        let log = read_log(&path).unwrap_or_else(|e| panic!("{e}"));
        assert!(log.problems.is_empty(), "{name}: {:?}", log.problems);
        assert_eq!(log.metadata.asset_id, "py-unit.1");
        assert_eq!(
            log.metadata.run_id,
            format!("py_{}", name.trim_end_matches(".mcap"))
        );
        assert_eq!(log.metadata.charge_pressure_bar, Some(7.5));
        assert_eq!(
            [
                log.acceleration.len(),
                log.position.len(),
                log.force.len(),
                log.temp_shock.len(),
                log.temp_ambient.len(),
                log.truth_pressure.len(),
            ],
            [100, 10, 5, 1, 1, 0],
            "{name}"
        );
        for (i, &(t_ns, a1, a2)) in log.acceleration.iter().enumerate() {
            let k = i as i64;
            assert_eq!(t_ns, T0_NS + k * MS);
            if k == 50 {
                assert!(a1.is_nan(), "{name}: Python NaN token");
            } else {
                assert_eq!(a1, k as f64 / 1024.0);
            }
            assert_eq!(a2, (k + 1) as f64 / 1024.0);
        }
        for (i, &(t_ns, f)) in log.force.iter().enumerate() {
            let k = 20 * i as i64;
            assert_eq!(t_ns, T0_NS + k * MS);
            if k == 40 {
                assert!(f.is_nan(), "{name}: null");
            } else {
                assert_eq!(f, k as f64 / 1024.0);
            }
        }
        assert_eq!(log.t0_ns(), Some(T0_NS));

        let bytes = std::fs::read(&path).unwrap();
        let raw = read_raw(name, &bytes).unwrap();
        match compression {
            Some(c) => assert_eq!(raw.chunks.keys().collect::<Vec<_>>(), [c], "{name}"),
            None => assert!(raw.chunks.is_empty(), "{name}"),
        }

        // the stream decoder, 13 bytes at a time, agrees with the file reader
        let mut decoder = LogDecoder::new(name);
        let mut samples: Vec<Sample> = Vec::new();
        for piece in bytes.chunks(13) {
            decoder.feed(piece);
            while let Some(e) = decoder.next_event() {
                if let LogEvent::Sample(s) = e.unwrap() {
                    samples.push(s);
                }
            }
        }
        decoder.finish().unwrap();
        let sorted = log.samples_sorted();
        assert_eq!(samples.len(), sorted.len());
        // NaN != NaN: compare bit patterns through Debug
        assert_eq!(format!("{samples:?}"), format!("{sorted:?}"), "{name}");
    }
}
