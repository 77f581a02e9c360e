//! Rectification prepared once per calibration: [`RectifyPlan`].
//!
//! Labs process folders of captures with one calibration, so everything [`rectify`]
//! derives from the warps, masks and gains alone is derived once: for each view and
//! rectified row, the runs of pixels that have a value and, per such pixel, its
//! footprint's top-left crop pixel and its two fractions (exactly the values
//! [`rectify`] computes); each row's footprint bounding box; and the gains of the crop
//! pixels some footprint reads, copied. A pixel is left out (NaN) when [`rectify`]
//! would make it NaN whatever the raw frame: masked, a NaN warp, a footprint leaving
//! the crop, or a gain in the footprint that is 0 or NaN.
//!
//! A capture's rectification is then a stream over the plan: per task of rows, the
//! gained raw pixels of the rows' footprint box into a buffer that stays in cache
//! (`raw * scale * gains`, as [`rectify`]; one buffer per worker, kept from task to
//! task), then per row NaN fills of the runs without data and the bilinear
//! interpolation of the others, in OpenCV's order of operations. The buffer's rows are
//! the crop's width apart, so a pixel's place in it follows from its crop index. No
//! position arithmetic, no mask or bounds tests beyond the slice accesses, and no NaN
//! tests when they cannot matter: an integer raw frame times finite gains below
//! [`TAME`] has no NaN and no infinity, so neither has its interpolation. That case,
//! with 3 or 4 channels on a CPU with AVX2, runs [`crate::simd::bilinear_band`] (eight
//! pixels' offsets at a time, two pixels per register), the others a portable loop.
//! The output is bit for bit [`rectify`]'s.
//!
//! [`rectify`]: super::rectify

use super::{Crop, Interp, MIN_TASK_ROWS, RawSample, TAME, ViewMaps, check_crop, internal};
use crate::error::{Error, Result};
use crate::image::ImageView;
use crate::parallel;
use crate::remap::{Lanes, Linear, MAX_CHANNELS, any_nan, lerp_lanes};
use crate::simd::{Avx2Kernel, BandTaps, Dispatch, bilinear_band};

/// The rectified pixels with a value of a view, in order, as parallel vectors: the
/// top-left pixel of each one's footprint, as its index `row * w + col` in the `w x h`
/// crop, and its fractions along x and y (0: the footprint has one column, or one row).
#[derive(Debug, Default)]
struct Taps {
    at: Vec<u32>,
    tx: Vec<f32>,
    ty: Vec<f32>,
}

impl Taps {
    fn len(&self) -> usize {
        self.at.len()
    }

    /// Taps `range`.
    fn get(&self, range: std::ops::Range<usize>) -> Option<BandTaps<'_>> {
        Some(BandTaps {
            at: self.at.get(range.clone())?,
            tx: self.tx.get(range.clone())?,
            ty: self.ty.get(range)?,
        })
    }
}

/// The first `n` taps and the rest.
#[inline(always)]
fn split_taps(t: BandTaps<'_>, n: usize) -> Option<(BandTaps<'_>, BandTaps<'_>)> {
    let (at0, at1) = t.at.split_at_checked(n)?;
    let (tx0, tx1) = t.tx.split_at_checked(n)?;
    let (ty0, ty1) = t.ty.split_at_checked(n)?;
    Some((
        BandTaps {
            at: at0,
            tx: tx0,
            ty: ty0,
        },
        BandTaps {
            at: at1,
            tx: tx1,
            ty: ty1,
        },
    ))
}

/// One rectified row of a view.
#[derive(Debug, Clone, Copy)]
struct RowPlan {
    /// Its runs: `ViewPlan::runs[runs.0..runs.1]`.
    runs: (usize, usize),
    /// Its taps: `ViewPlan::taps[taps.0..taps.1]`, the runs' pixels in order.
    taps: (usize, usize),
    /// The crop columns and rows its footprints read, inclusive (meaningless when it
    /// has no taps).
    cols: (usize, usize),
    rows: (usize, usize),
}

/// A crop row's gains in the plan: columns `lo..hi` (none when equal) at `at` in
/// `ViewPlan::gains`, `G` values per pixel.
#[derive(Debug, Clone, Copy, Default)]
struct GainRow {
    lo: usize,
    hi: usize,
    at: usize,
}

/// Everything one view needs.
#[derive(Debug)]
struct ViewPlan {
    crop: Crop,
    rows: Vec<RowPlan>,
    /// `(first column, length)` of each run of pixels with a value.
    runs: Vec<(u32, u32)>,
    taps: Taps,
    /// One per crop row: the columns some footprint reads.
    gain_rows: Vec<GainRow>,
    gains: Vec<f32>,
    /// Whether a footprint reads an infinite gain, or one of magnitude `>= TAME`.
    wild: bool,
}

