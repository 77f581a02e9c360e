//! `set_num_threads` / `get_num_threads` over `lfcam_core::parallel`.

use lfcam_core::parallel;
use pyo3::prelude::*;
use pyo3::types::PyBool;

use crate::errors::{guarded, input_error, to_pyerr};

/// Sets the number of threads lfcam's kernels run on (1 to 1024).
#[pyfunction]
pub fn set_num_threads(py: Python<'_>, n: &Bound<'_, PyAny>) -> PyResult<()> {
    guarded(py, "set_num_threads", || {
        let bad = || {
            let repr = n.repr().map_or_else(|_| "?".to_owned(), |r| r.to_string());
            input_error(py, "n", format!("expected a positive integer, got {repr}"))
        };
        if n.is_instance_of::<PyBool>() {
            return Err(bad());
        }
        let n: usize = n
            .extract::<i64>()
            .ok()
            .and_then(|v| usize::try_from(v).ok())
            .ok_or_else(bad)?;
        py.detach(|| parallel::set_num_threads(n))
            .map_err(|e| to_pyerr(py, e))
    })
}

/// The number of threads lfcam's kernels run on.
#[pyfunction]
pub fn get_num_threads(py: Python<'_>) -> PyResult<usize> {
    guarded(py, "get_num_threads", || Ok(parallel::num_threads()))
}
