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
/// to a subset; base: None or (H, W) float32 added to the candidates; active: None or
/// (H, W) uint8, the pixels wanted; cubic: bicubic samples; all C-contiguous. Returns
/// a new (H, W, S, 5) float32 array: per pixel and subset the parallax, cost,
/// curvature, second-best cost and the cost at the candidate nearest 0.
#[pyfunction]
#[pyo3(signature = (views, offsets, reference, candidates, subsets, trunc_colour, trunc_gradient, alpha, radius, eps, base=None, active=None, cubic=false))]
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
    base: Option<&Bound<'py, PyAny>>,
    active: Option<&Bound<'py, PyAny>>,
    cubic: bool,
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
            cubic,
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
        let map_shape = |shape: &[usize], arg: &str| {
            if shape == [h, w] {
                Ok(())
            } else {
                Err(input_error(
                    py,
                    arg,
                    format!("expected shape ({h}, {w}), got {shape:?}"),
                ))
            }
        };
        let base_ro = base
            .map(|b| typed::<f32>(b, "base", "float32"))
            .transpose()?;
        if let Some(b) = &base_ro {
            map_shape(b.shape(), "base")?;
        }
        let active_ro = active
            .map(|a| typed::<u8>(a, "active", "uint8"))
            .transpose()?;
        if let Some(a) = &active_ro {
            map_shape(a.shape(), "active")?;
        }
        let base_s = base_ro.as_ref().map(|b| c_slice(b, "base")).transpose()?;
        let active_s = active_ro
            .as_ref()
            .map(|a| c_slice(a, "active"))
            .transpose()?;
        let views_s = c_slice(&views_ro, "views")?;
        let cand_s = c_slice(&cand_ro, "candidates")?;
        let out = new_array::<f32>(py, &[h, w, n_sub, SWEEP_OUTPUTS])?;
        fill(&out, "plane_sweep", |slice| {
            core::plane_sweep(
                views_s,
                (n, h, w, c),
                reference,
                offset_rows,
                base_s,
                cand_s,
                &lists,
                active_s,
                &params,
                slice,
            )
        })?;
        Ok(out)
    })
}