/// A rectification prepared once per calibration (see the module docs); its
/// [`RectifyPlan::rectify`] equals [`super::rectify`] with the same gains, crops, warps,
/// masks and bilinear interpolation, bit for bit. The plan holds copies of what it
/// needs: changing the calibration's arrays afterwards does not change it.
#[derive(Debug)]
pub struct RectifyPlan {
    raw_height: usize,
    raw_width: usize,
    gain_channels: usize,
    height: usize,
    width: usize,
    views: Vec<ViewPlan>,
}

/// The footprint of `(x, y)` in a `w x h` crop as [`crate::remap::Bilinear`] reads it:
/// `(col, row, tx, ty)`, `None` if it is not entirely inside.
#[inline]
fn footprint(x: f32, y: f32, w: usize, h: usize) -> Option<(usize, usize, f32, f32)> {
    let ax = Linear::at(x, w)?;
    let ay = Linear::at(y, h)?;
    Some((ax.i0, ay.i0, ax.t, ay.t))
}

impl RectifyPlan {
    /// Prepares the rectification of raw frames of `gains`' `(H, W)` with `gains`,
    /// `crops` and `maps` (as [`super::rectify`] takes them), bilinear. Runs in lfcam's
    /// pool, one task per view.
    ///
    /// # Errors
    /// - [`Error::InvalidArgument`] `"interp"` unless it is [`Interp::Bilinear`] or
    ///   [`Interp::BilinearExact`] (the other methods run through [`super::rectify`]);
    /// - [`Error::InvalidArgument`] `"gains"` if it has more than [`MAX_CHANNELS`]
    ///   channels;
    /// - [`Error::InvalidArgument`] `"crops"` if there is not one rectangle per view of
    ///   `maps`; [`Error::InvalidItem`] `"crops"` naming the first rectangle that is
    ///   empty, not inside the frame, or more than 65536 pixels wide or high.
    pub fn new(
        gains: ImageView<'_, f32>,
        crops: &[[i64; 4]],
        maps: ViewMaps<'_>,
        interp: Interp,
    ) -> Result<Self> {
        if !matches!(interp, Interp::Bilinear | Interp::BilinearExact) {
            return Err(Error::invalid_argument(
                "interp",
                format!(
                    "a prepared plan is bilinear (\"bilinear\" or \"bilinear-exact\"), got {:?}; \
                     rectify without a plan for other methods",
                    interp.name()
                ),
            ));
        }
        let g = gains.channels();
        if g > MAX_CHANNELS {
            return Err(Error::invalid_argument(
                "gains",
                format!("has {g} channels; 1 to {MAX_CHANNELS} are supported"),
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
            .map(|(i, &r)| {
                let crop = check_crop(i, r, gains.width(), gains.height())?;
                const MAX: usize = 1 << 16;
                if crop.w > MAX || crop.h > MAX {
                    return Err(Error::invalid_item(
                        "crops",
                        i,
                        format!(
                            "is {}x{} pixels; a prepared plan takes crops of at most \
                             {MAX}x{MAX}",
                            crop.w, crop.h
                        ),
                    ));
                }
                Ok(crop)
            })
            .collect::<Result<Vec<_>>>()?;
        // One task per view (its warps' bytes measure the work).
        let work = crops.len() * maps.height() * maps.width() * 8;
        let views = parallel::map_tasks(crops.len(), work, |i| {
            let crop = *crops
                .get(i)
                .ok_or_else(|| Error::internal("RectifyPlan", format!("view {i}")))?;
            build_view(&gains, crop, &maps, i)
        })?;
        Ok(Self {
            raw_height: gains.height(),
            raw_width: gains.width(),
            gain_channels: g,
            height: maps.height(),
            width: maps.width(),
            views,
        })
    }

    /// Number of views `N`.
    pub fn views(&self) -> usize {
        self.views.len()
    }

    /// The raw frames' `(H, W)`.
    pub fn raw_shape(&self) -> (usize, usize) {
        (self.raw_height, self.raw_width)
    }

    /// The rectified `(H, W)`.
    pub fn shape(&self) -> (usize, usize) {
        (self.height, self.width)
    }

    /// Channels of the gains (1: shared by every channel of the raw frame).
    pub fn gain_channels(&self) -> usize {
        self.gain_channels
    }

    /// Number of rectified pixels with a value, over all views.
    pub fn kept(&self) -> usize {
        self.views.iter().map(|v| v.taps.len()).sum()
    }

    /// Bytes the plan holds (its heap allocations, about).
    pub fn nbytes(&self) -> usize {
        use std::mem::size_of;
        self.views
            .iter()
            .map(|v| {
                v.rows.len() * size_of::<RowPlan>()
                    + v.runs.len() * size_of::<(u32, u32)>()
                    + v.taps.len() * (size_of::<u32>() + 2 * size_of::<f32>())
                    + v.gain_rows.len() * size_of::<GainRow>()
                    + v.gains.len() * size_of::<f32>()
            })
            .sum::<usize>()
            + size_of::<Self>()
    }

    /// The output shape `(len(views), H, W, C)` of [`Self::rectify`], after validating
    /// the inputs exactly as it does.
    ///
    /// # Errors
    /// As [`Self::rectify`], except for the check of `out`.
    pub fn output_shape<T>(&self, raw: &ImageView<'_, T>, views: &[usize]) -> Result<[usize; 4]> {
        let c = raw.channels();
        if c > MAX_CHANNELS {
            return Err(Error::invalid_argument(
                "raw",
                format!("has {c} channels; 1 to {MAX_CHANNELS} are supported"),
            ));
        }
        if (raw.height(), raw.width()) != (self.raw_height, self.raw_width) {
            return Err(Error::invalid_argument(
                "raw",
                format!(
                    "(H, W) = ({}, {}) differs from the plan's ({}, {}), the gains' it was \
                     prepared with",
                    raw.height(),
                    raw.width(),
                    self.raw_height,
                    self.raw_width
                ),
            ));
        }
        let g = self.gain_channels;
        if g != 1 && g != c {
            return Err(Error::invalid_argument(
                "raw",
                format!(
                    "has {c} channels but the plan's gains have {g}; gains need 1 channel \
                     (shared by every channel of raw) or as many as raw"
                ),
            ));
        }
        if views.is_empty() {
            return Err(Error::invalid_argument(
                "views",
                "at least one view must be selected, got none",
            ));
        }
        if let Some((j, &i)) = views.iter().enumerate().find(|&(_, &i)| i >= self.views()) {
            return Err(Error::invalid_item(
                "views",
                j,
                format!("view index {i} is out of range for {} views", self.views()),
            ));
        }
        let shape = [views.len(), self.height, self.width, c];
        shape
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
            .ok_or_else(|| {
                Error::invalid_argument(
                    "views",
                    format!("the output shape {shape:?} has too many elements"),
                )
            })?;
        Ok(shape)
    }

    /// Rectifies the selected `views` of `raw` into `out`, laid out `(len(views), H, W,
    /// C)` C-contiguous, `C` the channels of raw: what [`super::rectify`] writes with
    /// the plan's gains, crops, warps and masks, bit for bit. Runs in lfcam's pool over
    /// tasks of rows.
    ///
    /// # Errors
    /// - [`Error::InvalidArgument`] `"raw"` if its `(H, W)` is not the plan's, it has
    ///   more than [`MAX_CHANNELS`] channels, or the plan's gains have neither 1 channel
    ///   nor as many as raw;
    /// - [`Error::InvalidArgument`] `"views"` if `views` is empty; [`Error::InvalidItem`]
    ///   `"views"` naming the first index `>= N`;
    /// - [`Error::InvalidArgument`] `"out"` if `out.len()` is not the product of the shape.
    pub fn rectify<T: RawSample>(
        &self,
        raw: ImageView<'_, T>,
        views: &[usize],
        out: &mut [f32],
    ) -> Result<()> {
        self.rectify_with(raw, views, out, &Dispatch::auto())
    }

    /// [`Self::rectify`] with the builds `simd` allows (see [`crate::simd`]).
    fn rectify_with<T: RawSample>(
        &self,
        raw: ImageView<'_, T>,
        views: &[usize],
        out: &mut [f32],
        simd: &Dispatch,
    ) -> Result<()> {
        let shape = self.output_shape(&raw, views)?;
        let expected: usize = shape.iter().product();
        if out.len() != expected {
            return Err(Error::invalid_argument(
                "out",
                format!(
                    "has {} elements, but the output {shape:?} needs {expected}",
                    out.len()
                ),
            ));
        }
        match (raw.channels(), self.gain_channels) {
            (1, 1) => self.run::<T, 1, 1>(&raw, views, out, simd),
            (2, 1) => self.run::<T, 2, 1>(&raw, views, out, simd),
            (2, 2) => self.run::<T, 2, 2>(&raw, views, out, simd),
            (3, 1) => self.run::<T, 3, 1>(&raw, views, out, simd),
            (3, 3) => self.run::<T, 3, 3>(&raw, views, out, simd),
            (4, 1) => self.run::<T, 4, 1>(&raw, views, out, simd),
            (4, 4) => self.run::<T, 4, 4>(&raw, views, out, simd),
            (c, g) => Err(Error::internal(
                "RectifyPlan.rectify",
                format!("unexpected channel counts raw {c}, gains {g}"),
            )),
        }
    }

    /// Output rows in tasks of whole rows (as [`super::rectify`]), each split into runs
    /// of rows of one view.
    fn run<T: RawSample, const C: usize, const G: usize>(
        &self,
        raw: &ImageView<'_, T>,
        views: &[usize],
        out: &mut [f32],
        simd: &Dispatch,
    ) -> Result<()> {
        let h = self.height;
        let row_len = self.width * C;
        let init = Scratch::default;
        parallel::for_each_row_chunk_init(
            out,
            row_len,
            MIN_TASK_ROWS,
            init,
            |scratch, first_row, rows| {
                let mut g = first_row;
                let mut rest = rows;
                while !rest.is_empty() {
                    let (j, v) = (g / h, g % h);
                    let n = (h - v).min(rest.len() / row_len);
                    let (part, tail) = std::mem::take(&mut rest).split_at_mut(n * row_len);
                    let view = views
                        .get(j)
                        .and_then(|&i| self.views.get(i))
                        .ok_or_else(|| internal("RectifyPlan.rectify", g))?;
                    let segment = Segment::<'_, '_, T, C, G> {
                        plan: self,
                        view,
                        raw,
                        v0: v,
                        out: part,
                        scratch,
                    };
                    crate::simd::run_avx2_or_portable(simd, segment)?;
                    rest = tail;
                    g += n;
                }
                Ok(())
            },
        )
    }

    /// Rows `v0..` of one view into `out` (whole rows).
    #[inline(always)]
    fn segment<
        T: RawSample,
        const C: usize,
        const G: usize,
        const CHECK_NAN: bool,
        const AVX2: bool,
    >(
        &self,
        view: &ViewPlan,
        raw: &ImageView<'_, T>,
        v0: usize,
        out: &mut [f32],
        scratch: &mut Scratch,
    ) -> Result<()> {
        let row_len = self.width * C;
        let n = out.len() / row_len;
        let rows = view
            .rows
            .get(v0..v0 + n)
            .ok_or_else(|| internal("RectifyPlan.rectify", v0))?;
        // The band: the rows' footprint box.
        let mut cols = (usize::MAX, 0);
        let mut rws = (usize::MAX, 0);
        for r in rows.iter().filter(|r| r.taps.1 > r.taps.0) {
            cols = (cols.0.min(r.cols.0), cols.1.max(r.cols.1));
            rws = (rws.0.min(r.rows.0), rws.1.max(r.rows.1));
        }
        if cols.0 > cols.1 {
            out.fill(f32::NAN);
            return Ok(());
        }
        let (c0, bw) = (cols.0, cols.1 - cols.0 + 1);
        let (r0, bh) = (rws.0, rws.1 - rws.0 + 1);
        let band = &mut scratch.band;
        fill_band::<T, C, G>(view, raw, (c0, bw), (r0, bh), band)
            .ok_or_else(|| internal("RectifyPlan.rectify", v0))?;
        // Band pixel `(r, c)` of the crop is at `(r - r0) * stride + c * C`: a tap at
        // crop index `at` starts at `(at - base) * C`.
        let (stride, base) = (view.crop.w * C, r0 * view.crop.w);
        for (k, (row, out_row)) in rows.iter().zip(out.chunks_exact_mut(row_len)).enumerate() {
            let bad = || internal("RectifyPlan.rectify", v0 + k);
            let runs = view.runs.get(row.runs.0..row.runs.1).ok_or_else(bad)?;
            let mut taps = view.taps.get(row.taps.0..row.taps.1).ok_or_else(bad)?;
            let mut done = 0;
            for &(u0, len) in runs {
                let (u0, len) = (u0 as usize, len as usize);
                // The gap first: the run's pixels but the last spill a lane into the
                // next one, written after it.
                out_row
                    .get_mut(done * C..u0 * C)
                    .ok_or_else(bad)?
                    .fill(f32::NAN);
                let (run, tail) = split_taps(taps, len).ok_or_else(bad)?;
                let dst = out_row.get_mut(u0 * C..(u0 + len) * C).ok_or_else(bad)?;
                let simd = AVX2 && !CHECK_NAN && (C == 3 || C == 4);
                if !simd || bilinear_band::<C>(band, stride, base, run, dst).is_none() {
                    sample_run::<C, CHECK_NAN>(band, stride, base, run, dst).ok_or_else(bad)?;
                }
                taps = tail;
                done = u0 + len;
            }
            out_row.get_mut(done * C..).ok_or_else(bad)?.fill(f32::NAN);
        }
        Ok(())
    }
}

/// Per-worker scratch buffers of [`RectifyPlan::run`]'s tasks.
#[derive(Debug, Default)]
struct Scratch {
    /// The gained raw pixels of a segment's footprint box ([`fill_band`]).
    band: Vec<f32>,
}

/// Rows `v0..` of one view into `out`: [`RectifyPlan::segment`], for
/// [`crate::simd::run_avx2_or_portable`].
struct Segment<'a, 'r, T, const C: usize, const G: usize> {
    plan: &'a RectifyPlan,
    view: &'a ViewPlan,
    raw: &'a ImageView<'r, T>,
    v0: usize,
    out: &'a mut [f32],
    scratch: &'a mut Scratch,
}

impl<T: RawSample, const C: usize, const G: usize> Avx2Kernel for Segment<'_, '_, T, C, G> {
    type Output = Result<()>;

    #[inline(always)]
    fn run<const AVX2: bool>(self) -> Result<()> {
        let Self {
            plan,
            view,
            raw,
            v0,
            out,
            scratch,
        } = self;
        // Integer samples times tame gains are finite: no NaN to test for.
        if !T::INTEGER || view.wild {
            plan.segment::<T, C, G, true, AVX2>(view, raw, v0, out, scratch)
        } else {
            plan.segment::<T, C, G, false, AVX2>(view, raw, v0, out, scratch)
        }
    }
}

/// `band` := the gained raw pixels (`raw * scale * gains`) of crop columns `c0 .. c0 +
/// bw`, rows `r0 .. r0 + bh`, `C` values each, crop pixel `(r, c)` at index
/// `(r - r0) * w * C + c * C` (`w` the crop's width: a tap's place in the band follows
/// from its crop index alone), where the plan keeps gains (every pixel a footprint
/// reads); the others are left as they were (never read). A row and 8 values of
/// padding follow, so that lanes past a pixel can be read anywhere. `None` if the plan
/// and the frame disagree (a bug).
#[inline(always)]
fn fill_band<T: RawSample, const C: usize, const G: usize>(
    view: &ViewPlan,
    raw: &ImageView<'_, T>,
    (c0, bw): (usize, usize),
    (r0, bh): (usize, usize),
    band: &mut Vec<f32>,
) -> Option<()> {
    let stride = view.crop.w * C;
    // A row more than the box: `simd::bilinear_band` wants `stride + C + 4` values
    // after every footprint's top-left pixel.
    let len = (bh + 1) * stride + 8;
    if band.len() < len {
        band.resize(len, 0.0);
    }
    for (k, y) in (r0..r0 + bh).enumerate() {
        let gr = *view.gain_rows.get(y)?;
        let (lo, hi) = (gr.lo.max(c0), gr.hi.min(c0 + bw));
        if lo >= hi {
            continue;
        }
        let n = hi - lo;
        let raw_px = raw.row_span(view.crop.y0 + y, view.crop.x0 + lo, n)?;
        let at = gr.at + (lo - gr.lo) * G;
        let gains = view.gains.get(at..at + n * G)?;
        let start = k * stride + lo * C;
        let dst = band.get_mut(start..start + n * C)?;
        if G == C {
            for ((d, &r), &g) in dst.iter_mut().zip(raw_px).zip(gains) {
                *d = (r.to_f32() * T::SCALE) * g;
            }
        } else {
            let (dst, _) = dst.as_chunks_mut::<C>();
            let (raw_px, _) = raw_px.as_chunks::<C>();
            for ((d, r), &g) in dst.iter_mut().zip(raw_px).zip(gains) {
                for (d, &r) in d.iter_mut().zip(r) {
                    *d = (r.to_f32() * T::SCALE) * g;
                }
            }
        }
    }
    Some(())
}

/// The four pixels of tap `(at, tx, ty)`'s footprint in the band (`stride` values per
/// row, crop index `base` first), as lanes: top left, top right, bottom left, bottom
/// right (the right ones are the left ones when `tx == 0`, the bottom ones the top
/// ones when `ty == 0`). `None` if they are not in the band (a bug).
#[inline(always)]
fn footprint_lanes<const C: usize>(
    band: &[f32],
    stride: usize,
    base: usize,
    at: u32,
    tx: f32,
    ty: f32,
) -> Option<[Lanes; 4]> {
    let top = (at as usize).wrapping_sub(base).wrapping_mul(C);
    let right = C * usize::from(tx > 0.0);
    let down = stride * usize::from(ty > 0.0);
    // Two bounds checks for the four reads (`right + 4 <= 8`).
    let q0 = band.get(top..)?.first_chunk::<8>()?;
    let q1 = band.get(top.wrapping_add(down)..)?.first_chunk::<8>()?;
    Some([
        lanes(q0, 0)?,
        lanes(q0, right)?,
        lanes(q1, 0)?,
        lanes(q1, right)?,
    ])
}

/// Four values of `band` from `at`.
#[inline(always)]
fn lanes(band: &[f32], at: usize) -> Option<Lanes> {
    band.get(at..)?.first_chunk::<4>().copied()
}

/// The pixels of one run, `taps`, into `dst` (`C` values a pixel): bilinear from the
/// band (`stride` values per row, crop index `base` first), in OpenCV's order, as
/// [`crate::remap::Bilinear`]. With `CHECK_NAN`, a NaN in one channel makes every
/// channel NaN. For 3 channels every pixel but the last is stored as four lanes: the
/// fourth lands on the next pixel, written after it. `None` if a tap is not in the
/// band (a bug) or `dst` is not the run's length.
#[inline(always)]
fn sample_run<const C: usize, const CHECK_NAN: bool>(
    band: &[f32],
    stride: usize,
    base: usize,
    taps: BandTaps<'_>,
    dst: &mut [f32],
) -> Option<()> {
    let n = taps.at.len();
    let (init, last) = split_taps(taps, n.checked_sub(1)?)?;
    let tap = |t: BandTaps<'_>, k: usize| Some((*t.at.get(k)?, *t.tx.get(k)?, *t.ty.get(k)?));
    let (at, tx, ty) = tap(last, 0)?;
    let last = bilinear::<C, CHECK_NAN>(band, stride, base, at, tx, ty)?;
    let init = init.at.iter().zip(init.tx).zip(init.ty);
    if C == 3 {
        // Four lanes at pixel `k < n - 1` end at `3 k + 4 <= 3 (n - 1) + 1`.
        let room = dst.get_mut(..(n - 1) * C + 1)?;
        for (k, ((&at, &tx), &ty)) in init.enumerate() {
            let v = bilinear::<C, CHECK_NAN>(band, stride, base, at, tx, ty)?;
            room.get_mut(k * C..k * C + 4)?.copy_from_slice(&v);
        }
    } else {
        for (px, ((&at, &tx), &ty)) in dst.chunks_exact_mut(C).zip(init) {
            let v = bilinear::<C, CHECK_NAN>(band, stride, base, at, tx, ty)?;
            px.copy_from_slice(v.get(..C)?);
        }
    }
    let at = (n - 1) * C;
    dst.get_mut(at..at + C)?.copy_from_slice(last.get(..C)?);
    Some(())
}

/// The bilinear interpolation of tap `(at, tx, ty)` from the band, as [`sample_run`]
/// computes it.
#[inline(always)]
fn bilinear<const C: usize, const CHECK_NAN: bool>(
    band: &[f32],
    stride: usize,
    base: usize,
    at: u32,
    tx: f32,
    ty: f32,
) -> Option<Lanes> {
    let [p00, p01, p10, p11] = footprint_lanes::<C>(band, stride, base, at, tx, ty)?;
    let v = lerp_lanes(lerp_lanes(p00, p01, tx), lerp_lanes(p10, p11, tx), ty);
    Some(if CHECK_NAN && any_nan(&v, C) {
        [f32::NAN; 4]
    } else {
        v
    })
}

/// [`gain_status`]: a gain of the pixel is 0 or NaN (its footprints are NaN).
const GAIN_MASKED: u8 = 1;
/// [`gain_status`]: a gain of the pixel is infinite or `>= TAME` in magnitude.
const GAIN_WILD: u8 = 2;

/// Per pixel of the crop, row-major: [`GAIN_MASKED`] and [`GAIN_WILD`] over its gains.
fn gain_status(gains: &ImageView<'_, f32>, crop: Crop) -> Option<Vec<u8>> {
    let g = gains.channels();
    let mut status = Vec::with_capacity(crop.w * crop.h);
    for y in crop.y0..crop.y0 + crop.h {
        let row = gains.row_span(y, crop.x0, crop.w)?;
        status.extend(row.chunks_exact(g.max(1)).map(|px| {
            px.iter().fold(0u8, |s, &v| {
                s | (u8::from(v == 0.0 || v.is_nan()) * GAIN_MASKED)
                    | (u8::from(v.abs() >= TAME) * GAIN_WILD)
            })
        }));
    }
    Some(status)
}

/// The plan of view `i` (see the module docs).
fn build_view(
    gains: &ImageView<'_, f32>,
    crop: Crop,
    maps: &ViewMaps<'_>,
    i: usize,
) -> Result<ViewPlan> {
    let g = gains.channels();
    let (w, h) = (crop.w, crop.h);
    let mut rows = Vec::with_capacity(maps.height());
    let mut runs = Vec::new();
    let mut taps = Taps::default();
    // Per crop row, the columns footprints read, inclusive; lo > hi for none.
    let mut used = vec![(usize::MAX, 0usize); h];
    let mut wild = false;
    let status = gain_status(gains, crop).ok_or_else(|| internal("RectifyPlan", 0))?;
    for v in 0..maps.height() {
        let bad = || internal("RectifyPlan", v);
        let (points, _) = maps.warp_row(i, v).ok_or_else(bad)?.as_chunks::<2>();
        let mask = maps.mask_row(i, v).ok_or_else(bad)?;
        let (runs0, taps0) = (runs.len(), taps.len());
        let mut cols = (usize::MAX, 0);
        let mut rws = (usize::MAX, 0);
        let mut run_start = None;
        for (u, &[x, y]) in points.iter().enumerate() {
            let kept = mask.is_none_or(|m| m.get(u).is_some_and(|&k| k != 0));
            let tap = footprint(x, y, w, h)
                .filter(|_| kept)
                .filter(|&(c, r, tx, ty)| {
                    let (c1, r1) = (c + usize::from(tx > 0.0), r + usize::from(ty > 0.0));
                    let at = |row: usize, col: usize| {
                        status.get(row * w + col).copied().unwrap_or(GAIN_MASKED)
                    };
                    let s = at(r, c) | at(r, c1) | at(r1, c) | at(r1, c1);
                    wild |= s & GAIN_WILD != 0;
                    s & GAIN_MASKED == 0
                });
            match tap {
                Some((c, r, tx, ty)) => {
                    let (c1, r1) = (c + usize::from(tx > 0.0), r + usize::from(ty > 0.0));
                    cols = (cols.0.min(c), cols.1.max(c1));
                    rws = (rws.0.min(r), rws.1.max(r1));
                    for row in r..=r1 {
                        let e = used.get_mut(row).ok_or_else(bad)?;
                        *e = (e.0.min(c), e.1.max(c1));
                    }
                    let Ok(at) = u32::try_from(r * w + c) else {
                        return Err(bad());
                    };
                    taps.at.push(at);
                    taps.tx.push(tx);
                    taps.ty.push(ty);
                    run_start.get_or_insert(u);
                }
                None => {
                    if let Some(s) = run_start.take() {
                        runs.push(run(s, u).ok_or_else(bad)?);
                    }
                }
            }
        }
        if let Some(s) = run_start.take() {
            runs.push(run(s, points.len()).ok_or_else(bad)?);
        }
        rows.push(RowPlan {
            runs: (runs0, runs.len()),
            taps: (taps0, taps.len()),
            cols,
            rows: rws,
        });
    }
    let mut gain_rows = vec![GainRow::default(); h];
    let mut kept_gains = Vec::new();
    for (y, (&(lo, hi), gr)) in used.iter().zip(gain_rows.iter_mut()).enumerate() {
        if lo > hi {
            continue;
        }
        let span = gains
            .row_span(crop.y0 + y, crop.x0 + lo, hi + 1 - lo)
            .ok_or_else(|| internal("RectifyPlan", y))?;
        *gr = GainRow {
            lo,
            hi: hi + 1,
            at: kept_gains.len(),
        };
        kept_gains.extend_from_slice(span);
    }
    debug_assert!(kept_gains.len().is_multiple_of(g.max(1)));
    taps.at.shrink_to_fit();
    taps.tx.shrink_to_fit();
    taps.ty.shrink_to_fit();
    runs.shrink_to_fit();
    Ok(ViewPlan {
        crop,
        rows,
        runs,
        taps,
        gain_rows,
        gains: kept_gains,
        wild,
    })
}

/// The run of columns `start..end` as `(start, length)`.
fn run(start: usize, end: usize) -> Option<(u32, u32)> {
    Some((u32::try_from(start).ok()?, u32::try_from(end - start).ok()?))
}

#[cfg(test)]
mod tests {
    use super::super::rectify;
    use super::*;
    use crate::simd::{Level, runs_or_skip};

    #[test]
    fn plan_equals_rectify_bit_for_bit() {
        // 2x2 views of 70x50 from a 150x110 frame, smooth warps with NaN holes, a mask,
        // zero gains, every channel layout, u8, u16 and f32 (with a NaN and an
        // infinity), serial and parallel, AVX2 (where it runs) and baseline.
        runs_or_skip(
            Level::Avx2,
            "plan_equals_rectify_bit_for_bit (its AVX2 half)",
        );
        let (fw, fh, vw, vh, rw, rh) = (150usize, 110usize, 70usize, 50usize, 90usize, 60usize);
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
                    // Whole-number positions too (one-column and one-row footprints).
                    let (x, y) = if (u + 2 * v) % 11 == 0 {
                        (x.round(), y.round())
                    } else {
                        (x, y)
                    };
                    warps[2 * k] = if (u + v) % 37 == 0 { f32::NAN } else { x };
                    warps[2 * k + 1] = y;
                    masks[k] = u8::from((u * 3 + v) % 41 != 0);
                }
            }
        }
        for c in 1..=4usize {
            for g in [1, c] {
                let mut gains: Vec<f32> = (0..fw * fh * g)
                    .map(|i| 0.5 + (i % 13) as f32 / 13.0)
                    .collect();
                for k in (0..gains.len()).step_by(397) {
                    gains[k] = 0.0;
                }
                gains[1000] = f32::NAN;
                let gains_v = ImageView::new(&gains, fh, fw, g).unwrap();
                let n = fw * fh * c;
                let raw8: Vec<u8> = (0..n).map(|i| (i * 7919 % 256) as u8).collect();
                let raw16: Vec<u16> = (0..n).map(|i| (i * 7919 % 65_536) as u16).collect();
                let mut rawf: Vec<f32> = (0..n).map(|i| (i % 101) as f32 / 101.0).collect();
                rawf[(20 * fw + 30) * c] = f32::NAN;
                rawf[(70 * fw + 100) * c] = f32::INFINITY;
                for masks in [None, Some(&masks[..])] {
                    let maps = ViewMaps::new(&warps, masks, 4, rh, rw).unwrap();
                    let plan = RectifyPlan::new(gains_v, &crops, maps, Interp::Bilinear).unwrap();
                    let views = [3, 0, 1, 2, 0];
                    let check =
                        |want: &[f32], got: &[f32]| {
                            assert!(
                                want.iter().zip(got).all(|(a, b)| a.to_bits() == b.to_bits()
                                    || (a.is_nan() && b.is_nan())),
                                "{c} channels, {g} gain channels"
                            );
                        };
                    let len = views.len() * rh * rw * c;
                    macro_rules! compare {
                        ($raw:expr) => {{
                            let raw_v = ImageView::new(&$raw, fh, fw, c).unwrap();
                            let mut want = vec![0f32; len];
                            rectify(
                                raw_v,
                                gains_v,
                                &crops,
                                maps,
                                &views,
                                Interp::Bilinear,
                                &mut want,
                            )
                            .unwrap();
                            assert!(want.iter().filter(|v| v.is_finite()).count() > len / 2);
                            for cap in [Level::Avx2, Level::Portable] {
                                let mut got = vec![7f32; len];
                                let simd = Dispatch::at_most(cap);
                                plan.rectify_with(raw_v, &views, &mut got, &simd).unwrap();
                                check(&want, &got);
                                // The SIMD build ran where it can (see `simd::runs_or_skip`).
                                assert_eq!(simd.ran(), simd.allowed());
                            }
                        }};
                    }
                    compare!(raw8);
                    compare!(raw16);
                    compare!(rawf);
                }
            }
        }
    }

