//! Sampling an image at real-valued positions given by a map (exact bilinear
//! interpolation), and the per-axis position arithmetic shared with [`mod@crate::rectify`].
//!
//! # Conventions
//! A map is a float32 `(H', W', 2)` array of positions `(x, y)` in the source, `x` the
//! column (OpenCV's convention). Pixel centres are at integer coordinates: `(0, 0)` is
//! the centre of the top-left pixel, `(W - 1, H - 1)` that of the bottom-right one.
//!
//! # The footprint
//! A sample at `(x, y)` reads the source pixels that get a non-zero weight: columns
//! `floor(x)` and `floor(x) + 1` (only `floor(x)` when `x` is a whole number), likewise
//! for rows. A sample whose footprint is not entirely inside the source is "no data"
//! (NaN): there is no border extrapolation. A position exactly on the last column
//! `x == W - 1` therefore still has a value, and reads nothing beyond the image.
//!
//! # OpenCV's position arithmetic
//! Measured on OpenCV 5.0.0 (opencv-python-headless, ALGO_HINT_ACCURATE) with float32
//! maps, against float64 references at true and at 1/32-pixel positions:
//! - `INTER_LINEAR` on 1-, 3- or 4-channel images (8U, 16U, 32F): true positions. The
//!   kernels of `warp_kernels.simd.hpp` / `warp_common.scalar.hpp` (since OpenCV 4.11)
//!   compute `ix = floor(x)`, `t = x - ix`, and `v0 = p00 + t (p01 - p00)`,
//!   `v1 = p10 + t (p11 - p10)`, `v = v0 + u (v1 - v0)` in float32. That is `Linear`
//!   and `Bilinear`; it agrees with `cv2.remap` to a few 1e-8 on values in [0, 1].
//! - `INTER_CUBIC` on float32 images (any channel count): true positions too, Keys'
//!   kernel with `A = -0.75` evaluated at the fraction; `Cubic` and `cubic_coeffs`
//!   agree with `cv2.remap` to about 1e-6.
//! - `INTER_LINEAR` on 2-channel images (and every method before OpenCV 4.11, or with
//!   fixed-point maps from `cv2.convertMaps`): the legacy path of `imgwarp.cpp`, which
//!   first rounds each coordinate to 1/32 pixel, `sx = cvRound(x * INTER_TAB_SIZE)`
//!   (`INTER_BITS = 5`, `INTER_TAB_SIZE = 32`, round half to even), integer part
//!   `sx >> INTER_BITS`, fraction index `sx & (INTER_TAB_SIZE - 1)`, then weighs with
//!   the float table `BilinearTab_f` of `initInterTab2D` (products of `1 - i/32` and
//!   `i/32`). That is `quantise`, `LinearQ32` and `LINEAR_Q32`. The position
//!   error is up to 1/64 pixel per axis, so such a sample differs from the exact one
//!   by up to `(|dx| + |dy|) / 64`, `dx` and `dy` the largest differences between
//!   horizontally and vertically adjacent values of the footprint.

use crate::error::{Error, Result};
use crate::image::ImageView;
use crate::parallel;

/// Largest number of interleaved channels the sampling kernels are specialised for.
pub const MAX_CHANNELS: usize = 4;

/// Sub-pixel steps per pixel of OpenCV's quantised positions (`INTER_TAB_SIZE`).
pub const TAB_SIZE: usize = 32;

/// `(n - 1)` as f32: the largest coordinate whose footprint can be inside `n` pixels.
#[inline(always)]
pub(crate) fn last(n: usize) -> f32 {
    n.saturating_sub(1) as f32
}

/// One axis of a bilinear footprint at a true (unquantised) position: pixels `i0` and
/// `i1` with weights `1 - t` and `t`. `i1 == i0` when `t == 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Linear {
    pub(crate) i0: usize,
    pub(crate) i1: usize,
    pub(crate) t: f32,
}

