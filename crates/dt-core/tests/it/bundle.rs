//! The model bundle (SPEC §5): loading the fixtures of `fixtures/bundle-*`
//! (made by `fixtures/make_bundles.py`), the network against the numpy forward
//! pass stored there (cross-checked with onnxruntime when the fixtures are
//! made): the float64 paths to 1e-9, the float32 hot path to
//! [`MLP_F32_PARITY_BAR`]; and every consistency check naming its file and part.

use std::path::{Path, PathBuf};

use dt_core::bundle::{mlp_f32_agrees, Bundle, BundleError, MLP_F32_PARITY_BAR};
use dt_core::features::Group;
use dt_core::params::PhysicsParams;
use serde_json::Value;
use sha2::Digest as _;

/// Agreement required between the float64 network paths and numpy (SPEC: 1e-9).
const TOL_BAR: f64 = 1e-9;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// `expected.json`: raw rows (row-major) and numpy's pressures.
fn expected(name: &str) -> (Vec<f64>, Vec<f64>) {
    let text = std::fs::read_to_string(fixture(name).join("expected.json")).unwrap();
    let v: Value = serde_json::from_str(&text).unwrap();
    let rows = v["rows"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
        .collect();
    let p = v["pressure_bar"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    (rows, p)
}

/// A copy of a fixture bundle in a temporary directory, with `twin.json`
/// edited by `edit`.
fn edited(name: &str, edit: impl FnOnce(&mut Value)) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for file in ["twin.json", "mlp.onnx"] {
        std::fs::copy(fixture(name).join(file), dir.path().join(file)).unwrap();
    }
    let path = dir.path().join("twin.json");
    let mut twin: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    edit(&mut twin);
    std::fs::write(&path, serde_json::to_string_pretty(&twin).unwrap()).unwrap();
    dir
}

/// Loads `dir`, expects an error, checks its message names every `part`.
fn load_err(dir: &Path, parts: &[&str]) -> BundleError {
    let err = Bundle::load(dir).expect_err("the bundle should not load");
    let msg = err.to_string();
    for part in parts {
        assert!(msg.contains(part), "error {msg:?} does not name {part:?}");
    }
    err
}

/// The float32 path within [`MLP_F32_PARITY_BAR`] of the float64 reference.
fn assert_f32_parity(got: &[f64], want: &[f64], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    let mut worst = 0.0_f64;
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            mlp_f32_agrees(*g, *w),
            "{what}: row {i}: float32 {g} vs float64 {w} (Δ {:e}, bar {MLP_F32_PARITY_BAR:e})",
            g - w
        );
        worst = worst.max((g - w).abs() / (1.0 + w.abs()));
    }
    eprintln!("{what}: worst float32 error {worst:.2e} × (1 + |p|) bar");
}

fn assert_close(got: &[f64], want: &[f64], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= TOL_BAR,
            "{what}: row {i}: {g} vs numpy {w} (Δ {:e})",
            g - w
        );
    }
}

#[test]
#[allow(clippy::float_cmp)] // exact: values read from JSON
fn fixture_loads_with_its_parts() {
    let b = Bundle::load(fixture("bundle-mlp13")).unwrap();
    assert_eq!(
        b.groups,
        [
            Group::Force,
            Group::Position,
            Group::Acceleration,
            Group::Velocity,
            Group::Mechanical,
            Group::Thermal
        ]
    );
    assert_eq!(b.n_inputs(), 12);
    assert_eq!(b.twin.permutation.id, 13);
    assert_eq!(b.physics(), &PhysicsParams::default());
    assert_eq!(b.twin.nominal_bar, 12.0);
    assert_eq!(b.twin.health.warn_bar, 9.0);
    assert_eq!(b.twin.provenance["seed"], 20_240_613);
    assert_eq!(b.backend(), "dense", "a plain MLP runs on the dense path");
    assert_eq!(b.precision(), "float32", "… in float32");
}

