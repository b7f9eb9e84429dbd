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
//!
//! # The hot path: a float32 MLP
//!
//! A plain MLP graph (`MatMul`/`Add`/`Relu` chain, the shape `train/model.py`
//! writes) is read from the ONNX initializers once at load and evaluated in
//! float32 with SIMD: each layer's weights are stored once, contiguous and
//! zero-padded to [`PAD`] outputs (`[n_in × pad]`, one row per input), and a
//! row is pushed through with broadcast-FMA kernels written against `pulp`'s
//! safe SIMD API, which picks AVX2+FMA (or NEON, or scalar code) at run time.
//! A tick's row runs on stack buffers: no allocation. Its agreement with the
//! float64 graph (onnxruntime, tract and the float64 dense path agree to
//! 1e-9) is [`MLP_F32_PARITY_BAR`], checked on probe rows at load; a network
//! that misses it runs in float64 instead.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tract_onnx::prelude::{
    tvec, DatumExt, Framework, InferenceFact, InferenceModelExt, IntoRunnable, Tensor,
    TypedRunnableModel,
};

use crate::features::{column_names, Group, N_COLUMNS};
use crate::params::PhysicsParams;

/// The `format` value this code reads and writes.
pub const BUNDLE_FORMAT: &str = "shocktwin-bundle/1";
/// Name of the JSON part of a bundle.
pub const TWIN_JSON: &str = "twin.json";

/// Agreement of the float32 network (what [`Bundle::predict`],
/// [`Bundle::predict_one`] and so the estimator run) with the bundle's ONNX
/// evaluated in float64 by onnxruntime (or tract, or
/// [`Bundle::predict_f64`], which agree with it to 1e-9):
/// `|p32 − p64| ≤ MLP_F32_PARITY_BAR · (1 + |p64|)`, bar — numpy's
/// `assert_allclose(p32, p64, rtol=MLP_F32_PARITY_BAR, atol=MLP_F32_PARITY_BAR)`.
/// See [`mlp_f32_agrees`].
pub const MLP_F32_PARITY_BAR: f64 = 1e-4;

/// Whether a float32 network output agrees with the float64 reference
/// within [`MLP_F32_PARITY_BAR`] (NaN agrees with NaN only).
#[must_use]
pub fn mlp_f32_agrees(p32: f64, p64: f64) -> bool {
    (p32.is_nan() && p64.is_nan()) || (p32 - p64).abs() <= MLP_F32_PARITY_BAR * (1.0 + p64.abs())
}

/// Errors of loading or running a bundle; each names the file and the part.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    /// A file of the bundle cannot be read.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error (in the message, not a `source`: shown as a
        /// chain it was said twice, "No such file … (os error 2): No such
        /// file … (os error 2)").
        error: std::io::Error,
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
    /// Input values that are not whole rows of the permutation's width.
    #[error("bundle expects rows of {expected} input columns, got {got} values")]
    Width {
        /// Number of columns of the permutation.
        expected: usize,
        /// Number of values given.
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

/// The 95 % interval of a bundle without the charge observer (SPEC §2a):
/// the 1 s average ± the 95th percentile of the 1 s average's absolute error
/// on runs kept out of training (their ticks that have one): the bundle's
/// own estimator on the runs `train.train --split runs` kept out, or, for
/// the study's bundles trained on every run, its folds' networks each on the
/// runs it was not trained on (`method`). Empirical: it holds as far as
/// those runs are like the ones the bundle will read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutInterval {
    /// Half the interval's width, bar.
    pub half_width_bar: f64,
    /// The central coverage it was sized for (0.95).
    pub level: f64,
    /// The held-out runs it was measured on.
    pub runs: Vec<String>,
    /// Their ticks with a 1 s average, the errors it was taken over.
    pub ticks: u64,
    /// Whose errors: `held-out` (the bundle itself, `train.train`) or
    /// `cross-validated` (the study's folds, for a bundle trained on all
    /// runs); absent in bundles written before the sixty-ninth session.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
}

/// [`HeldOutInterval::method`]'s values (`train.model`'s `HELD_OUT`,
/// `CROSS_VALIDATED`).
pub const HELD_OUT_METHODS: [&str; 2] = ["held-out", "cross-validated"];

