//! `weighted_median_fill`.

use lfcam_core::fill::{self as core, FillParams};
use numpy::{PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{c_slice, new_array, typed};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

/// Joint weighted median at the pixels to do (see lfcam-core's `fill` module).
///
/// values, weights: (H, W) float32; guide: (H, W, C) float32; todo: (H, W) uint8; all
/// C-contiguous. Returns (values, support): new (H, W) float32 arrays.
#[pyfunction]
#[pyo3(signature = (values, weights, guide, todo, radius, stride, sigma_colour, sigma_space))]
#[allow(clippy::too_many_arguments)]
pub fn weighted_median_fill<'py>(
    py: Python<'py>,
    values: &Bound<'py, PyAny>,
    weights: &Bound<'py, PyAny>,
    guide: &Bound<'py, PyAny>,
    todo: &Bound<'py, PyAny>,
    radius: i64,
    stride: i64,
    sigma_colour: f64,
    sigma_space: f64,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "weighted_median_fill", || {
        let count = |value: i64, arg: &str| {
            usize::try_from(value)
                .map_err(|_| input_error(py, arg, format!("expected an integer >= 1, got {value}")))
        };
        let params = FillParams {
            radius: count(radius, "radius")?,
            stride: count(stride, "stride")?,
            sigma_colour: sigma_colour as f32,
            sigma_space: sigma_space as f32,
        };
        let values_ro = typed::<f32>(values, "values", "float32")?;
        let (h, w) = match *values_ro.shape() {
            [h, w] => (h, w),
            ref shape => {
                return Err(input_error(
                    py,
                    "values",
                    format!("expected a 2-D (H, W) array, got shape {shape:?}"),
                ));
            }
        };
        let weights_ro = typed::<f32>(weights, "weights", "float32")?;
        let guide_ro = typed::<f32>(guide, "guide", "float32")?;
        let todo_ro = typed::<u8>(todo, "todo", "uint8")?;
        for (name, shape) in [("weights", weights_ro.shape()), ("todo", todo_ro.shape())] {
            if shape != [h, w] {
                return Err(input_error(
                    py,
                    name,
                    format!("expected shape ({h}, {w}) like values, got {shape:?}"),
                ));
            }
        }
        let channels = match *guide_ro.shape() {
            [gh, gw, c] if gh == h && gw == w => c,
            ref shape => {
                return Err(input_error(
                    py,
                    "guide",
                    format!("expected shape ({h}, {w}, C) like values, got {shape:?}"),
                ));
            }
        };
        let values_s = c_slice(&values_ro, "values")?;
        let weights_s = c_slice(&weights_ro, "weights")?;
        let guide_s = c_slice(&guide_ro, "guide")?;
        let todo_s = c_slice(&todo_ro, "todo")?;
        let out = new_array::<f32>(py, &[h, w])?;
        let support = new_array::<f32>(py, &[h, w])?;
        {
            let err = |e: String| internal_error(py, "weighted_median_fill", e);
            let mut out_rw = out
                .try_readwrite()
                .map_err(|e| err(format!("output: {e}")))?;
            let mut sup_rw = support
                .try_readwrite()
                .map_err(|e| err(format!("output: {e}")))?;
            let out_s = out_rw
                .as_slice_mut()
                .map_err(|e| err(format!("output: {e}")))?;
            let sup_s = sup_rw
                .as_slice_mut()
                .map_err(|e| err(format!("output: {e}")))?;
            py.detach(|| {
                core::weighted_median_fill(
                    values_s,
                    weights_s,
                    guide_s,
                    channels,
                    todo_s,
                    (h, w),
                    &params,
                    out_s,
                    sup_s,
                )
            })
            .map_err(|e| to_pyerr(py, e))?;
        }
        PyTuple::new(py, [out.into_any(), support.into_any()])
    })
}