#[test]
fn predict_equals_numpy_forward_pass() {
    for (name, backend, precision) in [
        ("bundle-mlp13", "dense", "float32"),
        ("bundle-force-skl", "dense", "float32"),
        ("bundle-force-tanh", "tract", "float64"),
    ] {
        let b = Bundle::load(fixture(name)).unwrap();
        assert_eq!(b.backend(), backend, "{name}");
        assert_eq!(b.precision(), precision, "{name}");
        let (rows, want) = expected(name);
        assert_close(&b.predict_f64(&rows).unwrap(), &want, name);
        assert_close(&b.predict_reference(&rows).unwrap(), &want, name);
        let batch = b.predict(&rows).unwrap();
        let one: Vec<f64> = rows
            .chunks_exact(b.n_inputs())
            .map(|r| b.predict_one(r).unwrap())
            .collect();
        if precision == "float32" {
            assert_f32_parity(&batch, &want, name);
        } else {
            assert_close(&batch, &want, name);
        }
        // One row at a time is the batch, bit for bit (streaming = batch).
        for (i, (o, p)) in one.iter().zip(&batch).enumerate() {
            assert_eq!(o.to_bits(), p.to_bits(), "{name} row {i}: {o} vs {p}");
        }
        // The outputs are not all alike (a constant network would pass too easily).
        let spread = want.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b))
            - want.iter().fold(f64::INFINITY, |a, &b| a.min(b));
        assert!(spread > 0.1, "{name}: spread {spread}");
    }
}