impl Linear {
    /// The footprint of coordinate `x` on an axis of `n` pixels, or `None` if it is not
    /// entirely inside (or `x` is NaN or infinite).
    #[inline(always)]
    pub(crate) fn at(x: f32, n: usize) -> Option<Self> {
        // Written so that NaN fails: `x >= 0` is false for NaN.
        if !(x >= 0.0 && x <= last(n)) {
            return None;
        }
        // Truncation is floor for x >= 0; `x - i0` is exact in float32.
        let i = x as i32;
        let t = x - i as f32;
        let i0 = i as usize;
        let i1 = i0 + usize::from(t > 0.0);
        (i1 < n).then_some(Self { i0, i1, t })
    }
}

/// The channels of one pixel in four lanes: its `C <= 4` channels, then padding
/// (whatever follows the pixel in memory). Whole-lane arithmetic lets the compiler use
/// SIMD; only the first `C` lanes are ever stored or checked.
pub(crate) type Lanes = [f32; 4];

/// `a + t (b - a)` lane by lane: one step of OpenCV's bilinear interpolation.
#[inline(always)]
pub(crate) fn lerp_lanes(a: Lanes, b: Lanes, t: f32) -> Lanes {
    let mut o = a;
    for (o, &b) in o.iter_mut().zip(&b) {
        *o += t * (b - *o);
    }
    o
}

/// `acc + w x`, lane by lane.
#[inline(always)]
pub(crate) fn add_scaled(acc: Lanes, x: Lanes, w: f32) -> Lanes {
    let mut o = acc;
    for (o, &x) in o.iter_mut().zip(&x) {
        *o += w * x;
    }
    o
}

/// Whether one of the first `c` lanes is NaN.
#[inline(always)]
pub(crate) fn any_nan(v: &Lanes, c: usize) -> bool {
    v.iter().take(c).fold(false, |n, s| n | s.is_nan())
}

/// Four consecutive elements of `s` from `start`, or if fewer are left, those padded
/// with `T::default()`; `None` if `start` is past the end.
#[inline(always)]
pub(crate) fn four<T: Copy + Default>(s: &[T], start: usize) -> Option<[T; 4]> {
    let tail = s.get(start..)?;
    match tail.first_chunk::<4>() {
        Some(a) => Some(*a),
        None => {
            let mut a = [T::default(); 4];
            for (a, &v) in a.iter_mut().zip(tail) {
                *a = v;
            }
            Some(a)
        }
    }
}

/// Where a sampler reads pixels: pixel `(row, col)` of a `w x h` frame as lanes, `None`
/// if the source does not hold it (a bug upstream, never user data: callers only ask
/// for pixels of footprints inside the frame).
pub(crate) trait Taps {
    fn tap(&self, row: usize, col: usize) -> Option<Lanes>;

    /// Pixels `(row, col)` and `(row, col + 1)`, or `(row, col)` twice if `!right`.
    #[inline(always)]
    fn pair(&self, row: usize, col: usize, right: bool) -> Option<(Lanes, Lanes)> {
        let a = self.tap(row, col)?;
        let b = if right { self.tap(row, col + 1)? } else { a };
        Some((a, b))
    }

    /// A bilinear footprint: [`Self::pair`] at `row` and at `row + 1` (`row` again if
    /// `!down`), top left, top right, bottom left, bottom right.
    #[inline(always)]
    fn quad(&self, row: usize, col: usize, right: bool, down: bool) -> Option<[Lanes; 4]> {
        let (a, b) = self.pair(row, col, right)?;
        let (c, d) = self.pair(row + usize::from(down), col, right)?;
        Some([a, b, c, d])
    }
}

/// A `rows x cols` region of a float32 image with `C` interleaved channels, at `(row0,
/// col0)` of the frame: frame pixel `(row, col)` is at `data[(row - row0) * stride +
/// (col - col0) * C]`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Packed<'a, const C: usize> {
    pub(crate) data: &'a [f32],
    pub(crate) stride: usize,
    pub(crate) row0: usize,
    pub(crate) col0: usize,
    pub(crate) rows: usize,
    pub(crate) cols: usize,
}

