//! Confidence-weighted, edge-aware filling of a parallax map: a joint weighted median.
//!
//! Flow is smooth across depth edges, so in a band along every occlusion boundary the
//! triangulated parallax is a mix of the foreground's and the background's, and the
//! triangulation's confidence there is low. [`weighted_median_fill`] replaces each
//! pixel marked "to do" by the weighted median of the values of its neighbours within
//! a radius, weighted by their confidence, by their colour similarity to the pixel in
//! a guide image (the reference view) and by their distance. A median, unlike a mean,
//! takes one side's value instead of a mixture, and the colour weight picks the side
//! whose colour the pixel shares: edges in the parallax snap to edges in the image.
//!
//! Reference: Ma, Zhang, Jia, "Constant time weighted median filtering for stereo
//! matching and beyond", ICCV 2013 (the filter), used here as confidence-weighted
//! filling of unreliable pixels, as in Hosni et al.'s cost-volume post-processing.

use crate::error::{Error, Result};
use crate::parallel;

/// Parameters of [`weighted_median_fill`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FillParams {
    /// Neighbourhood radius, px (a square window of side `2 * radius + 1`).
    pub radius: usize,
    /// Sample every `stride`-th neighbour in x and y (1: all).
    pub stride: usize,
    /// Colour distance (guide units) at which the colour weight is `exp(-1/2)`.
    pub sigma_colour: f32,
    /// Distance (px) at which the spatial weight is `exp(-1/2)`.
    pub sigma_space: f32,
}

