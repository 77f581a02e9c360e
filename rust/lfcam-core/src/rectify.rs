//! Rectification: the fused per-view pass (docs/design.md, "Rectification"): gain, crop and remap
//! in one read of the raw frame.
//!
//! For each selected view `i` and rectified pixel `(u, v)`, the raw position is
//! `(x, y) = warps[i, v, u] + (x0_i, y0_i)`, and the output is the interpolated value
//! of `raw * scale * gains` there (`scale` is 1/255 for `u8`, 1/65535 for `u16`, 1 for
//! `f32`). Positions are crop-relative in the warp maps, exactly as when the crop is cut
//! out first and remapped with OpenCV, so the sub-pixel arithmetic is the same.
//!
//! The output is NaN ("no data") in every channel where the view's mask is 0, the warp
//! is NaN, the interpolation footprint (the pixels with non-zero weight, see
//! [`crate::remap`]) leaves the crop rectangle, or a gain in the footprint is 0 (a
//! pixel the photometric calibration masked) or NaN.
//!
//! # How it runs
//! Output rows are split into tasks of at least `MIN_TASK_ROWS` rows (one loop body,
//! serial or in lfcam's pool, see [`crate::parallel`]). For the rows of one view in a
//! task, the kernel estimates the bounding box of their footprints (skipping masked
//! runs without reading their warps), computes `raw * scale * gains` for that band of
//! the crop once into a small buffer that stays in cache (0 gains become NaN, so the
//! interpolation needs no test for them), and interpolates from it; a footprint the
//! estimate missed is read from the raw frame directly, and so is every footprint
//! when the band would cost more than it saves (warps that jump around the crop).
//! Bilinear sampling from a band has its own loop (`Job::sample_rows_bilinear`):
//! per group of positions, offsets and fractions first (branch-free, vectorised),
//! positions without a sample pointed at NaN padding, then the interpolation; when
//! the band is *tame* (each pixel NaN in all channels or none, no huge values) the
//! result needs no NaN test. Nothing is precomputed for the whole frame, and every
//! output value is written once.
//!
//! For many captures with one calibration, [`RectifyPlan`] does what depends on the
//! maps and gains alone once, and its `rectify` only what depends on the raw frame.

mod plan;

use std::str::FromStr;

use crate::error::{Error, Result};
use crate::image::ImageView;
use crate::parallel;
use crate::remap::{
    Bicubic, Bilinear, BilinearQ32, Lanes, MAX_CHANNELS, Packed, Sampler, Taps, any_nan, first,
    four, last, lerp_lanes,
};
use crate::simd::Dispatch;
#[cfg(target_arch = "x86_64")]
use crate::simd::Level;

pub use plan::RectifyPlan;

/// How [`rectify`] interpolates the raw frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Interp {
    /// What `cv2.remap(..., cv2.INTER_LINEAR)` computes with float maps on a float32
    /// image in OpenCV >= 4.11 (including 5.0): true sub-pixel positions, float32
    /// arithmetic in OpenCV's order.
    Bilinear,
    /// Bilinear at the true position, as [`crate::remap::remap_bilinear`]. Since
    /// OpenCV 4.11 that is also what OpenCV does, so the result equals [`Self::Bilinear`];
    /// the name states the intent where it matters.
    BilinearExact,
    /// Bilinear at positions rounded to 1/32 pixel with OpenCV's weight table: what
    /// `cv2.remap(..., cv2.INTER_LINEAR)` computed with float maps before OpenCV 4.11,
    /// and still computes for 2-channel images or fixed-point maps.
    BilinearQ32,
    /// What `cv2.remap(..., cv2.INTER_CUBIC)` computes with float maps on a float32
    /// image in OpenCV 5.0: Keys' kernel with `a = -0.75` at the true position, 4x4
    /// footprint (1x1 on whole-number positions, where the other weights are 0).
    Bicubic,
}

impl Interp {
    /// Every variant, in the order of [`Self::NAMES`].
    pub const ALL: [Self; 4] = [
        Self::Bilinear,
        Self::BilinearExact,
        Self::BilinearQ32,
        Self::Bicubic,
    ];

    /// The names [`Interp::from_str`] accepts.
    pub const NAMES: [&'static str; 4] = ["bilinear", "bilinear-exact", "bilinear-q32", "bicubic"];

    /// The name of this method (one of [`Self::NAMES`]).
    pub fn name(self) -> &'static str {
        match self {
            Self::Bilinear => "bilinear",
            Self::BilinearExact => "bilinear-exact",
            Self::BilinearQ32 => "bilinear-q32",
            Self::Bicubic => "bicubic",
        }
    }
}

impl FromStr for Interp {
    type Err = Error;

    /// Parses one of [`Interp::NAMES`].
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] `"interp"` for any other string.
    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|i| i.name() == s)
            .ok_or_else(|| {
                Error::invalid_argument(
                    "interp",
                    format!(
                        "expected one of {}, got {s:?}",
                        Self::NAMES.map(|n| format!("{n:?}")).join(", ")
                    ),
                )
            })
    }
}

/// A raw sample type and its scale to `[0, 1]`.
pub trait RawSample: Copy + Default + Send + Sync + 'static {
    /// The factor that maps the type's full range to `[0, 1]`.
    const SCALE: f32;
    /// Whether the type is an integer (its values are finite).
    const INTEGER: bool;
    /// The value as f32, unscaled.
    fn to_f32(self) -> f32;
}

impl RawSample for u8 {
    const SCALE: f32 = 1.0 / 255.0;
    const INTEGER: bool = true;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
}

impl RawSample for u16 {
    const SCALE: f32 = 1.0 / 65535.0;
    const INTEGER: bool = true;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        f32::from(self)
    }
}

impl RawSample for f32 {
    const SCALE: f32 = 1.0;
    const INTEGER: bool = false;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self
    }
}

/// The per-view warp maps and optional masks, borrowed: `warps` is `(N, H, W, 2)` and
/// `masks` `(N, H, W)` (0: no data), both C-contiguous. Positions are crop-relative.
#[derive(Debug, Clone, Copy)]
pub struct ViewMaps<'a> {
    warps: &'a [f32],
    masks: Option<&'a [u8]>,
    views: usize,
    height: usize,
    width: usize,
}

