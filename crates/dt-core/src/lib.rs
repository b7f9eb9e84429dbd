//! `dt-core` owns the twin itself: the run-log format (shocktwin log v1 on
//! MCAP, SPEC §2), the twin's physics models (paper §5.1–5.3, SPEC §3), the
//! 50 Hz feature pipeline (SPEC §4), the model bundle (SPEC §5) and the
//! incremental estimator with its health state machine (SPEC §6).
//!
//! It knows nothing of pyo3, tokio or sockets: `dt-py` and `dt-server` are
//! thin shells around it.

pub mod bundle;
pub mod cancel;
pub mod charge;
pub mod error;
pub mod estimate;
pub mod estimator;
pub mod features;
pub mod force;
pub mod kalman;
pub mod log;
pub mod params;
pub mod road;
pub mod service;
pub mod thermal;
pub mod trend;
