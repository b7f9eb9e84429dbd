//! Fuzzing `shocktwin import`'s readers: the column mapping (`map::resolve`
//! on mutations of `docs/import.example.toml`), the CSV reader
//! (`table::read` on mutated dyno exports: cells replaced by empty, NaN,
//! inf, out-of-range or malformed numbers and times, quotes and
//! delimiters; lines removed, duplicated, swapped or inserted; bits flipped,
//! non-UTF-8 bytes, truncation) and the charge labels (`charge_bar`,
//! `charge_in_name` on generated labels and file names).
//!
//! Asserted: no panic or hang; an error names the file (the CSV's, or the
//! mapping's); a table read is in time order with finite values, one per
//! mapped column, and its row counts add up; skipping bad rows changes
//! nothing in a file without any; a charge is a finite number of bar.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use clap::Parser as _;
use dt_server::cli::{Cli, Command};
use dt_server::cmd_import::map::{self, Mapping};
use dt_server::cmd_import::table;
use proptest::prelude::*;
use proptest::sample::Index;

use crate::fuzz_config::{mutate, temp_file, text_mutation, toml_value, TextMutation};
use crate::fuzz_driver::fuzz;

fn example_map_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/import.example.toml")
}

/// `shocktwin import --out o --map <map> <flags> in.csv`, resolved.
fn resolve(map_path: &Path, flags: &[&str]) -> anyhow::Result<Mapping> {
    let mut argv = vec!["shocktwin", "import", "--out", "o"];
    let map = map_path.display().to_string();
    argv.extend(["--map", map.as_str()]);
    argv.extend(flags);
    argv.push("in.csv");
    let cli = Cli::try_parse_from(argv).unwrap();
    let Command::Import(args) = cli.command else {
        unreachable!("parsed an import command")
    };
    map::resolve(&args)
}

/// Mappings the CSV seeds are read with (index = `CsvCase::mapping`).
fn mappings() -> &'static [Mapping] {
    static MAPPINGS: OnceLock<Vec<Mapping>> = OnceLock::new();
    MAPPINGS.get_or_init(|| {
        let example = example_map_path();
        [
            &[][..],
            &["--header-line", "3"],
            &["--time-format", "auto"],
            &[
                "--delimiter",
                ";",
                "--time",
                "t",
                "--time-format",
                "elapsed_s",
                "--position",
                "x",
                "--force",
                "F",
                "--temp-shock",
                "T",
                "--charge",
                "150 psi",
            ],
            &[
                "--delimiter",
                ";",
                "--decimal",
                ",",
                "--time",
                "t",
                "--time-format",
                "elapsed_s",
                "--position",
                "x",
                "--force",
                "F",
                "--temp-shock",
                "T",
                "--charge",
                "150 psi",
            ],
            &[
                "--time-format",
                "epoch_ms",
                "--a1",
                "Accel rod [g]",
                "--a2",
                "Accel body [g]",
                "--accel-unit",
                "g",
            ],
            &["--encoding", "windows-1252"],
        ]
        .iter()
        .map(|flags| resolve(&example, flags).unwrap())
        .collect()
    })
}

/// Seed exports, each with the mapping it fits.
fn csv_seeds() -> Vec<(usize, String)> {
    let mut iso = String::from(
        "Test,p12.0-f2.0-s1 (simulated crank dyno; dt-sim)\nStroke [mm],80.0\nTimestamp,Force [N],Displacement [mm],Temperature [°C]\n",
    );
    let mut elapsed = String::from("t;x;F;T\n");
    let mut comma = String::from("t;x;F;T\n");
    let mut epoch = String::from(
        "Timestamp,Force [N],Displacement [mm],Temperature [°C],Accel rod [g],Accel body [g]\n",
    );
    for i in 0..24_u32 {
        let x = f64::from(i) * 0.1;
        let _ = writeln!(
            iso,
            "2024-05-01T10:00:{:02}.{:03}Z,{:.1},{:.3},{:.2}",
            i / 10,
            (i % 10) * 100,
            150.0 * x.sin(),
            40.0 + 30.0 * x.cos(),
            25.0 + 0.01 * x
        );
        let _ = writeln!(elapsed, "{:.3};{:.4};{:.2};\"{:.1}\"", x, x.cos(), -x, 30.0);
        let _ = writeln!(
            comma,
            "{}",
            format!("{:.3};{:.4};{:.2};\"{:.1}\"", x, x.cos(), -x, 30.0).replace('.', ",")
        );
        let _ = writeln!(
            epoch,
            "{},{:.1},{:.2},25.0,{:.3},{:.3}",
            1_714_557_600_000_u64 + u64::from(i) * 10,
            x,
            x,
            x.sin(),
            -x.sin()
        );
        if i == 7 {
            epoch.push('\n'); // a blank line
        }
    }
    vec![
        (0, iso.clone()),
        (1, iso.clone()),
        (2, iso.clone()),
        (6, iso),
        (3, elapsed),
        (4, comma),
        (5, epoch),
    ]
}

