//! All error mapping of the bindings, in one place (polars' `exceptions.rs`).
//!
//! The exception classes are defined in Python (`shocktwin/exceptions.py`)
//! so that each can also derive from the builtin a caller expects
//! (`ValueError`, `OSError`, `ArithmeticError`); this file maps each dt-core
//! error kind to exactly one of them. The message is always the core's
//! message, which names the file, topic, field or parameter at fault.

use dt_core::bundle::BundleError;
use dt_core::error::PhysicsError;
use dt_core::estimator::EstimatorError;
use dt_core::log::LogError;
use pyo3::PyErr;

/// The Python-defined exception classes (imported from
/// `shocktwin.exceptions` on first use).
#[allow(missing_docs, clippy::pedantic)]
mod py {
    pyo3::import_exception!(shocktwin.exceptions, LogError);
    pyo3::import_exception!(shocktwin.exceptions, LogReadError);
    pyo3::import_exception!(shocktwin.exceptions, MissingTopicsError);
    pyo3::import_exception!(shocktwin.exceptions, ParamsError);
    pyo3::import_exception!(shocktwin.exceptions, ParamsReadError);
    pyo3::import_exception!(shocktwin.exceptions, ParamsNotFoundError);
    pyo3::import_exception!(shocktwin.exceptions, PhysicsError);
    pyo3::import_exception!(shocktwin.exceptions, BundleError);
    pyo3::import_exception!(shocktwin.exceptions, BundleReadError);
    pyo3::import_exception!(shocktwin.exceptions, BundleNotFoundError);
    pyo3::import_exception!(shocktwin.exceptions, InputError);
}

/// A dt-core error on its way to Python. Bindings return
/// `Result<_, CoreError>` (or `?` it into a `PyResult`).
pub(crate) enum CoreError {
    /// Reading or decoding a run log.
    Log(LogError),
    /// The physics models and the feature pipeline.
    Physics(PhysicsError),
    /// Physics parameters given as a dict or JSON that do not parse (a key
    /// missing or unknown, a value not a number); the message names it.
    Params(String),
    /// Loading or running a model bundle.
    Bundle(BundleError),
    /// A file other than a run log (physics.json, a bundle file) cannot be read.
    Io {
        /// The path.
        file: String,
        /// The OS error.
        source: std::io::Error,
    },
}

impl CoreError {
    /// A parameter set `what` (a path or `parameters`) that does not parse.
    pub(crate) fn params(what: &str, err: &serde_json::Error) -> Self {
        CoreError::Params(format!("{what}: invalid physics parameters: {err}"))
    }

    /// A parameter set `what` whose value at a known path does not parse.
    pub(crate) fn params_at(
        what: &str,
        err: &serde_path_to_error::Error<serde_json::Error>,
    ) -> Self {
        let path = err.path().to_string();
        if path == "." || path.is_empty() {
            Self::params(what, err.inner())
        } else {
            CoreError::Params(format!(
                "{what}: invalid physics parameter `{path}`: {}",
                err.inner()
            ))
        }
    }
}

impl From<BundleError> for CoreError {
    fn from(err: BundleError) -> Self {
        CoreError::Bundle(err)
    }
}

impl From<EstimatorError> for CoreError {
    fn from(err: EstimatorError) -> Self {
        match err {
            EstimatorError::Bundle(err) => CoreError::Bundle(err),
            EstimatorError::Physics(err) => CoreError::Physics(err),
        }
    }
}

impl From<PhysicsError> for CoreError {
    fn from(err: PhysicsError) -> Self {
        CoreError::Physics(err)
    }
}

impl From<LogError> for CoreError {
    fn from(err: LogError) -> Self {
        CoreError::Log(err)
    }
}

impl From<CoreError> for PyErr {
    fn from(err: CoreError) -> PyErr {
        match err {
            // The file cannot be opened or read: an OSError subclass.
            CoreError::Log(err @ LogError::Io { .. }) => py::LogReadError::new_err(err.to_string()),
            // Every other log problem is a property of the file's contents.
            CoreError::Log(err) => py::LogError::new_err(err.to_string()),
            CoreError::Physics(err) => physics_error(&err),
            CoreError::Params(message) => py::ParamsError::new_err(message),
            // A part of a bundle cannot be read: a BundleError that is also
            // an OSError (FileNotFoundError when it is missing).
            CoreError::Bundle(err @ BundleError::Io { .. }) => {
                let missing = matches!(
                    &err,
                    BundleError::Io { error, .. } if error.kind() == std::io::ErrorKind::NotFound
                );
                if missing {
                    py::BundleNotFoundError::new_err(err.to_string())
                } else {
                    py::BundleReadError::new_err(err.to_string())
                }
            }
            // A network input of the wrong width is a caller's error.
            CoreError::Bundle(err @ BundleError::Width { .. }) => {
                py::InputError::new_err(err.to_string())
            }
            CoreError::Bundle(err) => py::BundleError::new_err(err.to_string()),
            CoreError::Io { file, source } => io_error(&file, &source),
        }
    }
}

/// An argument the bindings themselves reject (arrays of different lengths,
/// a time that is not finite): `InputError`, like the core's input errors.
pub(crate) fn input_error(message: String) -> PyErr {
    py::InputError::new_err(message)
}

/// A parameter or calibration file cannot be read: `ParamsReadError`, an
/// `OSError` (`ParamsNotFoundError`, a `FileNotFoundError`, when it is
/// missing). It was the builtin class alone, which `except ShocktwinError`
/// missed (a helper's trial).
pub(crate) fn io_error(file: &str, source: &std::io::Error) -> PyErr {
    let message = format!("{file}: {source}");
    if source.kind() == std::io::ErrorKind::NotFound {
        py::ParamsNotFoundError::new_err(message)
    } else {
        py::ParamsReadError::new_err(message)
    }
}

/// A parameter or calibration that cannot be used: `ParamsError`.
pub(crate) fn params_error(message: String) -> PyErr {
    py::ParamsError::new_err(message)
}

fn physics_error(err: &PhysicsError) -> PyErr {
    let message = err.to_string();
    match err {
        PhysicsError::InvalidParameter { .. } => py::ParamsError::new_err(message),
        PhysicsError::Numerical { .. } => py::PhysicsError::new_err(message),
        PhysicsError::MissingTopics { missing, .. } => {
            py::MissingTopicsError::new_err((message, missing.clone()))
        }
        PhysicsError::OutOfOrder { .. }
        | PhysicsError::LengthMismatch { .. }
        | PhysicsError::NotMonotonic { .. }
        | PhysicsError::UnknownGroup(_)
        | PhysicsError::WrongMode(_)
        | PhysicsError::NotARoadRun { .. } => py::InputError::new_err(message),
    }
}
