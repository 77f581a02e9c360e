//! `crop_lenslets`.

use lfcam_core::{ImageView, crop};
use numpy::{Element, PyArrayDescrMethods, PyUntypedArrayMethods, dtype};
use pyo3::prelude::*;

use crate::arrays::{as_untyped, dtype_name, fill, image_view, new_array, readonly, rect_rows};
use crate::errors::{guarded, input_error, to_pyerr};

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
        let rects = rect_rows(rects, "rects")?;
        let dt = raw.dtype();
        if dt.is_equiv_to(&dtype::<u8>(py)) {
            crop_typed::<u8>(raw, &rects)
        } else if dt.is_equiv_to(&dtype::<u16>(py)) {
            crop_typed::<u16>(raw, &rects)
        } else if dt.is_equiv_to(&dtype::<f32>(py)) {
            crop_typed::<f32>(raw, &rects)
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
    let out = new_array::<T>(py, &shape)?;
    fill(&out, "crop_lenslets", |slice| {
        crop::crop_lenslets(src, rects, slice)
    })?;
    Ok(out.into_any())
}