impl<const C: usize> Packed<'_, C> {
    /// The offset of frame pixel `(row, col)`, `None` unless the `(1 + down) x (1 +
    /// right)` pixels from there are inside the region.
    #[inline(always)]
    fn offset(&self, row: usize, col: usize, right: bool, down: bool) -> Option<usize> {
        let r = row
            .checked_sub(self.row0)
            .filter(|&r| r + usize::from(down) < self.rows)?;
        let c = col
            .checked_sub(self.col0)
            .filter(|&c| c + usize::from(right) < self.cols)?;
        Some(r * self.stride + c * C)
    }

    /// The pixel at `start` and the next (or itself again if `!right`): one read of
    /// eight values (callers pad `data` by 8 values; at the very end, two reads).
    #[inline(always)]
    fn pair_at(&self, start: usize, right: bool) -> Option<(Lanes, Lanes)> {
        let Some(eight) = self.data.get(start..).and_then(|s| s.first_chunk::<8>()) else {
            let a = four(self.data, start)?;
            let b = if right {
                four(self.data, start + C)?
            } else {
                a
            };
            return Some((a, b));
        };
        let a = *eight.first_chunk::<4>()?;
        let b = if right {
            *eight.get(C..)?.first_chunk::<4>()?
        } else {
            a
        };
        Some((a, b))
    }
}

impl<const C: usize> Taps for Packed<'_, C> {
    #[inline(always)]
    fn tap(&self, row: usize, col: usize) -> Option<Lanes> {
        four(self.data, self.offset(row, col, false, false)?)
    }

    #[inline(always)]
    fn pair(&self, row: usize, col: usize, right: bool) -> Option<(Lanes, Lanes)> {
        self.pair_at(self.offset(row, col, right, false)?, right)
    }

    #[inline(always)]
    fn quad(&self, row: usize, col: usize, right: bool, down: bool) -> Option<[Lanes; 4]> {
        let top = self.offset(row, col, right, down)?;
        let (a, b) = self.pair_at(top, right)?;
        let (c, d) = self.pair_at(if down { top + self.stride } else { top }, right)?;
        Some([a, b, c, d])
    }
}

/// An interpolation method: the value at `(x, y)` of a `w x h` frame whose pixels
/// `src` holds, `None` when the footprint (the pixels with non-zero weight) is not
/// entirely inside the frame. NaN in a lane where a footprint value is NaN.
pub(crate) trait Sampler {
    /// The footprint of a position spans columns `floor(x) - BEFORE ..= floor(x) +
    /// AFTER` at most (rounding included), likewise for rows.
    const BEFORE: usize;
    const AFTER: usize;
    /// Whether this is [`Bilinear`], which [`mod@crate::rectify`] runs through a
    /// specialised loop computing the same values.
    const IS_BILINEAR: bool = false;

    fn sample<S: Taps>(src: &S, w: usize, h: usize, x: f32, y: f32) -> Option<Lanes>;
}

/// Bilinear at the true position, in OpenCV's order of operations (see the module
/// docs): along x first, then along y.
#[derive(Debug)]
pub(crate) struct Bilinear;

impl Sampler for Bilinear {
    const BEFORE: usize = 0;
    const AFTER: usize = 1;
    const IS_BILINEAR: bool = true;

    #[inline(always)]
    fn sample<S: Taps>(src: &S, w: usize, h: usize, x: f32, y: f32) -> Option<Lanes> {
        let ax = Linear::at(x, w)?;
        let ay = Linear::at(y, h)?;
        let [p00, p01, p10, p11] = src.quad(ay.i0, ax.i0, ax.i1 > ax.i0, ay.i1 > ay.i0)?;
        let v0 = lerp_lanes(p00, p01, ax.t);
        let v1 = lerp_lanes(p10, p11, ax.t);
        Some(lerp_lanes(v0, v1, ay.t))
    }
}

