//! Super-resolution kernels (DESIGN.md section 5): warp-map inversion, placement of raw
//! samples in the reference view's rectified frame, robust shift-and-add onto an
//! r-times finer grid, and bilateral-TV deblurring (Farsiu, Robinson, Elad, Milanfar
//! 2004, "Fast and robust multiframe super resolution").
//!
//! # Conventions
//! Positions follow OpenCV: `(x, y)`, `x` the column, pixel centres at integers. A
//! rectified position `x` lands on the `r`-times finer grid at `X = (x + 0.5) r - 0.5`
//! (DESIGN.md section 2: fine pixel `U` sits at rectified `(U + 0.5) / r - 0.5`).
//!
//! # Indexing
//! Every function checks all sizes up front; the inner loops then index slices whose
//! lengths those checks guarantee, with explicit bounds tests on every computed index.

// Sizes are checked at the top of each public function and every computed index is
// bounds-tested before use (`get` or an explicit comparison with the checked length).
#![allow(clippy::indexing_slicing)]

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::parallel;
use crate::simd;

/// Largest super-resolution factor (and channel count) the kernels accept.
pub const MAX_FACTOR: f32 = 16.0;
/// Largest number of interleaved channels.
pub const MAX_CHANNELS: usize = 4;
/// Largest splat kernel radius, fine px.
pub const MAX_RADIUS: usize = 16;

/// `v > 0` (false for NaN): written as a function so that `!positive(v)` reads as
/// "not a usable positive number".
#[inline(always)]
fn positive(v: f32) -> bool {
    v > 0.0
}

fn check_len(arg: &str, got: usize, want: usize, what: &str) -> Result<()> {
    if got == want {
        Ok(())
    } else {
        Err(Error::invalid_argument(
            arg,
            format!("has {got} elements, {what} needs {want}"),
        ))
    }
}

fn mul(arg: &str, dims: &[usize]) -> Result<usize> {
    dims.iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| Error::invalid_argument(arg, format!("shape {dims:?} is too large")))
}

// --------------------------------------------------------------------------------------
// Map inversion
// --------------------------------------------------------------------------------------

/// The rectified position `(u + a, v + b)` of the raw point `(px, py)` inside the cell
/// whose corners map to `p00 = w(u, v)`, `p10 = w(u + 1, v)`, `p01 = w(u, v + 1)`,
/// `p11 = w(u + 1, v + 1)`: Newton's method on the bilinear patch, from its centre.
/// Returns `(a, b)` if it converged inside the cell (with a tolerance `eps`).
#[inline]
fn invert_bilinear(
    p00: [f32; 2],
    p10: [f32; 2],
    p01: [f32; 2],
    p11: [f32; 2],
    px: f32,
    py: f32,
    eps: f32,
) -> Option<(f32, f32)> {
    let (mut a, mut b) = (0.5f32, 0.5f32);
    for _ in 0..6 {
        let fx = (1.0 - a) * (1.0 - b) * p00[0]
            + a * (1.0 - b) * p10[0]
            + (1.0 - a) * b * p01[0]
            + a * b * p11[0]
            - px;
        let fy = (1.0 - a) * (1.0 - b) * p00[1]
            + a * (1.0 - b) * p10[1]
            + (1.0 - a) * b * p01[1]
            + a * b * p11[1]
            - py;
        let dxa = (1.0 - b) * (p10[0] - p00[0]) + b * (p11[0] - p01[0]);
        let dya = (1.0 - b) * (p10[1] - p00[1]) + b * (p11[1] - p01[1]);
        let dxb = (1.0 - a) * (p01[0] - p00[0]) + a * (p11[0] - p10[0]);
        let dyb = (1.0 - a) * (p01[1] - p00[1]) + a * (p11[1] - p10[1]);
        let det = dxa * dyb - dxb * dya;
        if !positive(det.abs() - 1e-12) {
            return None;
        }
        let da = (fx * dyb - fy * dxb) / det;
        let db = (dxa * fy - dya * fx) / det;
        a -= da;
        b -= db;
        if da.abs() < 1e-6 && db.abs() < 1e-6 {
            break;
        }
    }
    (a >= -eps && a <= 1.0 + eps && b >= -eps && b <= 1.0 + eps && a.is_finite() && b.is_finite())
        .then_some((a, b))
}

/// Inverts one view's warp map: for each pixel of its crop (`crop_h x crop_w`, raw
/// pixel centres at integers relative to the crop), the rectified position `(u, v)`
/// that the map sends there, NaN where no valid rectified cell covers it.
///
/// `warp` is `(h, w, 2)`, `mask` `(h, w)` (non-zero: valid) or `None`; `out` is
/// `(crop_h, crop_w, 2)`. A cell is valid when its four corners are finite and
/// unmasked. Raw points covered by two cells (on shared edges) take the first.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `warp`, `mask` or `out` if a size disagrees.
pub fn invert_map(
    warp: &[f32],
    mask: Option<&[u8]>,
    h: usize,
    w: usize,
    crop_h: usize,
    crop_w: usize,
    out: &mut [f32],
) -> Result<()> {
    check_len("warp", warp.len(), mul("warp", &[h, w, 2])?, "(H, W, 2)")?;
    if let Some(m) = mask {
        check_len("mask", m.len(), mul("mask", &[h, w])?, "(H, W)")?;
    }
    check_len(
        "out",
        out.len(),
        mul("out", &[crop_h, crop_w, 2])?,
        "(crop_h, crop_w, 2)",
    )?;
    out.fill(f32::NAN);
    if h < 2 || w < 2 {
        return Ok(());
    }
    let ok = |y: usize, x: usize| mask.is_none_or(|m| m[y * w + x] != 0);
    let at = |y: usize, x: usize| [warp[(y * w + x) * 2], warp[(y * w + x) * 2 + 1]];
    let (cw, ch) = (crop_w as f32, crop_h as f32);
    for v in 0..h - 1 {
        for u in 0..w - 1 {
            if !(ok(v, u) && ok(v, u + 1) && ok(v + 1, u) && ok(v + 1, u + 1)) {
                continue;
            }
            let (p00, p10, p01, p11) = (at(v, u), at(v, u + 1), at(v + 1, u), at(v + 1, u + 1));
            let xs = [p00[0], p10[0], p01[0], p11[0]];
            let ys = [p00[1], p10[1], p01[1], p11[1]];
            if xs.iter().chain(ys.iter()).any(|c| !c.is_finite()) {
                continue;
            }
            let xmin = xs.iter().copied().fold(f32::INFINITY, f32::min).max(0.0);
            let xmax = xs
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max)
                .min(cw - 1.0);
            let ymin = ys.iter().copied().fold(f32::INFINITY, f32::min).max(0.0);
            let ymax = ys
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max)
                .min(ch - 1.0);
            if !(xmin <= xmax && ymin <= ymax) {
                continue;
            }
            for py in (ymin.ceil() as usize)..=(ymax.floor() as usize) {
                for px in (xmin.ceil() as usize)..=(xmax.floor() as usize) {
                    if px >= crop_w || py >= crop_h {
                        continue;
                    }
                    let k = (py * crop_w + px) * 2;
                    if out[k].is_finite() {
                        continue;
                    }
                    if let Some((a, b)) =
                        invert_bilinear(p00, p10, p01, p11, px as f32, py as f32, 1e-4)
                    {
                        out[k] = u as f32 + a;
                        out[k + 1] = v as f32 + b;
                    }
                }
            }
        }
    }
    Ok(())
}

/// [`invert_map`] for all `N` views at once, in parallel over views, written into one
/// raw-frame-sized map: `inv` `(raw_h, raw_w, 2)` gets the rectified position of each
/// raw pixel in its view's frame (NaN if none) and `view` `(raw_h, raw_w)` the view's
/// index (-1 if none). `warps` is `(N, h, w, 2)` relative to each crop, `masks`
/// `(N, h, w)` or `None`, `crops` `(x0, y0, cw, ch)` per view. A raw pixel inside two
/// crops takes the first view that covers it.
///
/// # Errors
/// [`Error::InvalidArgument`] or [`Error::InvalidItem`] (a crop outside the frame).
#[allow(clippy::too_many_arguments)]
pub fn invert_maps(
    warps: &[f32],
    masks: Option<&[u8]>,
    crops: &[[i64; 4]],
    h: usize,
    w: usize,
    raw_h: usize,
    raw_w: usize,
    inv: &mut [f32],
    view: &mut [i32],
) -> Result<()> {
    let n = crops.len();
    let per = mul("warps", &[h, w, 2])?;
    check_len(
        "warps",
        warps.len(),
        mul("warps", &[n, h, w, 2])?,
        "(N, H, W, 2)",
    )?;
    if let Some(m) = masks {
        check_len("masks", m.len(), mul("masks", &[n, h, w])?, "(N, H, W)")?;
    }
    check_len(
        "inv",
        inv.len(),
        mul("inv", &[raw_h, raw_w, 2])?,
        "(H_raw, W_raw, 2)",
    )?;
    check_len(
        "view",
        view.len(),
        mul("view", &[raw_h, raw_w])?,
        "(H_raw, W_raw)",
    )?;
    let mut rects = Vec::with_capacity(n);
    for (i, c) in crops.iter().enumerate() {
        let [x0, y0, cw, ch] = *c;
        let inside = x0 >= 0
            && y0 >= 0
            && cw > 0
            && ch > 0
            && x0.checked_add(cw).is_some_and(|x1| x1 <= raw_w as i64)
            && y0.checked_add(ch).is_some_and(|y1| y1 <= raw_h as i64);
        if !inside {
            return Err(Error::invalid_item(
                "crops",
                i,
                format!("rectangle {c:?} is empty or outside the {raw_w}x{raw_h} frame"),
            ));
        }
        rects.push([x0 as usize, y0 as usize, cw as usize, ch as usize]);
    }
    let per_view: Vec<Vec<f32>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let [_, _, cw, ch] = rects[i];
            let mut buf = vec![0f32; ch * cw * 2];
            let m = masks.map(|m| &m[i * h * w..(i + 1) * h * w]);
            invert_map(&warps[i * per..(i + 1) * per], m, h, w, ch, cw, &mut buf)?;
            Ok(buf)
        })
        .collect::<Result<_>>()?;
    inv.fill(f32::NAN);
    view.fill(-1);
    for (i, (buf, rect)) in per_view.iter().zip(&rects).enumerate() {
        let [x0, y0, cw, ch] = *rect;
        for yc in 0..ch {
            for xc in 0..cw {
                let s = (yc * cw + xc) * 2;
                let d = (y0 + yc) * raw_w + x0 + xc;
                if buf[s].is_finite() && view[d] < 0 {
                    inv[2 * d] = buf[s];
                    inv[2 * d + 1] = buf[s + 1];
                    view[d] = i as i32;
                }
            }
        }
    }
    Ok(())
}

// --------------------------------------------------------------------------------------
// Placement in the reference frame
// --------------------------------------------------------------------------------------

/// Bilinear sample of a `(h, w)` map at `(x, y)`, skipping NaN corners (the others are
/// renormalised); NaN if the finite corners carry less than half the weight or the
/// point is outside the map by more than half a pixel.
#[inline(always)]
fn sample_nan_aware(map: &[f32], h: usize, w: usize, x: f32, y: f32) -> f32 {
    if !(x >= -0.5 && y >= -0.5 && x <= w as f32 - 0.5 && y <= h as f32 - 0.5) {
        return f32::NAN;
    }
    let xc = x.clamp(0.0, (w - 1) as f32);
    let yc = y.clamp(0.0, (h - 1) as f32);
    let x0 = (xc as usize).min(w - 1);
    let y0 = (yc as usize).min(h - 1);
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let (tx, ty) = (xc - x0 as f32, yc - y0 as f32);
    let (v00, v01) = (map[y0 * w + x0], map[y0 * w + x1]);
    let (v10, v11) = (map[y1 * w + x0], map[y1 * w + x1]);
    if (v00 + v01 + v10 + v11).is_finite() {
        // All four corners known (the usual case): the plain bilinear value. Adding the
        // terms of zero weight too changes nothing (`acc + 0 == acc`), so this is the
        // sum of the loop below, in the same order, without its branches.
        let (w00, w01) = ((1.0 - tx) * (1.0 - ty), tx * (1.0 - ty));
        let (w10, w11) = ((1.0 - tx) * ty, tx * ty);
        let acc = w00 * v00 + w01 * v01 + w10 * v10 + w11 * v11;
        let wsum = w00 + w01 + w10 + w11;
        return acc / wsum;
    }
    let mut acc = 0.0f32;
    let mut wsum = 0.0f32;
    for (yy, wy) in [(y0, 1.0 - ty), (y1, ty)] {
        for (xx, wx) in [(x0, 1.0 - tx), (x1, tx)] {
            let v = map[yy * w + xx];
            let wt = wx * wy;
            if v.is_finite() && wt > 0.0 {
                acc += wt * v;
                wsum += wt;
            }
        }
    }
    if wsum >= 0.5 { acc / wsum } else { f32::NAN }
}

/// Parameters of [`place_samples`].
#[derive(Debug, Clone, Copy)]
pub struct PlaceParams {
    /// Fixed-point iterations of `p = q - o_i s(p)`.
    pub iterations: usize,
    /// Largest accepted `|p + o_i s(p) - q|`, rectified px; other samples are dropped
    /// (no consistent reference point: occluded in the reference, or no depth).
    pub tolerance: f32,
}

