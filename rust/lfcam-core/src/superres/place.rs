//! Placement of raw samples in the reference view's rectified frame: the fixed-point
//! iteration `p <- q - o_i s(p)` on the parallax map.

use super::{check_len, mul};
use crate::error::{Error, Result};
use crate::parallel;
use crate::simd::{self, Dispatch};

/// Bilinear sample of a `(h, w)` map at `(x, y)`, skipping NaN corners (the others are
/// renormalised); NaN if the finite corners carry less than half the weight or the
/// point is outside the map by more than half a pixel.
#[inline(always)]
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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
/// `p + o_i s(p) = q` (docs/design.md, "Plane and parallax") by the fixed-point iteration
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
    let simd = Dispatch::auto();
    place_samples_with(inv, view, offsets, parallax, h, w, params, out, &simd)
}

/// [`place_samples`] with the builds `simd` allows (see [`crate::simd`]).
#[allow(clippy::too_many_arguments)]
fn place_samples_with(
    inv: &[f32],
    view: &[i32],
    offsets: &[[f64; 2]],
    parallax: &[f32],
    h: usize,
    w: usize,
    params: &PlaceParams,
    out: &mut [f32],
    simd: &Dispatch,
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
    // Off x86-64 there is no SIMD build to choose: the portable one runs.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = simd;
    let job = PlaceJob {
        inv,
        view,
        offsets: &offs,
        parallax,
        h,
        w,
        iterations: params.iterations,
        tolerance: params.tolerance,
        #[cfg(target_arch = "x86_64")]
        simd,
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
    /// Which builds of the loops may run (x86-64: elsewhere the portable one is all).
    #[cfg(target_arch = "x86_64")]
    simd: &'a Dispatch,
}

/// Samples placed side by side: their fixed-point iterations are independent, so
/// stepping [`PLACE_LANES`] of them together lets the CPU overlap their look-ups
/// (one sample's iterations form a chain of dependent loads).
const PLACE_LANES: usize = 8;

simd::avx2_or_portable!(
    job.simd,
    /// [`place_rows`], compiled for AVX2 and for the baseline.
    fn place_task(job: &PlaceJob<'_>, first: usize, out: &mut [f32]) -> () {
        place_rows(job, first, out)
    }
);

/// Samples `first..` into `out` (2 floats each), [`PLACE_LANES`] at a time. Each
/// sample goes through exactly the arithmetic of the one-at-a-time iteration (see
/// [`place_samples`]), so the result does not depend on the grouping.
#[inline(always)]
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
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

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::simd::Level;

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
        // Both builds (the AVX2 one where it runs), against the definition.
        simd::runs_or_skip(Level::Avx2, "placement_matches_one_sample_at_a_time (AVX2)");
        for cap in [Level::Avx2, Level::Portable] {
            let mut got = vec![0f32; inv.len()];
            let simd = Dispatch::at_most(cap);
            place_samples_with(&inv, &view, &offsets, &par, h, w, &p, &mut got, &simd).unwrap();
            assert_eq!(simd.ran(), simd.allowed());
            assert!(
                want.iter()
                    .zip(&got)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{cap:?}"
            );
            assert!(got.iter().filter(|v| v.is_finite()).count() > m / 2);
        }
        let mut got = vec![0f32; inv.len()];
        place_samples(&inv, &view, &offsets, &par, h, w, &p, &mut got).unwrap();
        assert!(
            want.iter()
                .zip(&got)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
    }
}