#[test]
fn dense_path_agrees_with_tract_far_from_the_data() {
    let b = Bundle::load(fixture("bundle-mlp13")).unwrap();
    let k = b.n_inputs();
    let norm = &b.twin.normalisation;
    let mut state = 7_u64;
    let mut rows = Vec::new();
    for i in 0..200 * k {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let u = (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
        let j = i % k;
        rows.push(norm.mean[j] + norm.std[j] * 20.0 * u);
    }
    let dense = b.predict_f64(&rows).unwrap();
    let tract = b.predict_reference(&rows).unwrap();
    for (d, t) in dense.iter().zip(&tract) {
        assert!(
            (d - t).abs() <= TOL_BAR * t.abs().max(1.0),
            "dense {d} vs tract {t}"
        );
    }
    // The float32 path far from the data too (outputs of tens of bar).
    assert_f32_parity(&b.predict(&rows).unwrap(), &tract, "far from the data");
}

#[test]
fn float32_path_propagates_nan_like_float64() {
    let b = Bundle::load(fixture("bundle-mlp13")).unwrap();
    let (rows, _) = expected("bundle-mlp13");
    let mut row = rows[..b.n_inputs()].to_vec();
    row[3] = f64::NAN;
    assert!(b.predict_one(&row).unwrap().is_nan());
    assert!(b.predict_f64(&row).unwrap()[0].is_nan());
}

#[test]
fn wrong_width_is_an_error() {
    let b = Bundle::load(fixture("bundle-mlp13")).unwrap();
    let err = b.predict(&[0.0; 13]).unwrap_err();
    assert!(
        matches!(
            err,
            BundleError::Width {
                expected: 12,
                got: 13
            }
        ),
        "{err}"
    );
    assert!(b.predict_one(&[0.0; 11]).is_err());
    assert!(b.predict(&[]).unwrap().is_empty());
}

#[test]
fn missing_files_are_named() {
    let dir = edited("bundle-mlp13", |_| {});
    std::fs::remove_file(dir.path().join("mlp.onnx")).unwrap();
    let err = load_err(dir.path(), &["mlp.onnx"]);
    assert!(matches!(err, BundleError::Io { .. }), "{err}");

    std::fs::remove_file(dir.path().join("twin.json")).unwrap();
    load_err(dir.path(), &["twin.json"]);

    // A missing key names the key.
    let dir = edited("bundle-mlp13", |t| {
        t.as_object_mut().unwrap().remove("normalisation");
    });
    let err = load_err(dir.path(), &["twin.json", "normalisation"]);
    assert!(matches!(err, BundleError::Json { .. }), "{err}");
}

#[test]
fn wrong_sha256_is_named() {
    let dir = edited("bundle-mlp13", |t| {
        t["onnx"]["sha256"] = Value::from("00".repeat(32));
    });
    load_err(dir.path(), &["mlp.onnx", "sha256", &"00".repeat(32)]);
    // A changed network with the old digest is caught too.
    let dir = edited("bundle-mlp13", |_| {});
    std::fs::copy(
        fixture("bundle-force-skl/mlp.onnx"),
        dir.path().join("mlp.onnx"),
    )
    .unwrap();
    load_err(dir.path(), &["mlp.onnx", "sha256"]);
}

#[test]
fn columns_must_match_the_groups() {
    let dir = edited("bundle-mlp13", |t| {
        let cols = t["permutation"]["columns"].as_array_mut().unwrap();
        cols.swap(0, 1);
    });
    load_err(
        dir.path(),
        &["twin.json", "permutation.columns", "position_m", "force_n"],
    );
    // A group dropped but its column kept.
    let dir = edited("bundle-mlp13", |t| {
        t["permutation"]["groups"].as_array_mut().unwrap().remove(0);
    });
    load_err(dir.path(), &["twin.json", "permutation.columns"]);
}

#[test]
fn normalisation_length_and_values_are_checked() {
    let dir = edited("bundle-mlp13", |t| {
        t["normalisation"]["std"].as_array_mut().unwrap().pop();
    });
    load_err(
        dir.path(),
        &["twin.json", "normalisation", "12 means and 11 stds"],
    );
    let dir = edited("bundle-mlp13", |t| {
        t["normalisation"]["std"][3] = Value::from(0.0);
    });
    load_err(
        dir.path(),
        &["twin.json", "normalisation.std[3]", "velocity_mps"],
    );
}

#[test]
fn unknown_group_is_named() {
    let dir = edited("bundle-mlp13", |t| {
        t["permutation"]["groups"][2] = Value::from("accelerometer");
    });
    load_err(
        dir.path(),
        &["twin.json", "permutation.groups", "accelerometer"],
    );
}

#[test]
fn health_thresholds_are_checked() {
    for fault in [9.0, 10.0] {
        let dir = edited("bundle-mlp13", |t| {
            t["health"]["fault_bar"] = Value::from(fault);
        });
        load_err(dir.path(), &["twin.json", "fault_bar", "warn_bar"]);
    }
    let dir = edited("bundle-mlp13", |t| {
        t["health"]["warn_bar"] = Value::from(13.0);
    });
    load_err(dir.path(), &["twin.json", "warn_bar", "nominal_bar"]);
    let dir = edited("bundle-mlp13", |t| {
        t["health"]["dwell_s"] = Value::from(-1.0);
    });
    load_err(dir.path(), &["twin.json", "dwell_s"]);
}

#[test]
fn physics_and_format_are_checked() {
    let dir = edited("bundle-mlp13", |t| {
        t["physics"]["thermal"]["c_oil"] = Value::from(-5.0);
    });
    load_err(dir.path(), &["twin.json", "physics", "c_oil"]);
    let dir = edited("bundle-mlp13", |t| {
        t["format"] = Value::from("shocktwin-bundle/2");
    });
    load_err(dir.path(), &["twin.json", "format", "shocktwin-bundle/2"]);
}

#[test]
fn network_names_and_dtype_are_checked() {
    let dir = edited("bundle-mlp13", |t| {
        t["onnx"]["input"] = Value::from("features");
    });
    load_err(dir.path(), &["mlp.onnx", "onnx.input", "features"]);
    let dir = edited("bundle-mlp13", |t| {
        t["onnx"]["output"] = Value::from("charge");
    });
    load_err(dir.path(), &["mlp.onnx", "onnx.output", "charge"]);
    let dir = edited("bundle-mlp13", |t| {
        t["onnx"]["dtype"] = Value::from("int8");
    });
    load_err(dir.path(), &["mlp.onnx", "onnx.dtype", "int8"]);
    // A network for another width (the force-only one under permutation 13),
    // its digest right.
    let with_network = |bytes: &[u8]| {
        let digest = sha2::Sha256::digest(bytes)
            .iter()
            .fold(String::new(), |mut s, b| {
                use std::fmt::Write as _;
                let _ = write!(s, "{b:02x}");
                s
            });
        let dir = edited("bundle-mlp13", |t| {
            t["onnx"]["sha256"] = Value::from(digest);
        });
        std::fs::write(dir.path().join("mlp.onnx"), bytes).unwrap();
        dir
    };
    let other = std::fs::read(fixture("bundle-force-skl/mlp.onnx")).unwrap();
    let dir = with_network(&other);
    let err = load_err(dir.path(), &["mlp.onnx"]);
    assert!(matches!(err, BundleError::Onnx { .. }), "{err}");
    // Not ONNX at all.
    let dir = with_network(b"not a network");
    load_err(dir.path(), &["mlp.onnx", "ONNX"]);
}

/// SPEC §5: every part present, or loading names what is not (a helper's
/// audit: without `health` or `provenance` a bundle loaded with defaults).
#[test]
fn every_part_must_be_present() {
    for part in ["health", "provenance"] {
        let dir = edited("bundle-mlp13", |t| {
            t.as_object_mut().unwrap().remove(part);
        });
        load_err(dir.path(), &["twin.json", part]);
    }
    for key in ["campaign_digest", "split", "seed", "metrics"] {
        let dir = edited("bundle-mlp13", |t| {
            t["provenance"].as_object_mut().unwrap().remove(key);
        });
        load_err(dir.path(), &["twin.json", "provenance", key]);
    }
    let dir = edited("bundle-mlp13", |t| {
        t["provenance"] = Value::from("trained somewhere");
    });
    load_err(dir.path(), &["twin.json", "provenance"]);
    let dir = edited("bundle-mlp13", |t| {
        t["onnx"].as_object_mut().unwrap().remove("sha256");
    });
    load_err(dir.path(), &["twin.json", "onnx.sha256"]);
    // a held-out interval that is not SPEC §2a's
    for (half, level, says) in [
        (0.0, 0.95, "half_width_bar"),
        (-1.0, 0.95, "half_width_bar"),
        (1.0, 0.68, "interval.level"),
    ] {
        let dir = edited("bundle-mlp13", |t| {
            t["interval"] = serde_json::json!({
                "half_width_bar": half, "level": level, "runs": ["r"], "ticks": 10
            });
        });
        load_err(dir.path(), &["twin.json", says]);
    }
    let dir = edited("bundle-mlp13", |t| {
        t["interval"] = serde_json::json!({
            "half_width_bar": 1.0, "level": 0.95, "runs": ["r"], "ticks": 10, "method": "guessed"
        });
    });
    load_err(dir.path(), &["twin.json", "interval.method", "guessed"]);
    // without `method` (written before it), and with each of its values
    for method in [None, Some("held-out"), Some("cross-validated")] {
        let dir = edited("bundle-mlp13", |t| {
            t["interval"] = serde_json::json!({"half_width_bar": 1.0, "level": 0.95, "runs": ["r"], "ticks": 10});
            if let Some(m) = method {
                t["interval"]["method"] = Value::from(m);
            }
        });
        let b = Bundle::load(dir.path()).unwrap();
        let i = b.twin.interval.as_ref().unwrap();
        assert_eq!(i.method.as_deref(), method);
    }
}

/// A run at an excitation the network was not trained on is named, with the
/// ones it was; a bundle or a log that does not say, or a bundle that reads
/// the charge observer (which says it per reversal), gives no such word.
#[test]
fn an_untrained_excitation_is_named() {
    use dt_core::log::RunMetadata;
    let trained = ["sine 1 Hz 80 mm p-p", "sine 2 Hz 80 mm p-p"];
    let dir = edited("bundle-mlp13", |t| {
        t["provenance"]["trained_excitations"] = serde_json::json!(trained);
    });
    let b = Bundle::load(dir.path()).unwrap();
    assert_eq!(b.trained_excitations().unwrap(), trained);
    let meta = |e: Option<&str>| RunMetadata {
        excitation: e.map(str::to_owned),
        ..RunMetadata::default()
    };
    assert_eq!(
        b.untrained_excitation(&meta(Some("sine 2 Hz 80 mm p-p"))),
        None
    );
    assert_eq!(b.untrained_excitation(&meta(None)), None);
    let why = b
        .untrained_excitation(&meta(Some("road class C 60 km/h")))
        .unwrap();
    for part in [
        "`road class C 60 km/h`",
        "`sine 1 Hz 80 mm p-p`",
        "`sine 2 Hz 80 mm p-p`",
        "extrapolation",
    ] {
        assert!(why.contains(part), "{why}");
    }
    // a bundle from before the record says nothing
    let older = Bundle::load(fixture("bundle-mlp13")).unwrap();
    assert_eq!(older.trained_excitations(), None);
    assert_eq!(older.untrained_excitation(&meta(Some("road"))), None);
}