/// The provenance key under which `train.train` lists the `excitation`
/// metadata of the runs a bundle's network was trained on, distinct and
/// sorted ([`Bundle::untrained_excitation`]).
pub const TRAINED_EXCITATIONS: &str = "trained_excitations";

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
    pub health: HealthConfig,
    /// The network file.
    pub onnx: OnnxInfo,
    /// The interval of a bundle without the charge observer (`None`: none,
    /// as for bundles trained on every run or before this field).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub interval: Option<HeldOutInterval>,
    /// Training provenance, kept verbatim: an object holding at least
    /// [`PROVENANCE_KEYS`] (SPEC §5; a value may be `null` where there is
    /// none, as for a fixture's random weights).
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

impl Bundle {
    /// Loads and checks `dir/twin.json` and the network it names.
    pub fn load(dir: impl AsRef<Path>) -> Result<Self, BundleError> {
        let dir = dir.as_ref().to_path_buf();
        let json_path = dir.join(TWIN_JSON);
        let text = std::fs::read_to_string(&json_path).map_err(|error| BundleError::Io {
            path: json_path.clone(),
            error,
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
        let bytes = std::fs::read(&onnx_path).map_err(|error| BundleError::Io {
            path: onnx_path.clone(),
            error,
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

    /// The `excitation` metadata (SPEC §2) of the runs its network was
    /// trained on, as `train.train` records them in the provenance
    /// ([`TRAINED_EXCITATIONS`]); `None` for a bundle that does not say.
    #[must_use]
    pub fn trained_excitations(&self) -> Option<Vec<&str>> {
        self.twin
            .provenance
            .get(TRAINED_EXCITATIONS)?
            .as_array()?
            .iter()
            .map(serde_json::Value::as_str)
            .collect()
    }

    /// Why this bundle's estimate of a run with metadata `meta` is an
    /// extrapolation: the bundle reads no charge observer (which says so
    /// itself, per reversal), records the excitations its network was
    /// trained on, and the run's `excitation` is none of them (a road run, a
    /// sine at another frequency or stroke). `None` when nothing says so,
    /// e.g. a log without `excitation` (a seventieth-session analyst: such a
    /// bundle answered a road run without a word).
    #[must_use]
    pub fn untrained_excitation(&self, meta: &crate::log::RunMetadata) -> Option<String> {
        const SHOWN: usize = 6;
        if self.groups.contains(&Group::Observer) {
            return None;
        }
        let run = meta.excitation.as_deref()?.trim();
        if run.is_empty() {
            return None;
        }
        let trained = self.trained_excitations()?;
        if trained.is_empty() || trained.iter().any(|t| t.trim() == run) {
            return None;
        }
        let mut list = trained
            .iter()
            .take(SHOWN)
            .map(|t| format!("`{t}`"))
            .collect::<Vec<_>>()
            .join(", ");
        if trained.len() > SHOWN {
            list = format!("{list} … ({} in all)", trained.len());
        }
        let interval = if self.twin.interval.is_some() {
            ", which the bundle's interval (from held-out runs) may not cover"
        } else {
            ""
        };
        Some(format!(
            "the run's excitation `{run}` is none of those the bundle's network was trained on \
             ({list}): its estimate is an extrapolation{interval}"
        ))
    }

    /// The physics parameters.
    #[must_use]
    pub fn physics(&self) -> &PhysicsParams {
        &self.twin.physics
    }

    /// Charge pressure (bar) for raw (un-normalised) feature rows, row-major
    /// `[n_rows × n_inputs]`: `(x − mean) / std`, then the network (the
    /// float32 path when the graph is a plain MLP: each row exactly as
    /// [`predict_one`](Self::predict_one) gives it).
    pub fn predict(&self, rows: &[f64]) -> Result<Vec<f64>, BundleError> {
        let x = self.normalise(rows)?;
        let k = self.n_inputs();
        self.network.run(&x, x.len() / k, k, &self.onnx_path())
    }

    /// [`predict`](Self::predict) in float64 throughout: the float64 dense
    /// path (checked against tract to 1e-9 at load), or tract's plan. What
    /// the float32 path is held to within [`MLP_F32_PARITY_BAR`].
    pub fn predict_f64(&self, rows: &[f64]) -> Result<Vec<f64>, BundleError> {
        let x = self.normalise(rows)?;
        let k = self.n_inputs();
        match &self.network.dense {
            Some(dense) => {
                let mut scratch = Vec::new();
                Ok(x.chunks_exact(k)
                    .map(|row| dense.forward_one(row, &mut scratch))
                    .collect())
            }
            None => self
                .network
                .run_tract(&x, x.len() / k, k, &self.onnx_path()),
        }
    }

    /// [`predict`](Self::predict) through tract-onnx's plan, whatever the
    /// backend (the reference the dense path is checked against at load).
    pub fn predict_reference(&self, rows: &[f64]) -> Result<Vec<f64>, BundleError> {
        let x = self.normalise(rows)?;
        let k = self.n_inputs();
        self.network
            .run_tract(&x, x.len() / k, k, &self.onnx_path())
    }

    /// Charge pressure for one raw feature row (no allocation on the dense
    /// paths for layers up to [`STACK_WIDTH`] wide).
    pub fn predict_one(&self, row: &[f64]) -> Result<f64, BundleError> {
        let k = self.n_inputs();
        if row.len() != k {
            return Err(BundleError::Width {
                expected: k,
                got: row.len(),
            });
        }
        let norm = &self.twin.normalisation;
        let mut x = [0.0; N_COLUMNS];
        for (xi, (v, (m, s))) in x
            .iter_mut()
            .zip(row.iter().zip(norm.mean.iter().zip(&norm.std)))
        {
            *xi = (v - m) / s;
        }
        match (&self.network.fast, &self.network.dense) {
            (Some(fast), _) => Ok(fast.forward(&x[..k])),
            (None, Some(dense)) => Ok(dense.forward_one(&x[..k], &mut Vec::new())),
            (None, None) => Ok(self.network.run_tract(&x[..k], 1, k, &self.onnx_path())?[0]),
        }
    }

    /// Which evaluator runs the network: `"dense"` (a plain MLP read from
    /// the ONNX initializers, checked against tract at load; float32 with
    /// SIMD, see [`precision`](Self::precision)) or `"tract"` (tract-onnx's
    /// optimised plan, any other graph).
    #[must_use]
    pub fn backend(&self) -> &'static str {
        if self.network.dense.is_some() {
            "dense"
        } else {
            "tract"
        }
    }

    /// The precision [`predict`](Self::predict) runs in: `"float32"` (the
    /// dense path within [`MLP_F32_PARITY_BAR`] of float64) or `"float64"`.
    #[must_use]
    pub fn precision(&self) -> &'static str {
        if self.network.fast.is_some() {
            "float32"
        } else {
            "float64"
        }
    }

    fn onnx_path(&self) -> PathBuf {
        self.dir.join(&self.twin.onnx.file)
    }

    /// Checks the width and normalises row-major rows.
    fn normalise(&self, rows: &[f64]) -> Result<Vec<f64>, BundleError> {
        let k = self.n_inputs();
        if rows.len() % k != 0 {
            return Err(BundleError::Width {
                expected: k,
                got: rows.len(),
            });
        }
        let norm = &self.twin.normalisation;
        Ok(rows
            .chunks_exact(k)
            .flat_map(|r| {
                r.iter()
                    .zip(norm.mean.iter().zip(&norm.std))
                    .map(|(x, (m, s))| (x - m) / s)
            })
            .collect())
    }
}

/// The network: tract-onnx's plan (the reference), and, when the graph is a
/// plain float64 MLP (`MatMul`/`Add`/`Relu`, with `Cast`/`Identity`/`Reshape`
/// that change nothing), the same layers evaluated directly from the ONNX
/// initializers that tract-onnx parsed.
#[derive(Debug)]
struct Network {
    plan: Arc<TypedRunnableModel>,
    f32_io: bool,
    dense: Option<DenseMlp>,
    /// The dense MLP in float32 (when it agrees with tract within
    /// [`MLP_F32_PARITY_BAR`]): what runs.
    fast: Option<MlpF32>,
}

/// One dense layer `y = x W + b` (`W` row-major `[n_in, n_out]`, as in ONNX
/// `MatMul`), optionally followed by `ReLU`.
#[derive(Debug, Clone)]
struct Dense {
    n_in: usize,
    n_out: usize,
    w: Vec<f64>,
    b: Vec<f64>,
    relu: bool,
}

/// A plain MLP read from the ONNX graph.
#[derive(Debug, Clone)]
struct DenseMlp {
    layers: Vec<Dense>,
    max_width: usize,
}

/// Layers up to this wide (float32: padded) run on stack buffers.
pub const STACK_WIDTH: usize = 256;

/// Outputs evaluated together in registers by [`Dense::forward`].
const LANES: usize = 16;

impl Dense {
    /// `out = x W + b` (then `ReLU`). Sums over the inputs in order for each
    /// output, `LANES` outputs at a time (vectorises without reassociation).
    fn forward(&self, x: &[f64], out: &mut [f64]) {
        let (n_in, n_out) = (self.n_in, self.n_out);
        let full = n_out - n_out % LANES;
        for (j0, out_block) in (0..full)
            .step_by(LANES)
            .zip(out[..full].chunks_exact_mut(LANES))
        {
            let mut acc = [0.0; LANES];
            acc.copy_from_slice(&self.b[j0..j0 + LANES]);
            for (&xi, w_row) in x[..n_in].iter().zip(self.w.chunks_exact(n_out)) {
                for (a, &w) in acc.iter_mut().zip(&w_row[j0..j0 + LANES]) {
                    *a += xi * w;
                }
            }
            out_block.copy_from_slice(&acc);
        }
        for (j, o) in out.iter_mut().enumerate().take(n_out).skip(full) {
            let mut acc = self.b[j];
            for (&xi, w_row) in x[..n_in].iter().zip(self.w.chunks_exact(n_out)) {
                acc += xi * w_row[j];
            }
            *o = acc;
        }
        if self.relu {
            // ONNX Relu: max(x, 0), NaN stays NaN.
            for v in &mut out[..n_out] {
                if *v < 0.0 {
                    *v = 0.0;
                }
            }
        }
    }
}

impl DenseMlp {
    /// The network's single output for one normalised row.
    fn forward_one(&self, x: &[f64], scratch: &mut Vec<f64>) -> f64 {
        let w = self.max_width;
        let mut stack = [0.0; 2 * STACK_WIDTH];
        let buf: &mut [f64] = if w <= STACK_WIDTH {
            &mut stack[..2 * w]
        } else {
            scratch.clear();
            scratch.resize(2 * w, 0.0);
            scratch
        };
        let (a, b) = buf.split_at_mut(w);
        a[..x.len()].copy_from_slice(x);
        let (mut cur, mut next) = (a, b);
        for layer in &self.layers {
            layer.forward(&cur[..layer.n_in], &mut next[..layer.n_out]);
            std::mem::swap(&mut cur, &mut next);
        }
        cur[0]
    }

    /// Reads a plain MLP from the graph, or says why it is not one (the
    /// caller then runs tract's plan).
    fn from_proto(
        proto: &tract_onnx::pb::ModelProto,
        onnx: &tract_onnx::Onnx,
        k: usize,
    ) -> Result<Self, String> {
        const DOUBLE: i64 = 11;
        let graph = proto.graph.as_ref().ok_or("no graph")?;
        let mut consts: std::collections::HashMap<&str, (Vec<usize>, Vec<f64>)> =
            std::collections::HashMap::new();
        for t in &graph.initializer {
            let tensor = tract_onnx::tensor::load_tensor(&*onnx.provider, t, None)
                .map_err(|e| format!("initializer {}: {e}", t.name))?;
            let shape = tensor.shape().to_vec();
            let values = tensor
                .cast_to::<f64>()
                .and_then(|c| {
                    c.to_plain_array_view::<f64>()
                        .map(|v| v.iter().copied().collect())
                })
                .map_err(|e| format!("initializer {}: {e}", t.name))?;
            consts.insert(t.name.as_str(), (shape, values));
        }
        let inputs: Vec<&str> = graph
            .input
            .iter()
            .map(|v| v.name.as_str())
            .filter(|n| !consts.contains_key(n))
            .collect();
        let [input] = inputs[..] else {
            return Err(format!("{} graph inputs", inputs.len()));
        };
        let mut current = input.to_owned();
        let mut width = k;
        let mut layers: Vec<Dense> = Vec::new();
        // Whether the last layer may still take its bias / ReLU.
        let (mut open_bias, mut open_relu) = (false, false);
        for node in &graph.node {
            let data: Vec<&str> = node
                .input
                .iter()
                .map(String::as_str)
                .filter(|n| !consts.contains_key(n))
                .collect();
            let weights: Vec<&(Vec<usize>, Vec<f64>)> = node
                .input
                .iter()
                .filter_map(|n| consts.get(n.as_str()))
                .collect();
            if data != [current.as_str()] || node.output.len() != 1 {
                return Err(format!(
                    "node {} ({}) is not on a chain",
                    node.name, node.op_type
                ));
            }
            match (node.op_type.as_str(), &weights[..]) {
                ("Identity", []) => {}
                ("Cast", []) => {
                    let to = node.attribute.iter().find(|a| a.name == "to").map(|a| a.i);
                    if to != Some(DOUBLE) {
                        return Err(format!("Cast to {to:?}"));
                    }
                }
                ("MatMul", [(shape, w)]) if node.input[1] != current => {
                    if shape[..] != [width, shape.get(1).copied().unwrap_or(0)] {
                        return Err(format!("MatMul weight {shape:?} for width {width}"));
                    }
                    layers.push(Dense {
                        n_in: width,
                        n_out: shape[1],
                        w: w.clone(),
                        b: vec![0.0; shape[1]],
                        relu: false,
                    });
                    width = shape[1];
                    (open_bias, open_relu) = (true, true);
                }
                ("Add", [(_, b)]) if open_bias && b.len() == width => {
                    if let Some(last) = layers.last_mut() {
                        last.b.clone_from(b);
                    }
                    open_bias = false;
                }
                ("Relu", []) if open_relu => {
                    if let Some(last) = layers.last_mut() {
                        last.relu = true;
                    }
                    (open_bias, open_relu) = (false, false);
                }
                ("Reshape", [(_, shape)])
                    if width == 1 && matches!(shape[..], [-1.0 | 0.0, 1.0] | [1.0]) => {}
                (op, _) => return Err(format!("operator {op} not supported by the dense path")),
            }
            current.clone_from(&node.output[0]);
        }
        let outputs: Vec<&str> = graph.output.iter().map(|v| v.name.as_str()).collect();
        if outputs != [current.as_str()] || width != 1 || layers.is_empty() {
            return Err("graph output is not the end of the chain".into());
        }
        let max_width = layers
            .iter()
            .map(|l| l.n_in.max(l.n_out))
            .max()
            .unwrap_or(1);
        Ok(Self { layers, max_width })
    }
}

/// Outputs of a float32 layer are padded to a multiple of this (zeros): a
/// whole number of [`F32_BLOCK`]-register blocks for SIMD widths up to 8
/// lanes.
const PAD: usize = 64;

/// SIMD registers of outputs accumulated together by [`MlpF32`] (8 × 8
/// lanes = a 64-wide layer in registers on AVX2: 8 independent FMA chains).
const F32_BLOCK: usize = 8;

/// One float32 layer: `y = x W + b` (then `ReLU`), `W` stored row-major
/// `[n_in × pad]` (one contiguous, zero-padded row of outputs per input),
/// or, for a single output, as one zero-padded column of `pad_in` values
/// (a dot product).
#[derive(Debug, Clone)]
struct LayerF32 {
    n_in: usize,
    /// `n_out` rounded up to [`PAD`].
    pad: usize,
    /// `n_in` rounded up to [`PAD`] (the width of the input buffer).
    pad_in: usize,
    w: Vec<f32>,
    b: Vec<f32>,
    relu: bool,
    /// `n_out == 1`: a dot product.
    dot: bool,
}

/// [`DenseMlp`] in float32, laid out for the SIMD kernels once at load.
#[derive(Debug, Clone)]
struct MlpF32 {
    layers: Vec<LayerF32>,
    /// The widest padded buffer.
    max_pad: usize,
    /// The instruction set detected at load (AVX2+FMA, NEON, … or scalar).
    arch: pulp::Arch,
}

const fn round_up(n: usize) -> usize {
    n.div_ceil(PAD) * PAD
}

impl MlpF32 {
    fn new(mlp: &DenseMlp) -> Self {
        let layers: Vec<LayerF32> = mlp
            .layers
            .iter()
            .map(|l| {
                let (pad, pad_in) = (round_up(l.n_out), round_up(l.n_in));
                let dot = l.n_out == 1;
                let mut w = vec![0.0_f32; if dot { pad_in } else { l.n_in * pad }];
                if dot {
                    for (wi, &v) in w.iter_mut().zip(&l.w) {
                        *wi = v as f32;
                    }
                } else {
                    for (dst, src) in w.chunks_exact_mut(pad).zip(l.w.chunks_exact(l.n_out)) {
                        for (d, &v) in dst.iter_mut().zip(src) {
                            *d = v as f32;
                        }
                    }
                }
                let mut b = vec![0.0_f32; pad];
                for (bi, &v) in b.iter_mut().zip(&l.b) {
                    *bi = v as f32;
                }
                LayerF32 {
                    n_in: l.n_in,
                    pad,
                    pad_in,
                    w,
                    b,
                    relu: l.relu,
                    dot,
                }
            })
            .collect();
        let max_pad = layers
            .iter()
            .map(|l| l.pad.max(l.pad_in))
            .max()
            .unwrap_or(PAD);
        Self {
            layers,
            max_pad,
            arch: pulp::Arch::new(),
        }
    }

    /// The network's single output for one normalised float64 row (cast to
    /// float32; the output widened back). A NaN input gives NaN.
    fn forward(&self, x: &[f64]) -> f64 {
        if x.iter().any(|v| v.is_nan()) {
            return f64::NAN;
        }
        if self.max_pad <= STACK_WIDTH {
            let mut a = [0.0_f32; STACK_WIDTH];
            let mut b = [0.0_f32; STACK_WIDTH];
            self.forward_in(x, &mut a, &mut b)
        } else {
            let (mut a, mut b) = (vec![0.0_f32; self.max_pad], vec![0.0_f32; self.max_pad]);
            self.forward_in(x, &mut a, &mut b)
        }
    }

    /// `a` and `b`: zeroed buffers of at least `max_pad` values.
    fn forward_in(&self, x: &[f64], a: &mut [f32], b: &mut [f32]) -> f64 {
        for (ai, &v) in a.iter_mut().zip(x) {
            *ai = v as f32;
        }
        f64::from(self.arch.dispatch(Forward {
            layers: &self.layers,
            a,
            b,
        }))
    }
}

/// One row through every layer, generic over the SIMD instruction set.
struct Forward<'a> {
    layers: &'a [LayerF32],
    a: &'a mut [f32],
    b: &'a mut [f32],
}

impl pulp::WithSimd for Forward<'_> {
    type Output = f32;

    #[allow(clippy::inline_always)] // pulp: the body must inline into its target-feature dispatch
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> f32 {
        let (mut cur, mut next) = (self.a, self.b);
        for layer in self.layers {
            if layer.dot {
                let y = dot_f32(simd, &cur[..layer.pad_in], &layer.w) + layer.b[0];
                next[..layer.pad].fill(0.0);
                next[0] = if layer.relu && y < 0.0 { 0.0 } else { y };
            } else {
                layer_f32(simd, layer, &cur[..layer.n_in], &mut next[..layer.pad]);
            }
            std::mem::swap(&mut cur, &mut next);
        }
        cur[0]
    }
}

/// `out = x W + b` (then `ReLU`) for one row: per block of [`F32_BLOCK`]
/// output registers, each input broadcast and FMA'd with its contiguous
/// weight row into the accumulators (no horizontal sums).
#[allow(clippy::inline_always)] // pulp: inlined into the SIMD dispatch of `with_simd`
#[inline(always)]
fn layer_f32<S: pulp::Simd>(simd: S, layer: &LayerF32, x: &[f32], out: &mut [f32]) {
    let (out_v, _) = S::as_mut_simd_f32s(out);
    let (bias_v, _) = S::as_simd_f32s(&layer.b);
    let zero = simd.splat_f32s(0.0);
    let mut v0 = 0;
    for (out_blk, bias_blk) in out_v
        .chunks_exact_mut(F32_BLOCK)
        .zip(bias_v.chunks_exact(F32_BLOCK))
    {
        let mut acc = [zero; F32_BLOCK];
        acc.copy_from_slice(bias_blk);
        for (&xi, row) in x.iter().zip(layer.w.chunks_exact(layer.pad)) {
            let (row_v, _) = S::as_simd_f32s(row);
            let w = &row_v[v0..v0 + F32_BLOCK];
            let xv = simd.splat_f32s(xi);
            for (a, &wv) in acc.iter_mut().zip(w) {
                *a = simd.mul_add_e_f32s(xv, wv, *a);
            }
        }
        if layer.relu {
            // max(0, a): a NaN stays NaN on x86 (the second operand is
            // returned); inputs with a NaN never get here (see `forward`).
            for a in &mut acc {
                *a = simd.max_f32s(zero, *a);
            }
        }
        out_blk.copy_from_slice(&acc);
        v0 += F32_BLOCK;
    }
    // Registers left over when the padded width is not a whole number of
    // blocks (SIMD wider than 8 lanes): one at a time.
    let rest = out_v.len() - v0;
    for j in 0..rest {
        let mut acc = bias_v[v0 + j];
        for (&xi, row) in x.iter().zip(layer.w.chunks_exact(layer.pad)) {
            let (row_v, _) = S::as_simd_f32s(row);
            acc = simd.mul_add_e_f32s(simd.splat_f32s(xi), row_v[v0 + j], acc);
        }
        if layer.relu {
            acc = simd.max_f32s(zero, acc);
        }
        out_v[v0 + j] = acc;
    }
}

/// `x · w` over equal-length, zero-padded slices (four accumulators).
#[allow(clippy::inline_always)] // pulp: inlined into the SIMD dispatch of `with_simd`
#[inline(always)]
fn dot_f32<S: pulp::Simd>(simd: S, x: &[f32], w: &[f32]) -> f32 {
    let (xv, xt) = S::as_simd_f32s(x);
    let (wv, wt) = S::as_simd_f32s(w);
    let zero = simd.splat_f32s(0.0);
    let mut acc = [zero; 4];
    let (x4, x_rest) = xv.split_at(xv.len() - xv.len() % 4);
    let (w4, w_rest) = wv.split_at(x4.len());
    for (xs, ws) in x4.chunks_exact(4).zip(w4.chunks_exact(4)) {
        for ((a, &xi), &wi) in acc.iter_mut().zip(xs).zip(ws) {
            *a = simd.mul_add_e_f32s(xi, wi, *a);
        }
    }
    for (&xi, &wi) in x_rest.iter().zip(w_rest) {
        acc[0] = simd.mul_add_e_f32s(xi, wi, acc[0]);
    }
    let sum = simd.add_f32s(simd.add_f32s(acc[0], acc[1]), simd.add_f32s(acc[2], acc[3]));
    simd.reduce_sum_f32s(sum) + xt.iter().zip(wt).map(|(a, b)| a * b).sum::<f32>()
}

impl Network {
    fn load(bytes: &[u8], twin: &TwinJson, path: &Path) -> Result<Self, BundleError> {
        let onnx_err = |e: &dyn std::fmt::Display| BundleError::Onnx {
            path: path.to_path_buf(),
            message: format!("{e:#}"),
        };
        let inconsistent = |message: String| BundleError::Inconsistent {
            path: path.to_path_buf(),
            message,
        };
        let f32_io = match twin.onnx.dtype.as_str() {
            "float64" => false,
            "float32" => true,
            other => {
                return Err(inconsistent(format!(
                    "onnx.dtype must be float64 or float32, found {other:?}"
                )))
            }
        };
        let k = twin.permutation.columns.len();
        let onnx = tract_onnx::onnx();
        let proto = onnx
            .proto_model_for_read(&mut &bytes[..])
            .map_err(|e| onnx_err(&e))?;
        check_io_names(&proto, twin).map_err(inconsistent)?;
        let fact: InferenceFact = if f32_io {
            f32::fact([1, k]).into()
        } else {
            f64::fact([1, k]).into()
        };
        let plan = onnx
            .model_for_proto_model(&proto)
            .and_then(|m| m.with_input_fact(0, fact))
            .and_then(InferenceModelExt::into_optimized)
            .and_then(IntoRunnable::into_runnable)
            .map_err(|e| onnx_err(&e))?;
        let mut net = Self {
            plan,
            f32_io,
            dense: None,
            fast: None,
        };
        // A probe run checks the output shape now, not at the first tick.
        let probe = net.run_tract(&vec![0.0; k], 1, k, path)?;
        if probe.len() != 1 {
            return Err(inconsistent(format!(
                "network output has {} values per row, expected 1",
                probe.len()
            )));
        }
        if !f32_io {
            // The dense path is used only if it agrees with tract on probe rows.
            if let Ok(dense) = DenseMlp::from_proto(&proto, &onnx, k) {
                let rows = probe_rows(k);
                let reference = net.run_tract(&rows, rows.len() / k, k, path)?;
                let mut scratch = Vec::new();
                let agrees = rows.chunks_exact(k).zip(&reference).all(|(row, r)| {
                    let d = dense.forward_one(row, &mut scratch);
                    (d - r).abs() <= 1e-9 * r.abs().max(1.0)
                });
                if agrees {
                    // The float32 copy runs if it is within the parity bar
                    // of tract on the same probe rows.
                    let fast = MlpF32::new(&dense);
                    let fast_agrees = rows
                        .chunks_exact(k)
                        .zip(&reference)
                        .all(|(row, &r)| mlp_f32_agrees(fast.forward(row), r));
                    if fast_agrees {
                        net.fast = Some(fast);
                    }
                    net.dense = Some(dense);
                }
            }
        }
        Ok(net)
    }

