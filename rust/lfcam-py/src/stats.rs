//! `nan_median`.

use lfcam_core::stats;
use numpy::{Element, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{c_slice, new_array, typed};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

/// Per-element median over axis 0 ignoring NaN, and the count of non-NaN values.
///
/// stack: (K, ...) float32, C-contiguous, K >= 1.
/// Returns (median, count): new arrays of shape stack.shape[1:], float32 and uint8
/// (K <= 255) or uint16 (K <= 65535).
#[pyfunction]
pub fn nan_median<'py>(
    py: Python<'py>,
    stack: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "nan_median", || {
        let ro = typed::<f32>(stack, "stack", "float32")?;
        let Some((&k, rest)) = ro.shape().split_first() else {
            return Err(input_error(
                py,
                "stack",
                "expected at least 1 dimension (K, ...), got a 0-d array",
            ));
        };
        if k == 0 {
            return Err(input_error(
                py,
                "stack",
                format!("has no values along axis 0 (K = 0), shape {:?}", ro.shape()),
            ));
        }
        let data = c_slice(&ro, "stack")?;
        let rest = rest.to_vec();
        if k <= usize::from(u8::MAX) {
            with_count::<u8>(py, data, k, &rest)
        } else if k <= usize::from(u16::MAX) {
            with_count::<u16>(py, data, k, &rest)
        } else {
            Err(input_error(
                py,
                "stack",
                format!("K = {k} values per element; at most 65535 are supported"),
            ))
        }
    })
}

fn with_count<'py, N>(
    py: Python<'py>,
    data: &[f32],
    k: usize,
    shape: &[usize],
) -> PyResult<Bound<'py, PyTuple>>
where
    N: Element + Copy + Send + Sync + TryFrom<usize>,
{
    let median = new_array::<f32>(py, shape)?;
    let count = new_array::<N>(py, shape)?;
    {
        let mut med_rw = median
            .try_readwrite()
            .map_err(|e| internal_error(py, "nan_median", format!("output borrow: {e}")))?;
        let mut cnt_rw = count
            .try_readwrite()
            .map_err(|e| internal_error(py, "nan_median", format!("output borrow: {e}")))?;
        let med = med_rw
            .as_slice_mut()
            .map_err(|e| internal_error(py, "nan_median", format!("output slice: {e}")))?;
        let cnt = cnt_rw
            .as_slice_mut()
            .map_err(|e| internal_error(py, "nan_median", format!("output slice: {e}")))?;
        py.detach(|| lfcam_core::parallel::install(|| stats::nan_median(data, k, med, cnt)))
            .and_then(|inner| inner)
            .map_err(|e| to_pyerr(py, e))?;
    }
    PyTuple::new(py, [median.into_any(), count.into_any()])
}
