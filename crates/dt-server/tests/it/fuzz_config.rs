//! Fuzzing the daemon's configuration loader, `Config::load` (read the file,
//! parse TOML with unknown keys refused, validate), from mutations of
//! `shocktwin.example.toml`: a value replaced by an interesting one (out of
//! range, NaN/inf, wrong type, deep nesting, long strings), lines removed,
//! duplicated, swapped or inserted (unknown keys and tables, asset ids off
//! the charset), bits flipped, non-UTF-8 bytes, truncation.
//!
//! Asserted: no panic or hang; an error names the file or the key at fault;
//! a configuration that loads survives a TOML round trip unchanged.
//! The text mutations here are shared with `fuzz_import`.

use std::path::Path;

use dt_server::server::{Config, ConfigOverrides};
use proptest::prelude::*;
use proptest::sample::Index;

use crate::fuzz_driver::fuzz;

/// Interesting TOML values.
pub fn toml_value() -> impl Strategy<Value = String> + Clone {
    let special = prop::sample::select(vec![
        "0",
        "-1",
        "1",
        "1024",
        "1023",
        "60000",
        "60001",
        "18446744073709551616",
        "-9223372036854775809",
        "1e309",
        "-1e309",
        "nan",
        "+inf",
        "-inf",
        "0.0",
        "-0.0",
        "1e-320",
        "true",
        "\"\"",
        "\"x\"",
        "\"256.0.0.1:1\"",
        "\"[::1]:0\"",
        "\"127.0.0.1:99999\"",
        "[]",
        "{}",
        "[1, \"a\"]",
        "1979-05-27T07:32:00Z",
        "\"\\uD800\"",
        "'''a\nb'''",
        "\"\\u0000\"",
        "0x10",
        "1_000",
        "inf",
        "\"from-name\"",
        "\"150 psi\"",
        "\"1e999 bar\"",
        "\"-5 psia\"",
    ])
    .prop_map(str::to_owned);
    prop_oneof![
        4 => special,
        2 => any::<f64>().prop_map(|x| format!("{x:?}")),
        2 => any::<i64>().prop_map(|x| x.to_string()),
        1 => "[ -~é]{0,20}".prop_map(|s| format!("{s:?}")),
        1 => (1..4000_usize, any::<bool>()).prop_map(|(depth, table)| {
            if table {
                format!("{}1{}", "{a=".repeat(depth), "}".repeat(depth))
            } else {
                format!("{}1{}", "[".repeat(depth), "]".repeat(depth))
            }
        }),
        1 => (1..100_000_usize).prop_map(|n| format!("\"{}\"", "x".repeat(n))),
    ]
}

/// A line to insert: a key with a value, or a table header.
fn toml_line() -> impl Strategy<Value = String> {
    let key = prop_oneof![
        prop::sample::select(vec![
            "listen",
            "http",
            "inbox",
            "max_connections",
            "max_record_bytes",
            "max_chunk_uncompressed_bytes",
            "queue_depth",
            "nominal_bar",
            "warn_bar",
            "fault_bar",
            "retention_days",
            "flush_ms",
            "column",
            "unit",
            "charge",
            "format",
            "header_line",
            "delimiter",
            "mid_stroke",
            "asset_id",
        ])
        .prop_map(str::to_owned),
        "[a-z_.\"]{1,12}",
    ];
    prop_oneof![
        3 => (key, toml_value()).prop_map(|(k, v)| format!("{k} = {v}")),
        1 => prop::sample::select(vec![
            "[server]", "[limits]", "[assets.\"a b\"]", "[assets.A-1]", "[[assets]]", "[assets]",
            "[defaults]", "[time]", "[position]", "[run]", "[acceleration]", "[x.y.z]", "[",
            "[store]", "[tls]", "[auth]",
        ])
        .prop_map(str::to_owned),
        1 => "[ -~]{0,30}",
    ]
}

/// One mutation of a text file (line-level or byte-level).
#[derive(Debug, Clone)]
pub enum TextMutation {
    /// The text after the first `=` of a line replaced.
    SetValue {
        line: Index,
        value: String,
    },
    /// A cell (between `delimiter`s) of a line replaced.
    SetCell {
        line: Index,
        cell: Index,
        value: String,
    },
    DuplicateLine {
        line: Index,
    },
    RemoveLine {
        line: Index,
    },
    SwapLines {
        a: Index,
        b: Index,
    },
    InsertLine {
        at: Index,
        text: String,
    },
    FlipBit {
        at: Index,
        bit: u8,
    },
    InsertBytes {
        at: Index,
        bytes: Vec<u8>,
    },
    Truncate {
        at: Index,
    },
}

