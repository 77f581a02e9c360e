//! `invert_maps`, `place_samples`, `shift_and_add`, `shift_and_add_mean`, `data_weights`,
//! `btv_deblur`.

use lfcam_core::parallel;
use lfcam_core::superres::{self as core, BtvParams, PlaceParams, SplatParams};
use numpy::{PyArrayDyn, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{c_slice, fill, new_array, output_arg, rect_rows, typed, writable};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

fn count(py: Python<'_>, value: i64, arg: &str) -> PyResult<usize> {
    usize::try_from(value)
        .map_err(|_| input_error(py, arg, format!("expected an integer >= 0, got {value}")))
}

/// Runs `kernel` on two outputs (fresh, or the caller's from [`output_arg`], named
/// `args` in errors) with the GIL released, inside lfcam's pool.
fn fill2<A, B, F>(
    a: &Bound<'_, PyArrayDyn<A>>,
    b: &Bound<'_, PyArrayDyn<B>>,
    args: [&str; 2],
    function: &str,
    kernel: F,
) -> PyResult<()>
where
    A: numpy::Element + Send,
    B: numpy::Element + Send,
    F: FnOnce(&mut [A], &mut [B]) -> lfcam_core::Result<()> + Send,
{
    let py = a.py();
    let mut ra = writable(a, args[0])?;
    let mut rb = writable(b, args[1])?;
    let sa = ra
        .as_slice_mut()
        .map_err(|e| internal_error(py, function, format!("output slice: {e}")))?;
    let sb = rb
        .as_slice_mut()
        .map_err(|e| internal_error(py, function, format!("output slice: {e}")))?;
    py.detach(|| parallel::install(|| kernel(sa, sb)))
        .and_then(|inner| inner)
        .map_err(|e| to_pyerr(py, e))
}

/// Inverts the warp maps of all views into one raw-frame-sized map.
///
/// warps: (N, H, W, 2) float32, crop-relative raw positions of each rectified pixel.
/// masks: None or (N, H, W) uint8 (0: no data).
/// crops: (N, 4) int64 rows (x0, y0, w, h).
/// Returns (inv, view): (H_raw, W_raw, 2) float32 rectified positions (NaN: none) and
/// (H_raw, W_raw) int32 view indices (-1: none).
#[pyfunction]
#[pyo3(signature = (warps, masks, crops, raw_height, raw_width))]
pub fn invert_maps<'py>(
    py: Python<'py>,
    warps: &Bound<'py, PyAny>,
    masks: Option<&Bound<'py, PyAny>>,
    crops: &Bound<'py, PyAny>,
    raw_height: i64,
    raw_width: i64,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "invert_maps", || {
        let raw_h = count(py, raw_height, "raw_height")?;
        let raw_w = count(py, raw_width, "raw_width")?;
        let warps_ro = typed::<f32>(warps, "warps", "float32")?;
        let [n, h, w] = match *warps_ro.shape() {
            [n, h, w, 2] => [n, h, w],
            ref shape => {
                return Err(input_error(
                    py,
                    "warps",
                    format!("expected shape (N, H, W, 2), got {shape:?}"),
                ));
            }
        };
        let masks_ro = masks
            .map(|m| typed::<u8>(m, "masks", "uint8"))
            .transpose()?;
        let masks_s = match &masks_ro {
            Some(ro) => {
                if ro.shape() != [n, h, w] {
                    return Err(input_error(
                        py,
                        "masks",
                        format!("expected shape ({n}, {h}, {w}), got {:?}", ro.shape()),
                    ));
                }
                Some(c_slice(ro, "masks")?)
            }
            None => None,
        };
        let rects = rect_rows(crops, "crops")?;
        if rects.len() != n {
            return Err(input_error(
                py,
                "crops",
                format!("has {} rows but warps has {n} views", rects.len()),
            ));
        }
        let warps_s = c_slice(&warps_ro, "warps")?;
        let inv = new_array::<f32>(py, &[raw_h, raw_w, 2])?;
        let view = new_array::<i32>(py, &[raw_h, raw_w])?;
        fill2(&inv, &view, ["inv", "view"], "invert_maps", |a, b| {
            core::invert_maps(warps_s, masks_s, &rects, h, w, raw_h, raw_w, a, b)
        })?;
        PyTuple::new(py, [inv.into_any(), view.into_any()])
    })
}