impl<'a> ViewMaps<'a> {
    /// Wraps `warps` (and `masks`) as `views` maps of `height x width` positions.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] `"warps"` if a dimension is zero or `warps.len() !=
    /// views * height * width * 2`; `"masks"` if `masks.len() != views * height * width`.
    pub fn new(
        warps: &'a [f32],
        masks: Option<&'a [u8]>,
        views: usize,
        height: usize,
        width: usize,
    ) -> Result<Self> {
        if views == 0 || height == 0 || width == 0 {
            return Err(Error::invalid_argument(
                "warps",
                format!(
                    "every dimension must be at least 1, got (N, H, W) = ({views}, {height}, {width})"
                ),
            ));
        }
        let pixels = views.checked_mul(height).and_then(|n| n.checked_mul(width));
        if pixels.and_then(|n| n.checked_mul(2)) != Some(warps.len()) {
            return Err(Error::invalid_argument(
                "warps",
                format!(
                    "has {} elements, but (N, H, W, 2) = ({views}, {height}, {width}, 2) needs \
                     2 per position",
                    warps.len()
                ),
            ));
        }
        if let Some(m) = masks
            && pixels != Some(m.len())
        {
            return Err(Error::invalid_argument(
                "masks",
                format!(
                    "has {} elements, but the warps' (N, H, W) = ({views}, {height}, {width}) \
                     needs one per position",
                    m.len()
                ),
            ));
        }
        Ok(Self {
            warps,
            masks,
            views,
            height,
            width,
        })
    }

    /// Number of views `N`.
    pub fn views(&self) -> usize {
        self.views
    }

    /// Rectified height `H`.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Rectified width `W`.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Row `v` of view `i`'s warp (`2 W` values).
    fn warp_row(&self, i: usize, v: usize) -> Option<&'a [f32]> {
        let len = 2 * self.width;
        let start = (i * self.height + v) * len;
        self.warps.get(start..start + len)
    }

    /// Row `v` of view `i`'s mask (`W` values), `Some(None)` without masks.
    fn mask_row(&self, i: usize, v: usize) -> Option<Option<&'a [u8]>> {
        match self.masks {
            None => Some(None),
            Some(m) => {
                let start = (i * self.height + v) * self.width;
                m.get(start..start + self.width).map(Some)
            }
        }
    }
}

/// A crop rectangle that passed validation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Crop {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
}

/// Everything [`rectify`] checks before it writes anything.
#[derive(Debug)]
struct Checked {
    crops: Vec<Crop>,
    shape: [usize; 4],
}

fn check_crop(index: usize, rect: [i64; 4], width: usize, height: usize) -> Result<Crop> {
    let [x0, y0, w, h] = rect;
    let describe = || format!("rectangle (x0, y0, w, h) = ({x0}, {y0}, {w}, {h})");
    if w < 1 || h < 1 {
        return Err(Error::invalid_item(
            "crops",
            index,
            format!("{} must have a width and height of at least 1", describe()),
        ));
    }
    let frame_w = i64::try_from(width).unwrap_or(i64::MAX);
    let frame_h = i64::try_from(height).unwrap_or(i64::MAX);
    let inside = x0 >= 0
        && y0 >= 0
        && x0.checked_add(w).is_some_and(|x1| x1 <= frame_w)
        && y0.checked_add(h).is_some_and(|y1| y1 <= frame_h);
    let as_usize = |v: i64| usize::try_from(v).ok();
    match (inside, as_usize(x0), as_usize(y0), as_usize(w), as_usize(h)) {
        (true, Some(x0), Some(y0), Some(w), Some(h)) => Ok(Crop { x0, y0, w, h }),
        _ => Err(Error::invalid_item(
            "crops",
            index,
            format!("{} lies outside the {width}x{height} raw frame", describe()),
        )),
    }
}

fn check<T>(
    raw: &ImageView<'_, T>,
    gains: &ImageView<'_, f32>,
    crops: &[[i64; 4]],
    maps: &ViewMaps<'_>,
    views: &[usize],
) -> Result<Checked> {
    let c = raw.channels();
    if c > MAX_CHANNELS {
        return Err(Error::invalid_argument(
            "raw",
            format!("has {c} channels; 1 to {MAX_CHANNELS} are supported"),
        ));
    }
    if (gains.height(), gains.width()) != (raw.height(), raw.width()) {
        return Err(Error::invalid_argument(
            "gains",
            format!(
                "(H, W) = ({}, {}) differs from raw's ({}, {})",
                gains.height(),
                gains.width(),
                raw.height(),
                raw.width()
            ),
        ));
    }
    let g = gains.channels();
    if g != 1 && g != c {
        return Err(Error::invalid_argument(
            "gains",
            format!(
                "has {g} channels but raw has {c}; gains need 1 channel (shared by every \
                 channel of raw) or {c}"
            ),
        ));
    }
    if crops.len() != maps.views() {
        return Err(Error::invalid_argument(
            "crops",
            format!(
                "has {} rectangles but warps has {} views; one rectangle per view is needed",
                crops.len(),
                maps.views()
            ),
        ));
    }
    let crops = crops
        .iter()
        .enumerate()
        .map(|(i, &r)| check_crop(i, r, raw.width(), raw.height()))
        .collect::<Result<Vec<_>>>()?;
    if views.is_empty() {
        return Err(Error::invalid_argument(
            "views",
            "at least one view must be selected, got none",
        ));
    }
    if let Some((j, &i)) = views.iter().enumerate().find(|&(_, &i)| i >= maps.views()) {
        return Err(Error::invalid_item(
            "views",
            j,
            format!("view index {i} is out of range for {} views", maps.views()),
        ));
    }
    let shape = [views.len(), maps.height(), maps.width(), c];
    shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| {
            Error::invalid_argument(
                "views",
                format!("the output shape {shape:?} has too many elements"),
            )
        })?;
    Ok(Checked { crops, shape })
}

/// The output shape `(len(views), H, W, C)` of [`rectify`], after validating the inputs
/// exactly as [`rectify`] does. Use it to allocate the output.
///
/// # Errors
/// As [`rectify`], except for the check of `out`.
pub fn rectify_output_shape<T>(
    raw: &ImageView<'_, T>,
    gains: &ImageView<'_, f32>,
    crops: &[[i64; 4]],
    maps: &ViewMaps<'_>,
    views: &[usize],
) -> Result<[usize; 4]> {
    check(raw, gains, crops, maps, views).map(|c| c.shape)
}