/// Bilinear at positions rounded to 1/32 pixel, with OpenCV's weight table and order.
#[derive(Debug)]
pub(crate) struct BilinearQ32;

impl Sampler for BilinearQ32 {
    const BEFORE: usize = 0;
    const AFTER: usize = 1;

    #[inline(always)]
    fn sample<S: Taps>(src: &S, w: usize, h: usize, x: f32, y: f32) -> Option<Lanes> {
        let ax = LinearQ32::at(x, w)?;
        let ay = LinearQ32::at(y, h)?;
        let &[wx0, wx1] = LINEAR_Q32.get(ax.f)?;
        let &[wy0, wy1] = LINEAR_Q32.get(ay.f)?;
        let [p00, p01, p10, p11] = src.quad(ay.i0, ax.i0, ax.i1 > ax.i0, ay.i1 > ay.i0)?;
        // OpenCV's 2-D table holds the float products; its sum runs left to right.
        let mut v = [0.0f32; 4];
        for (v, (((&a, &b), &c), &d)) in v.iter_mut().zip(p00.iter().zip(&p01).zip(&p10).zip(&p11))
        {
            *v = a * (wy0 * wx0) + b * (wy0 * wx1) + c * (wy1 * wx0) + d * (wy1 * wx1);
        }
        Some(v)
    }
}

/// Keys' bicubic (`A = -0.75`) at the true position, separable: along x within each
/// of the four rows, then along y.
#[derive(Debug)]
pub(crate) struct Bicubic;

impl Sampler for Bicubic {
    const BEFORE: usize = 1;
    const AFTER: usize = 2;

    #[inline(always)]
    fn sample<S: Taps>(src: &S, w: usize, h: usize, x: f32, y: f32) -> Option<Lanes> {
        let ax = Cubic::at(x, w)?;
        let ay = Cubic::at(y, h)?;
        let wx = cubic_coeffs(ax.t);
        let wy = cubic_coeffs(ay.t);
        let mut sum = [0.0f32; 4];
        for (&row, &w_row) in ay.idx.iter().zip(&wy) {
            let mut along_x = [0.0f32; 4];
            for (&col, &w_col) in ax.idx.iter().zip(&wx) {
                along_x = add_scaled(along_x, src.tap(row, col)?, w_col);
            }
            sum = add_scaled(sum, along_x, w_row);
        }
        Some(sum)
    }
}

/// `x` rounded to the nearest 1/32 pixel as OpenCV's `cvRound(x * INTER_TAB_SIZE)` does
/// (half to even), split into the integer part (floor) and the fraction index in
/// `0..32`. `None` for NaN, infinities and positions beyond `i64`.
#[inline(always)]
pub(crate) fn quantise(x: f32) -> Option<(i64, usize)> {
    // 1.5 * 2^23: adding and subtracting it rounds |v| < 2^22 to an integer, half to
    // even, without a call to `rintf` (not inlined on baseline x86-64).
    const MAGIC: f32 = 12_582_912.0;
    let v = x * TAB_SIZE as f32; // exact: a power of two
    let r = if v.abs() < 4_194_304.0 {
        (v + MAGIC) - MAGIC
    } else if v.is_finite() && v.abs() < 9.0e18 {
        v.round_ties_even()
    } else {
        return None;
    };
    let s = r as i64;
    Some((s >> 5, (s & 31) as usize))
}

/// One axis of a bilinear footprint at a position quantised to 1/32 pixel: pixels `i0`
/// and `i1` (`i1 == i0` when the fraction index `f` is 0), weights `LINEAR_Q32[f]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct LinearQ32 {
    pub(crate) i0: usize,
    pub(crate) i1: usize,
    pub(crate) f: usize,
}