/// Places raw samples in the reference view's rectified frame.
///
/// For raw pixel `k` of view `i = view[k]` (skipped if negative) at rectified position
/// `q = inv[k]` in its own view, finds the reference point `p` with
/// `p + o_i s(p) = q` (DESIGN.md section 3) by the fixed-point iteration
/// `p <- q - o_i s(p)` from `p = q`, `s` sampled bilinearly from `parallax` `(h, w)`
/// (NaN: unknown). Writes `p` to `out` (same layout as `inv`), NaN where the
/// iteration did not reach `tolerance` or the parallax is unknown. The reference view
/// (`o_i = 0`) keeps `q`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument whose size disagrees, or
/// `offsets` if a view index in `view` has no offset.
#[allow(clippy::too_many_arguments)]
pub fn place_samples(
    inv: &[f32],
    view: &[i32],
    offsets: &[[f64; 2]],
    parallax: &[f32],
    h: usize,
    w: usize,
    params: &PlaceParams,
    out: &mut [f32],
) -> Result<()> {
    let m = view.len();
    check_len(
        "inv",
        inv.len(),
        mul("inv", &[m, 2])?,
        "(..., 2) with view's size",
    )?;
    check_len("out", out.len(), inv.len(), "inv's size")?;
    check_len(
        "parallax",
        parallax.len(),
        mul("parallax", &[h, w])?,
        "(H, W)",
    )?;
    if h == 0 || w == 0 {
        return Err(Error::invalid_argument("parallax", "is empty"));
    }
    if let Some(&bad) = view
        .iter()
        .find(|&&v| v >= 0 && v as usize >= offsets.len())
    {
        return Err(Error::invalid_argument(
            "offsets",
            format!("has {} rows, but view index {bad} is used", offsets.len()),
        ));
    }
    let offs: Vec<[f32; 2]> = offsets.iter().map(|o| [o[0] as f32, o[1] as f32]).collect();
    let job = PlaceJob {
        inv,
        view,
        offsets: &offs,
        parallax,
        h,
        w,
        iterations: params.iterations,
        tolerance: params.tolerance,
    };
    parallel::for_each_row_chunk(out, 2, |first, rows| {
        place_task(&job, first, rows);
        Ok(())
    })
}

/// What [`place_samples`] reads (sizes checked).
struct PlaceJob<'a> {
    inv: &'a [f32],
    view: &'a [i32],
    offsets: &'a [[f32; 2]],
    parallax: &'a [f32],
    h: usize,
    w: usize,
    iterations: usize,
    tolerance: f32,
}

/// Samples placed side by side: their fixed-point iterations are independent, so
/// stepping [`PLACE_LANES`] of them together lets the CPU overlap their look-ups
/// (one sample's iterations form a chain of dependent loads).
const PLACE_LANES: usize = 8;

simd::avx2_or_portable!(
    true,
    /// [`place_rows`], compiled for AVX2 and for the baseline.
    fn place_task(job: &PlaceJob<'_>, first: usize, out: &mut [f32]) -> () {
        place_rows(job, first, out)
    }
);

/// Samples `first..` into `out` (2 floats each), [`PLACE_LANES`] at a time. Each
/// sample goes through exactly the arithmetic of the one-at-a-time iteration (see
/// [`place_samples`]), so the result does not depend on the grouping.
#[inline(always)]
fn place_rows(job: &PlaceJob<'_>, first: usize, out: &mut [f32]) {
    const L: usize = PLACE_LANES;
    let (h, w, par) = (job.h, job.w, job.parallax);
    let tol2 = job.tolerance * job.tolerance;
    for (g, group) in out.chunks_mut(2 * L).enumerate() {
        let base = first + g * L;
        let n = group.len() / 2;
        let mut q = [[0f32; 2]; L];
        let mut o = [[0f32; 2]; L];
        let mut p = [[0f32; 2]; L];
        let mut s = [f32::NAN; L];
        // 0: done, output NaN; 1: done, output q (reference view); 2: iterating.
        let mut state = [0u8; L];
        for l in 0..n {
            let idx = base + l;
            let vi = job.view[idx];
            let (qx, qy) = (job.inv[2 * idx], job.inv[2 * idx + 1]);
            q[l] = [qx, qy];
            if vi < 0 || !qx.is_finite() || !qy.is_finite() {
                continue;
            }
            let off = job.offsets[vi as usize];
            if off[0] == 0.0 && off[1] == 0.0 {
                state[l] = 1;
                continue;
            }
            o[l] = off;
            p[l] = [qx, qy];
            state[l] = 2;
        }
        let mut active = [false; L];
        for l in 0..L {
            if state[l] == 2 {
                s[l] = sample_nan_aware(par, h, w, p[l][0], p[l][1]);
                active[l] = true;
            }
        }
        for _ in 0..job.iterations {
            let mut any = false;
            for l in 0..L {
                if !active[l] {
                    continue;
                }
                if !s[l].is_finite() {
                    active[l] = false;
                    continue;
                }
                let (nx, ny) = (q[l][0] - o[l][0] * s[l], q[l][1] - o[l][1] * s[l]);
                let moved = (nx - p[l][0]).abs() + (ny - p[l][1]).abs();
                p[l] = [nx, ny];
                s[l] = sample_nan_aware(par, h, w, nx, ny);
                if moved < 1e-4 {
                    active[l] = false; // converged: p no longer moves
                } else {
                    any = true;
                }
            }
            if !any {
                break;
            }
        }
        for (l, out2) in group.chunks_exact_mut(2).enumerate() {
            let v = match state[l] {
                1 => q[l],
                2 => {
                    let ok = s[l].is_finite() && {
                        let ex = p[l][0] + o[l][0] * s[l] - q[l][0];
                        let ey = p[l][1] + o[l][1] * s[l] - q[l][1];
                        ex * ex + ey * ey <= tol2
                    };
                    if ok { p[l] } else { [f32::NAN; 2] }
                }
                _ => [f32::NAN; 2],
            };
            out2.copy_from_slice(&v);
        }
    }
}

// --------------------------------------------------------------------------------------
// Shift-and-add
// --------------------------------------------------------------------------------------

/// Parameters of [`shift_and_add`].
#[derive(Debug, Clone, Copy)]
pub struct SplatParams {
    /// The fine grid's factor `r` (> 0): rectified `x` lands at `(x + 0.5) r - 0.5`.
    pub factor: f32,
    /// Gaussian splat kernel's standard deviation, fine px; 0: nearest fine pixel only.
    pub sigma: f32,
    /// Kernel radius, fine px (taps with `|dX|, |dY| <= radius` around the nearest
    /// pixel); ignored (0) when `sigma` is 0.
    pub radius: usize,
    /// Robust reweighting passes (0: plain weighted mean).
    pub iterations: usize,
    /// Huber scale of the robust weights: a sample whose mean absolute residual over
    /// the channels is `e` gets weight `min(1, huber / e)` (an L1 fit beyond `huber`).
    pub huber: f32,
    /// Samples with residual above this are rejected outright (occlusions, mismatches).
    pub reject: f32,
}

/// A sample's fine position and its nearest fine pixel.
#[inline]
fn fine_pos(positions: &[f32], k: usize, factor: f32) -> Option<(f32, f32)> {
    let (x, y) = (positions[2 * k], positions[2 * k + 1]);
    let fx = (x + 0.5) * factor - 0.5;
    let fy = (y + 0.5) * factor - 0.5;
    (fx.is_finite() && fy.is_finite()).then_some((fx, fy))
}

/// The nearest fine pixel index, `floor(v + 0.5)` (round half up), without a libm
/// call: `v` is finite here, and positions beyond +-2^30 px are off any grid anyway
/// (those below come out as -2^30; the clamp keeps the subtraction from overflowing).
#[inline(always)]
fn nearest(v: f32) -> i64 {
    const SHIFT: f64 = (1u64 << 30) as f64;
    ((f64::from(v) + 0.5 + SHIFT).max(0.0) as i64) - (1i64 << 30)
}

/// `e^x` for `x <= 0` (clamped at -87, about 1.6e-38), within 2e-7 relative of `f32::exp`: Cody-Waite
/// reduction to `x = n ln 2 + f`, `|f| <= ln 2 / 2`, a degree-6 Taylor polynomial for
/// `e^f`, and `2^n` built from its exponent bits. No libm call and no branch, so loops
/// over several taps vectorise.
#[inline(always)]
fn exp_neg(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // Round to nearest without a libm call (1.5 * 2^23 forces the rounding).
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 0.0);
    let n = (x * LOG2E + ROUND) - ROUND;
    let f = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + f * (1.0
            + f * (0.5
                + f * (1.0 / 6.0 + f * (1.0 / 24.0 + f * (1.0 / 120.0 + f * (1.0 / 720.0))))));
    // n is an integer in [-126, 0]: 2^n is a normal float, whose exponent field n + 127
    // is read off the bits of n + 127 + 2^23 (an integer below 2^24 is exact there, in
    // the low mantissa bits; shifting by 23 drops the rest). No float-to-int
    // conversion, whose saturating semantics would keep a loop over lanes scalar.
    let scale = f32::from_bits((n + (127.0 + 8_388_608.0)).to_bits() << 23);
    p * scale
}

/// Samples per binning chunk: fixed (not per thread), so that the order in which a
/// pixel's samples are summed, hence the result, does not depend on the thread count.
const BIN_CHUNK: usize = 1 << 16;

/// One chunk's samples sorted into bands (a counting sort), as runs of consecutive
/// sample indices: band `b`'s samples are the runs `runs[starts[b]..starts[b + 1]]`
/// (`[k0, k1)` each), in increasing order. The samples of one raw row of a view land in
/// one or two bands, so a run is usually a whole row's worth of samples: the bands read
/// positions and values in order, and the bins are small.
struct ChunkRuns {
    starts: Vec<u32>,
    runs: Vec<[u32; 2]>,
}

struct Bins {
    band_rows: usize,
    chunks: Vec<ChunkRuns>,
}

/// Samples sorted into bands of output rows (a sample whose kernel touches two bands
/// is in both), so that bands can be accumulated in parallel without sharing output.
/// Chunks of [`BIN_CHUNK`] samples are sorted in parallel.
fn bin_samples(
    positions: &[f32],
    weights: Option<&[f32]>,
    m: usize,
    factor: f32,
    radius: usize,
    fine_h: usize,
    band_rows: usize,
) -> Result<Bins> {
    if m >= u32::MAX as usize {
        return Err(Error::invalid_argument(
            "positions",
            format!("{m} samples: fewer than {} are supported", u32::MAX),
        ));
    }
    // A kernel is at most 2 r + 1 < band_rows rows tall (checked by the caller): it
    // touches one band or two neighbours.
    debug_assert!(2 * radius < band_rows);
    let n_bands = fine_h.div_ceil(band_rows);
    let one = |c: usize| -> ChunkRuns {
        let k0 = c * BIN_CHUNK;
        let k1 = (k0 + BIN_CHUNK).min(m);
        let mut bands = BandOf::new(radius, fine_h, band_rows);
        // Runs in order of their first sample, `(band, [k0, k1))`; `open[b]`: band b's
        // last run (u32::MAX: none yet), which sample k extends if it ends at k.
        let mut seq: Vec<(u32, [u32; 2])> = Vec::new();
        let mut open = vec![u32::MAX; n_bands];
        let mut k = k0;
        while k < k1 {
            let n = (k1 - k).min(BIN_BLOCK);
            // k + n <= m < u32::MAX
            let (ka, kb) = (k as u32, (k + n) as u32);
            if let Some((b0, two)) = block_bands(positions, weights, k, n, factor, &mut bands) {
                // Every sample of the block goes to the same bands: as many additions
                // of one sample each, at once.
                for b in b0..=b0 + u32::from(two) {
                    add_run(&mut seq, &mut open, b, ka, kb);
                }
                k += n;
                continue;
            }
            for k in k..k + n {
                if weights.is_some_and(|wt| !positive(wt[k])) {
                    continue;
                }
                let Some((_, fy)) = fine_pos(positions, k, factor) else {
                    continue;
                };
                let Some((b0, two)) = bands.of(nearest(fy)) else {
                    continue;
                };
                let kk = k as u32; // k < m < u32::MAX
                for b in b0..=b0 + u32::from(two) {
                    add_run(&mut seq, &mut open, b, kk, kk + 1);
                }
            }
            k += n;
        }
        // Counting sort of the runs by band, stable: each band's runs stay in order.
        let mut starts = vec![0u32; n_bands + 1];
        for &(b, _) in &seq {
            starts[b as usize + 1] += 1;
        }
        for b in 0..n_bands {
            starts[b + 1] += starts[b];
        }
        let mut runs = vec![[0u32; 2]; seq.len()];
        let mut next = starts.clone();
        for &(b, run) in &seq {
            runs[next[b as usize] as usize] = run;
            next[b as usize] += 1;
        }
        ChunkRuns { starts, runs }
    };
    let n_chunks = m.div_ceil(BIN_CHUNK);
    let chunks = if n_chunks <= 1 {
        (0..n_chunks).map(one).collect()
    } else {
        parallel::install(|| (0..n_chunks).into_par_iter().map(one).collect())?
    };
    Ok(Bins { band_rows, chunks })
}

/// Samples per block of [`block_bands`].
const BIN_BLOCK: usize = 64;

/// Samples `k0..k1` added to band `b`'s runs: they extend its last run if that ends at
/// `k0`, else start a new one.
#[inline(always)]
fn add_run(seq: &mut Vec<(u32, [u32; 2])>, open: &mut [u32], b: u32, k0: u32, k1: u32) {
    let last = open[b as usize] as usize;
    match seq.get_mut(last) {
        Some((_, run)) if run[1] == k0 => run[1] = k1,
        _ => {
            open[b as usize] = seq.len() as u32;
            seq.push((b, [k0, k1]));
        }
    }
}

