//! `crop_lenslets`.

use lfcam_core::{ImageView, crop, parallel};
use numpy::{
    Element, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods, dtype,
};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyTuple;

use crate::arrays::{as_untyped, dtype_name, image_view, readonly};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

/// Crops equally sized rectangles out of a raw frame.
///
/// raw: (H, W) or (H, W, C) uint8, uint16 or float32, C-contiguous.
/// rects: (N, 4) int64, C-contiguous, rows (x0, y0, w, h) in raw pixels.
/// Returns a new (N, h, w) or (N, h, w, C) array of raw's dtype.
#[pyfunction]
pub fn crop_lenslets<'py>(
    py: Python<'py>,
    raw: &Bound<'py, PyAny>,
    rects: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "crop_lenslets", || {
        let raw = as_untyped(raw, "raw")?;
        let rects = rects_array(rects)?;
        let rects = rects.as_slice();
        let dt = raw.dtype();
        if dt.is_equiv_to(&dtype::<u8>(py)) {
            crop_typed::<u8>(raw, rects)
        } else if dt.is_equiv_to(&dtype::<u16>(py)) {
            crop_typed::<u16>(raw, rects)
        } else if dt.is_equiv_to(&dtype::<f32>(py)) {
            crop_typed::<f32>(raw, rects)
        } else {
            Err(input_error(
                py,
                "raw",
                format!(
                    "dtype {} is not supported; expected uint8, uint16 or float32",
                    dtype_name(raw)
                ),
            ))
        }
    })
}

/// `rects` as `(N, 4)` rows, copied out of an int64 C-contiguous array.
fn rects_array(rects: &Bound<'_, PyAny>) -> PyResult<Vec<[i64; 4]>> {
    let py = rects.py();
    let arr = as_untyped(rects, "rects")?;
    if !arr.dtype().is_equiv_to(&dtype::<i64>(py)) {
        return Err(input_error(
            py,
            "rects",
            format!("expected dtype int64, got {}", dtype_name(arr)),
        ));
    }
    let ro = readonly::<i64>(arr, "rects")?;
    let shape = ro.shape();
    if !matches!(shape, [_, 4]) {
        return Err(input_error(
            py,
            "rects",
            format!("expected shape (N, 4) of rows (x0, y0, w, h), got {shape:?}"),
        ));
    }
    let flat = ro
        .as_slice()
        .ok()
        .filter(|_| ro.is_c_contiguous())
        .ok_or_else(|| input_error(py, "rects", "must be C-contiguous"))?;
    let (rows, _) = flat.as_chunks::<4>();
    Ok(rows.to_vec())
}

/// `numpy.empty`, imported once.
fn numpy_empty(py: Python<'_>) -> PyResult<&Bound<'_, PyAny>> {
    static EMPTY: PyOnceLock<Py<PyAny>> = PyOnceLock::new();
    EMPTY.import(py, "numpy", "empty")
}

fn crop_typed<'py, T>(
    raw: &Bound<'py, numpy::PyUntypedArray>,
    rects: &[[i64; 4]],
) -> PyResult<Bound<'py, PyAny>>
where
    T: Element + Copy + Send + Sync,
{
    let py = raw.py();
    let ro = readonly::<T>(raw, "raw")?;
    let src: ImageView<'_, T> = image_view(&ro, "raw")?;
    let [n, h, w, c] = crop::crop_output_shape(&src, rects).map_err(|e| to_pyerr(py, e))?;
    let shape: Vec<usize> = if ro.ndim() == 2 {
        vec![n, h, w]
    } else {
        vec![n, h, w, c]
    };
    // The output is allocated by numpy (`numpy.empty`) rather than as a Rust `Vec` moved
    // out with `into_pyarray`: numpy madvises large allocations for transparent huge
    // pages, which makes the first-touch page faults (the dominant cost of filling a
    // fresh 39 MB output) several times cheaper; and `empty`, unlike `zeros` (calloc),
    // does not zero memory the allocator reuses. The kernel writes every element (it
    // checks `out.len()` and covers every row), and on error the array is dropped.
    // Measured with benchmarks/run.py, full size, 2 threads: ~9 ms, against 24 ms for
    // a `Vec`. No copy either way: the kernel writes into the array it returns.
    // Called through Python, not `PyArray::new`, so that a failed allocation raises
    // numpy's MemoryError instead of panicking (and no `unsafe` is needed).
    let out = numpy_empty(py)?
        .call1((PyTuple::new(py, &shape)?, dtype::<T>(py)))?
        .cast_into::<PyArrayDyn<T>>()?;
    {
        let mut rw = out
            .try_readwrite()
            .map_err(|e| internal_error(py, "crop_lenslets", format!("output borrow: {e}")))?;
        let out_slice = rw
            .as_slice_mut()
            .map_err(|e| internal_error(py, "crop_lenslets", format!("output slice: {e}")))?;
        py.detach(|| parallel::install(|| crop::crop_lenslets(src, rects, out_slice)))
            .and_then(|inner| inner)
            .map_err(|e| to_pyerr(py, e))?;
    }
    Ok(out.into_any())
}
