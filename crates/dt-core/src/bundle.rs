//! The model bundle (SPEC §5): a directory with `twin.json` and `mlp.onnx`.
//!
//! `twin.json` holds the format version, the permutation (id, name, groups
//! and the ordered feature columns), the input normalisation, every physics
//! parameter (SPEC §3.1–3.3), the nominal charge pressure, the health
//! thresholds and the training provenance. `mlp.onnx` is the network alone:
//! normalised inputs `[n, k]` in, the charge pressure in bar `[n, 1]` out,
//! float64 (written by `train/model.py` with skl2onnx).
//!
//! [`Bundle::load`] checks that every part is present and consistent and names
//! what is not (file, key, expected against found); the network runs through
//! tract-onnx.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tract_onnx::prelude::{
    tvec, DatumExt, Framework, InferenceFact, InferenceModelExt, IntoRunnable, Tensor,
    TypedRunnableModel,
};

use crate::features::{column_names, Group};
use crate::params::PhysicsParams;

/// The `format` value this code reads and writes.
pub const BUNDLE_FORMAT: &str = "shocktwin-bundle/1";
/// Name of the JSON part of a bundle.
pub const TWIN_JSON: &str = "twin.json";

/// Errors of loading or running a bundle; each names the file and the part.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// A file of the bundle cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// `twin.json` is not valid JSON or lacks a key.
    #[error("{path}: {message}")]
    Json {
        /// The file.
        path: PathBuf,
        /// serde's message (names the key, line and column).
        message: String,
    },
    /// The parts of the bundle disagree (or a value is out of its domain).
    #[error("{path}: {message}")]
    Inconsistent {
        /// The file at fault.
        path: PathBuf,
        /// What disagrees with what.
        message: String,
    },
    /// tract could not load or run the network.
    #[error("{path}: ONNX network: {message}")]
    Onnx {
        /// `mlp.onnx`.
        path: PathBuf,
        /// tract's message.
        message: String,
    },
    /// An input row of the wrong width.
    #[error("bundle expects {expected} input columns, got {got}")]
    Width {
        /// Number of columns of the permutation.
        expected: usize,
        /// Number given.
        got: usize,
    },
}

/// The permutation a bundle was trained for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BundlePermutation {
    /// Paper id (1–13), or 0 for a custom suite.
    pub id: u32,
    /// Human-readable name.
    pub name: String,
    /// Input groups (SPEC §4 names).
    pub groups: Vec<String>,
    /// Ordered feature columns the network reads.
    pub columns: Vec<String>,
}

/// Input normalisation: the network reads `(x − mean) / std`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Normalisation {
    /// Per-column mean.
    pub mean: Vec<f64>,
    /// Per-column standard deviation (> 0).
    pub std: Vec<f64>,
}

/// Health thresholds and the state machine's timing (SPEC §6).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HealthConfig {
    /// Below this 1 s average the state is `low`, bar gauge.
    pub warn_bar: f64,
    /// Below this 1 s average the state is `leak`, bar gauge.
    pub fault_bar: f64,
    /// A state is left only when the average is this far past its threshold, bar.
    pub hysteresis_bar: f64,
    /// A new state must hold this long before it is reported, s.
    pub dwell_s: f64,
    /// Below this 1 s velocity RMS the damper is not excited: `unknown`, m/s.
    pub min_excitation_mps: f64,
}

impl Default for HealthConfig {
    fn default() -> Self {
        Self {
            warn_bar: 9.0,
            fault_bar: 5.0,
            hysteresis_bar: 0.5,
            dwell_s: 3.0,
            min_excitation_mps: 0.05,
        }
    }
}

impl HealthConfig {
    /// Checks the thresholds: finite, `fault < warn`, non-negative timing.
    pub fn validate(&self) -> Result<(), String> {
        let all = [
            self.warn_bar,
            self.fault_bar,
            self.hysteresis_bar,
            self.dwell_s,
            self.min_excitation_mps,
        ];
        if all.iter().any(|x| !x.is_finite()) {
            return Err(format!("health thresholds must be finite: {self:?}"));
        }
        if self.fault_bar >= self.warn_bar {
            return Err(format!(
                "health: fault_bar ({}) must be below warn_bar ({})",
                self.fault_bar, self.warn_bar
            ));
        }
        if self.hysteresis_bar < 0.0 || self.dwell_s < 0.0 || self.min_excitation_mps < 0.0 {
            return Err(
                "health: hysteresis_bar, dwell_s and min_excitation_mps must be ≥ 0".into(),
            );
        }
        Ok(())
    }
}