/// The bands of the samples `k..k + n` if they all go to the same ones (`n` is
/// [`BIN_BLOCK`], every sample usable, and their nearest fine rows in one range of
/// `bands`' answer), else `None` (then they are binned one by one). Straight-line
/// arithmetic over the block, which vectorises: the usual block, samples of one raw row,
/// costs no test per sample.
#[inline(always)]
fn block_bands(
    positions: &[f32],
    weights: Option<&[f32]>,
    k: usize,
    n: usize,
    factor: f32,
    bands: &mut BandOf,
) -> Option<(u32, bool)> {
    const B: usize = BIN_BLOCK;
    if n != B {
        return None;
    }
    let pos: &[f32; 2 * B] = positions.get(2 * k..2 * (k + B))?.try_into().ok()?;
    if let Some(wt) = weights {
        let wt: &[f32; B] = wt.get(k..k + B)?.try_into().ok()?;
        let usable = wt.iter().map(|&w| u32::from(positive(w))).sum::<u32>();
        if usable != B as u32 {
            return None;
        }
    }
    // Lane by lane over the interleaved (x, y): the fine positions as `fine_pos` forms
    // them, a sum of `0 * v` that is NaN iff one is not finite, and the odd lanes' (y)
    // least and greatest.
    let mut nan = [0f32; 8];
    let mut lo = [f32::INFINITY; 8];
    let mut hi = [f32::NEG_INFINITY; 8];
    for p in pos.chunks_exact(8) {
        for l in 0..8 {
            let v = (p[l] + 0.5) * factor - 0.5;
            nan[l] += 0.0 * v;
            lo[l] = if v < lo[l] { v } else { lo[l] };
            hi[l] = if v > hi[l] { v } else { hi[l] };
        }
    }
    if nan.iter().sum::<f32>() != 0.0 {
        return None;
    }
    let ylo = lo[1].min(lo[3]).min(lo[5]).min(lo[7]);
    let yhi = hi[1].max(hi[3]).max(hi[5]).max(hi[7]);
    // `nearest` is non-decreasing: the block's nearest rows are in `lo..=hi`.
    let (ylo, yhi) = (nearest(ylo), nearest(yhi));
    let answer = bands.of(ylo)?;
    (bands.lo <= ylo && yhi <= bands.hi).then_some(answer)
}

/// The bands that the kernel of a sample whose nearest fine row is `yc` touches:
/// `(b, two)`, band `b` and, if `two`, band `b + 1`; `None` if no row of the grid. The
/// last answer's range of `yc` is kept: samples in scan order mostly stay in it, and
/// then cost no division.
struct BandOf {
    r: i64,
    last_row: i64,
    band_rows: i64,
    /// `yc` in `lo..=hi` gives `answer`.
    lo: i64,
    hi: i64,
    answer: (u32, bool),
}

impl BandOf {
    fn new(radius: usize, fine_h: usize, band_rows: usize) -> Self {
        Self {
            r: radius as i64,
            last_row: fine_h as i64 - 1,
            band_rows: band_rows as i64,
            lo: 1,
            hi: 0,
            answer: (0, false),
        }
    }

    #[inline(always)]
    fn of(&mut self, yc: i64) -> Option<(u32, bool)> {
        if yc >= self.lo && yc <= self.hi {
            return Some(self.answer);
        }
        let (r, br) = (self.r, self.band_rows);
        let lo = (yc - r).max(0);
        let hi = (yc + r).min(self.last_row);
        if lo > hi {
            return None;
        }
        let (b0, b1) = (lo / br, hi / br);
        self.answer = (b0 as u32, b1 > b0);
        // The same bands for yc' with b0 br <= yc' - r, yc' + r < (b1 + 1) br (away
        // from the grid's edges, where the clamps above act) and, for one band,
        // yc' + r < (b0 + 1) br; for two, yc' + r >= b1 br and yc' - r < b1 br.
        let (mut l, mut h) = (b0 * br + r, (b1 + 1) * br - 1 - r);
        if b1 > b0 {
            l = l.max(b1 * br - r);
            h = h.min(b1 * br - 1 + r);
        }
        self.lo = l.max(r);
        self.hi = h.min(self.last_row - r);
        Some(self.answer)
    }
}

/// What one accumulation pass of [`shift_and_add`] reads.
struct SplatJob<'a> {
    bins: &'a Bins,
    positions: &'a [f32],
    values: &'a [f32],
    weights: Option<&'a [f32]>,
    fine_w: usize,
    fine_h: usize,
    params: &'a SplatParams,
    /// The previous pass's estimate `(fine_h, fine_w, EST_LANES)` (`sum / wsum`, NaN
    /// where `wsum <= 1e-6`): samples are reweighted against it. `None`: the first pass.
    est: Option<&'a [f32]>,
}

/// Where a pass writes one band's rows.
enum BandOut<'o> {
    /// The sums and the weights (the last pass of [`shift_and_add`]).
    Sums(&'o mut [f32], &'o mut [f32]),
    /// The fused image, the weights and where the image has data (the last pass of
    /// [`shift_and_add_mean`], with its `min_weight`).
    Mean(&'o mut [f32], &'o mut [f32], &'o mut [bool], f32),
    /// The estimate `sum / wsum` (NaN where `wsum <= 1e-6`), for the next pass.
    Estimate(&'o mut [f32]),
}

impl BandOut<'_> {
    fn rows(&self, fine_w: usize) -> usize {
        match self {
            BandOut::Sums(_, ws) | BandOut::Mean(_, ws, _, _) => ws.len() / fine_w,
            BandOut::Estimate(e) => e.len() / (fine_w * EST_LANES),
        }
    }
}

/// What a pass writes, all bands.
enum PassOut<'o> {
    Sums(&'o mut [f32], &'o mut [f32]),
    Mean(&'o mut [f32], &'o mut [f32], &'o mut [bool], f32),
    Estimate(&'o mut [f32]),
}

impl<'o> PassOut<'o> {
    /// One [`BandOut`] per band of `band_rows` rows.
    fn bands(self, fine_w: usize, c: usize, band_rows: usize) -> Vec<BandOut<'o>> {
        let px = band_rows * fine_w;
        match self {
            PassOut::Sums(s, ws) => s
                .chunks_mut(px * c)
                .zip(ws.chunks_mut(px))
                .map(|(s, ws)| BandOut::Sums(s, ws))
                .collect(),
            PassOut::Mean(m, ws, have, min_weight) => m
                .chunks_mut(px * c)
                .zip(ws.chunks_mut(px))
                .zip(have.chunks_mut(px))
                .map(|((m, ws), have)| BandOut::Mean(m, ws, have, min_weight))
                .collect(),
            PassOut::Estimate(e) => e
                .chunks_mut(px * EST_LANES)
                .map(BandOut::Estimate)
                .collect(),
        }
    }
}

/// Sample `k`'s weight in a pass: its base weight `w0` (> 0), reweighted by its
/// residual against the previous pass's estimate (Farsiu et al. 2003's robust
/// shift-and-add): `w0 min(1, huber / e)`, 0 above `reject`; `w0` where there is no
/// estimate yet.
#[inline(always)]
fn robust_weight<const C: usize>(
    job: &SplatJob<'_>,
    est: &[f32],
    v: &[f32],
    fx: f32,
    fy: f32,
    w0: f32,
) -> f32 {
    let p = job.params;
    let mut buf = [0f32; EST_LANES];
    if !estimate_at(est, job.fine_h, job.fine_w, fx, fy, &mut buf) {
        return w0; // no estimate there yet: keep the sample
    }
    // Summed as `Iterator::sum` does (from -0, in order).
    let mut e = -0.0f32;
    for (a, b) in v.iter().zip(&buf[..C]) {
        e += (a - b).abs();
    }
    let e = e / C as f32;
    // Selects rather than branches: whether a sample is an outlier is as good as
    // random, and a mispredicted branch costs more than the division.
    let keep = e <= p.reject; // false for NaN
    let damped = w0 * p.huber / e;
    let w = if e > p.huber { damped } else { w0 };
    if keep { w } else { 0.0 }
}

/// One band of one pass: its samples accumulated in `acc` (each pixel's sums and
/// weight side by side in `L > channels` lanes, `[v_0 .. v_{C-1}, 1, 0 ..]` times the
/// tap weight: one vector add per tap), then written to `out`. The additions are those
/// of one accumulator per output value, in increasing sample order: the result does not
/// depend on the bands.
struct SplatBand<'a, 'o, const C: usize, const L: usize> {
    job: &'a SplatJob<'a>,
    band: usize,
    acc: &'a mut Vec<[f32; L]>,
    out: BandOut<'o>,
}

impl<const C: usize, const L: usize> simd::Avx2Kernel for SplatBand<'_, '_, C, L> {
    type Output = ();
    #[inline(always)]
    fn run<const AVX2: bool>(self) {
        splat_band::<C, L>(self.job, self.band, self.acc, self.out);
    }
}

/// Pixels of margin on each side of a row of a band's accumulator: taps just outside
/// the grid land there (and are dropped), so the 3 x 3 kernel needs no test per tap.
const ACC_PAD: usize = 2;

#[inline(always)]
fn splat_band<const C: usize, const L: usize>(
    job: &SplatJob<'_>,
    band: usize,
    acc: &mut Vec<[f32; L]>,
    out: BandOut<'_>,
) {
    let (fine_w, fine_h) = (job.fine_w, job.fine_h);
    let params = job.params;
    let row0 = band * job.bins.band_rows;
    let nrows = out.rows(fine_w);
    // Rows of `stride` (even) pixels, pixel x at `x + ACC_PAD`.
    let stride = (fine_w + 2 * ACC_PAD).next_multiple_of(2);
    // Grown once per task (with zeros), and all zeros between bands: each row is
    // zeroed when it has been read out, below, while it is in the L1 cache (a fill of
    // the whole band here, most of it no longer cached, cost ~6% of the fusion).
    if acc.len() < nrows * stride {
        acc.resize(nrows * stride, [0f32; L]);
    }
    let acc = &mut acc[..nrows * stride];
    let r = if params.sigma > 0.0 {
        params.radius as i64
    } else {
        0
    };
    let inv2s2 = if params.sigma > 0.0 {
        1.0 / (2.0 * params.sigma * params.sigma)
    } else {
        0.0
    };
    let (row_lo, row_hi) = (row0 as i64, (row0 + nrows).min(fine_h) as i64);
    for chunk in &job.bins.chunks {
        let (a, b) = (chunk.starts[band] as usize, chunk.starts[band + 1] as usize);
        for &[k0, k1] in &chunk.runs[a..b] {
            if r == 1 {
                // The usual 3 x 3 kernel, in blocks of consecutive samples.
                let mut k = k0 as usize;
                while k < k1 as usize {
                    let n = (k1 as usize - k).min(SPLAT_BLOCK);
                    splat3_block::<C, L>(job, k, n, acc, stride, row_lo, row_hi, inv2s2);
                    k += n;
                }
                continue;
            }
            for k in k0 as usize..k1 as usize {
                let w0 = job.weights.map_or(1.0, |wt| wt[k]);
                if !positive(w0) {
                    continue;
                }
                let Some((fx, fy)) = fine_pos(job.positions, k, params.factor) else {
                    continue;
                };
                let Some(v) = job.values.get(k * C..(k + 1) * C) else {
                    continue;
                };
                let wk = match job.est {
                    Some(est) => robust_weight::<C>(job, est, v, fx, fy, w0),
                    None => w0,
                };
                if !positive(wk) || v.iter().any(|c| !c.is_finite()) {
                    continue;
                }
                let mut vv = [0f32; L];
                vv[..C].copy_from_slice(v);
                vv[C] = 1.0;
                let xc = nearest(fx);
                let yc = nearest(fy);
                let (dx0, dy0) = ((xc - r) as f32 - fx, (yc - r) as f32 - fy);
                let mut gx = [1f32; 2 * MAX_RADIUS + 1];
                let mut gys = [1f32; 2 * MAX_RADIUS + 1];
                if r > 0 {
                    for (t, (g, gy)) in gx
                        .iter_mut()
                        .zip(gys.iter_mut())
                        .enumerate()
                        .take(2 * r as usize + 1)
                    {
                        let (dx, dy) = (dx0 + t as f32, dy0 + t as f32);
                        *g = exp_neg(-dx * dx * inv2s2);
                        *gy = exp_neg(-dy * dy * inv2s2);
                    }
                }
                for (ty, yy) in ((yc - r)..=(yc + r)).enumerate() {
                    if yy < row_lo || yy >= row_hi {
                        continue;
                    }
                    let wy = wk * gys[ty];
                    let ly = (yy - row_lo) as usize * stride + ACC_PAD;
                    for (t, xx) in ((xc - r)..=(xc + r)).enumerate() {
                        if xx < 0 || xx >= fine_w as i64 {
                            continue;
                        }
                        let wt = wy * gx[t];
                        for (o, &b) in acc[ly + xx as usize].iter_mut().zip(&vv) {
                            *o += wt * b;
                        }
                    }
                }
            }
        }
    }
    // The band's rows (with their margins, zeroed after use) and their pixels.
    let rows = acc.chunks_exact_mut(stride);
    debug_assert_eq!(rows.len(), nrows);
    match out {
        BandOut::Sums(sum, wsum) => {
            for ((padded, ws), s) in rows
                .zip(wsum.chunks_exact_mut(fine_w))
                .zip(sum.chunks_exact_mut(fine_w * C))
            {
                let row = &padded[ACC_PAD..ACC_PAD + fine_w];
                for ((a, ws), s) in row.iter().zip(ws).zip(s.chunks_exact_mut(C)) {
                    *ws = a[C];
                    s.copy_from_slice(&a[..C]);
                }
                padded.fill([0f32; L]);
            }
        }
        BandOut::Mean(mean, wsum, have, min_weight) => {
            for (((padded, ws), m), hv) in rows
                .zip(wsum.chunks_exact_mut(fine_w))
                .zip(mean.chunks_exact_mut(fine_w * C))
                .zip(have.chunks_exact_mut(fine_w))
            {
                let row = &padded[ACC_PAD..ACC_PAD + fine_w];
                for (((a, ws), m), hv) in row.iter().zip(ws).zip(m.chunks_exact_mut(C)).zip(hv) {
                    *ws = a[C];
                    let mut ok = a[C] >= min_weight;
                    for (o, &v) in m.iter_mut().zip(&a[..C]) {
                        *o = v / a[C];
                        ok &= o.is_finite();
                    }
                    if !ok {
                        m.fill(0.0);
                    }
                    *hv = ok;
                }
                padded.fill([0f32; L]);
            }
        }
        BandOut::Estimate(est) => {
            for (padded, e) in rows.zip(est.chunks_exact_mut(fine_w * EST_LANES)) {
                let row = &padded[ACC_PAD..ACC_PAD + fine_w];
                for (a, e) in row.iter().zip(e.chunks_exact_mut(EST_LANES)) {
                    let ws = a[C];
                    for (o, &v) in e.iter_mut().zip(&a[..C]) {
                        *o = if ws > 1e-6 { v / ws } else { f32::NAN };
                    }
                }
                padded.fill([0f32; L]);
            }
        }
    }
}

