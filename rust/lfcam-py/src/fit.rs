//! `fit_board_tilts`.

use lfcam_core::fit::{self as core, ParallaxSamples, TiltProblem};
use numpy::PyUntypedArrayMethods;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays::{c_slice, typed};
use crate::errors::{guarded, input_error, to_pyerr};

/// `obj`, a float64 `(M, 2)` array, as rows; `m` checks the row count when given.
fn pairs(obj: &Bound<'_, PyAny>, arg: &str, m: Option<usize>) -> PyResult<Vec<[f64; 2]>> {
    let py = obj.py();
    let ro = typed::<f64>(obj, arg, "float64")?;
    match *ro.shape() {
        [rows, 2] if m.is_none_or(|m| m == rows) => {}
        ref shape => {
            let rows = m.map_or("M".to_string(), |m| m.to_string());
            return Err(input_error(
                py,
                arg,
                format!("expected shape ({rows}, 2), got {shape:?}"),
            ));
        }
    }
    Ok(c_slice(&ro, arg)?
        .chunks_exact(2)
        .map(|c| {
            [
                c.first().copied().unwrap_or(0.0),
                c.get(1).copied().unwrap_or(0.0),
            ]
        })
        .collect())
}

/// A 1-D array of `T` as a vector.
fn vector<T: numpy::Element + Copy>(
    obj: &Bound<'_, PyAny>,
    arg: &str,
    name: &str,
) -> PyResult<Vec<T>> {
    let py = obj.py();
    let ro = typed::<T>(obj, arg, name)?;
    if ro.shape().len() != 1 {
        return Err(input_error(
            py,
            arg,
            format!("expected a 1-D array, got shape {:?}", ro.shape()),
        ));
    }
    Ok(c_slice(&ro, arg)?.to_vec())
}

fn indices(obj: &Bound<'_, PyAny>, arg: &str) -> PyResult<Vec<usize>> {
    let py = obj.py();
    vector::<i64>(obj, arg, "int64")?
        .into_iter()
        .map(|v| {
            usize::try_from(v).map_err(|_| input_error(py, arg, format!("negative index {v}")))
        })
        .collect()
}

/// Joint fit of `o_i`, `Z_c` and each board's tilt (gradient) to parallax samples (see
/// lfcam-core's `fit` module).
///
/// board, view: (M,) int64; pos, parallax: (M, 2) float64; weight: (M,) float64;
/// distances: (K,) float64 (the boards other than the reference); offsets: (N, 2)
/// float64, the start; centres: optional (N, 2) float64 with centres_weight; robust:
/// Cauchy-reweighted samples.
/// Returns a dict of the solution, standard errors and residuals.
#[pyfunction]
#[pyo3(signature = (
    board, view, pos, parallax, weight, distances, z_b, reference, offsets, z_c, centre,
    gradient_prior, centres=None, centres_weight=0.0, fit_reference=false, robust=false
))]
#[allow(clippy::too_many_arguments)]
pub fn fit_board_tilts<'py>(
    py: Python<'py>,
    board: &Bound<'py, PyAny>,
    view: &Bound<'py, PyAny>,
    pos: &Bound<'py, PyAny>,
    parallax: &Bound<'py, PyAny>,
    weight: &Bound<'py, PyAny>,
    distances: &Bound<'py, PyAny>,
    z_b: f64,
    reference: i64,
    offsets: &Bound<'py, PyAny>,
    z_c: f64,
    centre: (f64, f64),
    gradient_prior: f64,
    centres: Option<&Bound<'py, PyAny>>,
    centres_weight: f64,
    fit_reference: bool,
    robust: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(py, "fit_board_tilts", || {
        let board = indices(board, "board")?;
        let view = indices(view, "view")?;
        let m = view.len();
        let pos = pairs(pos, "pos", Some(m))?;
        let parallax = pairs(parallax, "parallax", Some(m))?;
        let weight = vector::<f64>(weight, "weight", "float64")?;
        let distances = vector::<f64>(distances, "distances", "float64")?;
        let start = pairs(offsets, "offsets", None)?;
        let n_views = start.len();
        let reference = usize::try_from(reference)
            .map_err(|_| input_error(py, "reference", format!("negative index {reference}")))?;
        let centres = match centres {
            Some(c) => Some((pairs(c, "centres", Some(n_views))?, centres_weight)),
            None => None,
        };
        let prob = TiltProblem {
            n_views,
            reference,
            z_b,
            distances,
            centre: [centre.0, centre.1],
            centres,
            gradient_prior,
            fit_reference,
            robust,
        };
        let data = ParallaxSamples {
            board: &board,
            view: &view,
            pos: &pos,
            parallax: &parallax,
            weight: &weight,
        };
        let fit = py
            .detach(|| core::fit_board_tilts(&prob, &data, &start, z_c))
            .map_err(|e| to_pyerr(py, e))?;
        let out = PyDict::new(py);
        out.set_item(
            "offsets",
            fit.offsets.iter().map(|o| o.to_vec()).collect::<Vec<_>>(),
        )?;
        out.set_item(
            "offsets_se",
            fit.offsets_se
                .iter()
                .map(|o| o.to_vec())
                .collect::<Vec<_>>(),
        )?;
        out.set_item("z_c", fit.z_c)?;
        out.set_item("z_c_se", fit.z_c_se)?;
        out.set_item("gradient_ref", fit.gradient_ref.to_vec())?;
        out.set_item("gradient_ref_se", fit.gradient_ref_se.to_vec())?;
        out.set_item(
            "gradients",
            fit.gradients.iter().map(|g| g.to_vec()).collect::<Vec<_>>(),
        )?;
        out.set_item(
            "gradients_se",
            fit.gradients_se
                .iter()
                .map(|g| g.to_vec())
                .collect::<Vec<_>>(),
        )?;
        out.set_item("board_rms_px", fit.board_rms)?;
        out.set_item("board_downweighted", fit.board_downweighted)?;
        out.set_item("rms_px", fit.rms)?;
        out.set_item("iterations", fit.iterations)?;
        Ok(out)
    })
}