fn csv_cell() -> impl Strategy<Value = String> + Clone {
    let special = prop::sample::select(vec![
        "",
        " ",
        "nan",
        "NaN",
        "inf",
        "-inf",
        "infinity",
        "1e309",
        "-1e309",
        "1e300",
        "-1e300",
        "9.3e9",
        "-9.3e9",
        "0",
        "-0",
        "1e-320",
        "0x1F",
        "1,5",
        "\"",
        "\"a,b\"",
        "\"a\nb\"",
        "\"\"\"",
        "2024-13-45T10:00:00Z",
        "9999-12-31T23:59:59Z",
        "1969-12-31T23:59:59Z",
        "2024-05-01T10:00:00+02:00",
        "2024-05-01 10:00:00",
        "2024-05-01T10:00:00.9999999999Z",
        "1714557600000",
        "99999999999999999999",
        "é",
        "\u{feff}1",
    ])
    .prop_map(str::to_owned);
    prop_oneof![
        4 => special,
        2 => any::<f64>().prop_map(|x| format!("{x:?}")),
        1 => any::<i64>().prop_map(|x| x.to_string()),
        1 => "[ -~]{0,12}",
        1 => (1..50_000_usize).prop_map(|n| "9".repeat(n)),
    ]
}

fn csv_line() -> impl Strategy<Value = String> {
    prop::collection::vec(csv_cell(), 0..8).prop_map(|cells| cells.join(","))
}

#[derive(Debug, Clone)]
struct CsvCase {
    seed: Index,
    mutations: Vec<TextMutation>,
}

fn csv_case() -> impl Strategy<Value = CsvCase> {
    (
        any::<Index>(),
        prop::collection::vec(text_mutation(csv_cell(), csv_line()), 1..6),
    )
        .prop_map(|(seed, mutations)| CsvCase { seed, mutations })
}

/// Reads `path` with `mapping` both ways and checks every invariant.
fn check_table(path: &Path, mapping: &Mapping) {
    let file = path.display().to_string();
    let strict = table::read(path, mapping, false);
    let lenient = table::read(path, mapping, true);
    for (result, skip_bad) in [(&strict, false), (&lenient, true)] {
        match result {
            Err(err) => {
                let text = format!("{err:#}");
                assert!(
                    text.contains(&file),
                    "the error does not name the file: {text}"
                );
                assert!(
                    !(text.contains("s earlier or equal") && text.contains("s (-")),
                    "a negative time difference in the message: {text}"
                );
            }
            Ok(t) => {
                assert!(
                    t.t_ns.windows(2).all(|w| w[0] < w[1]),
                    "times not increasing"
                );
                assert!(
                    t.lines.windows(2).all(|w| w[0] < w[1]),
                    "lines not increasing"
                );
                assert_eq!(t.lines.len(), t.t_ns.len());
                assert_eq!(t.values.len(), mapping.value_columns().len());
                for column in &t.values {
                    assert_eq!(column.len(), t.t_ns.len());
                    assert!(column.iter().all(|v| v.is_finite()), "a non-finite value");
                }
                assert_eq!(t.rows, t.t_ns.len() as u64 + t.skipped_rows());
                if !skip_bad {
                    assert!(t.skipped.is_empty());
                }
            }
        }
    }
    if let (Ok(a), Ok(b)) = (&strict, &lenient) {
        assert_eq!(
            format!("{:?}", (&a.t_ns, &a.values, &a.lines)),
            format!("{:?}", (&b.t_ns, &b.values, &b.lines)),
            "skipping bad rows changed a file without any"
        );
    } else if strict.is_ok() {
        panic!("the lenient read failed where the strict one did not: {lenient:?}");
    }
}

