//! Core errors and panics as exceptions of the `lfcam.errors` family.

use std::any::Any;
use std::panic::{AssertUnwindSafe, catch_unwind};

use lfcam_core::Error;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyType;

/// One exception class of `lfcam.errors`, imported on first use and cached.
struct ErrorClass {
    name: &'static str,
    cell: PyOnceLock<Py<PyType>>,
}

impl ErrorClass {
    const fn new(name: &'static str) -> Self {
        Self {
            name,
            cell: PyOnceLock::new(),
        }
    }

    /// An instance of the class with `message`; if `lfcam.errors` cannot be imported,
    /// the import error instead.
    fn err(&'static self, py: Python<'_>, message: String) -> PyErr {
        match self.cell.import(py, "lfcam.errors", self.name) {
            Ok(class) => PyErr::from_type(class.clone(), message),
            Err(import_error) => import_error,
        }
    }
}

static LFCAM_ERROR: ErrorClass = ErrorClass::new("LfcamError");
static INPUT_ERROR: ErrorClass = ErrorClass::new("InputError");
static NUMERICAL_ERROR: ErrorClass = ErrorClass::new("NumericalError");

/// `lfcam.InputError(message)`: for checks done in the bindings themselves.
pub fn input_error(py: Python<'_>, arg: &str, reason: impl std::fmt::Display) -> PyErr {
    INPUT_ERROR.err(py, format!("{arg}: {reason}"))
}

/// `lfcam.LfcamError` for a broken invariant of lfcam itself (not the caller's fault).
pub fn internal_error(py: Python<'_>, function: &str, detail: impl std::fmt::Display) -> PyErr {
    LFCAM_ERROR.err(
        py,
        format!("internal error in {function}: {detail}; please report this"),
    )
}

/// The exception a core error becomes: the message is the error's `Display`.
pub fn to_pyerr(py: Python<'_>, err: Error) -> PyErr {
    let class = match &err {
        Error::InvalidArgument { .. } | Error::InvalidItem { .. } => &INPUT_ERROR,
        Error::Numerical(_) => &NUMERICAL_ERROR,
        // A bug in lfcam, not the caller's fault: not an `InputError`.
        Error::Internal { .. } => &LFCAM_ERROR,
        // `Error` is `#[non_exhaustive]`, so this arm is required outside lfcam-core. A
        // variant added to the core without a class here still reaches Python as the
        // family's base class; add its arm here (and to `_raise_core_error`).
        _ => &LFCAM_ERROR,
    };
    class.err(py, err.to_string())
}

fn panic_message(payload: &(dyn Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("unknown panic payload")
}

/// Runs `f`, turning a panic into `lfcam.LfcamError("internal error in <function>:
/// <message>; please report this")` instead of pyo3's `PanicException` (which derives
/// from `BaseException` and escapes `except Exception`). Every binding's body runs
/// in here.
pub fn guarded<R>(py: Python<'_>, function: &str, f: impl FnOnce() -> PyResult<R>) -> PyResult<R> {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|payload| {
        Err(internal_error(
            py,
            function,
            panic_message(payload.as_ref()),
        ))
    })
}

/// Private test hook (feature `test-hooks`): raises the exception that the core error
/// variant `kind`
/// (`"InvalidArgument"`, `"InvalidItem"`, `"Numerical"` or `"Internal"`) maps to.
#[cfg(feature = "test-hooks")]
#[pyfunction]
pub fn _raise_core_error(py: Python<'_>, kind: &str) -> PyResult<()> {
    guarded(py, "_raise_core_error", || {
        let err = match kind {
            "InvalidArgument" => Error::invalid_argument("arg", "test InvalidArgument"),
            "InvalidItem" => Error::invalid_item("arg", 7, "test InvalidItem"),
            "Numerical" => Error::Numerical("test Numerical".into()),
            "Internal" => Error::internal("_raise_core_error", "test Internal"),
            other => {
                return Err(input_error(
                    py,
                    "kind",
                    format!("unknown core error variant {other:?}"),
                ));
            }
        };
        Err(to_pyerr(py, err))
    })
}

/// Private test hook (feature `test-hooks`): panics inside [`guarded`], which must
/// raise `LfcamError`.
#[cfg(feature = "test-hooks")]
#[pyfunction]
#[allow(clippy::panic)]
pub fn _panic_for_test(py: Python<'_>) -> PyResult<()> {
    guarded(py, "_panic_for_test", || {
        panic!("deliberate panic for testing")
    })
}
