//! Every official MCAP conformance file (`../shared/mcap-conformance`) reads
//! without error through `dt_core::log::raw` and yields exactly the expected
//! `Message` and `Metadata` records.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use dt_core::log::raw::read_raw;

/// Number of `.mcap` files in the conformance set (README.txt there).
const EXPECTED_FILES: usize = 416;

pub fn conformance_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/mcap-conformance")
}

pub fn conformance_files() -> Vec<PathBuf> {
    let mut files = Vec::new();
    let dir = conformance_dir();
    let entries = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("conformance data missing at {}: {e}", dir.display()));
    for group in entries {
        let group = group.unwrap().path();
        if !group.is_dir() {
            continue;
        }
        for f in std::fs::read_dir(&group).unwrap() {
            let f = f.unwrap().path();
            if f.extension().is_some_and(|e| e == "mcap") {
                files.push(f);
            }
        }
    }
    files.sort();
    files
}

fn field<'a>(record: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    record["fields"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f[0] == name)
        .unwrap_or_else(|| panic!("no field {name} in {record}"))
        .get(1)
        .unwrap()
}

fn int(v: &serde_json::Value) -> u64 {
    v.as_str().unwrap().parse().unwrap()
}

fn string_map(v: &serde_json::Value) -> BTreeMap<String, String> {
    v.as_object()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_str().unwrap().to_owned()))
        .collect()
}

#[test]
fn every_conformance_file_yields_the_expected_messages_and_metadata() {
    let files = conformance_files();
    assert_eq!(files.len(), EXPECTED_FILES, "conformance files found");
    let mut messages_checked = 0;
    let mut metadata_checked = 0;
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        let name = path.display().to_string();
        let raw = read_raw(&name, &bytes).unwrap_or_else(|e| panic!("{e}"));
        let expected: serde_json::Value =
            serde_json::from_slice(&std::fs::read(path.with_extension("json")).unwrap()).unwrap();
        let records = expected["records"].as_array().unwrap();

        let want_messages: Vec<_> = records
            .iter()
            .filter(|r| r["type"] == "Message")
            .map(|r| {
                let data: Vec<u8> = field(r, "data")
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|b| u8::try_from(int(b)).unwrap())
                    .collect();
                (
                    u16::try_from(int(field(r, "channel_id"))).unwrap(),
                    u32::try_from(int(field(r, "sequence"))).unwrap(),
                    int(field(r, "log_time")),
                    int(field(r, "publish_time")),
                    data,
                )
            })
            .collect();
        let got_messages: Vec<_> = raw
            .messages
            .iter()
            .map(|m| {
                (
                    m.channel_id,
                    m.sequence,
                    m.log_time,
                    m.publish_time,
                    m.data.clone(),
                )
            })
            .collect();
        assert_eq!(got_messages, want_messages, "{name}: messages");
        for m in &raw.messages {
            assert_eq!(m.topic, raw.channels[&m.channel_id].topic, "{name}");
        }
        messages_checked += want_messages.len();

        let want_metadata: Vec<_> = records
            .iter()
            .filter(|r| r["type"] == "Metadata")
            .map(|r| {
                (
                    field(r, "name").as_str().unwrap().to_owned(),
                    string_map(field(r, "metadata")),
                )
            })
            .collect();
        assert_eq!(raw.metadata, want_metadata, "{name}: metadata");
        metadata_checked += want_metadata.len();
    }
    // the set is not trivially empty
    assert!(messages_checked > 1000, "{messages_checked} messages");
    assert!(metadata_checked > 10, "{metadata_checked} metadata records");
}

#[test]
fn every_conformance_file_inspects_and_is_reported_as_not_a_shocktwin_log() {
    for path in conformance_files() {
        let report = dt_core::log::inspect(&path).unwrap_or_else(|e| panic!("{e}"));
        let bytes = std::fs::read(&path).unwrap();
        let raw = read_raw("x", &bytes).unwrap();
        assert_eq!(report.message_count, raw.messages.len() as u64);
        let per_channel: u64 = report.channels.iter().map(|c| c.message_count).sum();
        assert_eq!(per_channel, report.message_count, "{}", path.display());
        assert!(
            report.problems.iter().any(|p| p.contains("shocktwin.run")),
            "{}: {:?}",
            path.display(),
            report.problems
        );
    }
}
