//! Robust shift-and-add: scattered samples splatted onto the `r`-times finer grid
//! (nearest pixel or a small Gaussian kernel), with robust reweighting passes against
//! the previous pass's estimate. Bands of output rows are accumulated in parallel from
//! the samples sorted into them ([`bins`]).

mod bins;

use self::bins::{Bins, bin_samples};
use super::{MAX_CHANNELS, MAX_FACTOR, MAX_RADIUS, check_len, mul, positive};
use crate::error::{Error, Result};
use crate::parallel;
use crate::simd::{self, Dispatch};

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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
    /// Which builds of the loops may run.
    simd: &'a Dispatch,
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
fn splat_pass<const C: usize, const L: usize>(job: &SplatJob<'_>, out: PassOut<'_>) -> Result<()> {
    let bands = out.bands(job.fine_w, C, job.bins.band_rows);
    // One task per band, each with its accumulator (the sums and weights written
    // measure the work).
    let work = job.fine_h * job.fine_w * (C + 1) * 4;
    parallel::for_each_task_init(bands, work, Vec::new, |acc, band, out| {
        let task = SplatBand::<C, L> {
            job,
            band,
            acc,
            out,
        };
        simd::run_avx2_or_portable(job.simd, task);
        Ok(())
    })
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
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
        &Dispatch::auto(),
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
        &Dispatch::auto(),
    )
}

/// The passes of [`shift_and_add`] (sizes of the output checked by the caller), with
/// the builds `simd` allows (see [`crate::simd`]); the last one writes `last`.
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
    simd: &Dispatch,
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
        // least 16 kernel heights keep that under ~1/8 (docs/tuning.md, "Super-resolution
        // and refocus").
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
            simd,
        };
        let out = if pass == params.iterations {
            last.take()
                .ok_or_else(|| Error::internal("shift_and_add", "no last pass"))?
        } else {
            PassOut::Estimate(write)
        };
        match channels {
            1 => splat_pass::<1, 4>(&job, out)?,
            2 => splat_pass::<2, 4>(&job, out)?,
            3 => splat_pass::<3, 4>(&job, out)?,
            _ => splat_pass::<4, 8>(&job, out)?,
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::simd::Level;

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
        // Both builds (the AVX2 one where it runs), against the definition.
        simd::runs_or_skip(Level::Avx2, "shift_and_add_matches_the_definition (AVX2)");
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
            for (weights, cap) in [
                (None, Level::Avx2),
                (Some(&wts[..]), Level::Avx2),
                (None, Level::Portable),
                (Some(&wts[..]), Level::Portable),
            ] {
                let (ws_ref, wsum_ref) = splat_naive(&pos, &val, weights, c, fh, fw, &p);
                // NaN: an element the fusion does not write would show.
                let mut sum = vec![f32::NAN; fh * fw * c];
                let mut ws = vec![f32::NAN; fh * fw];
                let simd = Dispatch::at_most(cap);
                let out = PassOut::Sums(&mut sum, &mut ws);
                splat_all(&pos, &val, weights, c, fh, fw, &p, out, &simd).unwrap();
                assert_eq!(simd.ran(), simd.allowed());
                let same =
                    |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                let what = format!("C {c} r {radius} it {iterations} {cap:?}");
                assert!(same(&ws, &wsum_ref), "wsum, {what}");
                assert!(same(&sum, &ws_ref), "sum, {what}");
            }
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
