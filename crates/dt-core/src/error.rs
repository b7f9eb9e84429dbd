//! Errors of the twin's physics models and of the feature pipeline
//! (`params`, `kalman`, `thermal`, `force`, `features`).
//!
//! The run-log format has its own error type in [`crate::log`]; this one is
//! [`PhysicsError`]. Numerical failure is always one of these variants, never
//! a panic; each message names the parameter, input, topic or time at fault.

/// Everything that can go wrong in the physics models and the feature pipeline.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhysicsError {
    /// A physics parameter is non-finite or outside its domain.
    #[error("invalid physics parameter `{name}` = {value}: {reason}")]
    InvalidParameter {
        /// The parameter's SPEC (Python) name, e.g. `c_oil`.
        name: &'static str,
        /// The offending value.
        value: f64,
        /// What the value must satisfy.
        reason: &'static str,
    },

    /// Numerical failure inside a filter or integrator (non-finite or
    /// non-positive innovation variance, non-finite covariance, ...).
    #[error("numerical failure in {model} at t_ns = {t_ns}: {what}")]
    Numerical {
        /// Which model failed (`kalman`, `thermal`, ...).
        model: &'static str,
        /// Event time of the failure.
        t_ns: i64,
        /// What was found.
        what: String,
    },

    /// Events or samples arrived out of time order.
    #[error("{what}: time went backwards, t_ns = {t_ns} after {last_t_ns}")]
    OutOfOrder {
        /// The stream or input at fault, e.g. `kalman accel event`, `/position`.
        what: String,
        /// Time of the offending event.
        t_ns: i64,
        /// Time of the event before it.
        last_t_ns: i64,
    },

    /// Two inputs that must have the same length do not.
    #[error(
        "input `{name}` has {got} elements, expected {expected} (the length of `{reference}`)"
    )]
    LengthMismatch {
        /// The input at fault.
        name: &'static str,
        /// Its length.
        got: usize,
        /// The length it must have.
        expected: usize,
        /// The input whose length is the reference.
        reference: &'static str,
    },

    /// A time axis given as a batch input is not non-decreasing.
    #[error("input `{name}` is not non-decreasing at index {index}")]
    NotMonotonic {
        /// The input at fault.
        name: &'static str,
        /// The first index `i` with `t[i] < t[i-1]`.
        index: usize,
    },

    /// A run lacks topics that the requested feature groups need.
    #[error("run `{run_id}` lacks topics {missing:?} needed by feature groups {groups:?}")]
    MissingTopics {
        /// `shocktwin.run` `run_id` of the log.
        run_id: String,
        /// The missing (absent or empty) topics.
        missing: Vec<String>,
        /// The requested groups (names).
        groups: Vec<String>,
    },

    /// A name that is not a feature group.
    #[error("unknown feature group `{0}` (expected one of force, position, acceleration, velocity, mechanical, thermal, signature, residual, observer)")]
    UnknownGroup(String),

    /// A filter event of a kind the filter's mode does not take.
    #[error("{0}")]
    WrongMode(&'static str),

    /// A dyno run (its metadata's excitation is a sine) given to the road
    /// observer, which reads road drives: it read a healthy 6 bar unit's
    /// 1 Hz sine as `leak` without a word (sixty-second session).
    #[error(
        "run `{run_id}` is a dyno run (excitation {excitation:?}): the road observer reads road \
         drives; read it with the charge observer (a bundle with the `observer` group)"
    )]
    NotARoadRun {
        /// `shocktwin.run` `run_id` of the log.
        run_id: String,
        /// Its metadata's `excitation`.
        excitation: String,
    },
}
