//! `rectify`, and `RectifyPlan`: the same prepared once per calibration.

use lfcam_core::ImageView;
use lfcam_core::rectify::{Interp, RawSample, ViewMaps, rectify_output_shape};
use numpy::{Element, PyArrayDescrMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods, dtype};
use pyo3::prelude::*;

use crate::arrays::{
    as_untyped, c_slice, dtype_name, fill, image_view, output_array, readonly, rect_rows, typed,
};
use crate::errors::{guarded, input_error, to_pyerr};

/// Rectifies views of a raw frame: gain, crop and remap in one pass (NaN for no data).
///
/// raw: (H, W) or (H, W, C) uint8, uint16 or float32, C-contiguous, C <= 4.
/// gains: (H, W) or (H, W, G) float32, G = 1 or C; 0 marks a masked pixel.
/// crops: (N, 4) int64 rows (x0, y0, w, h).
/// warps: (N, Hr, Wr, 2) float32, crop-relative positions (x, y).
/// masks: None or (N, Hr, Wr) uint8 (0: no data), e.g. a bool mask viewed as uint8.
/// interp: "bilinear", "bilinear-exact", "bilinear-q32" or "bicubic".
/// views: None (all) or (M,) int64 view indices.
/// out: None, or a float32 C-contiguous array of the output's shape to write into.
/// Returns a new (M, Hr, Wr) or (M, Hr, Wr, C) float32 array, or `out`.
#[pyfunction]
#[pyo3(signature = (raw, gains, crops, warps, masks, interp, views, out=None))]
#[allow(clippy::too_many_arguments)]
pub fn rectify<'py>(
    py: Python<'py>,
    raw: &Bound<'py, PyAny>,
    gains: &Bound<'py, PyAny>,
    crops: &Bound<'py, PyAny>,
    warps: &Bound<'py, PyAny>,
    masks: Option<&Bound<'py, PyAny>>,
    interp: &str,
    views: Option<&Bound<'py, PyAny>>,
    out: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "rectify", || {
        let interp: Interp = interp.parse().map_err(|e| to_pyerr(py, e))?;
        let raw_arr = as_untyped(raw, "raw")?;
        let args = Args {
            gains,
            crops,
            warps,
            masks,
            views,
            interp,
            out,
        };
        let dt = raw_arr.dtype();
        if dt.is_equiv_to(&dtype::<u8>(py)) {
            rectify_typed::<u8>(raw_arr, &args)
        } else if dt.is_equiv_to(&dtype::<u16>(py)) {
            rectify_typed::<u16>(raw_arr, &args)
        } else if dt.is_equiv_to(&dtype::<f32>(py)) {
            rectify_typed::<f32>(raw_arr, &args)
        } else {
            Err(input_error(
                py,
                "raw",
                format!(
                    "dtype {} is not supported; expected uint8, uint16 or float32",
                    dtype_name(raw_arr)
                ),
            ))
        }
    })
}

/// The arguments besides `raw`.
struct Args<'a, 'py> {
    gains: &'a Bound<'py, PyAny>,
    crops: &'a Bound<'py, PyAny>,
    warps: &'a Bound<'py, PyAny>,
    masks: Option<&'a Bound<'py, PyAny>>,
    views: Option<&'a Bound<'py, PyAny>>,
    interp: Interp,
    out: Option<&'a Bound<'py, PyAny>>,
}

fn rectify_typed<'py, T>(
    raw: &Bound<'py, numpy::PyUntypedArray>,
    args: &Args<'_, 'py>,
) -> PyResult<Bound<'py, PyAny>>
where
    T: Element + RawSample,
{
    let py = raw.py();
    let raw_ro = readonly::<T>(raw, "raw")?;
    let raw_v: ImageView<'_, T> = image_view(&raw_ro, "raw")?;
    let gains_ro = typed::<f32>(args.gains, "gains", "float32")?;
    let gains_v = image_view(&gains_ro, "gains")?;
    let crops = rect_rows(args.crops, "crops")?;

    let warps_ro = typed::<f32>(args.warps, "warps", "float32")?;
    let masks_ro = args
        .masks
        .map(|m| typed::<u8>(m, "masks", "uint8"))
        .transpose()?;
    let (warps, masks, [n, h, w]) = warp_maps(&warps_ro, masks_ro.as_ref())?;
    let views = view_indices(args.views, n)?;
    let maps = ViewMaps::new(warps, masks, n, h, w).map_err(|e| to_pyerr(py, e))?;
    let shape = rectify_output_shape(&raw_v, &gains_v, &crops, &maps, &views)
        .map_err(|e| to_pyerr(py, e))?;
    let shape = numpy_shape(shape, raw_ro.ndim());
    let out = output_array::<f32>(py, args.out, &shape, "float32")?;
    let interp = args.interp;
    fill(&out, "rectify", |slice| {
        lfcam_core::rectify(raw_v, gains_v, &crops, maps, &views, interp, slice)
    })?;
    Ok(out.into_any())
}

