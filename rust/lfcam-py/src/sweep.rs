//! `plane_sweep`.

use lfcam_core::sweep::{self as core, SWEEP_OUTPUTS, SweepParams};
use numpy::{PyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use crate::arrays::{c_slice, fill, new_array, typed};
use crate::errors::{guarded, input_error};

/// Plane sweep along the parallax lines (see lfcam-core's `sweep` module).
///
/// views: (N, H, W, C) float32; offsets: (N, 2) float64; candidates: (K,) float32,
/// increasing and equally spaced; subsets: (S, N) uint8, non-zero where a view belongs
/// to a subset; all C-contiguous. Returns a new (H, W, S, 4) float32 array: per pixel
/// and subset the parallax, cost, curvature and second-best cost.
#[pyfunction]
#[pyo3(signature = (views, offsets, reference, candidates, subsets, trunc_colour, trunc_gradient, alpha, radius, eps))]
#[allow(clippy::too_many_arguments)]
pub fn plane_sweep<'py>(
    py: Python<'py>,
    views: &Bound<'py, PyAny>,
    offsets: &Bound<'py, PyAny>,
    reference: i64,
    candidates: &Bound<'py, PyAny>,
    subsets: &Bound<'py, PyAny>,
    trunc_colour: f64,
    trunc_gradient: f64,
    alpha: f64,
    radius: i64,
    eps: f64,
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    guarded(py, "plane_sweep", || {
        let count = |value: i64, arg: &str| {
            usize::try_from(value)
                .map_err(|_| input_error(py, arg, format!("expected an integer >= 0, got {value}")))
        };
        let reference = count(reference, "reference")?;
        let params = SweepParams {
            trunc_colour: trunc_colour as f32,
            trunc_gradient: trunc_gradient as f32,
            alpha: alpha as f32,
            radius: count(radius, "radius")?,
            eps: eps as f32,
        };
        let views_ro = typed::<f32>(views, "views", "float32")?;
        let [n, h, w, c] = match *views_ro.shape() {
            [n, h, w, c] => [n, h, w, c],
            ref shape => {
                return Err(input_error(
                    py,
                    "views",
                    format!("expected a 4-D (N, H, W, C) array, got shape {shape:?}"),
                ));
            }
        };
        let offsets_ro = typed::<f64>(offsets, "offsets", "float64")?;
        if offsets_ro.shape() != [n, 2] {
            return Err(input_error(
                py,
                "offsets",
                format!("expected shape ({n}, 2), got {:?}", offsets_ro.shape()),
            ));
        }
        let (offset_rows, _) = c_slice(&offsets_ro, "offsets")?.as_chunks::<2>();
        let cand_ro = typed::<f32>(candidates, "candidates", "float32")?;
        if cand_ro.shape().len() != 1 {
            return Err(input_error(
                py,
                "candidates",
                format!("expected a 1-D array, got shape {:?}", cand_ro.shape()),
            ));
        }
        let subsets_ro = typed::<u8>(subsets, "subsets", "uint8")?;
        let n_sub = match *subsets_ro.shape() {
            [s, sn] if sn == n => s,
            ref shape => {
                return Err(input_error(
                    py,
                    "subsets",
                    format!("expected shape (S, {n}), got {shape:?}"),
                ));
            }
        };
        let lists: Vec<Vec<usize>> = c_slice(&subsets_ro, "subsets")?
            .chunks_exact(n.max(1))
            .map(|row| {
                (0..n)
                    .filter(|&i| row.get(i).is_some_and(|&v| v != 0))
                    .collect()
            })
            .collect();
        let views_s = c_slice(&views_ro, "views")?;
        let cand_s = c_slice(&cand_ro, "candidates")?;
        let out = new_array::<f32>(py, &[h, w, n_sub, SWEEP_OUTPUTS])?;
        fill(&out, "plane_sweep", |slice| {
            core::plane_sweep(
                views_s,
                (n, h, w, c),
                reference,
                offset_rows,
                cand_s,
                &lists,
                &params,
                slice,
            )
        })?;
        Ok(out)
    })
}