impl LinearQ32 {
    #[inline(always)]
    pub(crate) fn at(x: f32, n: usize) -> Option<Self> {
        let (i, f) = quantise(x)?;
        let i0 = usize::try_from(i).ok()?;
        let i1 = i0 + usize::from(f > 0);
        (i1 < n).then_some(Self { i0, i1, f })
    }
}

/// One axis of a bicubic footprint at a true position: the four pixels `idx` with
/// weights `cubic_coeffs(t)`. When `t == 0` the weights are exactly `(0, 1, 0, 0)` and
/// the footprint is the one pixel `idx[1]` (repeated in `idx`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Cubic {
    pub(crate) idx: [usize; 4],
    pub(crate) t: f32,
}

impl Cubic {
    #[inline(always)]
    pub(crate) fn at(x: f32, n: usize) -> Option<Self> {
        if !(x >= 0.0 && x <= last(n)) {
            return None;
        }
        let i = x as i32;
        let t = x - i as f32;
        let i = i as usize;
        if t == 0.0 {
            return (i < n).then_some(Self { idx: [i; 4], t });
        }
        let first = i.checked_sub(1)?;
        (i + 2 < n).then_some(Self {
            idx: [first, i, i + 1, i + 2],
            t,
        })
    }
}

/// OpenCV's `interpolateCubic` (Keys' kernel with `A = -0.75`), term for term in
/// float32, for the fraction `x` in `[0, 1)`.
#[inline(always)]
pub(crate) const fn cubic_coeffs(x: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let c0 = ((A * (x + 1.0) - 5.0 * A) * (x + 1.0) + 8.0 * A) * (x + 1.0) - 4.0 * A;
    let c1 = ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let c2 = ((A + 2.0) * (1.0 - x) - (A + 3.0)) * (1.0 - x) * (1.0 - x) + 1.0;
    [c0, c1, c2, 1.0 - c0 - c1 - c2]
}

// Evaluated at compile time only: an index out of range is a build error, not a panic.
#[allow(clippy::indexing_slicing)]
const fn linear_table() -> [[f32; 2]; TAB_SIZE] {
    let mut tab = [[0.0; 2]; TAB_SIZE];
    let mut i = 0;
    while i < TAB_SIZE {
        let x = i as f32 * (1.0 / TAB_SIZE as f32);
        tab[i] = [1.0 - x, x];
        i += 1;
    }
    tab
}

/// OpenCV's 1-D bilinear weights at fractions `i / 32` (`initInterTab1D`).
pub(crate) const LINEAR_Q32: [[f32; 2]; TAB_SIZE] = linear_table();

/// Samples `src` at the positions of `map` with exact bilinear interpolation and
/// writes the result to `out`, laid out `(H', W', C)` C-contiguous (`H' x W'` the size
/// of `map`, `C` that of `src`).
///
/// Output pixel `(r, c)` samples `src` at `(x, y) = map[r, c]`: the weights come from
/// the true fractional position (no 1/32-pixel quantisation) and the arithmetic is
/// float32 in OpenCV's order (see the module docs). A sample is NaN in every channel
/// when its map entry is NaN or infinite, when its footprint is not entirely inside
/// `src`, or when any source value in the footprint is NaN.
///
/// With a `(H, W, 2)` map as `src`, this composes maps: `out[r, c]` is the map `src`
/// sampled at the positions `map[r, c]`.
///
/// # Errors
/// - [`Error::InvalidArgument`] `"map"` if `map` does not have 2 channels;
/// - [`Error::InvalidArgument`] `"src"` if `src` has more than [`MAX_CHANNELS`]
///   channels;
/// - [`Error::InvalidArgument`] `"out"` if `out.len() != H' * W' * C`.
pub fn remap_bilinear(
    src: ImageView<'_, f32>,
    map: ImageView<'_, f32>,
    out: &mut [f32],
) -> Result<()> {
    if map.channels() != 2 {
        return Err(Error::invalid_argument(
            "map",
            format!(
                "expected a (H', W', 2) map of positions (x, y), got {} channels",
                map.channels()
            ),
        ));
    }
    let c = src.channels();
    let expected = map
        .height()
        .checked_mul(map.width())
        .and_then(|n| n.checked_mul(c));
    if expected != Some(out.len()) {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "has {} elements, but the output (H', W', C) = ({}, {}, {c}) needs {}",
                out.len(),
                map.height(),
                map.width(),
                expected.map_or_else(|| "more than usize::MAX".to_owned(), |n| n.to_string()),
            ),
        ));
    }
    match c {
        1 => remap_channels::<1>(src, map, out),
        2 => remap_channels::<2>(src, map, out),
        3 => remap_channels::<3>(src, map, out),
        4 => remap_channels::<4>(src, map, out),
        _ => Err(Error::invalid_argument(
            "src",
            format!("has {c} channels; 1 to {MAX_CHANNELS} are supported"),
        )),
    }
}