/// Mutations with `value` for values and cells and `line` for new lines.
pub fn text_mutation(
    value: impl Strategy<Value = String> + Clone + 'static,
    line: impl Strategy<Value = String> + 'static,
) -> impl Strategy<Value = TextMutation> {
    let high = prop_oneof![Just(0xff_u8), Just(0xc3), Just(0x80), Just(0), any::<u8>()];
    prop_oneof![
        4 => (any::<Index>(), value.clone())
            .prop_map(|(line, value)| TextMutation::SetValue { line, value }),
        4 => (any::<Index>(), any::<Index>(), value)
            .prop_map(|(line, cell, value)| TextMutation::SetCell { line, cell, value }),
        1 => any::<Index>().prop_map(|line| TextMutation::DuplicateLine { line }),
        1 => any::<Index>().prop_map(|line| TextMutation::RemoveLine { line }),
        1 => (any::<Index>(), any::<Index>()).prop_map(|(a, b)| TextMutation::SwapLines { a, b }),
        2 => (any::<Index>(), line).prop_map(|(at, text)| TextMutation::InsertLine { at, text }),
        2 => (any::<Index>(), 0_u8..8).prop_map(|(at, bit)| TextMutation::FlipBit { at, bit }),
        1 => (any::<Index>(), prop::collection::vec(high, 1..4))
            .prop_map(|(at, bytes)| TextMutation::InsertBytes { at, bytes }),
        1 => any::<Index>().prop_map(|at| TextMutation::Truncate { at }),
    ]
}

#[allow(clippy::trivially_copy_pass_by_ref)] // called with fields of a borrowed `TextMutation`
fn pick(index: &Index, len: usize) -> usize {
    if len == 0 {
        0
    } else {
        index.index(len)
    }
}

/// `text` with `mutations` applied; `delimiter` separates cells.
#[must_use]
pub fn mutate(text: &[u8], mutations: &[TextMutation], delimiter: u8) -> Vec<u8> {
    let mut bytes = text.to_vec();
    for m in mutations {
        let mut lines: Vec<Vec<u8>> = bytes.split(|&b| b == b'\n').map(<[u8]>::to_vec).collect();
        let n = lines.len();
        match m {
            TextMutation::SetValue { line, value } => {
                let l = &mut lines[pick(line, n)];
                if let Some(eq) = l.iter().position(|&b| b == b'=') {
                    l.truncate(eq + 1);
                    l.push(b' ');
                    l.extend_from_slice(value.as_bytes());
                }
            }
            TextMutation::SetCell { line, cell, value } => {
                let l = &mut lines[pick(line, n)];
                let mut cells: Vec<Vec<u8>> =
                    l.split(|&b| b == delimiter).map(<[u8]>::to_vec).collect();
                let k = pick(cell, cells.len());
                cells[k] = value.as_bytes().to_vec();
                *l = cells.join(&delimiter);
            }
            TextMutation::DuplicateLine { line } => {
                let i = pick(line, n);
                let copy = lines[i].clone();
                lines.insert(i, copy);
            }
            TextMutation::RemoveLine { line } => {
                lines.remove(pick(line, n));
            }
            TextMutation::SwapLines { a, b } => lines.swap(pick(a, n), pick(b, n)),
            TextMutation::InsertLine { at, text } => {
                lines.insert(pick(at, n + 1), text.as_bytes().to_vec());
            }
            TextMutation::FlipBit { .. }
            | TextMutation::InsertBytes { .. }
            | TextMutation::Truncate { .. } => {}
        }
        bytes = lines.join(&b'\n');
        match m {
            TextMutation::FlipBit { at, bit } if !bytes.is_empty() => {
                let i = pick(at, bytes.len());
                bytes[i] ^= 1 << bit;
            }
            TextMutation::InsertBytes { at, bytes: new } => {
                let i = pick(at, bytes.len() + 1);
                bytes.splice(i..i, new.iter().copied());
            }
            TextMutation::Truncate { at } => bytes.truncate(pick(at, bytes.len() + 1)),
            _ => {}
        }
    }
    bytes
}

/// Writes `bytes` to a fresh file `name` in a temporary directory.
pub fn temp_file(name: &str, bytes: &[u8]) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, bytes).unwrap();
    (dir, path)
}

fn example_config() -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("shocktwin.example.toml")).unwrap()
}

#[derive(Debug, Clone)]
struct ConfigCase {
    mutations: Vec<TextMutation>,
}

fn config_case() -> impl Strategy<Value = ConfigCase> {
    prop::collection::vec(text_mutation(toml_value(), toml_line()), 1..5)
        .prop_map(|mutations| ConfigCase { mutations })
}

fn check_config(case: &ConfigCase) {
    let bytes = mutate(&example_config(), &case.mutations, b',');
    let (_dir, path) = temp_file("shocktwin.toml", &bytes);
    let no_env = |_: &str| None;
    match Config::load(Some(&path), &no_env, &ConfigOverrides::default()) {
        Ok(config) => {
            let text = toml::to_string(&config)
                .unwrap_or_else(|e| panic!("a loaded configuration does not serialise: {e}"));
            let again = Config::from_toml(&text).unwrap_or_else(|e| {
                panic!("a serialised configuration does not parse: {e}\n{text}")
            });
            assert_eq!(
                format!("{again:?}"),
                format!("{config:?}"),
                "the TOML round trip changed the configuration"
            );
        }
        Err(err) => {
            let text = err.to_string();
            let names_file = text.contains(&path.display().to_string());
            let names_key =
                text.starts_with("configuration `") && !text.starts_with("configuration ``");
            assert!(
                names_file || names_key,
                "the error names neither the file nor a key: {text}"
            );
        }
    }
}

#[test]
fn fuzz_config_file() {
    fuzz("config/toml", 300, &config_case(), check_config);
}