/// Samples per block of [`splat3_block`].
const SPLAT_BLOCK: usize = 64;

/// [`nearest`] as a float: `floor(v + 0.5)` computed exactly as `nearest` does
/// (`(v + 0.5) + 2^30`, truncated, minus `2^30`), with float operations only, which
/// vectorise (a saturating float-to-int conversion per lane does not).
#[inline(always)]
fn nearest_f64(v: f32) -> f64 {
    const SHIFT: f64 = (1u64 << 30) as f64;
    // Truncating a non-negative number floors it; below -2^30 (far off any grid) the
    // two differ, which changes nothing.
    ((f64::from(v) + 0.5 + SHIFT).floor()) - SHIFT
}

/// Samples `k0..k0 + n` (`n <= SPLAT_BLOCK`, one run of the band) with the 3 x 3
/// kernel: first, for the whole block, their fine positions, nearest pixels and
/// Gaussian taps (straight-line arithmetic over arrays, which vectorises), then each
/// sample's taps added by [`splat3`]. The arithmetic per sample is that of the general
/// kernel in [`splat_band`].
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn splat3_block<const C: usize, const L: usize>(
    job: &SplatJob<'_>,
    k0: usize,
    n: usize,
    acc: &mut [[f32; L]],
    stride: usize,
    row_lo: i64,
    row_hi: i64,
    inv2s2: f32,
) {
    const B: usize = SPLAT_BLOCK;
    // 1, the weight lane's value, opaque to the optimiser: knowing that lane's products
    // are `wt * 1`, it would split each pixel's vector product into scalar ones and
    // reassemble the vector lane by lane.
    let one = std::hint::black_box(1.0f32);
    let factor = job.params.factor;
    let Some(pos) = job.positions.get(2 * k0..2 * (k0 + n)) else {
        return;
    };
    let mut fx = [0f32; B];
    let mut fy = [0f32; B];
    for (i, p) in pos.chunks_exact(2).enumerate() {
        fx[i] = (p[0] + 0.5) * factor - 0.5;
        fy[i] = (p[1] + 0.5) * factor - 0.5;
    }
    let mut cx = [0f64; B];
    let mut cy = [0f64; B];
    // Taps along x (t = 0..3) and y (t = 4..7), tap by tap over the block's samples
    // (rounded up to a multiple of 8 for whole vectors; the rest is not read).
    let nv = n.next_multiple_of(8).min(B);
    let mut g = [[0f32; B]; 8];
    for i in 0..nv {
        cx[i] = nearest_f64(fx[i]);
        cy[i] = nearest_f64(fy[i]);
        let dx0 = (cx[i] - 1.0) as f32 - fx[i];
        let dy0 = (cy[i] - 1.0) as f32 - fy[i];
        for t in 0..3 {
            let (dx, dy) = (dx0 + t as f32, dy0 + t as f32);
            g[t][i] = -dx * dx * inv2s2;
            g[4 + t][i] = -dy * dy * inv2s2;
        }
    }
    for (t, row) in g.iter_mut().enumerate() {
        if t % 4 == 3 {
            continue; // unused
        }
        for v in &mut row[..nv] {
            *v = exp_neg(*v);
        }
    }
    let mut w0 = [1f32; B];
    if let Some(wt) = job.weights.and_then(|wt| wt.get(k0..k0 + n)) {
        w0[..n].copy_from_slice(wt);
    }
    let mut wk = w0;
    if let Some(est) = job.est {
        robust_weights::<C>(job, est, k0, n, &fx, &fy, &w0, &mut wk);
    }
    for i in 0..n {
        let k = k0 + i;
        if !(positive(w0[i]) && fx[i].is_finite() && fy[i].is_finite()) {
            continue;
        }
        let Some(v) = job.values.get(k * C..(k + 1) * C) else {
            continue;
        };
        let wk = wk[i];
        if !positive(wk) || v.iter().any(|c| !c.is_finite()) {
            continue;
        }
        let mut vv = [0f32; L];
        vv[..C].copy_from_slice(v);
        vv[C] = one;
        // Integers (exact in f64); beyond +-2^40, far off any grid, clamped so that
        // the index arithmetic cannot overflow.
        const FAR: f64 = (1u64 << 40) as f64;
        let (xc, yc) = (cx[i].clamp(-FAR, FAR) as i64, cy[i].clamp(-FAR, FAR) as i64);
        let e = [
            g[0][i], g[1][i], g[2][i], 0.0, g[4][i], g[5][i], g[6][i], 0.0,
        ];
        splat3::<L>(acc, stride, row_lo, row_hi, xc, yc, wk, &e, &vv);
    }
}

/// [`robust_weight`] for the samples `k0..k0 + n` of a block (`wk[i]` for sample
/// `k0 + i`, from its fine position `(fx[i], fy[i])` and base weight `w0[i]`; lanes
/// whose sample is unusable get some value, not read): the same arithmetic per sample,
/// as loops over the block that vectorise, around a loop that fetches the estimate's
/// corners.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn robust_weights<const C: usize>(
    job: &SplatJob<'_>,
    est: &[f32],
    k0: usize,
    n: usize,
    fx: &[f32; SPLAT_BLOCK],
    fy: &[f32; SPLAT_BLOCK],
    w0: &[f32; SPLAT_BLOCK],
    wk: &mut [f32; SPLAT_BLOCK],
) {
    const B: usize = SPLAT_BLOCK;
    let (h, w) = (job.fine_h, job.fine_w);
    let (huber, reject) = (job.params.huber, job.params.reject);
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    // Bilinear weights of the corners (y0, x0), (y0, x1), (y1, x0), (y1, x1), as
    // `estimate_at` forms them, and where the corners are.
    let mut b = [[0f32; B]; 4];
    let mut at = [[0usize; 4]; B];
    for i in 0..B {
        let xc = fx[i].clamp(0.0, xmax);
        let yc = fy[i].clamp(0.0, ymax);
        let x0 = (xc as usize).min(w - 1);
        let y0 = (yc as usize).min(h - 1);
        let x1 = (x0 + 1).min(w - 1);
        let y1 = (y0 + 1).min(h - 1);
        let (tx, ty) = (xc - x0 as f32, yc - y0 as f32);
        b[0][i] = (1.0 - tx) * (1.0 - ty);
        b[1][i] = tx * (1.0 - ty);
        b[2][i] = (1.0 - tx) * ty;
        b[3][i] = tx * ty;
        at[i] = [
            (y0 * w + x0) * EST_LANES,
            (y0 * w + x1) * EST_LANES,
            (y1 * w + x0) * EST_LANES,
            (y1 * w + x1) * EST_LANES,
        ];
    }
    // The corners' estimates and the samples' values, channel by channel.
    let mut e = [[[0f32; B]; C]; 4];
    let mut v = [[0f32; B]; C];
    for i in 0..n {
        for (corner, &p) in at[i].iter().enumerate() {
            if let Some(px) = est.get(p..p + C) {
                for (ch, &x) in px.iter().enumerate() {
                    e[corner][ch][i] = x;
                }
            }
        }
        if let Some(px) = job.values.get((k0 + i) * C..(k0 + i + 1) * C) {
            for (ch, &x) in px.iter().enumerate() {
                v[ch][i] = x;
            }
        }
    }
    for i in 0..B {
        // The estimate: corners without one add exact zeros (see `estimate_at`).
        let mut total = 0.0f32;
        let mut out = [0f32; C];
        for corner in 0..4 {
            let bc = b[corner][i];
            let used = !e[corner][0][i].is_nan() && bc > 0.0;
            total += if used { bc } else { 0.0 };
            for ch in 0..C {
                out[ch] += if used { bc * e[corner][ch][i] } else { 0.0 };
            }
        }
        let mut err = -0.0f32;
        for ch in 0..C {
            err += (v[ch][i] - out[ch] / total).abs();
        }
        let err = err / C as f32;
        let keep = err <= reject; // false for NaN
        let damped = w0[i] * huber / err;
        let weight = if err > huber { damped } else { w0[i] };
        let weight = if keep { weight } else { 0.0 };
        // No estimate there yet: the sample keeps its weight.
        wk[i] = if total < 0.25 { w0[i] } else { weight };
    }
}

/// One sample's 3 x 3 taps (`e[0..3]` along x, `e[4..7]` along y, times `wk`) added to
/// the rows of `acc` (rows of `stride` pixels, pixel x at `x + ACC_PAD`) that lie in
/// `row_lo..row_hi`. A row's three taps are added as two pairs of pixels aligned on even
/// pixel indices (the fourth pixel with weight 0, which adds nothing: a sum that starts
/// at +0 never becomes -0): consecutive samples, about two fine pixels apart, then
/// read exactly the pair the previous one wrote, which the CPU forwards from its store.
/// Each value gets `(wk g_y) g_x` times the sample's lane, as in the general kernel.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn splat3<const L: usize>(
    acc: &mut [[f32; L]],
    stride: usize,
    row_lo: i64,
    row_hi: i64,
    xc: i64,
    yc: i64,
    wk: f32,
    e: &[f32; 8],
    vv: &[f32; L],
) {
    // Padded index of the first tap, x = xc - 1.
    let xp = xc - 1 + ACC_PAD as i64;
    // (An infinite weight would turn the fourth pixel's zero weight into NaN.)
    if L == 4 && xp >= 0 && xp + 3 < stride as i64 && wk.is_finite() {
        let odd = (xp & 1) as usize;
        let base = xp as usize - odd;
        // [e0, e1, e2, 0] or [0, e0, e1, e2], by index rather than by a branch (the
        // parity of jittered samples is unpredictable).
        let ext = [0.0, e[0], e[1], e[2], 0.0];
        let g4: [f32; 4] = std::array::from_fn(|t| ext[t + 1 - odd]);
        let g16: [f32; 16] = std::array::from_fn(|i| g4[i / 4]);
        let v16: [f32; 16] = std::array::from_fn(|i| vv[i % L]);
        let flat = acc.as_flattened_mut();
        for ty in 0..3 {
            let yy = yc - 1 + ty as i64;
            if yy < row_lo || yy >= row_hi {
                continue;
            }
            let wy = wk * e[4 + ty];
            let at = ((yy - row_lo) as usize * stride + base) * L;
            let Some(dst) = flat.get_mut(at..at + 16) else {
                continue;
            };
            for ((o, &g), &b) in dst.iter_mut().zip(&g16).zip(&v16) {
                *o += (wy * g) * b;
            }
        }
        return;
    }
    for ty in 0..3 {
        let yy = yc - 1 + ty as i64;
        if yy < row_lo || yy >= row_hi {
            continue;
        }
        let wy = wk * e[4 + ty];
        let ly = (yy - row_lo) as usize * stride;
        for (xx, &gx) in (xp..xp + 3).zip(&e[..3]) {
            if xx < 0 || xx >= stride as i64 {
                continue;
            }
            let wt = wy * gx;
            for (o, &b) in acc[ly + xx as usize].iter_mut().zip(vv) {
                *o += wt * b;
            }
        }
    }
}

/// One accumulation pass over all bands, into `out`.
fn splat_pass<const C: usize, const L: usize>(
    job: &SplatJob<'_>,
    out: PassOut<'_>,
    threads: usize,
) -> Result<()> {
    let fine_w = job.fine_w;
    let go = |acc: &mut Vec<[f32; L]>, (band, out): (usize, BandOut<'_>)| {
        simd::run_avx2_or_portable(
            true,
            SplatBand::<C, L> {
                job,
                band,
                acc,
                out,
            },
        );
    };
    let bands = out.bands(fine_w, C, job.bins.band_rows);
    if parallel::run_serially(job.fine_h * fine_w * (C + 1) * 4, threads) {
        let mut acc = Vec::new();
        bands.into_iter().enumerate().for_each(|b| go(&mut acc, b));
        Ok(())
    } else {
        parallel::install(|| {
            bands
                .into_par_iter()
                .enumerate()
                .for_each_init(Vec::new, go);
        })
    }
}

/// Floats per pixel of an estimate image: `C <= 4` values, then zeros.
const EST_LANES: usize = 4;

/// The fused estimate at fine `(x, y)`: bilinear (clamped to the grid) in `est`
/// (`(h, w, EST_LANES)`: `sum / wsum` per pixel, NaN where `wsum <= 1e-6`) over the
/// corners that have an estimate, channel by channel into `out`; false if none.
///
/// The corners without an estimate add exact zeros rather than being skipped, which is
/// the same (a sum that starts at +0 never becomes -0) without a branch per corner.
#[inline(always)]
fn estimate_at(
    est: &[f32],
    h: usize,
    w: usize,
    x: f32,
    y: f32,
    out: &mut [f32; EST_LANES],
) -> bool {
    let xc = x.clamp(0.0, (w - 1) as f32);
    let yc = y.clamp(0.0, (h - 1) as f32);
    let x0 = (xc as usize).min(w - 1);
    let y0 = (yc as usize).min(h - 1);
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let (tx, ty) = (xc - x0 as f32, yc - y0 as f32);
    let mut total = 0.0f32;
    *out = [0.0; EST_LANES];
    for (yy, wy) in [(y0, 1.0 - ty), (y1, ty)] {
        for (xx, wx) in [(x0, 1.0 - tx), (x1, tx)] {
            let p = (yy * w + xx) * EST_LANES;
            let Some(e) = est.get(p..p + EST_LANES) else {
                continue;
            };
            let b = wx * wy;
            let used = !e[0].is_nan() && b > 0.0;
            total += if used { b } else { 0.0 };
            for (o, &v) in out.iter_mut().zip(e) {
                *o += if used { b * v } else { 0.0 };
            }
        }
    }
    if total < 0.25 {
        return false;
    }
    out.iter_mut().for_each(|o| *o /= total);
    true
}