/// Rectifies the selected `views` of the raw frame `raw` (gain, crop and remap fused)
/// into `out`, laid out `(len(views), H, W, C)` C-contiguous, `C` the channels of raw;
/// `out[j]` is view `views[j]`. See the module docs for the formula and for where the
/// output is NaN.
///
/// `gains` has raw's `(H, W)` and 1 channel (applied to every channel of raw) or as
/// many as raw. `crops[i] = (x0, y0, w, h)` is view `i`'s rectangle in raw pixels; the
/// warp positions of view `i` are relative to it, and its footprints must stay inside
/// it. Every input is checked before anything is written. Runs in lfcam's pool over
/// (view, row) tasks.
///
/// # Errors
/// - [`Error::InvalidArgument`] `"raw"` if raw has more than [`MAX_CHANNELS`] channels;
/// - [`Error::InvalidArgument`] `"gains"` if its `(H, W)` differs from raw's, or its
///   channel count is neither 1 nor raw's;
/// - [`Error::InvalidArgument`] `"crops"` if there is not one rectangle per view of
///   `maps`; [`Error::InvalidItem`] `"crops"` naming the first rectangle that is empty
///   or not inside the raw frame;
/// - [`Error::InvalidArgument`] `"views"` if `views` is empty; [`Error::InvalidItem`]
///   `"views"` naming the first index `>= N`;
/// - [`Error::InvalidArgument`] `"out"` if `out.len()` is not the product of the shape.
pub fn rectify<T: RawSample>(
    raw: ImageView<'_, T>,
    gains: ImageView<'_, f32>,
    crops: &[[i64; 4]],
    maps: ViewMaps<'_>,
    views: &[usize],
    interp: Interp,
    out: &mut [f32],
) -> Result<()> {
    rectify_with(
        raw,
        gains,
        crops,
        maps,
        views,
        interp,
        out,
        &Dispatch::auto(),
    )
}

/// [`rectify`] with the builds `simd` allows (see [`crate::simd`]).
#[allow(clippy::too_many_arguments)]
fn rectify_with<T: RawSample>(
    raw: ImageView<'_, T>,
    gains: ImageView<'_, f32>,
    crops: &[[i64; 4]],
    maps: ViewMaps<'_>,
    views: &[usize],
    interp: Interp,
    out: &mut [f32],
    simd: &Dispatch,
) -> Result<()> {
    let checked = check(&raw, &gains, crops, &maps, views)?;
    let expected: usize = checked.shape.iter().product();
    if out.len() != expected {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "has {} elements, but the output {:?} needs {expected}",
                out.len(),
                checked.shape
            ),
        ));
    }
    // Off x86-64 there is no SIMD build to choose: the portable one runs.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = simd;
    let job = Job {
        raw,
        gains,
        crops: &checked.crops,
        maps,
        views,
        #[cfg(target_arch = "x86_64")]
        simd,
    };
    match (raw.channels(), gains.channels()) {
        (1, 1) => job.run::<1, 1>(interp, out),
        (2, 1) => job.run::<2, 1>(interp, out),
        (2, 2) => job.run::<2, 2>(interp, out),
        (3, 1) => job.run::<3, 1>(interp, out),
        (3, 3) => job.run::<3, 3>(interp, out),
        (4, 1) => job.run::<4, 1>(interp, out),
        (4, 4) => job.run::<4, 4>(interp, out),
        (c, g) => Err(Error::internal(
            "rectify",
            format!("unexpected channel counts raw {c}, gains {g}"),
        )),
    }
}

/// `(raw * scale) * gain` at raw pixel `px` (row-major index), lane by lane; NaN in
/// a lane whose gain is 0 (a masked pixel). `None` outside the frame.
#[inline(always)]
fn gained<T: RawSample, const C: usize, const G: usize>(
    raw: &[T],
    gains: &[f32],
    px: usize,
) -> Option<Lanes> {
    let r = four(raw, px * C)?;
    let g: Lanes = if G == 1 {
        [*gains.get(px)?; 4]
    } else {
        four(gains, px * G)?
    };
    let mut v = [0.0f32; 4];
    for ((v, &r), &g) in v.iter_mut().zip(&r).zip(&g) {
        *v = if g == 0.0 {
            f32::NAN
        } else {
            (r.to_f32() * T::SCALE) * g
        };
    }
    Some(v)
}

/// The raw frame and its gains read pixel by pixel, in one crop's coordinates.
#[derive(Debug, Clone, Copy)]
struct Direct<'a, T, const C: usize, const G: usize> {
    raw: &'a [T],
    gains: &'a [f32],
    width: usize,
    x0: usize,
    y0: usize,
}

impl<T: RawSample, const C: usize, const G: usize> Taps for Direct<'_, T, C, G> {
    #[inline(always)]
    fn tap(&self, row: usize, col: usize) -> Option<Lanes> {
        gained::<T, C, G>(
            self.raw,
            self.gains,
            (self.y0 + row) * self.width + self.x0 + col,
        )
    }
}

/// Output rows per task, at least: a task first computes the gained raw pixels its
/// footprints need (a band a little taller than the task, see [`Job::segment`]), so
/// short tasks would recompute the rows shared with their neighbours: with 32 rows
/// (about 29 raw rows at the usual scale) the band is some 15% taller than the rows it
/// serves; 16 to 64 rows time the same, and 32 keeps hundreds of tasks to balance
/// (docs/tuning.md, "Rectification").
const MIN_TASK_ROWS: usize = 32;

/// The band of gained pixels is computed when its area is at most this many times the
/// number of positions that sample it (plus [`BAND_SLACK`]); beyond that (warps that
/// jump around the crop), taps are read from the raw frame directly. Computing a
/// band pixel costs about a fifth of sampling one position from the raw frame.
const BAND_PER_POSITION: usize = 4;
const BAND_SLACK: usize = 4096;

/// [`Job::extent`] reads the positions of every this many rows (and the last): the
/// warps are smooth, and a footprint the estimate misses is still sampled, from the
/// raw frame. Reading every row cost about 6% of the whole (benchmarks/run.py, full
/// size).
const EXTENT_ROW_STEP: usize = 4;

/// Positions handled together where masks allow skipping: 16 mask bytes are one
/// `u128` comparison.
const GROUP: usize = 16;