fn check_csv(case: &CsvCase) {
    let seeds = csv_seeds();
    let (mapping, text) = &seeds[case.seed.index(seeds.len())];
    let mapping = &mappings()[*mapping];
    let bytes = mutate(text.as_bytes(), &case.mutations, mapping.delimiter);
    let (_dir, path) = temp_file("dyno_150psi_2Hz.csv", &bytes);
    check_table(&path, mapping);
}

#[test]
fn fuzz_import_csv() {
    fuzz("import/csv", 300, &csv_case(), check_csv);
}

#[derive(Debug, Clone)]
struct MapCase {
    mutations: Vec<TextMutation>,
}

fn check_map(case: &MapCase) {
    let example = std::fs::read(example_map_path()).unwrap();
    let bytes = mutate(&example, &case.mutations, b',');
    let (_dir, path) = temp_file("map.toml", &bytes);
    match resolve(&path, &[]) {
        Err(err) => {
            let text = format!("{err:#}");
            assert!(
                text.contains(&path.display().to_string()),
                "the error does not name the mapping file: {text}"
            );
        }
        Ok(mapping) => {
            // whatever the mapping, the CSV reader copes with a real export
            let (_, iso) = &csv_seeds()[0];
            let (_csv_dir, csv) = temp_file("run.csv", iso.as_bytes());
            check_table(&csv, &mapping);
        }
    }
}

#[test]
fn fuzz_import_map() {
    let case = prop::collection::vec(text_mutation(toml_value(), map_line()), 1..5)
        .prop_map(|mutations| MapCase { mutations });
    fuzz("import/map", 200, &case, check_map);
}

fn map_line() -> impl Strategy<Value = String> {
    (
        prop::sample::select(vec![
            "column",
            "unit",
            "positive",
            "mid_stroke",
            "format",
            "charge",
            "a1",
            "a2",
            "header_line",
            "delimiter",
            "decimal",
            "encoding",
            "asset_id",
            "run_id",
            "frequency_hz",
            "stroke_pp_mm",
            "[time]",
            "[run]",
            "[acceleration]",
            "[temperature_ambient]",
        ]),
        toml_value(),
    )
        .prop_map(|(k, v)| {
            if k.starts_with('[') {
                k.to_owned()
            } else {
                format!("{k} = {v}")
            }
        })
}

/// Charge labels and file names: a number (any spelling) and a unit (any case).
fn label() -> impl Strategy<Value = String> {
    let number = prop_oneof![
        any::<f64>().prop_map(|x| format!("{x:?}")),
        Just("1e999".to_owned()),
        Just("-".to_owned()),
        Just("+.e".to_owned()),
        (1..5000_usize).prop_map(|n| "9".repeat(n)),
        "[0-9.eE+-]{0,12}",
    ];
    let unit = prop_oneof![
        prop::sample::select(vec![
            "psi", "PSIA", "psig", "bar", "BarA", "barg", "kPa", "MPa", "atm", "", "psi psi",
        ])
        .prop_map(str::to_owned),
        "\\PC{0,6}",
    ];
    (
        number,
        prop::sample::select(vec!["", " ", "\t", "  "]),
        unit,
    )
        .prop_map(|(n, ws, u)| format!("{n}{ws}{u}"))
}

#[allow(clippy::ptr_arg)] // the driver's `fn(&Value)` with `Value = String`
fn check_label(text: &String) {
    match map::charge_bar(text) {
        Ok(bar) => assert!(bar.is_finite(), "{text:?} gave {bar}"),
        Err(err) => {
            let msg = err.to_string();
            assert!(
                msg.contains(&format!("{text:?}")),
                "the error does not quote the label: {msg}"
            );
        }
    }
    let name = format!("dyno-unit-A_{text}_2Hz_s1");
    if let Some((label, bar)) = map::charge_in_name(&name) {
        assert!(bar.is_finite());
        assert_eq!(map::charge_bar(&label).unwrap().to_bits(), bar.to_bits());
    }
}

#[test]
fn fuzz_import_charge_labels() {
    fuzz("import/charge_labels", 300, &label(), check_label);
}