fn remap_channels<const C: usize>(
    src: ImageView<'_, f32>,
    map: ImageView<'_, f32>,
    out: &mut [f32],
) -> Result<()> {
    let (w, h) = (src.width(), src.height());
    let taps = Packed::<C> {
        data: src.as_slice(),
        stride: src.row_len(),
        row0: 0,
        col0: 0,
        rows: h,
        cols: w,
    };
    let row_len = map.width() * C;
    parallel::for_each_row_chunk(out, row_len, |first_row, rows| {
        for (k, out_row) in rows.chunks_exact_mut(row_len).enumerate() {
            let r = first_row + k;
            let map_row = map
                .row(r)
                .ok_or_else(|| Error::internal("remap_bilinear", format!("no map row {r}")))?;
            let (pixels, _) = out_row.as_chunks_mut::<C>();
            let (points, _) = map_row.as_chunks::<2>();
            for (px, &[x, y]) in pixels.iter_mut().zip(points) {
                *px = match Bilinear::sample(&taps, w, h, x, y) {
                    // A NaN value in the footprint makes its channel NaN: make it every
                    // channel's.
                    Some(v) if !any_nan(&v, C) => first::<C>(&v),
                    _ => [f32::NAN; C],
                };
            }
        }
        Ok(())
    })
}