/// Extra columns and rows around the estimated footprints in a band (see
/// [`Job::extent`]): positions the estimate skipped lie between seen ones, and with
/// smooth warps within this much of them. Footprints outside the band are still
/// sampled, from the raw frame.
const BAND_MARGIN: usize = 1;

/// The positions of a run of rows of one view: the bounding box of those that may
/// have a footprint inside the crop, and about how many there are.
#[derive(Debug, Clone, Copy)]
struct Extent {
    x: (f32, f32),
    y: (f32, f32),
    count: usize,
    /// Whether any position is kept at all (every one is, without masks).
    any_kept: bool,
}

/// One call's validated inputs.
#[derive(Debug)]
struct Job<'a, T> {
    raw: ImageView<'a, T>,
    gains: ImageView<'a, f32>,
    crops: &'a [Crop],
    maps: ViewMaps<'a>,
    views: &'a [usize],
    /// Which builds of the loops may run (x86-64: elsewhere the portable one is all).
    #[cfg(target_arch = "x86_64")]
    simd: &'a Dispatch,
}

impl<T: RawSample> Job<'_, T> {
    fn run<const C: usize, const G: usize>(&self, interp: Interp, out: &mut [f32]) -> Result<()> {
        match interp {
            Interp::Bilinear | Interp::BilinearExact => self.rows::<C, G, Bilinear>(out),
            Interp::BilinearQ32 => self.rows::<C, G, BilinearQ32>(out),
            Interp::Bicubic => self.rows::<C, G, Bicubic>(out),
        }
    }

    /// Output rows in tasks of whole rows, serial or parallel; each task splits its
    /// rows into runs of one view.
    fn rows<const C: usize, const G: usize, S: Sampler>(&self, out: &mut [f32]) -> Result<()> {
        let h = self.maps.height();
        let row_len = self.maps.width() * C;
        parallel::for_each_row_chunk_min(out, row_len, MIN_TASK_ROWS, |first_row, rows| {
            let mut band = Vec::new();
            let mut g = first_row;
            let mut rest = rows;
            while !rest.is_empty() {
                let (j, v) = (g / h, g % h);
                let n = (h - v).min(rest.len() / row_len);
                let (run, tail) = std::mem::take(&mut rest).split_at_mut(n * row_len);
                let view = *self.views.get(j).ok_or_else(|| internal("rectify", g))?;
                self.segment::<C, G, S>(view, v, run, &mut band)?;
                rest = tail;
                g += n;
            }
            Ok(())
        })
    }

    /// [`Self::segment_impl`], compiled for AVX2 if [`Self::simd`] selects it (see
    /// [`crate::simd`]), else for the baseline.
    fn segment<const C: usize, const G: usize, S: Sampler>(
        &self,
        view: usize,
        v0: usize,
        out: &mut [f32],
        band: &mut Vec<f32>,
    ) -> Result<()> {
        #[cfg(target_arch = "x86_64")]
        if self.simd.select(Level::Avx2) {
            // SAFETY: `segment_avx2` needs only AVX2, which this CPU has: a `Dispatch`
            // selects only levels `simd::level` allows.
            #[allow(unsafe_code)]
            let result = unsafe { self.segment_avx2::<C, G, S>(view, v0, out, band) };
            return result;
        }
        self.segment_impl::<C, G, S>(view, v0, out, band)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn segment_avx2<const C: usize, const G: usize, S: Sampler>(
        &self,
        view: usize,
        v0: usize,
        out: &mut [f32],
        band: &mut Vec<f32>,
    ) -> Result<()> {
        self.segment_impl::<C, G, S>(view, v0, out, band)
    }

    /// Rows `v0..` of view `view` into `out` (whole rows). Estimates the bounding box
    /// of the footprints, computes the gained raw pixels of that band once into `band`
    /// and samples them, reading the raw frame directly for the footprints the band
    /// misses; reads the raw frame for every tap when the band would be much larger
    /// than the work it saves.
    #[inline(always)]
    fn segment_impl<const C: usize, const G: usize, S: Sampler>(
        &self,
        view: usize,
        v0: usize,
        out: &mut [f32],
        band: &mut Vec<f32>,
    ) -> Result<()> {
        let crop = *self
            .crops
            .get(view)
            .ok_or_else(|| internal("rectify", v0))?;
        let n_rows = out.len() / (self.maps.width() * C);
        let direct = Direct::<T, C, G> {
            raw: self.raw.as_slice(),
            gains: self.gains.as_slice(),
            width: self.raw.width(),
            x0: crop.x0,
            y0: crop.y0,
        };
        let extent = self.extent(view, v0, n_rows, &crop)?;
        if !extent.any_kept {
            out.fill(f32::NAN);
            return Ok(());
        }
        // Footprint columns and rows: floor(x) - BEFORE ..= floor(x) + AFTER, widened
        // by MARGIN for the positions the estimate skipped, clipped to the crop.
        let span = |(lo, hi): (f32, f32), n: usize| {
            let lo = (lo.floor() as i64 - (S::BEFORE + BAND_MARGIN) as i64).max(0);
            let hi = (hi.floor() as i64 + (S::AFTER + BAND_MARGIN) as i64).min(n as i64 - 1);
            (lo <= hi).then(|| (lo as usize, (hi - lo + 1) as usize))
        };
        match (span(extent.x, crop.w), span(extent.y, crop.h)) {
            (Some((col0, bw)), Some((row0, bh)))
                if bw * bh <= BAND_PER_POSITION * extent.count + BAND_SLACK =>
            {
                let tame = self.fill_band::<C, G>(&crop, (col0, bw), (row0, bh), band)?;
                let taps = Packed::<C> {
                    data: band,
                    stride: bw * C,
                    row0,
                    col0,
                    rows: bh,
                    cols: bw,
                };
                if S::IS_BILINEAR && tame {
                    self.sample_rows_bilinear::<C, false, _>(&taps, &direct, view, v0, &crop, out)
                } else if S::IS_BILINEAR {
                    self.sample_rows_bilinear::<C, true, _>(&taps, &direct, view, v0, &crop, out)
                } else {
                    self.sample_rows::<C, S, _, _>(&taps, Some(&direct), view, v0, &crop, out)
                }
            }
            _ => self
                .sample_rows::<C, S, _, Direct<'_, T, C, G>>(&direct, None, view, v0, &crop, out),
        }
    }

    /// An estimate of the [`Extent`] of rows `v0..v0 + n_rows` of view `view`: every
    /// fourth kept position within `[-1, w] x [-1, h]` of the crop (a superset of
    /// those with a footprint inside) on every [`EXTENT_ROW_STEP`]-th row and the last
    /// one; `count` scales the positions seen to all. `any_kept` is exact.
    #[inline(always)]
    fn extent(&self, view: usize, v0: usize, n_rows: usize, crop: &Crop) -> Result<Extent> {
        let mut any_kept = false;
        let mut e = Extent {
            x: (f32::INFINITY, f32::NEG_INFINITY),
            y: (f32::INFINITY, f32::NEG_INFINITY),
            count: 0,
            any_kept: false,
        };
        let (xmax, ymax) = (crop.w as f32, crop.h as f32);
        let mut add = |[x, y]: [f32; 2], keep: bool| {
            // NaN fails every comparison.
            if keep && x >= -1.0 && x <= xmax && y >= -1.0 && y <= ymax {
                e.x = (
                    if x < e.x.0 { x } else { e.x.0 },
                    if x > e.x.1 { x } else { e.x.1 },
                );
                e.y = (
                    if y < e.y.0 { y } else { e.y.0 },
                    if y > e.y.1 { y } else { e.y.1 },
                );
                e.count += 4 * EXTENT_ROW_STEP;
            }
        };
        for v in v0..v0 + n_rows {
            if !(v - v0).is_multiple_of(EXTENT_ROW_STEP) && v + 1 != v0 + n_rows {
                // Not sampled: only whether a position is kept.
                if !any_kept {
                    any_kept = match self
                        .maps
                        .mask_row(view, v)
                        .ok_or_else(|| internal("rectify", v))?
                    {
                        None => true,
                        Some(mask) => mask.iter().any(|&k| k != 0),
                    };
                }
                continue;
            }
            let points = self
                .maps
                .warp_row(view, v)
                .ok_or_else(|| internal("rectify", v))?
                .as_chunks::<2>()
                .0;
            // The last position of a row is always seen: extremes are often there.
            let last = points.len().saturating_sub(1);
            match self
                .maps
                .mask_row(view, v)
                .ok_or_else(|| internal("rectify", v))?
            {
                None => {
                    any_kept = true;
                    for (i, &p) in points.iter().enumerate() {
                        if i % 4 == 0 || i == last {
                            add(p, true);
                        }
                    }
                }
                Some(mask) => {
                    // Masks come in long runs: skip a group of masked positions at a
                    // time without reading their warps.
                    for (j, (group, keep)) in
                        points.chunks(GROUP).zip(mask.chunks(GROUP)).enumerate()
                    {
                        if keep
                            .first_chunk::<GROUP>()
                            .is_some_and(|k| u128::from_ne_bytes(*k) == 0)
                        {
                            continue;
                        }
                        any_kept |= keep.iter().any(|&k| k != 0);
                        for (i, (&p, &k)) in group.iter().zip(keep).enumerate() {
                            if i % 4 == 0 || GROUP * j + i == last {
                                add(p, k != 0);
                            }
                        }
                    }
                }
            }
        }
        e.any_kept = any_kept;
        Ok(e)
    }

    /// Row `v` of view `view`: its positions, and their mask in groups of [`GROUP`]
    /// (all 1 without masks).
    #[inline(always)]
    fn row_inputs(
        &self,
        view: usize,
        v: usize,
    ) -> Result<(&[[f32; 2]], impl Iterator<Item = &[u8]>)> {
        const KEEP_ALL: [u8; GROUP] = [1; GROUP];
        let warp_row = self
            .maps
            .warp_row(view, v)
            .ok_or_else(|| internal("rectify", v))?;
        let mask_row = self
            .maps
            .mask_row(view, v)
            .ok_or_else(|| internal("rectify", v))?;
        let keep = mask_row
            .into_iter()
            .flat_map(|m| m.chunks(GROUP))
            .chain(std::iter::repeat(&KEEP_ALL[..]));
        Ok((warp_row.as_chunks::<2>().0, keep))
    }

    /// `band` := the gained raw pixels of crop columns `col0 .. col0 + bw`, rows
    /// `row0 .. row0 + bh`, `C` channels each, row after row (plus 8 NaN values, so
    /// that two pixels' lanes can be read at the last pixel). Returns whether the band
    /// is *tame*: each pixel NaN in all its channels or in none, and every value NaN or
    /// below [`TAME`] in magnitude. Bilinear interpolation of a tame band is NaN in all
    /// channels or in none (an infinity could make one channel NaN: `inf - inf`).
    #[inline(always)]
    fn fill_band<const C: usize, const G: usize>(
        &self,
        crop: &Crop,
        (col0, bw): (usize, usize),
        (row0, bh): (usize, usize),
        band: &mut Vec<f32>,
    ) -> Result<bool> {
        band.clear();
        band.reserve(bh * bw * C + 8);
        let mut wild = false;
        let x = crop.x0 + col0;
        for y in crop.y0 + row0..crop.y0 + row0 + bh {
            let bad = || internal("rectify", y);
            let raw = self.raw.row_span(y, x, bw).ok_or_else(bad)?;
            let gains = self.gains.row_span(y, x, bw).ok_or_else(bad)?;
            // Written as a select so that the loops vectorise.
            let gained = |r: T, g: f32| {
                let v = (r.to_f32() * T::SCALE) * g;
                if g == 0.0 { f32::NAN } else { v }
            };
            let start = band.len();
            if G == C {
                band.extend(raw.iter().zip(gains).map(|(&r, &g)| gained(r, g)));
            } else {
                let (raw, _) = raw.as_chunks::<C>();
                for (r, &g) in raw.iter().zip(gains) {
                    band.extend(r.iter().map(|&r| gained(r, g)));
                }
            }
            let row = band.get(start..).ok_or_else(bad)?;
            // `|` rather than `||`: branch-free, so that the loops vectorise.
            wild |= row.iter().fold(false, |w, &v| w | (v.abs() >= TAME));
            // With one gain for all channels of an integer raw, a pixel is NaN in all
            // channels (gain 0 or NaN) or in none, but for `0 * inf`, which `wild`
            // catches.
            if C > 1 && (G > 1 || !T::INTEGER) {
                let (pixels, _) = row.as_chunks::<C>();
                wild |= pixels.iter().fold(false, |w, p| {
                    w | p.windows(2).fold(false, |m, v| {
                        m | (v.first().is_some_and(|a| a.is_nan())
                            != v.last().is_some_and(|b| b.is_nan()))
                    })
                });
            }
        }
        band.extend([f32::NAN; 8]);
        Ok(!wild)
    }

    /// The one sampling loop: every output pixel of rows `v0..` of view `view` is
    /// written once, from taps read through `taps`, or through `fallback` for the
    /// footprints `taps` does not hold.
    #[inline(always)]
    fn sample_rows<const C: usize, S: Sampler, P: Taps, Q: Taps>(
        &self,
        taps: &P,
        fallback: Option<&Q>,
        view: usize,
        v0: usize,
        crop: &Crop,
        out: &mut [f32],
    ) -> Result<()> {
        let row_len = self.maps.width() * C;
        for (k, out_row) in out.chunks_exact_mut(row_len).enumerate() {
            let (points, keep) = self.row_inputs(view, v0 + k)?;
            let (pixels, _) = out_row.as_chunks_mut::<C>();
            let groups = pixels.chunks_mut(GROUP).zip(points.chunks(GROUP)).zip(keep);
            for ((pixels, points), keep) in groups {
                // Masks come in long runs: a masked group is one fill.
                if keep
                    .first_chunk::<GROUP>()
                    .is_some_and(|k| u128::from_ne_bytes(*k) == 0)
                {
                    pixels.as_flattened_mut().fill(f32::NAN);
                    continue;
                }
                for ((px, &[x, y]), &keep) in pixels.iter_mut().zip(points).zip(keep) {
                    let value = if keep != 0 {
                        S::sample(taps, crop.w, crop.h, x, y)
                            .or_else(|| fallback.and_then(|f| S::sample(f, crop.w, crop.h, x, y)))
                    } else {
                        None
                    };
                    *px = match value {
                        Some(v) if !any_nan(&v, C) => first::<C>(&v),
                        _ => [f32::NAN; C],
                    };
                }
            }
        }
        Ok(())
    }
}

