//! Bilateral-TV deblurring of the shift-and-add image (Farsiu, Robinson, Elad,
//! Milanfar 2004), and its data weights from the shift-and-add weights.

use super::{MAX_CHANNELS, check_len, mul, positive};
use crate::error::{Error, Result};
use crate::parallel;
use crate::simd::{self, Dispatch};

/// The `k`-th smallest (from 0) of the positive values of `v` (NaN and non-positive
/// ones left out), `k` below their count: a radix select on the bit patterns, which
/// order positive floats as their values do (two passes of 16 bits, no sorting).
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
        let wsum = wsum
            .get(first..)
            .ok_or_else(|| Error::internal("data_weights", format!("element {first}")))?;
        for (o, &w) in rows.iter_mut().zip(wsum) {
            *o = (w / t).clamp(0.0, 4.0).sqrt();
        }
        Ok(())
    })?;
    Ok(t)
}

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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
    #[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
    #[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
    fn has(&self, y: usize) -> bool {
        self.tags[y % self.tags.len()] == y
    }
    #[inline(always)]
    #[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
    fn row(&self, y: usize) -> &[f32] {
        let s = y % self.tags.len();
        &self.data[s * self.len..(s + 1) * self.len]
    }
    #[inline(always)]
    #[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
    /// Which builds of the loops may run (x86-64: elsewhere the portable one is all).
    #[cfg(target_arch = "x86_64")]
    simd: &'a Dispatch,
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
fn ensure_diffs(job: &BtvStep<'_>, sc: &mut BtvScratch, y: usize) {
    if sc.diffs.has(y) {
        return;
    }
    let (h, w, c) = (job.h, job.w, job.c);
    let row_len = w * c;
    let xrow = &job.x[y * row_len..(y + 1) * row_len];
    let planes = sc.diffs.claim(y);
    for (&(l, m, _), plane) in job.shifts.iter().zip(planes.chunks_exact_mut(row_len)) {
        // Pixels xx with xx + l inside the row (none when |l| >= w: the span is empty).
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
            if lo >= hi {
                continue; // |l| >= w: the shifted row does not overlap this one
            }
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
    job.simd,
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
    btv_deblur_with(z, a, h, w, c, params, x, &Dispatch::auto())
}

/// [`btv_deblur`] with the builds `simd` allows (see [`crate::simd`]).
#[allow(clippy::too_many_arguments)]
fn btv_deblur_with(
    z: &[f32],
    a: &[f32],
    h: usize,
    w: usize,
    c: usize,
    params: &BtvParams,
    x: &mut [f32],
    simd: &Dispatch,
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
    // Off x86-64 there is no SIMD build to choose: the portable one runs.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = simd;
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
            #[cfg(target_arch = "x86_64")]
            simd,
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
    use crate::simd::Level;

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
        simd::runs_or_skip(Level::Avx2, "btv_matches_the_formula (its AVX2 comparison)");
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
            // Windows wider than the image: shifts that leave it contribute nothing.
            (3, 3, 3, 0.5, 8, 0.01, 2),
            (20, 2, 1, 0.6, 4, 0.01, 2),
            (1, 5, 2, 0.6, 8, 0.0, 2),
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
            // Both builds (the AVX2 one where it runs), bit for bit.
            let [simd_x, portable_x] = [Level::Avx2, Level::Portable].map(|cap| {
                let mut x = z.clone();
                let simd = Dispatch::at_most(cap);
                btv_deblur_with(&z, &a, h, w, c, &p, &mut x, &simd).unwrap();
                assert_eq!(simd.ran(), simd.allowed());
                x
            });
            assert!(
                simd_x
                    .iter()
                    .zip(&portable_x)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{h}x{w}x{c} window {window}"
            );
        }
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
}