    fn run(&self, x: &[f64], n: usize, k: usize, path: &Path) -> Result<Vec<f64>, BundleError> {
        if let Some(fast) = &self.fast {
            return Ok(x.chunks_exact(k).map(|row| fast.forward(row)).collect());
        }
        match &self.dense {
            Some(dense) => {
                let mut scratch = Vec::new();
                Ok(x.chunks_exact(k)
                    .map(|row| dense.forward_one(row, &mut scratch))
                    .collect())
            }
            None => self.run_tract(x, n, k, path),
        }
    }

    fn run_tract(
        &self,
        x: &[f64],
        n: usize,
        k: usize,
        path: &Path,
    ) -> Result<Vec<f64>, BundleError> {
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

/// Deterministic normalised probe rows in [-3, 3] (and a zero row).
fn probe_rows(k: usize) -> Vec<f64> {
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut rows = vec![0.0; k];
    for _ in 0..16 * k {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        rows.push(((state >> 11) as f64 / (1u64 << 53) as f64) * 6.0 - 3.0);
    }
    rows
}

/// The graph's input and output names must be those `twin.json` gives.
fn check_io_names(proto: &tract_onnx::pb::ModelProto, twin: &TwinJson) -> Result<(), String> {
    let graph = proto.graph.as_ref().ok_or("the ONNX model has no graph")?;
    let initializers: std::collections::HashSet<&str> =
        graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs: Vec<&str> = graph
        .input
        .iter()
        .map(|v| v.name.as_str())
        .filter(|n| !initializers.contains(n))
        .collect();
    let outputs: Vec<&str> = graph.output.iter().map(|v| v.name.as_str()).collect();
    if inputs != [twin.onnx.input.as_str()] {
        return Err(format!(
            "network inputs {inputs:?} do not match twin.json onnx.input {:?}",
            twin.onnx.input
        ));
    }
    if outputs != [twin.onnx.output.as_str()] {
        return Err(format!(
            "network outputs {outputs:?} do not match twin.json onnx.output {:?}",
            twin.onnx.output
        ));
    }
    Ok(())
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

/// What a bundle's training provenance must say (SPEC §5).
pub const PROVENANCE_KEYS: [&str; 4] = ["campaign_digest", "split", "seed", "metrics"];

/// Checks the JSON part for consistency; returns the parsed groups.
fn check_twin(twin: &TwinJson) -> Result<Vec<Group>, String> {
    if twin.format != BUNDLE_FORMAT {
        return Err(format!("format {:?} is not {BUNDLE_FORMAT:?}", twin.format));
    }
    // SPEC §5: every part present (a helper's audit: a bundle without its
    // thresholds or provenance loaded with defaults, without a word).
    let Some(provenance) = twin.provenance.as_object() else {
        return Err(format!(
            "provenance is {}, not an object with {PROVENANCE_KEYS:?}",
            twin.provenance
        ));
    };
    let missing: Vec<&str> = PROVENANCE_KEYS
        .into_iter()
        .filter(|k| !provenance.contains_key(*k))
        .collect();
    if !missing.is_empty() {
        return Err(format!("provenance lacks {missing:?}"));
    }
    if let Some(i) = &twin.interval {
        if !(i.half_width_bar.is_finite() && i.half_width_bar > 0.0) {
            return Err(format!(
                "interval.half_width_bar = {} must be finite and > 0",
                i.half_width_bar
            ));
        }
        if (i.level - 0.95).abs() > 1e-12 {
            return Err(format!(
                "interval.level = {} is not 0.95 (SPEC §2a's central 95 % interval)",
                i.level
            ));
        }
        if let Some(m) = i
            .method
            .as_deref()
            .filter(|m| !HELD_OUT_METHODS.contains(m))
        {
            return Err(format!(
                "interval.method = `{m}` is neither of {HELD_OUT_METHODS:?}"
            ));
        }
        if twin.permutation.groups.iter().any(|g| g == "observer") {
            return Err(
                "interval is given for a bundle that reads the observer, which gives its own"
                    .into(),
            );
        }
    }
    if twin.onnx.sha256.is_none() {
        return Err("onnx.sha256 is missing (the network file's digest, checked at load)".into());
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