/// Where the network is and what it is called.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OnnxInfo {
    /// File name inside the bundle (`mlp.onnx`).
    pub file: String,
    /// Input name.
    pub input: String,
    /// Output name.
    pub output: String,
    /// Element type (`float64` or `float32`).
    pub dtype: String,
    /// SHA-256 of the file, hex (checked when present).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
}

/// Contents of `twin.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TwinJson {
    /// [`BUNDLE_FORMAT`].
    pub format: String,
    /// The permutation.
    pub permutation: BundlePermutation,
    /// Input normalisation.
    pub normalisation: Normalisation,
    /// Physics parameters (SPEC §3).
    pub physics: PhysicsParams,
    /// The asset model's nominal charge pressure, bar gauge at 20 °C.
    pub nominal_bar: f64,
    /// Health thresholds (SPEC §6).
    #[serde(default)]
    pub health: HealthConfig,
    /// The network file.
    pub onnx: OnnxInfo,
    /// Training provenance (campaign digest, split, seed, metrics …), kept verbatim.
    #[serde(default)]
    pub provenance: serde_json::Value,
}

/// A loaded, checked bundle with its network ready to run. Cheap to share
/// (`Arc`) between the estimators of many assets.
#[derive(Debug)]
pub struct Bundle {
    /// The bundle directory.
    pub dir: PathBuf,
    /// `twin.json`.
    pub twin: TwinJson,
    /// Parsed groups of the permutation.
    pub groups: Vec<Group>,
    network: Network,
}

#[derive(Debug)]
struct Network {
    plan: Arc<TypedRunnableModel>,
    f32_io: bool,
}

impl Bundle {
    /// Loads and checks `dir/twin.json` and the network it names.
    pub fn load(dir: impl AsRef<Path>) -> Result<Self, BundleError> {
        let dir = dir.as_ref().to_path_buf();
        let json_path = dir.join(TWIN_JSON);
        let text = std::fs::read_to_string(&json_path).map_err(|source| BundleError::Io {
            path: json_path.clone(),
            source,
        })?;
        let twin: TwinJson = serde_json::from_str(&text).map_err(|e| BundleError::Json {
            path: json_path.clone(),
            message: e.to_string(),
        })?;
        let groups = check_twin(&twin).map_err(|message| BundleError::Inconsistent {
            path: json_path.clone(),
            message,
        })?;
        let onnx_path = dir.join(&twin.onnx.file);
        let bytes = std::fs::read(&onnx_path).map_err(|source| BundleError::Io {
            path: onnx_path.clone(),
            source,
        })?;
        if let Some(expected) = &twin.onnx.sha256 {
            let found = hex_digest(&bytes);
            if !found.eq_ignore_ascii_case(expected) {
                return Err(BundleError::Inconsistent {
                    path: onnx_path,
                    message: format!(
                        "sha256 {found} does not match twin.json onnx.sha256 {expected}"
                    ),
                });
            }
        }
        let network = Network::load(&bytes, &twin, &onnx_path)?;
        Ok(Self {
            dir,
            twin,
            groups,
            network,
        })
    }

    /// Number of input columns.
    #[must_use]
    pub fn n_inputs(&self) -> usize {
        self.twin.permutation.columns.len()
    }

    /// The physics parameters.
    #[must_use]
    pub fn physics(&self) -> &PhysicsParams {
        &self.twin.physics
    }

    /// Charge pressure (bar) for raw (un-normalised) feature rows, row-major
    /// `[n_rows × n_inputs]`.
    pub fn predict(&self, rows: &[f64]) -> Result<Vec<f64>, BundleError> {
        let k = self.n_inputs();
        if k == 0 || rows.len() % k != 0 {
            return Err(BundleError::Width {
                expected: k,
                got: rows.len() % k.max(1),
            });
        }
        let n = rows.len() / k;
        let norm = &self.twin.normalisation;
        let x: Vec<f64> = rows
            .chunks_exact(k)
            .flat_map(|r| {
                r.iter()
                    .zip(norm.mean.iter().zip(&norm.std))
                    .map(|(x, (m, s))| (x - m) / s)
            })
            .collect();
        self.network.run(&x, n, k, &self.dir)
    }

    /// Charge pressure for one raw feature row.
    pub fn predict_one(&self, row: &[f64]) -> Result<f64, BundleError> {
        if row.len() != self.n_inputs() {
            return Err(BundleError::Width {
                expected: self.n_inputs(),
                got: row.len(),
            });
        }
        Ok(self.predict(row)?[0])
    }
}