    #[test]
    fn plan_checks_its_arguments() {
        let gains = vec![1.0f32; 20 * 10];
        let gains_v = ImageView::new(&gains, 10, 20, 1).unwrap();
        let warps = vec![0.5f32; 2 * 2 * 3 * 2];
        let maps = ViewMaps::new(&warps, None, 2, 2, 3).unwrap();
        let crops = [[0, 0, 5, 5], [15, 5, 5, 5]];
        let err = RectifyPlan::new(gains_v, &crops, maps, Interp::Bicubic).unwrap_err();
        assert!(
            err.to_string()
                .starts_with("interp: a prepared plan is bilinear")
        );
        let err = RectifyPlan::new(gains_v, &crops[..1], maps, Interp::Bilinear).unwrap_err();
        assert!(err.to_string().starts_with("crops: has 1 rectangles"));
        let err = RectifyPlan::new(
            gains_v,
            &[[0, 0, 5, 5], [16, 0, 5, 5]],
            maps,
            Interp::Bilinear,
        )
        .unwrap_err();
        assert!(err.to_string().starts_with("crops[1]: rectangle"));
        let plan = RectifyPlan::new(gains_v, &crops, maps, Interp::Bilinear).unwrap();
        assert_eq!(
            (plan.views(), plan.shape(), plan.raw_shape()),
            (2, (2, 3), (10, 20))
        );
        assert_eq!(plan.kept(), 12);
        let raw = vec![0u8; 20 * 11 * 3];
        let wrong = ImageView::new(&raw, 11, 20, 3).unwrap();
        let err = plan.rectify(wrong, &[0], &mut [0.0; 18]).unwrap_err();
        assert!(
            err.to_string()
                .starts_with("raw: (H, W) = (11, 20) differs")
        );
        let raw_v = ImageView::new(&raw[..600], 10, 20, 3).unwrap();
        assert_eq!(plan.output_shape(&raw_v, &[1, 1]).unwrap(), [2, 2, 3, 3]);
        let err = plan.rectify(raw_v, &[2], &mut [0.0; 18]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "views[0]: view index 2 is out of range for 2 views"
        );
        let err = plan.rectify(raw_v, &[0], &mut [0.0; 17]).unwrap_err();
        assert!(err.to_string().starts_with("out: has 17 elements"));
        let mut out = [0.0; 18];
        plan.rectify(raw_v, &[0], &mut out).unwrap();
        assert!(out.iter().all(|&v| v == 0.0));
    }
}