/// The first `C <= 4` lanes.
#[inline(always)]
pub(crate) fn first<const C: usize>(v: &Lanes) -> [f32; C] {
    let mut o = [0.0f32; C];
    for (o, &v) in o.iter_mut().zip(v) {
        *o = v;
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_axis_edges() {
        assert_eq!(
            Linear::at(0.0, 5),
            Some(Linear {
                i0: 0,
                i1: 0,
                t: 0.0
            })
        );
        assert_eq!(
            Linear::at(4.0, 5),
            Some(Linear {
                i0: 4,
                i1: 4,
                t: 0.0
            })
        );
        assert_eq!(
            Linear::at(3.5, 5),
            Some(Linear {
                i0: 3,
                i1: 4,
                t: 0.5
            })
        );
        assert_eq!(Linear::at(4.0001, 5), None);
        assert_eq!(Linear::at(-0.0001, 5), None);
        assert_eq!(
            Linear::at(0.0, 1),
            Some(Linear {
                i0: 0,
                i1: 0,
                t: 0.0
            })
        );
        assert_eq!(Linear::at(0.5, 1), None);
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 1e30] {
            assert_eq!(Linear::at(bad, 5), None);
        }
    }

    #[test]
    fn quantise_rounds_half_to_even_like_cvround() {
        assert_eq!(quantise(0.0), Some((0, 0)));
        assert_eq!(quantise(1.0 / 64.0), Some((0, 0))); // 0.5 -> 0
        assert_eq!(quantise(3.0 / 64.0), Some((0, 2))); // 1.5 -> 2
        assert_eq!(quantise(2.99), Some((3, 0)));
        assert_eq!(quantise(-1.0 / 64.0), Some((0, 0))); // -0.5 -> -0
        assert_eq!(quantise(-3.0 / 64.0), Some((-1, 30))); // -1.5 -> -2
        assert_eq!(quantise(200_000.5), Some((200_000, 16)));
        assert_eq!(quantise(f32::NAN), None);
        assert_eq!(quantise(f32::INFINITY), None);
    }

    #[test]
    fn quantised_axes_edges() {
        // 4.99 rounds to 5.0: outside 5 pixels; -0.01 rounds to 0: inside.
        assert_eq!(LinearQ32::at(4.99, 5), None);
        assert_eq!(
            LinearQ32::at(-0.01, 5),
            Some(LinearQ32 { i0: 0, i1: 0, f: 0 })
        );
        assert_eq!(
            LinearQ32::at(1.25, 5),
            Some(LinearQ32 { i0: 1, i1: 2, f: 8 })
        );
    }

    #[test]
    fn cubic_axis_edges() {
        assert_eq!(
            Cubic::at(2.0, 3),
            Some(Cubic {
                idx: [2; 4],
                t: 0.0
            })
        );
        assert_eq!(
            Cubic::at(0.0, 3),
            Some(Cubic {
                idx: [0; 4],
                t: 0.0
            })
        );
        assert_eq!(Cubic::at(0.5, 4), None);
        assert_eq!(
            Cubic::at(1.5, 4),
            Some(Cubic {
                idx: [0, 1, 2, 3],
                t: 0.5
            })
        );
        assert_eq!(Cubic::at(1.5, 3), None);
        assert_eq!(Cubic::at(f32::NAN, 3), None);
    }

    #[test]
    fn weight_tables() {
        // OpenCV's kernel at 0 is exactly (0, 1, 0, 0); weights always sum to 1.
        assert_eq!(cubic_coeffs(0.0), [0.0, 1.0, 0.0, 0.0]);
        for i in 0..100 {
            let w = cubic_coeffs(i as f32 / 100.0);
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        }
        for l in &LINEAR_Q32 {
            assert_eq!(l[0] + l[1], 1.0);
        }
        assert_eq!(LINEAR_Q32[8], [0.75, 0.25]);
        // Keys' kernel at 1/2 with A = -0.75: (-0.09375, 0.59375, 0.59375, -0.09375).
        assert_eq!(cubic_coeffs(0.5), [-0.09375, 0.59375, 0.59375, -0.09375]);
    }

    #[test]
    fn remaps_a_small_image() {
        // 2x3 mono, values 0..6.
        let data: Vec<f32> = (0..6).map(|v| v as f32).collect();
        let src = ImageView::new(&data, 2, 3, 1).unwrap();
        let pts = [
            0.5f32,
            0.5,
            2.0,
            1.0,
            2.0,
            0.25,
            2.5,
            0.0,
            f32::NAN,
            0.0,
            0.0,
            -1.0,
        ];
        let map = ImageView::new(&pts, 1, 6, 2).unwrap();
        let mut out = [0.0f32; 6];
        remap_bilinear(src, map, &mut out).unwrap();
        assert_eq!(out[..3], [2.0, 5.0, 2.75]);
        assert!(out[3..].iter().all(|v| v.is_nan()));
    }

    #[test]
    fn bad_sizes_name_the_argument() {
        let data = [0.0f32; 12];
        let src = ImageView::new(&data, 2, 2, 3).unwrap();
        let map = ImageView::new(&data, 2, 2, 3).unwrap();
        let err = remap_bilinear(src, map, &mut [0.0; 12]).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "map"));
        let map = ImageView::new(&data[..8], 2, 2, 2).unwrap();
        let err = remap_bilinear(src, map, &mut [0.0; 11]).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "out"));
        let wide = ImageView::new(&data, 1, 2, 6).unwrap();
        let err = remap_bilinear(wide, map, &mut [0.0; 24]).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "src"));
    }
}