/// Robust shift-and-add of scattered samples onto a fine grid.
///
/// Sample `k` (value `values[k*C..(k+1)*C]`, weight `weights[k]`, default 1; NaN or
/// non-positive weights and NaN positions or values are skipped) at rectified position
/// `positions[k] = (x, y)` lands at fine `(X, Y) = ((x + 0.5) r - 0.5, (y + 0.5) r -
/// 0.5)`. With `sigma = 0` it adds to the nearest fine pixel (round half up); else to
/// the pixels within `radius` of it, with Gaussian weights
/// `exp(-|(U, V) - (X, Y)|^2 / (2 sigma^2))`. Writes `sum` `(fine_h, fine_w, C)`, the
/// weighted sums `sum_k w_k g_k v_k`, and `wsum` `(fine_h, fine_w)`, `sum_k w_k g_k`.
///
/// With `iterations > 0`, each pass computes the estimate `sum / wsum`, each sample's
/// residual against it (bilinear at `(X, Y)`, mean absolute over channels) and
/// reweights: `w_k min(1, huber / e_k)`, 0 if `e_k > reject` (robust, L1-like: Farsiu
/// et al. 2003's robust shift-and-add), then accumulates again.
///
/// Parallel over bands of output rows; the result does not depend on the thread count.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument whose size or value is unusable.
#[allow(clippy::too_many_arguments)]
pub fn shift_and_add(
    positions: &[f32],
    values: &[f32],
    weights: Option<&[f32]>,
    channels: usize,
    fine_h: usize,
    fine_w: usize,
    params: &SplatParams,
    sum: &mut [f32],
    wsum: &mut [f32],
) -> Result<()> {
    check_len(
        "sum",
        sum.len(),
        mul("sum", &[fine_h, fine_w, channels])?,
        "(H, W, C)",
    )?;
    check_len(
        "wsum",
        wsum.len(),
        mul("wsum", &[fine_h, fine_w])?,
        "(H, W)",
    )?;
    splat_all(
        positions,
        values,
        weights,
        channels,
        fine_h,
        fine_w,
        params,
        PassOut::Sums(sum, wsum),
    )
}

/// [`shift_and_add`] that writes the fused image instead of the sums: `mean`
/// `(fine_h, fine_w, C)` gets `sum / wsum` where `wsum >= min_weight` and that is finite
/// in every channel, else 0; `have` `(fine_h, fine_w)` is true there (false: the pixels
/// to fill); `wsum` as in [`shift_and_add`]. The values are those `sum / wsum` gives
/// with [`shift_and_add`]'s sums, without a pass over them.
///
/// # Errors
/// As [`shift_and_add`]; `min_weight` if it is NaN.
#[allow(clippy::too_many_arguments)]
pub fn shift_and_add_mean(
    positions: &[f32],
    values: &[f32],
    weights: Option<&[f32]>,
    channels: usize,
    fine_h: usize,
    fine_w: usize,
    params: &SplatParams,
    min_weight: f32,
    mean: &mut [f32],
    wsum: &mut [f32],
    have: &mut [bool],
) -> Result<()> {
    check_len(
        "mean",
        mean.len(),
        mul("mean", &[fine_h, fine_w, channels])?,
        "(H, W, C)",
    )?;
    check_len(
        "wsum",
        wsum.len(),
        mul("wsum", &[fine_h, fine_w])?,
        "(H, W)",
    )?;
    check_len(
        "have",
        have.len(),
        mul("have", &[fine_h, fine_w])?,
        "(H, W)",
    )?;
    if min_weight.is_nan() {
        return Err(Error::invalid_argument("min_weight", "is NaN"));
    }
    splat_all(
        positions,
        values,
        weights,
        channels,
        fine_h,
        fine_w,
        params,
        PassOut::Mean(mean, wsum, have, min_weight),
    )
}

/// The passes of [`shift_and_add`] (sizes of the output checked by the caller); the
/// last one writes `last`.
#[allow(clippy::too_many_arguments)]
fn splat_all(
    positions: &[f32],
    values: &[f32],
    weights: Option<&[f32]>,
    channels: usize,
    fine_h: usize,
    fine_w: usize,
    params: &SplatParams,
    last: PassOut<'_>,
) -> Result<()> {
    if !(1..=MAX_CHANNELS).contains(&channels) {
        return Err(Error::invalid_argument(
            "values",
            format!("must have 1 to {MAX_CHANNELS} channels, got {channels}"),
        ));
    }
    if !positions.len().is_multiple_of(2) {
        return Err(Error::invalid_argument(
            "positions",
            "must be (M, 2) positions (x, y)",
        ));
    }
    let m = positions.len() / 2;
    check_len(
        "values",
        values.len(),
        mul("values", &[m, channels])?,
        "(M, C)",
    )?;
    if let Some(wt) = weights {
        check_len("weights", wt.len(), m, "(M,)")?;
    }
    if fine_h == 0 || fine_w == 0 {
        return Err(Error::invalid_argument("shape", "the fine grid is empty"));
    }
    if !(params.factor > 0.0 && params.factor <= MAX_FACTOR) {
        return Err(Error::invalid_argument(
            "factor",
            format!("must be in (0, {MAX_FACTOR}], got {}", params.factor),
        ));
    }
    if !(params.sigma >= 0.0 && params.sigma.is_finite()) || params.radius > MAX_RADIUS {
        return Err(Error::invalid_argument(
            "sigma",
            format!(
                "needs sigma >= 0 and radius <= 16, got {} and {}",
                params.sigma, params.radius
            ),
        ));
    }
    if params.iterations > 0 && !(params.huber > 0.0 && params.reject > 0.0) {
        return Err(Error::invalid_argument(
            "huber",
            "robust passes need huber > 0 and reject > 0",
        ));
    }
    let radius = if params.sigma > 0.0 { params.radius } else { 0 };
    let threads = parallel::num_threads();
    let band_rows = parallel::rows_per_task(fine_h, fine_w * (channels + 1) * 4, threads)
        .max(2 * radius + 1)
        // A sample whose kernel straddles two bands is splatted in both: bands of at
        // least 16 kernel heights keep that under ~1/8. (8 kernel heights, a band's
        // rows in L2: the benchmark's fusion 13.5 -> 12.3 ms at 16, the best of 8
        // processes each; 32: the same as 16.)
        .max(16 * (2 * radius + 1))
        .max(4);
    let bins = bin_samples(
        positions,
        weights,
        m,
        params.factor,
        radius,
        fine_h,
        band_rows,
    )?;
    // Pass j reads the estimate of pass j - 1 (none for the first) and writes the one
    // pass j + 1 reads; the last pass writes the sums. Two estimates take turns.
    let scratch = |passes: usize| {
        if params.iterations >= passes {
            vec![0f32; fine_h * fine_w * EST_LANES]
        } else {
            Vec::new()
        }
    };
    let (mut est_a, mut est_b) = (scratch(1), scratch(2));
    let mut last = Some(last);
    for pass in 0..=params.iterations {
        if pass >= 2 {
            std::mem::swap(&mut est_a, &mut est_b);
        }
        // `est_a` holds the previous pass's estimate; `est_b` is written.
        let (read, write): (Option<&[f32]>, &mut [f32]) = match pass {
            0 => (None, &mut est_a),
            _ => (Some(&est_a), &mut est_b),
        };
        let job = SplatJob {
            bins: &bins,
            positions,
            values,
            weights,
            fine_w,
            fine_h,
            params,
            est: read,
        };
        let out = if pass == params.iterations {
            last.take()
                .ok_or_else(|| Error::internal("shift_and_add", "no last pass"))?
        } else {
            PassOut::Estimate(write)
        };
        match channels {
            1 => splat_pass::<1, 4>(&job, out, threads)?,
            2 => splat_pass::<2, 4>(&job, out, threads)?,
            3 => splat_pass::<3, 4>(&job, out, threads)?,
            _ => splat_pass::<4, 8>(&job, out, threads)?,
        }
    }
    Ok(())
}

/// The `k`-th smallest (from 0) of the positive values of `v` (NaN and non-positive
/// ones left out), `k` below their count: a radix select on the bit patterns, which
/// order positive floats as their values do (two passes of 16 bits, no sorting).
fn kth_positive(v: &[f32], k: usize) -> f32 {
    let mut counts = vec![0usize; 1 << 16];
    for &x in v {
        if positive(x) {
            counts[(x.to_bits() >> 16) as usize] += 1;
        }
    }
    let (mut hi, mut below) = (0usize, 0usize);
    for (b, &n) in counts.iter().enumerate() {
        if below + n > k {
            hi = b;
            break;
        }
        below += n;
    }
    counts.fill(0);
    for &x in v {
        if positive(x) && (x.to_bits() >> 16) as usize == hi {
            counts[(x.to_bits() & 0xffff) as usize] += 1;
        }
    }
    let mut lo = 0usize;
    for (b, &n) in counts.iter().enumerate() {
        if below + n > k {
            lo = b;
            break;
        }
        below += n;
    }
    f32::from_bits(((hi as u32) << 16) | lo as u32)
}

/// The deblurring's data weights from the shift-and-add weights `wsum`:
/// `a = sqrt(clip(wsum / t, 0, 4))` in f32, `t` the median of the positive weights (1
/// if there are none). The median is numpy's: the middle value, or for an even count
/// the f32 mean of the two middle ones, so `a` is what
/// `np.sqrt(np.clip(wsum / float(np.median(wsum[wsum > 0])), 0, 4))` gives. Returns `t`.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `a` if its length differs from `wsum`'s.
pub fn data_weights(wsum: &[f32], a: &mut [f32]) -> Result<f32> {
    check_len("a", a.len(), wsum.len(), "wsum's size")?;
    let n = wsum.iter().filter(|&&x| positive(x)).count();
    let t = match n {
        0 => 1.0,
        _ if n % 2 == 1 => kth_positive(wsum, n / 2),
        _ => (kth_positive(wsum, n / 2 - 1) + kth_positive(wsum, n / 2)) / 2.0,
    };
    parallel::for_each_row_chunk(a, 1, |first, rows| {
        for (o, &w) in rows.iter_mut().zip(&wsum[first..]) {
            *o = (w / t).clamp(0.0, 4.0).sqrt();
        }
        Ok(())
    })?;
    Ok(t)
}

// --------------------------------------------------------------------------------------
// Bilateral-TV deblurring
// --------------------------------------------------------------------------------------

/// Parameters of [`btv_deblur`].
#[derive(Debug, Clone, Copy)]
pub struct BtvParams {
    /// Standard deviation of the Gaussian blur `H` between the image sought and the
    /// shift-and-add image, fine px (0: no blur, pure denoising).
    pub psf_sigma: f32,
    /// Regularisation weight `lambda`.
    pub lambda: f32,
    /// Decay `alpha` (0 < alpha <= 1) of the BTV weights `alpha^(|l| + |m|)`.
    pub alpha: f32,
    /// BTV window `P`: shifts `|l|, |m| <= P`.
    pub window: usize,
    /// Steepest-descent iterations.
    pub iterations: usize,
    /// Step `beta`.
    pub step: f32,
    /// Smoothing of `sign` (`t / sqrt(t^2 + eps^2)`), image units; 0: exact sign.
    pub eps: f32,
}