/// Warps and masks borrowed as slices, with the warps' `(N, H, W)`.
type WarpMaps<'a> = (&'a [f32], Option<&'a [u8]>, [usize; 3]);

/// `warps` as `(N, H, W, 2)` positions and `masks` as `(N, H, W)`, C-contiguous.
fn warp_maps<'a>(
    warps: &'a PyReadonlyArrayDyn<'_, f32>,
    masks: Option<&'a PyReadonlyArrayDyn<'_, u8>>,
) -> PyResult<WarpMaps<'a>> {
    let py = warps.py();
    let &[n, h, w, 2] = warps.shape() else {
        return Err(input_error(
            py,
            "warps",
            format!(
                "expected shape (N, H, W, 2) of positions (x, y), got {:?}",
                warps.shape()
            ),
        ));
    };
    let warps = c_slice(warps, "warps")?;
    let masks = match masks {
        None => None,
        Some(ro) => {
            if ro.shape() != [n, h, w] {
                return Err(input_error(
                    py,
                    "masks",
                    format!(
                        "shape {:?} differs from the warps' (N, H, W) = ({n}, {h}, {w})",
                        ro.shape()
                    ),
                ));
            }
            Some(c_slice(ro, "masks")?)
        }
    };
    Ok((warps, masks, [n, h, w]))
}

/// `views` as view indices (all `n` views if `None`).
fn view_indices(views: Option<&Bound<'_, PyAny>>, n: usize) -> PyResult<Vec<usize>> {
    let Some(v) = views else {
        return Ok((0..n).collect());
    };
    let py = v.py();
    let ro = typed::<i64>(v, "views", "int64")?;
    if ro.ndim() != 1 {
        return Err(input_error(
            py,
            "views",
            format!(
                "expected a 1-D array of view indices, got shape {:?}",
                ro.shape()
            ),
        ));
    }
    c_slice(&ro, "views")?
        .iter()
        .enumerate()
        .map(|(j, &i)| {
            usize::try_from(i).map_err(|_| {
                input_error(
                    py,
                    &format!("views[{j}]"),
                    format!("view index {i} is negative"),
                )
            })
        })
        .collect()
}

/// The numpy shape of an output `(M, H, W, C)`: without `C` for a 2-D raw frame.
fn numpy_shape([m, h, w, c]: [usize; 4], raw_ndim: usize) -> Vec<usize> {
    if raw_ndim == 2 {
        vec![m, h, w]
    } else {
        vec![m, h, w, c]
    }
}

/// A rectification prepared once per calibration: gains, crops, warps and masks
/// digested into what a capture's rectification reads (bilinear only).
///
/// gains: (H, W) or (H, W, G) float32, C-contiguous, G <= 4; 0 marks a masked pixel.
/// crops: (N, 4) int64 rows (x0, y0, w, h), inside the (H, W) frame.
/// warps: (N, Hr, Wr, 2) float32, crop-relative positions (x, y).
/// masks: None or (N, Hr, Wr) uint8 (0: no data).
/// interp: "bilinear" or "bilinear-exact".
/// The plan copies what it needs; it does not keep the arrays.
#[pyclass(frozen, module = "lfcam._lfcam", name = "RectifyPlan")]
#[derive(Debug)]
pub struct RectifyPlan {
    inner: lfcam_core::rectify::RectifyPlan,
}