/// Places raw samples in the reference frame: `p` with `p + o_i s(p) = q`.
///
/// inv: (..., 2) float32 positions q in each sample's own view; view: (...) int32
/// view indices (-1: none); offsets: (N, 2) float64; parallax: (H, W) float32.
/// Returns (..., 2) float32 reference positions (NaN: dropped).
#[pyfunction]
#[pyo3(signature = (inv, view, offsets, parallax, iterations, tolerance))]
pub fn place_samples<'py>(
    py: Python<'py>,
    inv: &Bound<'py, PyAny>,
    view: &Bound<'py, PyAny>,
    offsets: &Bound<'py, PyAny>,
    parallax: &Bound<'py, PyAny>,
    iterations: i64,
    tolerance: f64,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "place_samples", || {
        let params = PlaceParams {
            iterations: count(py, iterations, "iterations")?,
            tolerance: tolerance as f32,
        };
        let inv_ro = typed::<f32>(inv, "inv", "float32")?;
        let view_ro = typed::<i32>(view, "view", "int32")?;
        let shape = inv_ro.shape().to_vec();
        if shape.last() != Some(&2) || shape[..shape.len() - 1] != *view_ro.shape() {
            return Err(input_error(
                py,
                "inv",
                format!(
                    "expected shape (..., 2) matching view's {:?}, got {shape:?}",
                    view_ro.shape()
                ),
            ));
        }
        let offsets_ro = typed::<f64>(offsets, "offsets", "float64")?;
        if !matches!(offsets_ro.shape(), [_, 2]) {
            return Err(input_error(
                py,
                "offsets",
                format!("expected shape (N, 2), got {:?}", offsets_ro.shape()),
            ));
        }
        let (offset_rows, _) = c_slice(&offsets_ro, "offsets")?.as_chunks::<2>();
        let par_ro = typed::<f32>(parallax, "parallax", "float32")?;
        let [h, w] = match *par_ro.shape() {
            [h, w] => [h, w],
            ref s => {
                return Err(input_error(
                    py,
                    "parallax",
                    format!("expected shape (H, W), got {s:?}"),
                ));
            }
        };
        let inv_s = c_slice(&inv_ro, "inv")?;
        let view_s = c_slice(&view_ro, "view")?;
        let par_s = c_slice(&par_ro, "parallax")?;
        let out = new_array::<f32>(py, &shape)?;
        fill(&out, "place_samples", |o| {
            core::place_samples(inv_s, view_s, offset_rows, par_s, h, w, &params, o)
        })?;
        Ok(out.into_any())
    })
}

/// Positions, values and weights, as [`Samples::slices`] gives them.
type SampleSlices<'a> = (&'a [f32], &'a [f32], Option<&'a [f32]>);

/// The samples of a shift-and-add call, borrowed and checked.
struct Samples<'py> {
    pos: PyReadonlyArrayDyn<'py, f32>,
    val: PyReadonlyArrayDyn<'py, f32>,
    weights: Option<PyReadonlyArrayDyn<'py, f32>>,
    channels: usize,
}

impl<'py> Samples<'py> {
    /// positions: (..., 2) float32; values: (..., C) float32; weights: None or (...).
    fn borrow(
        positions: &Bound<'py, PyAny>,
        values: &Bound<'py, PyAny>,
        weights: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Self> {
        let py = positions.py();
        let pos = typed::<f32>(positions, "positions", "float32")?;
        let val = typed::<f32>(values, "values", "float32")?;
        let pshape = pos.shape();
        let vshape = val.shape();
        if pshape.last() != Some(&2)
            || vshape.len() != pshape.len()
            || vshape[..vshape.len() - 1] != pshape[..pshape.len() - 1]
        {
            return Err(input_error(
                py,
                "values",
                format!(
                    "expected shape (..., C) matching positions' (..., 2) {pshape:?}, got {vshape:?}"
                ),
            ));
        }
        let channels = *vshape.last().unwrap_or(&0);
        let weights = weights
            .map(|o| typed::<f32>(o, "weights", "float32"))
            .transpose()?;
        if let Some(ro) = &weights
            && ro.shape() != &pshape[..pshape.len() - 1]
        {
            return Err(input_error(
                py,
                "weights",
                format!(
                    "expected shape {:?}, got {:?}",
                    &pshape[..pshape.len() - 1],
                    ro.shape()
                ),
            ));
        }
        Ok(Self {
            pos,
            val,
            weights,
            channels,
        })
    }

    /// The positions, values and weights as contiguous slices.
    fn slices(&self) -> PyResult<SampleSlices<'_>> {
        let w = self
            .weights
            .as_ref()
            .map(|w| c_slice(w, "weights"))
            .transpose()?;
        Ok((
            c_slice(&self.pos, "positions")?,
            c_slice(&self.val, "values")?,
            w,
        ))
    }
}