impl FillParams {
    fn check(&self) -> Result<()> {
        if self.radius == 0 || self.radius > 256 {
            return Err(Error::invalid_argument(
                "radius",
                format!("expected 1..=256 px, got {}", self.radius),
            ));
        }
        if self.stride == 0 || self.stride > self.radius {
            return Err(Error::invalid_argument(
                "stride",
                format!("expected 1..=radius ({}), got {}", self.radius, self.stride),
            ));
        }
        for (name, v) in [
            ("sigma_colour", self.sigma_colour),
            ("sigma_space", self.sigma_space),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid_argument(
                    name,
                    format!("expected a finite number > 0, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// Joint weighted median of `values` at the pixels where `todo` is non-zero.
///
/// All planes are `h x w`, row-major: `values`, `weights` (>= 0; 0 or NaN: not a
/// candidate), `todo` (non-zero: replace this pixel) and the outputs; `guide` is
/// `h x w x channels` (e.g. Lab colour; a pixel with a NaN channel is never a candidate
/// and is never filled). For a pixel `p` to do, the candidates are the neighbours `q`
/// on the stride grid `p + (k * stride, l * stride)` within `radius`, inside the image,
/// with a finite value and a positive weight; each counts
/// `weights[q] * exp(-|guide[q] - guide[p]|^2 / (2 sigma_colour^2) - |q - p|^2 / (2 sigma_space^2))`.
/// `out_values[p]` is the weighted median of their values (the smallest value at which
/// the cumulative weight reaches half the total; NaN without candidates) and
/// `out_support[p]` the total weight divided by the number of grid positions in the
/// window (0..1 when weights are in 0..1). Pixels not to do are copied:
/// `out_values[p] = values[p]`, `out_support[p] = weights[p]`. Runs in lfcam's pool.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument if a plane's length is not `h * w`
/// (`h * w * channels` for `guide`), if `channels == 0`, or if a parameter is out of
/// range (see [`FillParams`]).
#[allow(clippy::too_many_arguments)]
pub fn weighted_median_fill(
    values: &[f32],
    weights: &[f32],
    guide: &[f32],
    channels: usize,
    todo: &[u8],
    (h, w): (usize, usize),
    params: &FillParams,
    out_values: &mut [f32],
    out_support: &mut [f32],
) -> Result<()> {
    params.check()?;
    if channels == 0 {
        return Err(Error::invalid_argument(
            "guide",
            "needs at least one channel",
        ));
    }
    let n = h
        .checked_mul(w)
        .ok_or_else(|| Error::invalid_argument("values", "image size overflows"))?;
    for (name, len) in [
        ("values", values.len()),
        ("weights", weights.len()),
        ("todo", todo.len()),
        ("out_values", out_values.len()),
        ("out_support", out_support.len()),
    ] {
        if len != n {
            return Err(Error::invalid_argument(
                name,
                format!("has {len} elements, expected {h} x {w} = {n}"),
            ));
        }
    }
    if Some(guide.len()) != n.checked_mul(channels) {
        return Err(Error::invalid_argument(
            "guide",
            format!(
                "has {} elements, expected {h} x {w} x {channels}",
                guide.len()
            ),
        ));
    }
    if n == 0 {
        return Ok(());
    }
    // The window's grid offsets and their spatial weights, computed once.
    let r = params.radius as isize;
    let step = params.stride;
    let inv2s = 1.0 / (2.0 * params.sigma_space * params.sigma_space);
    let inv2c = 1.0 / (2.0 * params.sigma_colour * params.sigma_colour);
    let mut window: Vec<(isize, isize, f32)> = Vec::new();
    for dy in (-r..=r).step_by(step) {
        for dx in (-r..=r).step_by(step) {
            let d2 = (dx * dx + dy * dy) as f32;
            window.push((dy, dx, (-d2 * inv2s).exp()));
        }
    }
    let slots = window.len() as f32;
    let (hi, wi) = (h as isize, w as isize);

    // Both outputs share rows: process them as (value, support) pairs per row chunk.
    parallel::for_each_row_chunk_pair(out_values, out_support, w, w, |y0, vals_out, supp_out| {
        let mut cand: Vec<(f32, f32)> = Vec::with_capacity(window.len());
        for (k, (vo, so)) in vals_out.iter_mut().zip(supp_out.iter_mut()).enumerate() {
            let p = y0 * w + k;
            let (Some(&v), Some(&wt), Some(&t)) = (values.get(p), weights.get(p), todo.get(p))
            else {
                continue;
            };
            if t == 0 {
                *vo = v;
                *so = wt;
                continue;
            }
            let gp = guide.get(p * channels..(p + 1) * channels).unwrap_or(&[]);
            if gp.len() != channels || gp.iter().any(|g| !g.is_finite()) {
                *vo = f32::NAN;
                *so = 0.0;
                continue;
            }
            let (py, px) = ((p / w) as isize, (p % w) as isize);
            cand.clear();
            let mut total = 0f32;
            for &(dy, dx, ws) in &window {
                let (qy, qx) = (py + dy, px + dx);
                if qy < 0 || qy >= hi || qx < 0 || qx >= wi {
                    continue;
                }
                let q = (qy * wi + qx) as usize;
                let (Some(&vq), Some(&wq)) = (values.get(q), weights.get(q)) else {
                    continue;
                };
                // NaN and non-positive weights are not candidates.
                if !vq.is_finite() || wq.is_nan() || wq <= 0.0 {
                    continue;
                }
                let gq = guide.get(q * channels..(q + 1) * channels).unwrap_or(&[]);
                let mut d2 = 0f32;
                for (a, b) in gp.iter().zip(gq) {
                    d2 += (a - b) * (a - b);
                }
                // NaN guide: NaN weight, rejected below.
                let wgt = wq * ws * (-d2 * inv2c).exp();
                if wgt > 0.0 {
                    cand.push((vq, wgt));
                    total += wgt;
                }
            }
            if cand.is_empty() || total.is_nan() || total <= 0.0 {
                *vo = f32::NAN;
                *so = 0.0;
                continue;
            }
            *vo = weighted_median(&mut cand, 0.5 * total);
            *so = (total / slots).min(1.0);
        }
        Ok(())
    })
}

/// The first value, in ascending order, at which the weights summed in that order
/// reach `half`: the weighted median of `(value, weight)` pairs (reordered). Instead of
/// sorting all of them, quickselect halves keep the part holding the median, and only
/// a short remainder is sorted and scanned; NaN if the weights never reach `half`.
fn weighted_median(cand: &mut [(f32, f32)], half: f32) -> f32 {
    const SORT_BELOW: usize = 24;
    let cmp = |a: &(f32, f32), b: &(f32, f32)| a.0.total_cmp(&b.0);
    let mut part = cand;
    let mut before = 0f32; // weight of the pairs below `part`
    while part.len() > SORT_BELOW {
        let mid = part.len() / 2;
        let (lower, pivot, upper) = part.select_nth_unstable_by(mid, cmp);
        let low: f32 = lower.iter().map(|c| c.1).sum();
        if before + low >= half {
            part = lower;
        } else if before + low + pivot.1 >= half {
            return pivot.0;
        } else {
            before += low + pivot.1;
            part = upper;
        }
    }
    part.sort_unstable_by(cmp);
    let mut acc = before;
    for &(val, wgt) in part.iter() {
        acc += wgt;
        if acc >= half {
            return val;
        }
    }
    part.last().map_or(f32::NAN, |c| c.0)
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    fn params(radius: usize) -> FillParams {
        FillParams {
            radius,
            stride: 1,
            sigma_colour: 0.1,
            sigma_space: 100.0,
        }
    }

    /// Runs the kernel into fresh outputs: (values, support).
    fn run(
        values: &[f32],
        weights: &[f32],
        guide: &[f32],
        channels: usize,
        todo: &[u8],
        size: (usize, usize),
        params: &FillParams,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let (mut out, mut sup) = (vec![0f32; values.len()], vec![0f32; values.len()]);
        weighted_median_fill(
            values, weights, guide, channels, todo, size, params, &mut out, &mut sup,
        )?;
        Ok((out, sup))
    }

    /// A step edge in the guide; the values left of it are 1, right of it 5, with a
    /// band of wrong, unconfident values around the edge: the fill restores the step.
    #[test]
    fn snaps_to_the_guide_edge() {
        let (h, w) = (5, 20);
        let mut guide = vec![0f32; h * w];
        let mut values = vec![0f32; h * w];
        let mut weights = vec![1f32; h * w];
        let mut todo = vec![0u8; h * w];
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                guide[p] = if x < 10 { 0.0 } else { 1.0 };
                values[p] = if x < 10 { 1.0 } else { 5.0 };
                if (7..13).contains(&x) {
                    values[p] = 3.0; // smeared
                    weights[p] = 0.0;
                    todo[p] = 1;
                }
            }
        }
        let (out, sup) = run(&values, &weights, &guide, 1, &todo, (h, w), &params(4)).unwrap();
        for y in 0..h {
            for x in 0..w {
                let want = if x < 10 { 1.0 } else { 5.0 };
                assert_eq!(out[y * w + x], want, "({x}, {y})");
            }
        }
        // Copied where not to do; support in (0, 1] where filled.
        assert_eq!(sup[0], 1.0);
        assert!(sup[2 * w + 9] > 0.0 && sup[2 * w + 9] <= 1.0);
    }

    /// Against a naive weighted median on random data.
    #[test]
    fn equals_a_naive_weighted_median() {
        let (h, w) = (9, 11);
        let mut state = 7u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 40) as f32) / ((1u64 << 24) as f32)
        };
        let values: Vec<f32> = (0..h * w).map(|_| rnd() * 10.0).collect();
        let weights: Vec<f32> = (0..h * w).map(|_| rnd()).collect();
        let guide: Vec<f32> = (0..h * w * 2).map(|_| rnd()).collect();
        let todo = vec![1u8; h * w];
        let p = FillParams {
            radius: 3,
            stride: 1,
            sigma_colour: 0.3,
            sigma_space: 2.0,
        };
        let (out, sup) = run(&values, &weights, &guide, 2, &todo, (h, w), &p).unwrap();
        for y in 0..h as isize {
            for x in 0..w as isize {
                let pi = (y * w as isize + x) as usize;
                let mut c = Vec::new();
                for dy in -3..=3isize {
                    for dx in -3..=3isize {
                        let (qy, qx) = (y + dy, x + dx);
                        if qy < 0 || qx < 0 || qy >= h as isize || qx >= w as isize {
                            continue;
                        }
                        let q = (qy * w as isize + qx) as usize;
                        let d2 = (guide[2 * q] - guide[2 * pi]).powi(2)
                            + (guide[2 * q + 1] - guide[2 * pi + 1]).powi(2);
                        let s2 = (dx * dx + dy * dy) as f32;
                        let wt = weights[q] * (-d2 / 0.18 - s2 / 8.0).exp();
                        c.push((values[q], wt));
                    }
                }
                c.sort_by(|a, b| a.0.total_cmp(&b.0));
                let tot: f32 = c.iter().map(|x| x.1).sum();
                let mut acc = 0.0;
                let mut med = f32::NAN;
                for (v, wt) in c {
                    acc += wt;
                    med = v;
                    if acc >= 0.5 * tot {
                        break;
                    }
                }
                assert_eq!(out[pi], med, "({x}, {y})");
                assert!((sup[pi] - tot / 49.0).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn no_candidates_give_nan_and_bad_sizes_are_errors() {
        let (h, w) = (3, 3);
        let values = vec![f32::NAN; 9];
        let ones = vec![1f32; 9];
        let todo = vec![1u8; 9];
        let (out, sup) = run(&values, &ones, &ones, 1, &todo, (h, w), &params(1)).unwrap();
        assert!(out.iter().all(|v| v.is_nan()) && sup.iter().all(|&s| s == 0.0));
        let err = run(&values, &ones, &ones[..8], 1, &todo, (h, w), &params(1)).unwrap_err();
        assert!(err.to_string().starts_with("guide:"), "{err}");
        let bad = FillParams {
            sigma_colour: f32::NAN,
            ..params(1)
        };
        let err = run(&values, &ones, &ones, 1, &todo, (h, w), &bad).unwrap_err();
        assert!(err.to_string().starts_with("sigma_colour:"), "{err}");
    }
}