#[pymethods]
impl RectifyPlan {
    #[new]
    #[pyo3(signature = (gains, crops, warps, masks, interp))]
    fn new(
        py: Python<'_>,
        gains: &Bound<'_, PyAny>,
        crops: &Bound<'_, PyAny>,
        warps: &Bound<'_, PyAny>,
        masks: Option<&Bound<'_, PyAny>>,
        interp: &str,
    ) -> PyResult<Self> {
        guarded(py, "RectifyPlan", || {
            let interp: Interp = interp.parse().map_err(|e| to_pyerr(py, e))?;
            let gains_ro = typed::<f32>(gains, "gains", "float32")?;
            let gains_v = image_view(&gains_ro, "gains")?;
            let crops = rect_rows(crops, "crops")?;
            let warps_ro = typed::<f32>(warps, "warps", "float32")?;
            let masks_ro = masks
                .map(|m| typed::<u8>(m, "masks", "uint8"))
                .transpose()?;
            let (warps, masks, [n, h, w]) = warp_maps(&warps_ro, masks_ro.as_ref())?;
            let maps = ViewMaps::new(warps, masks, n, h, w).map_err(|e| to_pyerr(py, e))?;
            let inner = py
                .detach(|| lfcam_core::rectify::RectifyPlan::new(gains_v, &crops, maps, interp))
                .map_err(|e| to_pyerr(py, e))?;
            Ok(Self { inner })
        })
    }

    /// Rectifies views of raw, (H, W) or (H, W, C) uint8, uint16 or float32,
    /// C-contiguous: views None (all) or (M,) int64 indices; out None or a float32
    /// C-contiguous array of the output's shape. Returns (M, Hr, Wr[, C]) float32.
    #[pyo3(signature = (raw, views=None, out=None))]
    fn rectify<'py>(
        &self,
        py: Python<'py>,
        raw: &Bound<'py, PyAny>,
        views: Option<&Bound<'py, PyAny>>,
        out: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        guarded(py, "RectifyPlan.rectify", || {
            let raw_arr = as_untyped(raw, "raw")?;
            let dt = raw_arr.dtype();
            if dt.is_equiv_to(&dtype::<u8>(py)) {
                self.rectify_typed::<u8>(raw_arr, views, out)
            } else if dt.is_equiv_to(&dtype::<u16>(py)) {
                self.rectify_typed::<u16>(raw_arr, views, out)
            } else if dt.is_equiv_to(&dtype::<f32>(py)) {
                self.rectify_typed::<f32>(raw_arr, views, out)
            } else {
                Err(input_error(
                    py,
                    "raw",
                    format!(
                        "dtype {} is not supported; expected uint8, uint16 or float32",
                        dtype_name(raw_arr)
                    ),
                ))
            }
        })
    }

    /// Number of views N.
    #[getter]
    fn n_views(&self) -> usize {
        self.inner.views()
    }

    /// The rectified (H, W).
    #[getter]
    fn shape(&self) -> (usize, usize) {
        self.inner.shape()
    }

    /// The raw frames' (H, W).
    #[getter]
    fn raw_shape(&self) -> (usize, usize) {
        self.inner.raw_shape()
    }

    /// Channels of the gains.
    #[getter]
    fn gain_channels(&self) -> usize {
        self.inner.gain_channels()
    }

    /// Rectified pixels with a value, over all views.
    #[getter]
    fn kept(&self) -> usize {
        self.inner.kept()
    }

    /// Bytes the plan holds.
    #[getter]
    fn nbytes(&self) -> usize {
        self.inner.nbytes()
    }
}

impl RectifyPlan {
    fn rectify_typed<'py, T>(
        &self,
        raw: &Bound<'py, numpy::PyUntypedArray>,
        views: Option<&Bound<'py, PyAny>>,
        out: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyAny>>
    where
        T: Element + RawSample,
    {
        let py = raw.py();
        let raw_ro = readonly::<T>(raw, "raw")?;
        let raw_v: ImageView<'_, T> = image_view(&raw_ro, "raw")?;
        let views = view_indices(views, self.inner.views())?;
        let shape = self
            .inner
            .output_shape(&raw_v, &views)
            .map_err(|e| to_pyerr(py, e))?;
        let out = output_array::<f32>(py, out, &numpy_shape(shape, raw_ro.ndim()), "float32")?;
        let plan = &self.inner;
        fill(&out, "RectifyPlan.rectify", |slice| {
            plan.rectify(raw_v, &views, slice)
        })?;
        Ok(out.into_any())
    }
}