#[allow(clippy::too_many_arguments)]
fn splat_params(
    py: Python<'_>,
    factor: f64,
    sigma: f64,
    radius: i64,
    iterations: i64,
    huber: f64,
    reject: f64,
) -> PyResult<SplatParams> {
    Ok(SplatParams {
        factor: factor as f32,
        sigma: sigma as f32,
        radius: count(py, radius, "radius")?,
        iterations: count(py, iterations, "iterations")?,
        huber: huber as f32,
        reject: reject as f32,
    })
}

/// Robust shift-and-add of scattered samples onto a fine grid.
///
/// positions: (..., 2) float32 rectified (x, y); values: (..., C) float32, C <= 4;
/// weights: None or (...) float32. Returns (sum, wsum): (fine_h, fine_w, C) and
/// (fine_h, fine_w) float32: fresh arrays, or sum_out / wsum_out (C-contiguous
/// float32 of those shapes, every element overwritten) when given.
#[pyfunction]
#[pyo3(signature = (positions, values, weights, fine_height, fine_width, factor, sigma, radius, iterations, huber, reject, sum_out=None, wsum_out=None))]
#[allow(clippy::too_many_arguments)]
pub fn shift_and_add<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    values: &Bound<'py, PyAny>,
    weights: Option<&Bound<'py, PyAny>>,
    fine_height: i64,
    fine_width: i64,
    factor: f64,
    sigma: f64,
    radius: i64,
    iterations: i64,
    huber: f64,
    reject: f64,
    sum_out: Option<&Bound<'py, PyAny>>,
    wsum_out: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "shift_and_add", || {
        let fh = count(py, fine_height, "fine_height")?;
        let fw = count(py, fine_width, "fine_width")?;
        let params = splat_params(py, factor, sigma, radius, iterations, huber, reject)?;
        let s = Samples::borrow(positions, values, weights)?;
        let (pos_s, val_s, w_s) = s.slices()?;
        let c = s.channels;
        let sum = output_arg::<f32>(py, sum_out, &[fh, fw, c], "float32", "out[0]")?;
        let wsum = output_arg::<f32>(py, wsum_out, &[fh, fw], "float32", "out[1]")?;
        fill2(
            &sum,
            &wsum,
            ["out[0]", "out[1]"],
            "shift_and_add",
            |sm, ws| core::shift_and_add(pos_s, val_s, w_s, c, fh, fw, &params, sm, ws),
        )?;
        PyTuple::new(py, [sum.into_any(), wsum.into_any()])
    })
}

/// Robust shift-and-add that returns the fused image itself.
///
/// As `shift_and_add`, plus min_weight. Returns (mean, wsum, have): mean (fine_h,
/// fine_w, C) float32, sum / wsum where wsum >= min_weight and finite, else 0; wsum
/// (fine_h, fine_w) float32; have (fine_h, fine_w) bool, where mean is data.
#[pyfunction]
#[pyo3(signature = (positions, values, weights, fine_height, fine_width, factor, sigma, radius, iterations, huber, reject, min_weight))]
#[allow(clippy::too_many_arguments)]
pub fn shift_and_add_mean<'py>(
    py: Python<'py>,
    positions: &Bound<'py, PyAny>,
    values: &Bound<'py, PyAny>,
    weights: Option<&Bound<'py, PyAny>>,
    fine_height: i64,
    fine_width: i64,
    factor: f64,
    sigma: f64,
    radius: i64,
    iterations: i64,
    huber: f64,
    reject: f64,
    min_weight: f64,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "shift_and_add_mean", || {
        let fh = count(py, fine_height, "fine_height")?;
        let fw = count(py, fine_width, "fine_width")?;
        let params = splat_params(py, factor, sigma, radius, iterations, huber, reject)?;
        let s = Samples::borrow(positions, values, weights)?;
        let (pos_s, val_s, w_s) = s.slices()?;
        let c = s.channels;
        let mean = new_array::<f32>(py, &[fh, fw, c])?;
        let wsum = new_array::<f32>(py, &[fh, fw])?;
        let have = new_array::<bool>(py, &[fh, fw])?;
        let mut ra = writable(&mean, "mean")?;
        let mut rb = writable(&wsum, "wsum")?;
        let mut rc = writable(&have, "have")?;
        let slice_err = |e| internal_error(py, "shift_and_add_mean", format!("output slice: {e}"));
        let m_s = ra.as_slice_mut().map_err(slice_err)?;
        let ws_s = rb.as_slice_mut().map_err(slice_err)?;
        let have_s = rc.as_slice_mut().map_err(slice_err)?;
        let min_w = min_weight as f32;
        py.detach(|| {
            parallel::install(|| {
                core::shift_and_add_mean(
                    pos_s, val_s, w_s, c, fh, fw, &params, min_w, m_s, ws_s, have_s,
                )
            })
        })
        .and_then(|inner| inner)
        .map_err(|e| to_pyerr(py, e))?;
        PyTuple::new(py, [mean.into_any(), wsum.into_any(), have.into_any()])
    })
}

