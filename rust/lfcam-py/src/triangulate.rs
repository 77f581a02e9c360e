//! `triangulate`.

use lfcam_core::parallel;
use lfcam_core::triangulate::{self as core, Outputs, Params, ViewStack};
use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{c_slice, new_array, typed};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

/// Robust plane + parallax triangulation (see lfcam-core's `triangulate` module).
///
/// flows: (N, H, W, 2) float32, C-contiguous: flow (x, y) from the reference to view i.
/// offsets: (N, 2) float64, C-contiguous: o_i, zero for the reference.
/// weights: None or (N, H, W) float32, C-contiguous, >= 0 (0 or NaN: not used).
/// Returns (parallax, confidence, residual, perpendicular, n_used): new (H, W) arrays,
/// four float32 and one uint8.
#[pyfunction]
#[pyo3(signature = (flows, offsets, reference, weights, min_views, sigma_floor, cutoff, iterations))]
#[allow(clippy::too_many_arguments)]
pub fn triangulate<'py>(
    py: Python<'py>,
    flows: &Bound<'py, PyAny>,
    offsets: &Bound<'py, PyAny>,
    reference: i64,
    weights: Option<&Bound<'py, PyAny>>,
    min_views: i64,
    sigma_floor: f64,
    cutoff: f64,
    iterations: i64,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "triangulate", || {
        let count = |value: i64, arg: &str| {
            usize::try_from(value)
                .map_err(|_| input_error(py, arg, format!("expected an integer >= 0, got {value}")))
        };
        let reference = count(reference, "reference")?;
        let params = Params {
            min_views: count(min_views, "min_views")?,
            // Out-of-range values become 0 or infinity, which the core refuses.
            sigma_floor: sigma_floor as f32,
            cutoff: cutoff as f32,
            iterations: count(iterations, "iterations")?,
        };

        let flows_ro = typed::<f32>(flows, "flows", "float32")?;
        let [n, h, w, c] = match *flows_ro.shape() {
            [n, h, w, c] => [n, h, w, c],
            ref shape => {
                return Err(input_error(
                    py,
                    "flows",
                    format!("expected a 4-D (N, H, W, 2) array, got shape {shape:?}"),
                ));
            }
        };
        let flow_stack = ViewStack::new(c_slice(&flows_ro, "flows")?, [n, h, w, c], "flows")
            .map_err(|e| to_pyerr(py, e))?;

        let weights_ro = weights
            .map(|obj| typed::<f32>(obj, "weights", "float32"))
            .transpose()?;
        let weight_stack = match &weights_ro {
            None => None,
            Some(ro) => {
                let [wn, wh, ww] = match *ro.shape() {
                    [wn, wh, ww] => [wn, wh, ww],
                    ref shape => {
                        return Err(input_error(
                            py,
                            "weights",
                            format!("expected a 3-D (N, H, W) array, got shape {shape:?}"),
                        ));
                    }
                };
                let stack = ViewStack::new(c_slice(ro, "weights")?, [wn, wh, ww, 1], "weights")
                    .map_err(|e| to_pyerr(py, e))?;
                Some(stack)
            }
        };

        let offsets_ro = typed::<f64>(offsets, "offsets", "float64")?;
        if !matches!(offsets_ro.shape(), [_, 2]) {
            return Err(input_error(
                py,
                "offsets",
                format!("expected shape (N, 2), got {:?}", offsets_ro.shape()),
            ));
        }
        let (offset_rows, _) = c_slice(&offsets_ro, "offsets")?.as_chunks::<2>();

        let parallax = new_array::<f32>(py, &[h, w])?;
        let confidence = new_array::<f32>(py, &[h, w])?;
        let residual = new_array::<f32>(py, &[h, w])?;
        let perpendicular = new_array::<f32>(py, &[h, w])?;
        let n_used = new_array::<u8>(py, &[h, w])?;
        {
            let mut par = readwrite(&parallax)?;
            let mut conf = readwrite(&confidence)?;
            let mut res = readwrite(&residual)?;
            let mut perp = readwrite(&perpendicular)?;
            let mut used = readwrite(&n_used)?;
            let out = Outputs {
                parallax: slice_mut(&mut par)?,
                confidence: slice_mut(&mut conf)?,
                residual: slice_mut(&mut res)?,
                perpendicular: slice_mut(&mut perp)?,
                n_used: slice_mut(&mut used)?,
            };
            py.detach(|| {
                parallel::install(|| {
                    core::triangulate(
                        flow_stack,
                        weight_stack,
                        offset_rows,
                        reference,
                        &params,
                        out,
                    )
                })
            })
            .and_then(|inner| inner)
            .map_err(|e| to_pyerr(py, e))?;
        }
        PyTuple::new(
            py,
            [
                parallax.into_any(),
                confidence.into_any(),
                residual.into_any(),
                perpendicular.into_any(),
                n_used.into_any(),
            ],
        )
    })
}

/// A fresh output array borrowed for writing.
fn readwrite<'py, T: numpy::Element>(
    arr: &Bound<'py, PyArrayDyn<T>>,
) -> PyResult<numpy::PyReadwriteArrayDyn<'py, T>> {
    arr.try_readwrite()
        .map_err(|e| internal_error(arr.py(), "triangulate", format!("output borrow: {e}")))
}

/// The elements of a fresh (C-contiguous) output array.
fn slice_mut<'a, T: numpy::Element>(
    rw: &'a mut numpy::PyReadwriteArrayDyn<'_, T>,
) -> PyResult<&'a mut [T]> {
    let py = rw.py();
    rw.as_slice_mut()
        .map_err(|e| internal_error(py, "triangulate", format!("output slice: {e}")))
}