impl<T: RawSample> Job<'_, T> {
    /// [`Self::sample_rows`] for [`Bilinear`] from a band, the values bit for bit, in
    /// two steps per group of [`GROUP`] positions: first, branch-free and vectorisable,
    /// each position's band offset, steps to its right and lower neighbours and
    /// fractions, with the positions that have no sample pointed at the band's NaN
    /// padding (so they come out NaN with no test); then the interpolation, one pixel
    /// after the other. Footprints inside the crop but outside the band (rare: the band
    /// is estimated) are sampled from `fallback` afterwards. Without `CHECK_NAN`, the
    /// band must be tame (see [`Self::fill_band`]): the result is then NaN in all
    /// channels or in none without a test.
    #[inline(always)]
    fn sample_rows_bilinear<const C: usize, const CHECK_NAN: bool, Q: Taps>(
        &self,
        band: &Packed<'_, C>,
        fallback: &Q,
        view: usize,
        v0: usize,
        crop: &Crop,
        out: &mut [f32],
    ) -> Result<()> {
        let data = band.data;
        // `fill_band` pads the band with 8 NaN values.
        let nan_at = data
            .len()
            .checked_sub(8)
            .ok_or_else(|| internal("rectify", v0))?;
        let as_i32 = |v: usize| i32::try_from(v).ok();
        let (Some(nan_at), Some(stride), Some(row0), Some(col0), Some(rows), Some(cols)) = (
            as_i32(nan_at),
            as_i32(band.stride),
            as_i32(band.row0),
            as_i32(band.col0),
            as_i32(band.rows),
            as_i32(band.cols),
        ) else {
            // A band beyond i32 offsets: the general loop.
            return self.sample_rows::<C, Bilinear, _, _>(
                band,
                Some(fallback),
                view,
                v0,
                crop,
                out,
            );
        };
        if crop.w > FLOOR_LIMIT || crop.h > FLOOR_LIMIT {
            return self.sample_rows::<C, Bilinear, _, _>(
                band,
                Some(fallback),
                view,
                v0,
                crop,
                out,
            );
        }
        let (wl, hl) = (last(crop.w), last(crop.h));
        let row_len = self.maps.width() * C;
        for (k, out_row) in out.chunks_exact_mut(row_len).enumerate() {
            let (points, keep) = self.row_inputs(view, v0 + k)?;
            let (pixels, _) = out_row.as_chunks_mut::<C>();
            let groups = pixels.chunks_mut(GROUP).zip(points.chunks(GROUP)).zip(keep);
            for ((pixels, points), keep) in groups {
                // Masks come in long runs: a masked group is one fill.
                if keep
                    .first_chunk::<GROUP>()
                    .is_some_and(|k| u128::from_ne_bytes(*k) == 0)
                {
                    pixels.as_flattened_mut().fill(f32::NAN);
                    continue;
                }
                // The group padded to GROUP positions (a row's last group may be short).
                let mut pts = [[f32::NAN; 2]; GROUP];
                let mut kept = [0u8; GROUP];
                pts.iter_mut().zip(points).for_each(|(d, &s)| *d = s);
                kept.iter_mut().zip(keep).for_each(|(d, &s)| *d = s);
                let mut off = [0i32; GROUP];
                let mut down = [0i32; GROUP];
                let mut right = [false; GROUP];
                let mut tx = [0f32; GROUP];
                let mut ty = [0f32; GROUP];
                let mut slow = [false; GROUP];
                let lanes = off
                    .iter_mut()
                    .zip(down.iter_mut())
                    .zip(right.iter_mut())
                    .zip(tx.iter_mut().zip(ty.iter_mut()))
                    .zip(slow.iter_mut().zip(pts.iter().zip(&kept)));
                for ((((off, down), right), (tx, ty)), (slow, (&[x, y], &k))) in lanes {
                    // As `Linear::at` on both axes (NaN fails every comparison).
                    let inside = (k != 0) & (x >= 0.0) & (x <= wl) & (y >= 0.0) & (y <= hl);
                    let (xs, ys) = if inside { (x, y) } else { (0.0, 0.0) };
                    let ((ix, fx), (iy, fy)) = (floor_fract(xs), floor_fract(ys));
                    let (r, d) = (fx > 0.0, fy > 0.0);
                    let (c, row) = (ix.wrapping_sub(col0), iy.wrapping_sub(row0));
                    let in_band = (c >= 0)
                        & (c.wrapping_add(i32::from(r)) < cols)
                        & (row >= 0)
                        & (row.wrapping_add(i32::from(d)) < rows);
                    let ok = inside & in_band;
                    *slow = inside & !in_band;
                    let at = row
                        .wrapping_mul(stride)
                        .wrapping_add(c.wrapping_mul(C as i32));
                    *off = if ok { at } else { nan_at };
                    *down = if ok & d { stride } else { 0 };
                    *right = ok & r;
                    (*tx, *ty) = (fx, fy);
                }
                let lanes = off.iter().zip(&down).zip(&right).zip(tx.iter().zip(&ty));
                for (px, (((&off, &down), &right), (&tx, &ty))) in pixels.iter_mut().zip(lanes) {
                    // Offsets are in 0..=nan_at, and every pixel start in the band has 8
                    // values from it (the padding).
                    let top = off as usize;
                    let (Some((p00, p01)), Some((p10, p11))) = (
                        pair8::<C>(data, top, right),
                        pair8::<C>(data, top + down as usize, right),
                    ) else {
                        return Err(internal("rectify", v0 + k));
                    };
                    let v = lerp_lanes(lerp_lanes(p00, p01, tx), lerp_lanes(p10, p11, tx), ty);
                    *px = if CHECK_NAN && any_nan(&v, C) {
                        [f32::NAN; C]
                    } else {
                        first::<C>(&v)
                    };
                }
                if slow.iter().any(|&s| s) {
                    for ((px, &[x, y]), &s) in pixels.iter_mut().zip(&pts).zip(&slow) {
                        if s {
                            *px = match Bilinear::sample(fallback, crop.w, crop.h, x, y) {
                                Some(v) if !any_nan(&v, C) => first::<C>(&v),
                                _ => [f32::NAN; C],
                            };
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// Values at least this large make a band wild (see [`Job::fill_band`]).
const TAME: f32 = 1e37;

/// Crops up to this many pixels wide and high use [`floor_fract`].
const FLOOR_LIMIT: usize = 1 << 22;

/// `(floor(x), x - floor(x))` for `0 <= x < 2^22`, exactly as `x as i32` and `x - (x as
/// i32) as f32`, but with float and integer arithmetic that vectorises (Rust's `as`
/// saturates, which takes several instructions per value on x86-64): adding `2^23`
/// rounds to an integer, whose bits hold it.
#[inline(always)]
fn floor_fract(x: f32) -> (i32, f32) {
    const MAGIC: f32 = 8_388_608.0; // 2^23
    let r = x + MAGIC;
    let rounded = r - MAGIC;
    let up = rounded > x;
    let i = (r.to_bits().wrapping_sub(MAGIC.to_bits()) as i32) - i32::from(up);
    let floor = if up { rounded - 1.0 } else { rounded };
    (i, x - floor)
}

/// The pixel at `start` of `data` and the next one (`C` values on), or itself again
/// if `!right`, from one read of eight values.
#[inline(always)]
fn pair8<const C: usize>(data: &[f32], start: usize, right: bool) -> Option<(Lanes, Lanes)> {
    let eight = data.get(start..)?.first_chunk::<8>()?;
    let a = *eight.first_chunk::<4>()?;
    let b = *eight.get(C..)?.first_chunk::<4>()?;
    Some((a, if right { b } else { a }))
}

/// The error of a broken internal invariant of `function` at row `at` (never the
/// caller's fault).
fn internal(function: &'static str, at: usize) -> Error {
    Error::internal(function, format!("row {at}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::Level;

    #[test]
    fn interp_names_round_trip() {
        for i in Interp::ALL {
            assert_eq!(i.name().parse::<Interp>().unwrap(), i);
        }
        let err = "nearest".parse::<Interp>().unwrap_err();
        assert_eq!(
            err.to_string(),
            "interp: expected one of \"bilinear\", \"bilinear-exact\", \"bilinear-q32\", \
             \"bicubic\", got \"nearest\""
        );
    }

    #[test]
    fn one_view_of_a_tiny_frame() {
        // 3x4 mono u8 frame, crop the right 2x3 part; gains 2 everywhere but one pixel.
        let raw: Vec<u8> = (0..12).map(|v| v * 10).collect();
        let mut gains = vec![2.0f32; 12];
        gains[11] = 0.0; // raw (2, 3)
        let raw_v = ImageView::new(&raw, 3, 4, 1).unwrap();
        let gains_v = ImageView::new(&gains, 3, 4, 1).unwrap();
        // Crop x0 = 2, y0 = 0, 2 wide, 3 high; 1x4 rectified row.
        let warps = [0.5f32, 0.0, 1.0, 0.5, 1.0, 1.5, f32::NAN, 0.0];
        let maps = ViewMaps::new(&warps, None, 1, 1, 4).unwrap();
        let mut out = [0.0f32; 4];
        rectify(
            raw_v,
            gains_v,
            &[[2, 0, 2, 3]],
            maps,
            &[0],
            Interp::Bilinear,
            &mut out,
        )
        .unwrap();
        let s = 2.0 / 255.0;
        assert!((out[0] - 25.0 * s).abs() < 1e-6, "{out:?}");
        assert!((out[1] - 50.0 * s).abs() < 1e-6, "{out:?}");
        // (1, 1.5) reads raw (2, 3), whose gain is 0.
        assert!(out[2].is_nan() && out[3].is_nan(), "{out:?}");
    }

    #[test]
    fn a_nan_in_one_channel_makes_every_channel_nan() {
        // 2x4 RGB f32 frame; warps sample between pixel columns 0-1 and columns 2-3 of
        // row 0, and exactly on pixel (1, 3).
        let run = |raw: &[f32], gains: &[f32], g: usize| {
            let raw_v = ImageView::new(raw, 2, 4, 3).unwrap();
            let gains_v = ImageView::new(gains, 2, 4, g).unwrap();
            let warps = [0.5f32, 0.0, 2.5, 0.0, 3.0, 1.0];
            let maps = ViewMaps::new(&warps, None, 1, 1, 3).unwrap();
            let mut out = [0.0f32; 9];
            let crops = [[0, 0, 4, 2]];
            rectify(
                raw_v,
                gains_v,
                &crops,
                maps,
                &[0],
                Interp::Bilinear,
                &mut out,
            )
            .unwrap();
            out
        };
        let nan_where = |out: [f32; 9]| out.map(|v| v.is_nan());
        let raw: Vec<f32> = (0..24).map(|v| v as f32 / 24.0).collect();
        let ones = vec![1.0f32; 24];
        let out = run(&raw, &ones, 3);
        assert!(out.iter().all(|v| v.is_finite()), "{out:?}");
        // A NaN raw value in one channel, an infinity making `inf - inf`, a zero gain
        // in one channel: the samples whose footprint holds them are NaN in all three.
        let mut nan_raw = raw.clone();
        nan_raw[1] = f32::NAN; // pixel (0, 0), green
        let mut inf_raw = raw.clone();
        inf_raw[6] = f32::INFINITY; // pixel (0, 2), red
        inf_raw[9] = f32::INFINITY; // pixel (0, 3), red
        let mut zero_gain = ones.clone();
        zero_gain[23] = 0.0; // pixel (1, 3), blue
        let expected = |a: bool, b: bool, c: bool| [a, a, a, b, b, b, c, c, c];
        assert_eq!(
            nan_where(run(&nan_raw, &ones, 3)),
            expected(true, false, false)
        );
        assert_eq!(
            nan_where(run(&inf_raw, &ones, 3)),
            expected(false, true, false)
        );
        assert_eq!(
            nan_where(run(&raw, &zero_gain, 3)),
            expected(false, false, true)
        );
        // One infinite gain: `0 * inf` is NaN in the channel whose raw value is 0.
        let mut inf_gain = vec![1.0f32; 8];
        inf_gain[0] = f32::INFINITY;
        assert_eq!(
            nan_where(run(&raw, &inf_gain, 1)),
            expected(true, false, false)
        );
    }

    #[test]
    fn avx2_and_baseline_builds_agree() {
        if !crate::simd::runs_or_skip(Level::Avx2, "rectify avx2_and_baseline_builds_agree") {
            return;
        }
        // 2x2 views of 70x50 from a 150x110 RGB u16 frame, smooth warps with NaN
        // holes, a mask, a few zero gains (per channel and per pixel).
        let (fw, fh, vw, vh, rw, rh) = (150usize, 110usize, 70usize, 50usize, 90usize, 60usize);
        let raw: Vec<u16> = (0..fw * fh * 3)
            .map(|i| (i * 7919 % 65_536) as u16)
            .collect();
        let mut gains: Vec<f32> = (0..fw * fh * 3)
            .map(|i| 0.5 + (i % 13) as f32 / 13.0)
            .collect();
        for i in (0..gains.len()).step_by(397) {
            gains[i] = 0.0;
        }
        let crops: Vec<[i64; 4]> = (0..4)
            .map(|i| [5 + 72 * (i % 2), 4 + 52 * (i / 2), vw as i64, vh as i64])
            .collect();
        let mut warps = vec![0f32; 4 * rh * rw * 2];
        let mut masks = vec![1u8; 4 * rh * rw];
        for i in 0..4 {
            for v in 0..rh {
                for u in 0..rw {
                    let k = (i * rh + v) * rw + u;
                    let x = u as f32 * 0.8 - 3.0 + (v as f32 * 0.1).sin() + i as f32;
                    let y = v as f32 * 0.85 - 2.0 + (u as f32 * 0.07).cos();
                    warps[2 * k] = if (u + v) % 37 == 0 { f32::NAN } else { x };
                    warps[2 * k + 1] = y;
                    masks[k] = u8::from((u * 3 + v) % 41 != 0);
                }
            }
        }
        let raw_v = ImageView::new(&raw, fh, fw, 3).unwrap();
        for g in [1usize, 3] {
            let gains_g: Vec<f32> = gains
                .iter()
                .step_by(4 - g)
                .copied()
                .take(fw * fh * g)
                .collect();
            let gains_v = ImageView::new(&gains_g, fh, fw, g).unwrap();
            for masks in [None, Some(&masks[..])] {
                let maps = ViewMaps::new(&warps, masks, 4, rh, rw).unwrap();
                for interp in Interp::ALL {
                    let results = [Level::Avx2, Level::Portable].map(|cap| {
                        let mut out = vec![0f32; 4 * rh * rw * 3];
                        let simd = Dispatch::at_most(cap);
                        rectify_with(
                            raw_v,
                            gains_v,
                            &crops,
                            maps,
                            &[0, 1, 2, 3],
                            interp,
                            &mut out,
                            &simd,
                        )
                        .unwrap();
                        assert_eq!(simd.ran(), cap, "{interp:?}");
                        out
                    });
                    let [a, b] = &results;
                    assert!(
                        a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()),
                        "{interp:?}, {g} gain channels"
                    );
                    assert!(a.iter().filter(|v| v.is_finite()).count() > a.len() / 2);
                }
            }
        }
    }

    #[test]
    fn floor_fract_is_truncation() {
        for x in [
            0.0f32,
            0.25,
            0.5,
            1.0,
            1.5,
            2.5,
            2.999_999_8,
            1023.75,
            4_194_303.5,
        ] {
            assert_eq!(floor_fract(x), (x as i32, x - (x as i32) as f32), "{x}");
        }
        let mut x = 0.0f32;
        while x < 70_000.0 {
            assert_eq!(floor_fract(x), (x as i32, x - (x as i32) as f32), "{x}");
            x = x * 1.001 + 0.000_37;
        }
    }

    #[test]
    fn crops_are_checked_against_the_frame() {
        let raw = vec![0u16; 20 * 10];
        let gains = vec![1.0f32; 20 * 10];
        let raw_v = ImageView::new(&raw, 10, 20, 1).unwrap();
        let gains_v = ImageView::new(&gains, 10, 20, 1).unwrap();
        let warps = vec![0.0f32; 2 * 2 * 3 * 2];
        let maps = ViewMaps::new(&warps, None, 2, 2, 3).unwrap();
        let err = rectify_output_shape(
            &raw_v,
            &gains_v,
            &[[0, 0, 5, 5], [16, 0, 5, 5]],
            &maps,
            &[0],
        )
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "crops[1]: rectangle (x0, y0, w, h) = (16, 0, 5, 5) lies outside the 20x10 raw frame"
        );
        let shape = rectify_output_shape(
            &raw_v,
            &gains_v,
            &[[0, 0, 5, 5], [15, 5, 5, 5]],
            &maps,
            &[1, 1, 0],
        )
        .unwrap();
        assert_eq!(shape, [3, 2, 3, 1]);
    }
}