fn gaussian_taps(sigma: f32) -> Vec<f32> {
    if !positive(sigma) {
        return vec![1.0];
    }
    // Truncated at 2.5 sigma (98.8% of the mass, renormalised).
    let r = (2.5 * sigma).ceil() as i64;
    let mut k: Vec<f32> = (-r..=r)
        .map(|d| (-(d * d) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// `t / sqrt(t^2 + eps^2)` for every `a[i] - b[i]` into `out` (`eps = 0`: the sign, 0 at
/// 0). Odd in `t`, exactly: `soft(-t) = -soft(t)`.
#[inline(always)]
fn soft_sign_diff(out: &mut [f32], a: &[f32], b: &[f32], eps: f32) {
    if eps > 0.0 {
        let e2 = eps * eps;
        for ((o, &va), &vb) in out.iter_mut().zip(a).zip(b) {
            let t = va - vb;
            *o = t / (t * t + e2).sqrt();
        }
    } else {
        for ((o, &va), &vb) in out.iter_mut().zip(a).zip(b) {
            let t = va - vb;
            *o = if t > 0.0 {
                1.0
            } else if t < 0.0 {
                -1.0
            } else {
                0.0
            };
        }
    }
}

/// [`soft_sign_diff`] times `m[i]`, element by element (`soft(t) * m`).
#[inline(always)]
fn soft_sign_diff_times(out: &mut [f32], a: &[f32], b: &[f32], m: &[f32], eps: f32) {
    if eps > 0.0 {
        let e2 = eps * eps;
        for (((o, &va), &vb), &vm) in out.iter_mut().zip(a).zip(b).zip(m) {
            let t = va - vb;
            *o = (t / (t * t + e2).sqrt()) * vm;
        }
    } else {
        soft_sign_diff(out, a, b, eps);
        for (o, &vm) in out.iter_mut().zip(m) {
            *o *= vm;
        }
    }
}

/// `dst = sum_t taps[t] src[x + t - r]` along one row of `w` pixels of `c` channels,
/// clamped at the ends (via `pad`, `(w + 2r) c` long).
#[inline(always)]
fn blur_row(src: &[f32], dst: &mut [f32], pad: &mut [f32], w: usize, c: usize, taps: &[f32]) {
    let r = taps.len() / 2;
    let row_len = w * c;
    pad[r * c..(r + w) * c].copy_from_slice(src);
    for k in 0..r {
        pad[k * c..(k + 1) * c].copy_from_slice(&src[..c]);
        let e = (r + w + k) * c;
        pad[e..e + c].copy_from_slice(&src[row_len - c..]);
    }
    let pad: &[f32] = pad;
    weighted_rows(dst, taps, |t| &pad[t * c..t * c + row_len]);
}

/// `dst[i] = sum_t taps[t] rows(t)[i]`, the terms added in order of `t` from 0 (as
/// `dst` zeroed, then `dst += taps[t] rows(t)` tap by tap, but in registers: one pass
/// over `dst`). `rows(t)` has `dst.len()` elements. The usual tap counts are constants
/// here, so that the loop over taps unrolls and the one over `i` vectorises.
#[inline(always)]
fn weighted_rows<'r>(dst: &mut [f32], taps: &[f32], rows: impl Fn(usize) -> &'r [f32]) {
    #[inline(always)]
    fn fixed<const K: usize>(dst: &mut [f32], taps: &[f32; K], rows: [&[f32]; K]) {
        let n = dst.len();
        let rows: [&[f32]; K] = rows.map(|r| &r[..n]);
        for (i, o) in dst.iter_mut().enumerate() {
            let mut acc = 0.0f32;
            for t in 0..K {
                acc += taps[t] * rows[t][i];
            }
            *o = acc;
        }
    }
    macro_rules! go {
        ($k:literal) => {
            if let Ok(t) = <&[f32; $k]>::try_from(taps) {
                return fixed::<$k>(dst, t, std::array::from_fn(|i| rows(i)));
            }
        };
    }
    go!(1);
    go!(3);
    go!(5);
    go!(7);
    go!(9);
    go!(11);
    go!(13);
    dst.fill(0.0);
    for (t, &g) in taps.iter().enumerate() {
        for (o, &v) in dst.iter_mut().zip(rows(t)) {
            *o += g * v;
        }
    }
}

/// Rows computed on demand and kept while a task walks down the image: slot
/// `y % slots` holds row `y` (tags say which row a slot holds).
struct Ring {
    data: Vec<f32>,
    tags: Vec<usize>,
    len: usize,
}

impl Ring {
    fn new(slots: usize, len: usize) -> Self {
        Self {
            data: vec![0.0; slots * len],
            tags: vec![usize::MAX; slots],
            len,
        }
    }
    #[inline(always)]
    fn has(&self, y: usize) -> bool {
        self.tags[y % self.tags.len()] == y
    }
    #[inline(always)]
    fn row(&self, y: usize) -> &[f32] {
        let s = y % self.tags.len();
        &self.data[s * self.len..(s + 1) * self.len]
    }
    #[inline(always)]
    fn claim(&mut self, y: usize) -> &mut [f32] {
        let s = y % self.tags.len();
        self.tags[s] = y;
        &mut self.data[s * self.len..(s + 1) * self.len]
    }
}

/// What one steepest-descent step of [`btv_deblur`] reads.
struct BtvStep<'a> {
    /// The current estimate, `(h, w, c)`.
    x: &'a [f32],
    z: &'a [f32],
    a: &'a [f32],
    h: usize,
    w: usize,
    c: usize,
    taps: &'a [f32],
    /// Half of the BTV shifts, `(l, m, alpha^(|l| + |m|))` with `m > 0` or `m = 0, l > 0`:
    /// the other half is the same differences with the sign flipped.
    shifts: &'a [(i64, usize, f32)],
    window: usize,
    step: f32,
    lambda: f32,
    eps: f32,
}

/// One task's rolling rows.
struct BtvScratch {
    /// Rows of `x` blurred along x.
    xh: Ring,
    /// Rows of `A sign(H x - z)` blurred along x.
    dh: Ring,
    /// Per row `y`, for each shift `s = (l, m)` of [`BtvStep::shifts`], the row of
    /// `D_s(p) = sign(x(p) - x(p + s))` (0 where `p + s` is outside).
    diffs: Ring,
    pad: Vec<f32>,
    hx: Vec<f32>,
    g: Vec<f32>,
    reg: Vec<f32>,
    /// A's row, each weight repeated over the channels.
    arow: Vec<f32>,
}

impl BtvScratch {
    fn new(job: &BtvStep<'_>) -> Self {
        let row_len = job.w * job.c;
        let k = job.taps.len();
        let r = k / 2;
        Self {
            xh: Ring::new(k, row_len),
            dh: Ring::new(k, row_len),
            diffs: Ring::new(job.window + 1, job.shifts.len() * row_len),
            pad: vec![0.0; (job.w + 2 * r) * job.c],
            hx: vec![0.0; row_len],
            g: vec![0.0; row_len],
            reg: vec![0.0; row_len],
            arow: vec![0.0; row_len],
        }
    }
}

/// Row `y + t - r` clamped to the image.
#[inline(always)]
fn clamp_row(y: usize, t: usize, r: usize, h: usize) -> usize {
    (y + t).saturating_sub(r).min(h - 1)
}

/// Makes sure `sc.xh` holds row `y` of `x` blurred along x.
#[inline(always)]
fn ensure_xh(job: &BtvStep<'_>, sc: &mut BtvScratch, y: usize) {
    if sc.xh.has(y) {
        return;
    }
    let row_len = job.w * job.c;
    let src = &job.x[y * row_len..(y + 1) * row_len];
    blur_row(src, sc.xh.claim(y), &mut sc.pad, job.w, job.c, job.taps);
}

/// Makes sure `sc.dh` holds row `y` of `H_x (A sign(H x - z))` (the x half of `H^T`).
#[inline(always)]
fn ensure_dh(job: &BtvStep<'_>, sc: &mut BtvScratch, y: usize) {
    if sc.dh.has(y) {
        return;
    }
    let (h, w, c) = (job.h, job.w, job.c);
    let row_len = w * c;
    let r = job.taps.len() / 2;
    for t in 0..job.taps.len() {
        ensure_xh(job, sc, clamp_row(y, t, r, h));
    }
    let xh = &sc.xh;
    weighted_rows(&mut sc.hx, job.taps, |t| xh.row(clamp_row(y, t, r, h)));
    // d = A sign(H x - z), into `g` (free until the row's own gradient is formed): the
    // signs times A's row spread over the channels (`sign * a`, as before).
    let z = &job.z[y * row_len..(y + 1) * row_len];
    let a = &job.a[y * w..(y + 1) * w];
    for (px, &aw) in sc.arow.chunks_exact_mut(c).zip(a) {
        px.fill(aw);
    }
    soft_sign_diff_times(&mut sc.g, &sc.hx, z, &sc.arow, job.eps);
    blur_row(&sc.g, sc.dh.claim(y), &mut sc.pad, w, c, job.taps);
}

/// Makes sure `sc.diffs` holds the shift differences of row `y`.
#[inline(always)]
fn ensure_diffs(job: &BtvStep<'_>, sc: &mut BtvScratch, y: usize) {
    if sc.diffs.has(y) {
        return;
    }
    let (h, w, c) = (job.h, job.w, job.c);
    let row_len = w * c;
    let xrow = &job.x[y * row_len..(y + 1) * row_len];
    let planes = sc.diffs.claim(y);
    for (&(l, m, _), plane) in job.shifts.iter().zip(planes.chunks_exact_mut(row_len)) {
        // Pixels xx with xx + l inside the row (|l| <= window < w checked by the caller
        // or the span is empty).
        let lo = ((-l).max(0) as usize).min(w);
        let hi = (w as i64 - l.max(0)).clamp(lo as i64, w as i64) as usize;
        if y + m >= h || lo >= hi {
            plane.fill(0.0);
            continue;
        }
        let srow = &job.x[(y + m) * row_len..(y + m + 1) * row_len];
        plane[..lo * c].fill(0.0);
        plane[hi * c..].fill(0.0);
        let b0 = (lo as i64 + l) as usize * c;
        let b1 = (hi as i64 + l) as usize * c;
        soft_sign_diff(
            &mut plane[lo * c..hi * c],
            &xrow[lo * c..hi * c],
            &srow[b0..b1],
            job.eps,
        );
    }
}

/// Rows `first..` of the next estimate into `out`.
#[inline(always)]
fn btv_rows(job: &BtvStep<'_>, first: usize, out: &mut [f32]) -> Result<()> {
    let (h, w, c) = (job.h, job.w, job.c);
    let row_len = w * c;
    let k = job.taps.len();
    let r = k / 2;
    let mut sc = BtvScratch::new(job);
    for (j, orow) in out.chunks_exact_mut(row_len).enumerate() {
        let y = first + j;
        // Data term: H^T A sign(H x - z), H^T = H (separable, symmetric Gaussian).
        for t in 0..k {
            ensure_dh(job, &mut sc, clamp_row(y, t, r, h));
        }
        let dh = &sc.dh;
        weighted_rows(&mut sc.g, job.taps, |t| dh.row(clamp_row(y, t, r, h)));
        // BTV term: sum over all shifts s of w_s D_s(p), which (D_{-s}(p) = -D_s(p - s))
        // is the sum over half of them of w_s (D_s(p) - D_s(p - s)).
        for yy in y.saturating_sub(job.window)..=y {
            ensure_diffs(job, &mut sc, yy);
        }
        let here = sc.diffs.row(y);
        let xrow = &job.x[y * row_len..(y + 1) * row_len];
        let kk = 2.0 * job.lambda;
        // Window 1 (four shifts) past the first row: the interior pixels in one pass,
        // the four terms of each shift added in the order of the general passes below.
        let fused = if let [s0, s1, s2, s3] = *job.shifts
            && y >= 1
            && w >= 3
        {
            let shifts = [s0, s1, s2, s3];
            let planes: [&[f32]; 4] =
                std::array::from_fn(|si| &here[si * row_len..(si + 1) * row_len]);
            let prevs: [&[f32]; 4] = std::array::from_fn(|si| {
                let (_, m, _) = shifts[si];
                &sc.diffs.row(y - m)[si * row_len..(si + 1) * row_len]
            });
            // Interior elements [c, (w - 1) c): every shift's D_s(xx - l) exists there.
            let (i0, i1) = (c, (w - 1) * c);
            let wt: [f32; 4] = shifts.map(|(_, _, wt)| wt);
            // prev_s[i - l_s c] for i in i0..i1, as slices aligned with the interior.
            let back: [&[f32]; 4] = std::array::from_fn(|si| {
                let l = shifts[si].0;
                let s0 = (i0 as i64 - l * c as i64) as usize;
                &prevs[si][s0..s0 + (i1 - i0)]
            });
            let here_i: [&[f32]; 4] = planes.map(|p| &p[i0..i1]);
            for (k, ((o, &v), &gv)) in orow[i0..i1]
                .iter_mut()
                .zip(&xrow[i0..i1])
                .zip(&sc.g[i0..i1])
                .enumerate()
            {
                let mut r = 0.0f32;
                for si in 0..4 {
                    r += wt[si] * here_i[si][k];
                    r -= wt[si] * back[si][k];
                }
                *o = v - job.step * (gv + kk * r);
            }
            true
        } else {
            false
        };
        if fused {
            // The first and last pixel, term by term as the general passes add them.
            for i in (0..c).chain((w - 1) * c..row_len) {
                let xx = (i / c) as i64;
                let mut r = 0.0f32;
                for (si, &(l, m, wt)) in job.shifts.iter().enumerate() {
                    r += wt * here[si * row_len + i];
                    if y >= m && xx - l >= 0 && xx - l < w as i64 {
                        let prev = sc.diffs.row(y - m);
                        let j = (i as i64 - l * c as i64) as usize; // in the row: checked
                        r -= wt * prev[si * row_len + j];
                    }
                }
                orow[i] = xrow[i] - job.step * (sc.g[i] + kk * r);
            }
            continue;
        }
        sc.reg.fill(0.0);
        for (si, &(l, m, wt)) in job.shifts.iter().enumerate() {
            let plane = &here[si * row_len..(si + 1) * row_len];
            for (o, &v) in sc.reg.iter_mut().zip(plane) {
                *o += wt * v;
            }
            if y < m {
                continue;
            }
            let prev = &sc.diffs.row(y - m)[si * row_len..(si + 1) * row_len];
            // reg[xx] -= wt D_s(xx - l) for 0 <= xx - l < w.
            let lo = (l.max(0) as usize).min(w);
            let hi = (w as i64 + l.min(0)).clamp(lo as i64, w as i64) as usize;
            let p0 = (lo as i64 - l) as usize * c;
            let p1 = (hi as i64 - l) as usize * c;
            for (o, &v) in sc.reg[lo * c..hi * c].iter_mut().zip(&prev[p0..p1]) {
                *o -= wt * v;
            }
        }
        for (((o, &v), &gv), &rv) in orow.iter_mut().zip(xrow).zip(&sc.g).zip(&sc.reg) {
            *o = v - job.step * (gv + kk * rv);
        }
    }
    Ok(())
}

simd::avx2_or_portable!(
    true,
    /// [`btv_rows`], compiled for AVX2 and for the baseline.
    fn btv_task(job: &BtvStep<'_>, first: usize, out: &mut [f32]) -> Result<()> {
        btv_rows(job, first, out)
    }
);

/// Rows per BTV task: a task recomputes `2 r + window` rows above its first and `2 r`
/// below its last (the blur's and the regulariser's reach), so tasks of at least 8 times
/// that keep the overlap under ~1/8; otherwise the usual balance (4 tasks per thread).
fn btv_min_rows(h: usize, r: usize, window: usize) -> usize {
    let halo = 4 * r + window;
    let balance = h.div_ceil(parallel::num_threads() * parallel::TASKS_PER_THREAD);
    balance.max(8 * halo).max(1)
}

/// Bilateral-TV deblurring by steepest descent (Farsiu et al. 2004, eq. 22 with the
/// shift-and-add image):
///
/// `x <- x - beta [H^T A sign(H x - z) + lambda sum_{l,m} alpha^(|l|+|m|)
///        (I - S_x^-l S_y^-m) sign(x - S_x^l S_y^m x)]`
///
/// `z` is the shift-and-add image `(h, w, c)` (finite everywhere: fill holes first),
/// `a` `(h, w)` the data weights (0 for holes, which the regulariser then fills),
/// `H` a Gaussian of `psf_sigma` (symmetric: `H^T = H`). `x` holds the starting image
/// on entry (usually `z`) and the result on return.
///
/// Each iteration is one pass over the image in tasks of whole rows: a task walks down
/// its rows keeping the few rows the blurs and shifts need (blurred along x, the data
/// residual's signs, the shift differences) in small rolling buffers, so an iteration
/// reads `x`, `z` and `a` and writes the next `x` once. Shifts `s` and `-s` share their
/// differences (`sign(x(p) - x(p - s)) = -sign(x(p - s) - x(p))`): half of the signs
/// are computed. Runs in lfcam's pool; the result does not depend on the thread count.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument whose size or value is unusable.
#[allow(clippy::too_many_arguments)]
pub fn btv_deblur(
    z: &[f32],
    a: &[f32],
    h: usize,
    w: usize,
    c: usize,
    params: &BtvParams,
    x: &mut [f32],
) -> Result<()> {
    if h == 0 || w == 0 || !(1..=MAX_CHANNELS).contains(&c) {
        return Err(Error::invalid_argument(
            "z",
            format!("expected a non-empty (H, W, C) image with C <= {MAX_CHANNELS}"),
        ));
    }
    let n = mul("z", &[h, w, c])?;
    check_len("z", z.len(), n, "(H, W, C)")?;
    check_len("a", a.len(), h * w, "(H, W)")?;
    check_len("x", x.len(), n, "(H, W, C)")?;
    let p = &params;
    let bad = |name: &str, why: &str| Err(Error::invalid_argument(name, why.to_owned()));
    if !(p.psf_sigma >= 0.0 && p.psf_sigma <= 16.0) {
        return bad("psf_sigma", "must be in [0, 16]");
    }
    if !(p.lambda >= 0.0 && p.lambda.is_finite()) {
        return bad("lambda", "must be finite and >= 0");
    }
    if !(p.alpha > 0.0 && p.alpha <= 1.0) {
        return bad("alpha", "must be in (0, 1]");
    }
    if p.window > 8 {
        return bad("window", "must be at most 8");
    }
    if !(p.step > 0.0 && p.step.is_finite()) {
        return bad("step", "must be finite and > 0");
    }
    if !(p.eps >= 0.0 && p.eps.is_finite()) {
        return bad("eps", "must be finite and >= 0");
    }
    if p.iterations == 0 {
        return Ok(());
    }
    let taps = gaussian_taps(p.psf_sigma);
    let win = p.window as i64;
    let shifts: Vec<(i64, usize, f32)> = (0..=win)
        .flat_map(|m| (-win..=win).map(move |l| (l, m)))
        .filter(|&(l, m)| m > 0 || l > 0)
        .map(|(l, m)| (l, m as usize, p.alpha.powi((l.abs() + m) as i32)))
        .collect();
    let row_len = w * c;
    let min_rows = btv_min_rows(h, taps.len() / 2, p.window);
    let mut other = vec![0f32; n];
    // `x` and `other` take turns as the estimate read and the one written.
    for it in 0..p.iterations {
        let (src, dst): (&[f32], &mut [f32]) = if it % 2 == 0 {
            (&*x, &mut other)
        } else {
            (&other, &mut *x)
        };
        let job = BtvStep {
            x: src,
            z,
            a,
            h,
            w,
            c,
            taps: &taps,
            shifts: &shifts,
            window: p.window,
            step: p.step,
            lambda: p.lambda,
            eps: p.eps,
        };
        parallel::for_each_row_chunk_min(dst, row_len, min_rows, |first, rows| {
            btv_task(&job, first, rows)
        })?;
    }
    if p.iterations % 2 == 1 {
        x.copy_from_slice(&other);
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// BTV straight from the formula, one pixel at a time (blurs with clamped borders,
    /// all `(2P + 1)^2 - 1` shifts).
    fn btv_naive(z: &[f32], a: &[f32], h: usize, w: usize, c: usize, p: &BtvParams) -> Vec<f32> {
        let taps = gaussian_taps(p.psf_sigma);
        let r = (taps.len() / 2) as i64;
        let at = |y: i64, x: i64| {
            ((y.clamp(0, h as i64 - 1) as usize) * w + x.clamp(0, w as i64 - 1) as usize) * c
        };
        let blur = |img: &[f32]| -> Vec<f32> {
            let mut tmp = vec![0f32; img.len()];
            let mut out = vec![0f32; img.len()];
            for y in 0..h as i64 {
                for x in 0..w as i64 {
                    for ch in 0..c {
                        tmp[at(y, x) + ch] = taps
                            .iter()
                            .enumerate()
                            .map(|(t, g)| g * img[at(y, x + t as i64 - r) + ch])
                            .sum();
                    }
                }
            }
            for y in 0..h as i64 {
                for x in 0..w as i64 {
                    for ch in 0..c {
                        out[at(y, x) + ch] = taps
                            .iter()
                            .enumerate()
                            .map(|(t, g)| g * tmp[at(y + t as i64 - r, x) + ch])
                            .sum();
                    }
                }
            }
            out
        };
        let ss = |t: f32| {
            if p.eps > 0.0 {
                t / (t * t + p.eps * p.eps).sqrt()
            } else {
                t.signum() * f32::from(t != 0.0)
            }
        };
        let win = p.window as i64;
        let mut x = z.to_vec();
        for _ in 0..p.iterations {
            let hx = blur(&x);
            let d: Vec<f32> = (0..x.len()).map(|i| a[i / c] * ss(hx[i] - z[i])).collect();
            let g = blur(&d);
            let mut next = x.clone();
            for y in 0..h as i64 {
                for xx in 0..w as i64 {
                    for ch in 0..c {
                        let i = at(y, xx) + ch;
                        let mut reg = 0.0f32;
                        for m in -win..=win {
                            for l in -win..=win {
                                let (yy, xs) = (y + m, xx + l);
                                if (l, m) == (0, 0)
                                    || yy < 0
                                    || yy >= h as i64
                                    || xs < 0
                                    || xs >= w as i64
                                {
                                    continue;
                                }
                                reg += p.alpha.powi((l.abs() + m.abs()) as i32)
                                    * ss(x[i] - x[at(yy, xs) + ch]);
                            }
                        }
                        next[i] = x[i] - p.step * (g[i] + 2.0 * p.lambda * reg);
                    }
                }
            }
            x = next;
        }
        x
    }

    #[test]
    fn btv_matches_the_formula() {
        let mut seed = 12345u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        for &(h, w, c, psf, window, eps, iters) in &[
            (37usize, 41usize, 3usize, 1.17f32, 1usize, 0.01f32, 3usize),
            (20, 9, 1, 0.6, 2, 0.0, 2),
            (5, 300, 4, 2.0, 1, 0.05, 4),
            (2, 3, 2, 0.0, 3, 0.01, 2),
            (1, 1, 3, 1.0, 1, 0.01, 1),
        ] {
            let z: Vec<f32> = (0..h * w * c).map(|_| rnd()).collect();
            let a: Vec<f32> = (0..h * w).map(|_| 2.0 * rnd()).collect();
            let p = BtvParams {
                psf_sigma: psf,
                lambda: 0.02,
                alpha: 0.7,
                window,
                iterations: iters,
                step: 0.02,
                eps,
            };
            let want = btv_naive(&z, &a, h, w, c, &p);
            let mut got = z.clone();
            btv_deblur(&z, &a, h, w, c, &p, &mut got).unwrap();
            let err = want
                .iter()
                .zip(&got)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(err < 1e-5, "{h}x{w}x{c} window {window}: {err}");
        }
    }

    #[test]
    fn exp_neg_matches_exp() {
        let mut worst = 0f32;
        for i in 0..=200_000 {
            let x = -(i as f32) * 87.0 / 200_000.0;
            let (a, b) = (exp_neg(x), x.exp());
            worst = worst.max((a - b).abs() / b);
        }
        assert!(worst < 5e-7, "{worst}");
        assert_eq!(exp_neg(0.0), 1.0);
    }

    #[test]
    fn invert_affine_map() {
        // w(u, v) = (2 + 1.1 u + 0.1 v, 1 + 0.05 u + 0.9 v) on a 12 x 10 grid.
        let (h, w) = (10, 12);
        let mut warp = vec![0f32; h * w * 2];
        for v in 0..h {
            for u in 0..w {
                warp[(v * w + u) * 2] = 2.0 + 1.1 * u as f32 + 0.1 * v as f32;
                warp[(v * w + u) * 2 + 1] = 1.0 + 0.05 * u as f32 + 0.9 * v as f32;
            }
        }
        let (ch, cw) = (12, 16);
        let mut out = vec![0f32; ch * cw * 2];
        invert_map(&warp, None, h, w, ch, cw, &mut out).unwrap();
        let mut n = 0;
        for y in 0..ch {
            for x in 0..cw {
                let (u, v) = (out[(y * cw + x) * 2], out[(y * cw + x) * 2 + 1]);
                if u.is_finite() {
                    n += 1;
                    let fx = 2.0 + 1.1 * u + 0.1 * v;
                    let fy = 1.0 + 0.05 * u + 0.9 * v;
                    assert!((fx - x as f32).abs() < 1e-4 && (fy - y as f32).abs() < 1e-4);
                }
            }
        }
        assert!(n > 80, "{n}");
    }

    /// Shift-and-add straight from its definition, one sample at a time in increasing
    /// order (robust passes as documented): the kernel must match it bit for bit.
    fn splat_naive(
        pos: &[f32],
        val: &[f32],
        weights: Option<&[f32]>,
        c: usize,
        fh: usize,
        fw: usize,
        p: &SplatParams,
    ) -> (Vec<f32>, Vec<f32>) {
        let m = pos.len() / 2;
        let r = if p.sigma > 0.0 { p.radius as i64 } else { 0 };
        let inv2s2 = if p.sigma > 0.0 {
            1.0 / (2.0 * p.sigma * p.sigma)
        } else {
            0.0
        };
        let accumulate = |wk: &[f32]| {
            let mut sum = vec![0f32; fh * fw * c];
            let mut ws = vec![0f32; fh * fw];
            for k in 0..m {
                let Some((fx, fy)) = fine_pos(pos, k, p.factor) else {
                    continue;
                };
                let v = &val[k * c..(k + 1) * c];
                if !positive(wk[k]) || v.iter().any(|x| !x.is_finite()) {
                    continue;
                }
                let (xc, yc) = (nearest(fx), nearest(fy));
                let (dx0, dy0) = ((xc - r) as f32 - fx, (yc - r) as f32 - fy);
                for ty in 0..=2 * r {
                    let yy = yc - r + ty;
                    let dy = dy0 + ty as f32;
                    let gy = if r > 0 {
                        exp_neg(-dy * dy * inv2s2)
                    } else {
                        1.0
                    };
                    let wy = wk[k] * gy;
                    for tx in 0..=2 * r {
                        let xx = xc - r + tx;
                        if yy < 0 || yy >= fh as i64 || xx < 0 || xx >= fw as i64 {
                            continue;
                        }
                        let dx = dx0 + tx as f32;
                        let gx = if r > 0 {
                            exp_neg(-dx * dx * inv2s2)
                        } else {
                            1.0
                        };
                        let wt = wy * gx;
                        let px = yy as usize * fw + xx as usize;
                        for ch in 0..c {
                            sum[px * c + ch] += wt * v[ch];
                        }
                        ws[px] += wt;
                    }
                }
            }
            (sum, ws)
        };
        let base: Vec<f32> = (0..m).map(|k| weights.map_or(1.0, |w| w[k])).collect();
        let (mut sum, mut ws) = accumulate(&base);
        for _ in 0..p.iterations {
            let mut est = vec![0f32; fh * fw * EST_LANES];
            for (px, e) in est.chunks_exact_mut(EST_LANES).enumerate() {
                for ch in 0..c {
                    e[ch] = if ws[px] > 1e-6 {
                        sum[px * c + ch] / ws[px]
                    } else {
                        f32::NAN
                    };
                }
            }
            let wk: Vec<f32> = (0..m)
                .map(|k| {
                    let w0 = base[k];
                    let Some((fx, fy)) = fine_pos(pos, k, p.factor) else {
                        return 0.0;
                    };
                    if !positive(w0) {
                        return 0.0;
                    }
                    let mut buf = [0f32; EST_LANES];
                    if !estimate_at(&est, fh, fw, fx, fy, &mut buf) {
                        return w0;
                    }
                    let v = &val[k * c..(k + 1) * c];
                    let e = v.iter().zip(&buf).map(|(a, b)| (a - b).abs()).sum::<f32>() / c as f32;
                    let keep = e <= p.reject; // false for NaN
                    if !keep {
                        0.0
                    } else if e > p.huber {
                        w0 * p.huber / e
                    } else {
                        w0
                    }
                })
                .collect();
            (sum, ws) = accumulate(&wk);
        }
        (sum, ws)
    }

    #[test]
    fn shift_and_add_matches_the_definition_bit_for_bit() {
        let mut seed = 99u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        let (h, w) = (23usize, 31usize);
        for &(c, factor, sigma, radius, iterations, scan) in &[
            (3usize, 2.0f32, 0.4f32, 1usize, 1usize, true),
            (3, 2.0, 0.4, 1, 0, false),
            // An odd fine width (31): the read-out's last pixel comes alone.
            (3, 1.0, 0.4, 1, 0, true),
            (1, 3.0, 0.0, 0, 1, true),
            (2, 1.0, 0.35, 1, 2, false),
            (4, 2.0, 0.5, 1, 1, true),
            (3, 2.0, 0.8, 2, 1, true),
            (4, 1.5, 0.6, 3, 0, false),
        ] {
            let (fh, fw) = (
                (h as f32 * factor).round() as usize,
                (w as f32 * factor).round() as usize,
            );
            let m = 4000;
            let mut pos = Vec::with_capacity(2 * m);
            for k in 0..m {
                if scan {
                    // Rows of a slightly rotated grid with jitter, as placed raw samples.
                    let (i, j) = ((k % 70) as f32, (k / 70) as f32);
                    pos.push(-2.0 + 0.5 * i + 0.01 * j + 0.2 * rnd());
                    pos.push(-1.0 + 0.45 * j - 0.01 * i + 0.2 * rnd());
                } else {
                    pos.push(-2.0 + (w + 3) as f32 * rnd());
                    pos.push(-2.0 + (h + 3) as f32 * rnd());
                }
            }
            // Unusable and extreme samples.
            pos[10] = f32::NAN;
            pos[21] = f32::INFINITY;
            pos[30] = 1e30;
            pos[41] = -1e30;
            pos[50] = -3e9;
            pos[61] = 5e9;
            let mut val: Vec<f32> = (0..m * c).map(|_| rnd()).collect();
            val[7 * c] = f32::NAN;
            // Outliers for the robust passes.
            for k in (0..m).step_by(9) {
                val[k * c] += 0.5;
            }
            let wts: Vec<f32> = (0..m)
                .map(|k| if k % 17 == 0 { 0.0 } else { 0.5 + rnd() })
                .collect();
            let p = SplatParams {
                factor,
                sigma,
                radius,
                iterations,
                huber: 0.05,
                reject: 0.3,
            };
            for weights in [None, Some(&wts[..])] {
                let (ws_ref, wsum_ref) = splat_naive(&pos, &val, weights, c, fh, fw, &p);
                // NaN: an element the fusion does not write would show.
                let mut sum = vec![f32::NAN; fh * fw * c];
                let mut ws = vec![f32::NAN; fh * fw];
                shift_and_add(&pos, &val, weights, c, fh, fw, &p, &mut sum, &mut ws).unwrap();
                let same =
                    |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(
                    same(&ws, &wsum_ref),
                    "wsum, C {c} r {radius} it {iterations}"
                );
                assert!(same(&sum, &ws_ref), "sum, C {c} r {radius} it {iterations}");
            }
        }
    }

    /// Placement one sample at a time (the fixed-point iteration as documented).
    fn place_naive(
        inv: &[f32],
        view: &[i32],
        offsets: &[[f64; 2]],
        par: &[f32],
        h: usize,
        w: usize,
        p: &PlaceParams,
    ) -> Vec<f32> {
        let mut out = vec![f32::NAN; inv.len()];
        for (k, &vi) in view.iter().enumerate() {
            let (qx, qy) = (inv[2 * k], inv[2 * k + 1]);
            if vi < 0 || !qx.is_finite() || !qy.is_finite() {
                continue;
            }
            let (ox, oy) = (
                offsets[vi as usize][0] as f32,
                offsets[vi as usize][1] as f32,
            );
            if ox == 0.0 && oy == 0.0 {
                out[2 * k] = qx;
                out[2 * k + 1] = qy;
                continue;
            }
            let (mut px, mut py) = (qx, qy);
            let mut s = sample_nan_aware(par, h, w, px, py);
            for _ in 0..p.iterations {
                if !s.is_finite() {
                    break;
                }
                let (nx, ny) = (qx - ox * s, qy - oy * s);
                let moved = (nx - px).abs() + (ny - py).abs();
                (px, py) = (nx, ny);
                s = sample_nan_aware(par, h, w, px, py);
                if moved < 1e-4 {
                    break;
                }
            }
            let (ex, ey) = (px + ox * s - qx, py + oy * s - qy);
            if s.is_finite() && ex * ex + ey * ey <= p.tolerance * p.tolerance {
                out[2 * k] = px;
                out[2 * k + 1] = py;
            }
        }
        out
    }

    #[test]
    fn placement_matches_one_sample_at_a_time() {
        let (h, w) = (40usize, 50usize);
        let mut par = vec![0f32; h * w];
        for y in 0..h {
            for x in 0..w {
                // Smooth, with a step (an occlusion edge) and a hole.
                let s = 0.05 * (x as f32 / 7.0).sin() + if x > 30 { 0.15 } else { 0.0 };
                par[y * w + x] = if (10..13).contains(&y) && (5..9).contains(&x) {
                    f32::NAN
                } else {
                    s
                };
            }
        }
        let offsets = [[0.0, 0.0], [12.0, -3.0], [-20.0, 8.0]];
        let m = 5003;
        let mut inv = Vec::with_capacity(2 * m);
        let mut view = Vec::with_capacity(m);
        for k in 0..m {
            inv.push(-1.0 + (k % 97) as f32 * 0.53);
            inv.push(-1.0 + (k / 97) as f32 * 0.8);
            view.push((k % 4) as i32 - 1);
        }
        inv[6] = f32::NAN;
        let p = PlaceParams {
            iterations: 6,
            tolerance: 0.25,
        };
        let want = place_naive(&inv, &view, &offsets, &par, h, w, &p);
        let mut got = vec![0f32; inv.len()];
        place_samples(&inv, &view, &offsets, &par, h, w, &p, &mut got).unwrap();
        assert!(
            want.iter()
                .zip(&got)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        assert!(got.iter().filter(|v| v.is_finite()).count() > m / 2);
    }

    #[test]
    fn weighted_rows_add_taps_in_order() {
        // The unrolled sums (tap counts 1..=13) equal tap-by-tap accumulation exactly.
        let rows: Vec<Vec<f32>> = (0..13)
            .map(|t| {
                (0..101)
                    .map(|i| ((i * 7 + t * 13) % 17) as f32 * 0.37 - 2.0)
                    .collect()
            })
            .collect();
        for k in [1usize, 3, 5, 7, 9, 11, 13, 2] {
            let taps: Vec<f32> = (0..k).map(|t| 0.1 + t as f32 * 0.173).collect();
            let mut got = vec![0f32; 101];
            weighted_rows(&mut got, &taps, |t| &rows[t]);
            let mut want = vec![0f32; 101];
            for (t, &g) in taps.iter().enumerate() {
                for (o, &v) in want.iter_mut().zip(&rows[t]) {
                    *o += g * v;
                }
            }
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{k}"
            );
        }
    }

    #[test]
    fn bands_reuse_their_accumulator() {
        // A grid of several bands (of at least 48 rows) run one after the other on one
        // accumulator, which each band must leave zeroed: all three ways out of a band
        // (estimate, sums, fused image) against the definition.
        let mut seed = 5u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        let (fh, fw) = (230usize, 37usize);
        let m = 9000;
        let mut pos = Vec::with_capacity(2 * m);
        for k in 0..m {
            let (i, j) = ((k % 40) as f32, (k / 40) as f32);
            pos.push(-1.0 + 0.48 * i + 0.01 * j + 0.2 * rnd());
            pos.push(-1.0 + 0.52 * j - 0.01 * i + 0.2 * rnd());
        }
        for c in [3usize, 4] {
            let val: Vec<f32> = (0..m * c).map(|_| rnd()).collect();
            for iterations in [0usize, 1] {
                let p = SplatParams {
                    factor: 2.0,
                    sigma: 0.4,
                    radius: 1,
                    iterations,
                    huber: 0.05,
                    reject: 0.3,
                };
                let (sum_ref, ws_ref) = splat_naive(&pos, &val, None, c, fh, fw, &p);
                let mut sum = vec![0f32; fh * fw * c];
                let mut ws = vec![0f32; fh * fw];
                shift_and_add(&pos, &val, None, c, fh, fw, &p, &mut sum, &mut ws).unwrap();
                let same =
                    |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                assert!(same(&ws, &ws_ref), "wsum, C {c} it {iterations}");
                assert!(same(&sum, &sum_ref), "sum, C {c} it {iterations}");
                let min_weight = 0.05;
                let mut mean = vec![0f32; fh * fw * c];
                let mut have = vec![false; fh * fw];
                shift_and_add_mean(
                    &pos, &val, None, c, fh, fw, &p, min_weight, &mut mean, &mut ws, &mut have,
                )
                .unwrap();
                assert!(same(&ws, &ws_ref), "mean's wsum, C {c} it {iterations}");
                for (px, &w) in ws_ref.iter().enumerate() {
                    let want: Vec<f32> = (0..c).map(|ch| sum_ref[px * c + ch] / w).collect();
                    let ok = w >= min_weight && want.iter().all(|v| v.is_finite());
                    assert_eq!(have[px], ok, "have, C {c} it {iterations} px {px}");
                    let got = &mean[px * c..(px + 1) * c];
                    if ok {
                        assert!(same(got, &want), "mean, C {c} it {iterations} px {px}");
                    } else {
                        assert!(got.iter().all(|&v| v == 0.0));
                    }
                }
            }
        }
    }

    /// The runs of [`bin_samples`] formed one sample at a time, as documented.
    fn bin_naive(
        positions: &[f32],
        weights: Option<&[f32]>,
        radius: usize,
        factor: f32,
        fine_h: usize,
        band_rows: usize,
    ) -> Vec<(Vec<u32>, Vec<[u32; 2]>)> {
        let m = positions.len() / 2;
        let n_bands = fine_h.div_ceil(band_rows);
        (0..m.div_ceil(BIN_CHUNK))
            .map(|c| {
                let mut runs: Vec<Vec<[u32; 2]>> = vec![Vec::new(); n_bands];
                for k in c * BIN_CHUNK..((c + 1) * BIN_CHUNK).min(m) {
                    if weights.is_some_and(|wt| !positive(wt[k])) {
                        continue;
                    }
                    let Some((_, fy)) = fine_pos(positions, k, factor) else {
                        continue;
                    };
                    let yc = nearest(fy);
                    let r = radius as i64;
                    let (lo, hi) = ((yc - r).max(0), (yc + r).min(fine_h as i64 - 1));
                    if lo > hi {
                        continue;
                    }
                    let kk = k as u32;
                    for b in lo / band_rows as i64..=hi / band_rows as i64 {
                        let band = &mut runs[b as usize];
                        match band.last_mut() {
                            Some(run) if run[1] == kk => run[1] = kk + 1,
                            _ => band.push([kk, kk + 1]),
                        }
                    }
                }
                let mut starts = vec![0u32];
                for band in &runs {
                    starts.push(starts.last().unwrap() + band.len() as u32);
                }
                (starts, runs.concat())
            })
            .collect()
    }

    #[test]
    fn binning_by_blocks_equals_one_by_one() {
        let mut seed = 7u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        // Raw rows of 300 samples in scan order, slightly rotated, with jitter, over
        // more rows than the grid has (samples off it), past one chunk.
        let m = BIN_CHUNK + 10_000;
        let mut pos = Vec::with_capacity(2 * m);
        for k in 0..m {
            let (i, j) = ((k % 300) as f32, (k / 300) as f32);
            pos.push(0.5 * i + 0.01 * j + 0.2 * rnd());
            pos.push(-3.0 + 0.5 * j + 0.03 * i + 0.2 * rnd());
        }
        // Unusable and extreme samples, alone and in runs.
        for k in [5usize, 700, 701, 4000, 30_000] {
            pos[2 * k + k % 2] = f32::NAN;
        }
        pos[2 * 1000 + 1] = f32::INFINITY;
        pos[2 * 1200 + 1] = 1e30;
        pos[2 * 1300] = -1e38;
        pos[2 * 1400 + 1] = -3e9;
        let wts: Vec<f32> = (0..m)
            .map(|k| match k % 997 {
                0 => 0.0,
                1 => f32::NAN,
                _ => 0.5 + rnd(),
            })
            .collect();
        for (factor, radius, fine_h, band_rows) in [
            (2.0f32, 1usize, 250usize, 48usize),
            (2.0, 1, 250, 17),
            (1.0, 0, 100, 4),
            (3.0, 2, 400, 80),
        ] {
            for weights in [None, Some(&wts[..])] {
                let want = bin_naive(&pos, weights, radius, factor, fine_h, band_rows);
                let got = bin_samples(&pos, weights, m, factor, radius, fine_h, band_rows).unwrap();
                assert_eq!(got.chunks.len(), want.len());
                for (g, (starts, runs)) in got.chunks.iter().zip(&want) {
                    assert_eq!(&g.starts, starts, "{factor} {radius} {band_rows}");
                    assert_eq!(&g.runs, runs, "{factor} {radius} {band_rows}");
                }
            }
        }
    }

    #[test]
    fn nearest_splat_counts() {
        let pos = [0.0f32, 0.0, 0.26, 0.0, f32::NAN, 0.0];
        let val = [1.0f32, 3.0, 5.0];
        let mut sum = vec![0f32; 4 * 4];
        let mut ws = vec![0f32; 4 * 4];
        let p = SplatParams {
            factor: 2.0,
            sigma: 0.0,
            radius: 0,
            iterations: 0,
            huber: 0.0,
            reject: 0.0,
        };
        shift_and_add(&pos, &val, None, 1, 4, 4, &p, &mut sum, &mut ws).unwrap();
        // x = 0 -> X = 0.5 -> rounds to 1; x = 0.26 -> X = 1.02 -> 1.
        assert_eq!(ws[4 + 1], 2.0);
        assert_eq!(sum[4 + 1], 4.0);
        assert_eq!(ws.iter().sum::<f32>(), 2.0);
    }
}