/// The deblurring's data weights: a = sqrt(clip(wsum / t, 0, 4)), t the median of the
/// positive weights (numpy's median; 1 if none).
///
/// wsum: (H, W) float32. Returns a (H, W) float32.
#[pyfunction]
pub fn data_weights<'py>(py: Python<'py>, wsum: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "data_weights", || {
        let ws_ro = typed::<f32>(wsum, "wsum", "float32")?;
        let shape = ws_ro.shape().to_vec();
        let ws_s = c_slice(&ws_ro, "wsum")?;
        let out = new_array::<f32>(py, &shape)?;
        fill(&out, "data_weights", |a| {
            core::data_weights(ws_s, a).map(|_| ())
        })?;
        Ok(out.into_any())
    })
}

/// Bilateral-TV deblurring (Farsiu et al. 2004) of a shift-and-add image.
///
/// z: (H, W, C) float32, finite; a: (H, W) float32 data weights; x0: None (start
/// from z) or (H, W, C) float32. Returns the (H, W, C) float32 result.
#[pyfunction]
#[pyo3(signature = (z, a, x0, psf_sigma, lam, alpha, window, iterations, step, eps))]
#[allow(clippy::too_many_arguments)]
pub fn btv_deblur<'py>(
    py: Python<'py>,
    z: &Bound<'py, PyAny>,
    a: &Bound<'py, PyAny>,
    x0: Option<&Bound<'py, PyAny>>,
    psf_sigma: f64,
    lam: f64,
    alpha: f64,
    window: i64,
    iterations: i64,
    step: f64,
    eps: f64,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "btv_deblur", || {
        let params = BtvParams {
            psf_sigma: psf_sigma as f32,
            lambda: lam as f32,
            alpha: alpha as f32,
            window: count(py, window, "window")?,
            iterations: count(py, iterations, "iterations")?,
            step: step as f32,
            eps: eps as f32,
        };
        let z_ro = typed::<f32>(z, "z", "float32")?;
        let [h, w, c] = match *z_ro.shape() {
            [h, w, c] => [h, w, c],
            ref s => {
                return Err(input_error(
                    py,
                    "z",
                    format!("expected shape (H, W, C), got {s:?}"),
                ));
            }
        };
        let a_ro = typed::<f32>(a, "a", "float32")?;
        if a_ro.shape() != [h, w] {
            return Err(input_error(
                py,
                "a",
                format!("expected shape ({h}, {w}), got {:?}", a_ro.shape()),
            ));
        }
        let z_s = c_slice(&z_ro, "z")?;
        let a_s = c_slice(&a_ro, "a")?;
        let x0_ro = x0.map(|o| typed::<f32>(o, "x0", "float32")).transpose()?;
        let start: &[f32] = match &x0_ro {
            Some(ro) => {
                if ro.shape() != [h, w, c] {
                    return Err(input_error(
                        py,
                        "x0",
                        format!("expected shape ({h}, {w}, {c}), got {:?}", ro.shape()),
                    ));
                }
                c_slice(ro, "x0")?
            }
            None => z_s,
        };
        let out = new_array::<f32>(py, &[h, w, c])?;
        fill(&out, "btv_deblur", |x| {
            if x.len() != start.len() {
                return Err(lfcam_core::Error::invalid_argument("x0", "size mismatch"));
            }
            x.copy_from_slice(start);
            core::btv_deblur(z_s, a_s, h, w, c, &params, x)
        })?;
        Ok(out.into_any())
    })
}