impl Network {
    fn load(bytes: &[u8], twin: &TwinJson, path: &Path) -> Result<Self, BundleError> {
        let onnx_err = |e: &dyn std::fmt::Display| BundleError::Onnx {
            path: path.to_path_buf(),
            message: format!("{e:#}"),
        };
        let f32_io = match twin.onnx.dtype.as_str() {
            "float64" => false,
            "float32" => true,
            other => {
                return Err(BundleError::Inconsistent {
                    path: path.to_path_buf(),
                    message: format!("onnx.dtype must be float64 or float32, found {other:?}"),
                })
            }
        };
        let k = twin.permutation.columns.len();
        let fact: InferenceFact = if f32_io {
            f32::fact([1, k]).into()
        } else {
            f64::fact([1, k]).into()
        };
        let plan = tract_onnx::onnx()
            .model_for_read(&mut &bytes[..])
            .and_then(|m| m.with_input_fact(0, fact))
            .and_then(InferenceModelExt::into_optimized)
            .and_then(IntoRunnable::into_runnable)
            .map_err(|e| onnx_err(&e))?;
        let net = Self { plan, f32_io };
        // A probe run checks the output shape now, not at the first tick.
        let probe = net.run(&vec![0.0; k], 1, k, path)?;
        if probe.len() != 1 {
            return Err(BundleError::Inconsistent {
                path: path.to_path_buf(),
                message: format!(
                    "network output has {} values per row, expected 1",
                    probe.len()
                ),
            });
        }
        Ok(net)
    }

    fn run(&self, x: &[f64], n: usize, k: usize, path: &Path) -> Result<Vec<f64>, BundleError> {
        let err = |e: &dyn std::fmt::Display| BundleError::Onnx {
            path: path.to_path_buf(),
            message: format!("{e:#}"),
        };
        let mut out = Vec::with_capacity(n);
        for row in x.chunks_exact(k) {
            let input = if self.f32_io {
                let r: Vec<f32> = row.iter().map(|&v| v as f32).collect();
                Tensor::from_shape(&[1, k], &r)
            } else {
                Tensor::from_shape(&[1, k], row)
            }
            .map_err(|e| err(&e))?;
            let result = self.plan.run(tvec!(input.into())).map_err(|e| err(&e))?;
            let value = if self.f32_io {
                result[0]
                    .to_plain_array_view::<f32>()
                    .map(|s| s.iter().map(|&v| f64::from(v)).collect::<Vec<_>>())
            } else {
                result[0]
                    .to_plain_array_view::<f64>()
                    .map(|s| s.iter().copied().collect())
            }
            .map_err(|e| err(&e))?;
            out.extend(value);
        }
        Ok(out)
    }
}

fn hex_digest(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    Sha256::digest(bytes)
        .iter()
        .fold(String::with_capacity(64), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

/// Checks the JSON part for consistency; returns the parsed groups.
fn check_twin(twin: &TwinJson) -> Result<Vec<Group>, String> {
    if twin.format != BUNDLE_FORMAT {
        return Err(format!("format {:?} is not {BUNDLE_FORMAT:?}", twin.format));
    }
    let perm = &twin.permutation;
    if perm.groups.is_empty() {
        return Err("permutation.groups is empty".into());
    }
    let groups = perm
        .groups
        .iter()
        .map(|g| Group::from_name(g).map_err(|e| format!("permutation.groups: {e}")))
        .collect::<Result<Vec<_>, _>>()?;
    let expected = column_names(&groups);
    if perm.columns != expected {
        return Err(format!(
            "permutation.columns {:?} do not match groups {:?} (expected {expected:?})",
            perm.columns, perm.groups
        ));
    }
    let k = perm.columns.len();
    let norm = &twin.normalisation;
    if norm.mean.len() != k || norm.std.len() != k {
        return Err(format!(
            "normalisation has {} means and {} stds for {k} columns",
            norm.mean.len(),
            norm.std.len()
        ));
    }
    if let Some(i) = norm.mean.iter().position(|m| !m.is_finite()) {
        return Err(format!(
            "normalisation.mean[{i}] ({}) is not finite",
            perm.columns[i]
        ));
    }
    if let Some(i) = norm.std.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(format!(
            "normalisation.std[{i}] ({}) = {} must be finite and > 0",
            perm.columns[i], norm.std[i]
        ));
    }
    twin.physics
        .validate()
        .map_err(|e| format!("physics: {e}"))?;
    if !(twin.nominal_bar.is_finite() && twin.nominal_bar > 0.0) {
        return Err(format!("nominal_bar = {} must be > 0", twin.nominal_bar));
    }
    twin.health.validate()?;
    if twin.health.warn_bar > twin.nominal_bar {
        return Err(format!(
            "health.warn_bar ({}) is above nominal_bar ({})",
            twin.health.warn_bar, twin.nominal_bar
        ));
    }
    Ok(groups)
}
