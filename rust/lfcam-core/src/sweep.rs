//! Plane sweep along the calibrated parallax lines: a photo-consistency cost of the
//! reference view against every other view at candidate parallaxes, aggregated
//! edge-aware, with occlusion-aware subsets of the views
//! (docs/design.md, "Depth refinement").
//!
//! For a candidate `s`, the reference pixel `p` is compared with view `i` at
//! `p + o_i s` (bilinear). The per-view cost mixes a truncated colour difference and a
//! truncated difference of grey gradients (the gradients survive vignetting and
//! exposure differences between views). A subset's raw cost is the mean over its views
//! that see the sample; it is aggregated over the window of a guided filter (He, Sun,
//! Tang 2013) guided by the grey reference, so that windows do not mix the two sides
//! of an image edge. Each subset keeps its minimum over the candidates, a parabola
//! through the minimum and its neighbours (sub-candidate position), the curve's
//! curvature there and the lowest cost at least two candidates away from the minimum
//! (confidence). Occlusion-aware view selection (Wang, Efros, Ramamoorthi 2015): near
//! an occluding edge the views on one side of the reference see the same point, so the
//! caller passes subsets such as half-planes of the views and picks one per pixel.

use crate::error::{Error, Result};
use crate::parallel;

/// Outputs per subset and pixel: parallax, cost, curvature, second-best cost.
pub const SWEEP_OUTPUTS: usize = 4;

/// Parameters of [`plane_sweep`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SweepParams {
    /// Truncation of the colour difference (mean over channels), image units.
    pub trunc_colour: f32,
    /// Truncation of the gradient difference (`|dgx| + |dgy|` of the grey image).
    pub trunc_gradient: f32,
    /// Weight of the gradient term (0..1); the colour term weighs `1 - alpha`. Each term
    /// is divided by its truncation, so a cost lies in 0..1.
    pub alpha: f32,
    /// Radius (px) of the guided filter's square windows; 0: no aggregation.
    pub radius: usize,
    /// Regularisation of the guided filter (guide units squared).
    pub eps: f32,
}

impl SweepParams {
    fn check(&self) -> Result<()> {
        for (name, v) in [
            ("trunc_colour", self.trunc_colour),
            ("trunc_gradient", self.trunc_gradient),
            ("eps", self.eps),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid_argument(
                    name,
                    format!("expected a finite number > 0, got {v}"),
                ));
            }
        }
        if !(0.0..=1.0).contains(&self.alpha) {
            return Err(Error::invalid_argument(
                "alpha",
                format!("expected 0..1, got {}", self.alpha),
            ));
        }
        if self.radius > 64 {
            return Err(Error::invalid_argument(
                "radius",
                format!("expected 0..=64 px, got {}", self.radius),
            ));
        }
        Ok(())
    }
}

/// A view's features: `channels` colour values then the grey image's x and y
/// gradients (central differences, one-sided at the border), per pixel.
fn features(view: &[f32], h: usize, w: usize, c: usize) -> Vec<f32> {
    let f = c + 2;
    let mut out = vec![0.0f32; h * w * f];
    let grey: Vec<f32> = view
        .chunks_exact(c)
        .map(|px| px.iter().sum::<f32>() / c as f32)
        .collect();
    let g = |y: usize, x: usize| grey.get(y * w + x).copied().unwrap_or(f32::NAN);
    for y in 0..h {
        for x in 0..w {
            let base = (y * w + x) * f;
            let (xa, xb) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let (ya, yb) = (y.saturating_sub(1), (y + 1).min(h - 1));
            let gx = if xb > xa {
                (g(y, xb) - g(y, xa)) / (xb - xa) as f32
            } else {
                0.0
            };
            let gy = if yb > ya {
                (g(yb, x) - g(ya, x)) / (yb - ya) as f32
            } else {
                0.0
            };
            if let (Some(dst), Some(src)) = (
                out.get_mut(base..base + f),
                view.get((y * w + x) * c..(y * w + x + 1) * c),
            ) {
                for (d, v) in dst.iter_mut().zip(src.iter().chain([gx, gy].iter())) {
                    *d = *v;
                }
            }
        }
    }
    out
}

/// Box means over square windows of radius `r` clipped to the image rows `0..h` and
/// columns `0..w`, of `src` holding image rows `y0..y0 + n` (`n * w` values), written
/// for the image rows `out_rows` (which with their windows must lie in `y0..y0 + n`)
/// into `dst` (`out_rows.len() * w`). `tmp`: scratch.
#[allow(clippy::too_many_arguments)]
fn box_mean(
    src: &[f32],
    y0: usize,
    n: usize,
    (h, w): (usize, usize),
    r: usize,
    out_rows: std::ops::Range<usize>,
    dst: &mut [f32],
    tmp: &mut Vec<f32>,
) {
    // Horizontal window sums per row, by a running sum.
    tmp.clear();
    tmp.resize(n * w, 0.0);
    for (row_in, row_out) in src.chunks_exact(w).zip(tmp.chunks_exact_mut(w)).take(n) {
        let mut acc = 0.0f64;
        let mut hi = 0usize; // next column to add
        let mut lo = 0usize; // next column to remove
        for (x, o) in row_out.iter_mut().enumerate() {
            let want_hi = (x + r + 1).min(w);
            while hi < want_hi {
                acc += f64::from(row_in.get(hi).copied().unwrap_or(0.0));
                hi += 1;
            }
            let want_lo = x.saturating_sub(r);
            while lo < want_lo {
                acc -= f64::from(row_in.get(lo).copied().unwrap_or(0.0));
                lo += 1;
            }
            *o = acc as f32;
        }
    }
    // Vertical sums of the horizontal sums, divided by the window's pixel count.
    let count_x: Vec<f32> = (0..w)
        .map(|x| ((x + r + 1).min(w) - x.saturating_sub(r)) as f32)
        .collect();
    let mut acc = vec![0.0f64; w];
    let (first, last) = (out_rows.start, out_rows.end);
    if first >= last {
        return;
    }
    let mut hi = first.saturating_sub(r); // next row to add
    let mut lo = hi; // next row to remove
    for (y, row_out) in (first..last).zip(dst.chunks_exact_mut(w)) {
        let want_hi = (y + r + 1).min(h);
        while hi < want_hi {
            if let Some(row) = tmp.get((hi - y0) * w..(hi - y0 + 1) * w) {
                for (a, v) in acc.iter_mut().zip(row) {
                    *a += f64::from(*v);
                }
            }
            hi += 1;
        }
        let want_lo = y.saturating_sub(r);
        while lo < want_lo {
            if let Some(row) = tmp.get((lo - y0) * w..(lo - y0 + 1) * w) {
                for (a, v) in acc.iter_mut().zip(row) {
                    *a -= f64::from(*v);
                }
            }
            lo += 1;
        }
        let count_y = (want_hi - want_lo) as f32;
        for ((o, a), cx) in row_out.iter_mut().zip(&acc).zip(&count_x) {
            *o = *a as f32 / (cx * count_y);
        }
    }
}

/// Bilinear sample of `f` features at `(x, y)` of a `h x w` image into `out`; false if
/// the position is outside the image or a tap is not finite.
#[inline]
fn sample(feat: &[f32], (h, w): (usize, usize), f: usize, x: f32, y: f32, out: &mut [f32]) -> bool {
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
        return false;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let x1 = (x0 + 1).min(w - 1);
    let y1 = (y0 + 1).min(h - 1);
    let tap = |yy: usize, xx: usize| feat.get((yy * w + xx) * f..(yy * w + xx + 1) * f);
    let (Some(a), Some(b), Some(c), Some(d)) = (tap(y0, x0), tap(y0, x1), tap(y1, x0), tap(y1, x1))
    else {
        return false;
    };
    let (wa, wb, wc, wd) = (
        (1.0 - fx) * (1.0 - fy),
        fx * (1.0 - fy),
        (1.0 - fx) * fy,
        fx * fy,
    );
    let mut ok = true;
    for (k, o) in out.iter_mut().enumerate().take(f) {
        let v = wa * a.get(k).copied().unwrap_or(f32::NAN)
            + wb * b.get(k).copied().unwrap_or(f32::NAN)
            + wc * c.get(k).copied().unwrap_or(f32::NAN)
            + wd * d.get(k).copied().unwrap_or(f32::NAN);
        ok &= v.is_finite();
        *o = v;
    }
    ok
}

/// Cost of one view's sample against the reference's features (see [`SweepParams`]).
#[inline]
fn view_cost(reference: &[f32], sampled: &[f32], c: usize, p: &SweepParams) -> f32 {
    let mut colour = 0.0f32;
    for k in 0..c {
        colour += (sampled.get(k).copied().unwrap_or(0.0)
            - reference.get(k).copied().unwrap_or(0.0))
        .abs();
    }
    colour /= c as f32;
    let g = |k: usize| {
        (sampled.get(k).copied().unwrap_or(0.0) - reference.get(k).copied().unwrap_or(0.0)).abs()
    };
    let gradient = g(c) + g(c + 1);
    (1.0 - p.alpha) * colour.min(p.trunc_colour) / p.trunc_colour
        + p.alpha * gradient.min(p.trunc_gradient) / p.trunc_gradient
}

/// Raw (not aggregated) cost of every subset at candidate `s` for the image rows
/// `rows`: `out[(y - rows.start) * w * n_sub + x * n_sub + j]`... stored per subset as
/// planes: `out[j][(y - rows.start) * w + x]`. A subset none of whose views sees the
/// sample costs 1 (the maximum), as does a reference pixel without data.
#[allow(clippy::too_many_arguments)]
fn raw_costs(
    feats: &[Vec<f32>],
    reference: usize,
    offsets: &[[f64; 2]],
    subsets: &[Vec<usize>],
    s: f32,
    (h, w): (usize, usize),
    c: usize,
    rows: std::ops::Range<usize>,
    p: &SweepParams,
    out: &mut [Vec<f32>],
    scratch: &mut Vec<f32>,
) {
    let f = c + 2;
    let n = feats.len();
    let n_rows = rows.len();
    for plane in out.iter_mut() {
        plane.clear();
        plane.resize(n_rows * w, 1.0);
    }
    let Some(ref_feat) = feats.get(reference) else {
        return;
    };
    scratch.resize(f + n, 0.0);
    let (sampled, per_view) = scratch.split_at_mut(f);
    let shifts: Vec<(f32, f32)> = offsets
        .iter()
        .map(|o| ((o[0] * f64::from(s)) as f32, (o[1] * f64::from(s)) as f32))
        .collect();
    for (row_i, y) in rows.enumerate() {
        for x in 0..w {
            let base = (y * w + x) * f;
            let Some(r) = ref_feat.get(base..base + f) else {
                continue;
            };
            if !r.iter().all(|v| v.is_finite()) {
                continue;
            }
            for (i, cost) in per_view.iter_mut().enumerate() {
                *cost = f32::NAN;
                if i == reference {
                    continue;
                }
                let (Some(feat), Some(&(dx, dy))) = (feats.get(i), shifts.get(i)) else {
                    continue;
                };
                if sample(feat, (h, w), f, x as f32 + dx, y as f32 + dy, sampled) {
                    *cost = view_cost(r, sampled, c, p);
                }
            }
            for (views, plane) in subsets.iter().zip(out.iter_mut()) {
                let (mut sum, mut cnt) = (0.0f32, 0u32);
                for &i in views {
                    if let Some(&v) = per_view.get(i)
                        && v.is_finite()
                    {
                        sum += v;
                        cnt += 1;
                    }
                }
                if cnt > 0
                    && let Some(o) = plane.get_mut(row_i * w + x)
                {
                    *o = sum / cnt as f32;
                }
            }
        }
    }
}

/// Plane sweep of `views` along their parallax vectors over `candidates`.
///
/// `views`: `n` images `h x w x c`, row-major, one after the other (NaN: no data);
/// `offsets[i]`: view `i`'s parallax vector (px per unit parallax; the reference
/// pixel `p` is seen at `p + o_i s`); `candidates`: increasing, equally spaced
/// parallaxes (at least 3); `subsets`: the view index lists whose mean costs are
/// swept (the reference is ignored in them). `out` holds `h x w x subsets x`
/// [`SWEEP_OUTPUTS`] values: per pixel and subset the parallax at the aggregated
/// cost's minimum (parabola through it and its neighbours; the end candidate itself at
/// either end of the range), that minimum cost, the parabola's curvature (cost per
/// unit parallax squared) and the lowest cost at least two candidates from the
/// minimum (infinite if none). Runs in lfcam's pool, in bands of rows.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument if sizes disagree, `reference` is
/// not a view, a subset names a view out of range or is empty, the candidates are not
/// finite, increasing and equally spaced, or a parameter is out of range.
#[allow(clippy::too_many_arguments)]
pub fn plane_sweep(
    views: &[f32],
    (n, h, w, c): (usize, usize, usize, usize),
    reference: usize,
    offsets: &[[f64; 2]],
    candidates: &[f32],
    subsets: &[Vec<usize>],
    params: &SweepParams,
    out: &mut [f32],
) -> Result<()> {
    params.check()?;
    if c == 0 || n < 2 {
        return Err(Error::invalid_argument(
            "views",
            format!("expected at least 2 views with at least 1 channel, got {n} x {c}"),
        ));
    }
    let plane = h
        .checked_mul(w)
        .and_then(|p| p.checked_mul(c))
        .ok_or_else(|| Error::invalid_argument("views", "image size overflows"))?;
    if Some(views.len()) != plane.checked_mul(n) {
        return Err(Error::invalid_argument(
            "views",
            format!(
                "has {} elements, expected {n} x {h} x {w} x {c}",
                views.len()
            ),
        ));
    }
    if reference >= n {
        return Err(Error::invalid_argument(
            "reference",
            format!("{reference} is not a view index (0..{})", n - 1),
        ));
    }
    if offsets.len() != n || !offsets.iter().flatten().all(|v| v.is_finite()) {
        return Err(Error::invalid_argument(
            "offsets",
            format!("expected {n} finite (x, y) pairs, got {}", offsets.len()),
        ));
    }
    let k = candidates.len();
    let ds = match (candidates.first(), candidates.get(1)) {
        (Some(&a), Some(&b)) if k >= 3 => b - a,
        _ => {
            return Err(Error::invalid_argument(
                "candidates",
                format!("expected at least 3, got {k}"),
            ));
        }
    };
    let spaced = candidates.windows(2).all(|p| {
        let d = p.get(1).copied().unwrap_or(f32::NAN) - p.first().copied().unwrap_or(f32::NAN);
        d.is_finite() && d > 0.0 && (d - ds).abs() <= 1e-3 * ds
    });
    if !(ds.is_finite() && ds > 0.0 && spaced) {
        return Err(Error::invalid_argument(
            "candidates",
            "expected finite, increasing and equally spaced values",
        ));
    }
    if subsets.is_empty() {
        return Err(Error::invalid_argument(
            "subsets",
            "expected at least one subset",
        ));
    }
    for (j, s) in subsets.iter().enumerate() {
        if s.iter().all(|&i| i == reference) {
            return Err(Error::invalid_item(
                "subsets",
                j,
                "holds no view besides the reference",
            ));
        }
        if let Some(&bad) = s.iter().find(|&&i| i >= n) {
            return Err(Error::invalid_item(
                "subsets",
                j,
                format!("view {bad} is out of range (0..{})", n - 1),
            ));
        }
    }
    let n_sub = subsets.len();
    let row_len = w * n_sub * SWEEP_OUTPUTS;
    if Some(out.len()) != h.checked_mul(row_len) {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "has {} elements, expected {h} x {w} x {n_sub} x {SWEEP_OUTPUTS}",
                out.len()
            ),
        ));
    }
    if h == 0 || w == 0 {
        return Ok(());
    }
    // Every view's features once (colour, grey gradients), then the guide.
    let feats: Vec<Vec<f32>> = parallel::map_tasks(n, plane.saturating_mul(n * 4), |i| {
        Ok(views
            .get(i * plane..(i + 1) * plane)
            .map_or_else(Vec::new, |v| features(v, h, w, c)))
    })?;
    let f = c + 2;
    let guide: Vec<f32> = feats
        .get(reference)
        .map(|ft| {
            ft.chunks_exact(f)
                .map(|px| {
                    let g = px.iter().take(c).sum::<f32>() / c as f32;
                    if g.is_finite() { g } else { 0.0 }
                })
                .collect()
        })
        .unwrap_or_default();
    let r = params.radius;
    // A band's tasks recompute a halo of 2 r rows on each side: at least 4 r rows
    // per band keeps that below half the work.
    let min_rows = (4 * r).max(8);
    parallel::for_each_row_chunk_init(
        out,
        row_len,
        min_rows,
        || (Vec::new(), Vec::new(), Vec::new()),
        |(tmp, scratch, planes): &mut (Vec<f32>, Vec<f32>, Vec<Vec<f32>>), first, rows_out| {
            let last = first + rows_out.len() / row_len;
            let ya = first.saturating_sub(2 * r);
            let yb = (last + 2 * r).min(h);
            let nb = yb - ya;
            let mid = first.saturating_sub(r)..(last + r).min(h); // stage-1 rows
            let nm = mid.len();
            let ni = last - first;
            let band = |a: &[f32]| {
                a.get(ya * w..yb * w)
                    .map(<[f32]>::to_vec)
                    .unwrap_or_default()
            };
            let g_band = band(&guide);
            let gg_band: Vec<f32> = g_band.iter().map(|v| v * v).collect();
            // The guide's window means and variances over the stage-1 rows.
            let mut mean_i = vec![0.0f32; nm * w];
            let mut var_i = vec![0.0f32; nm * w];
            box_mean(&g_band, ya, nb, (h, w), r, mid.clone(), &mut mean_i, tmp);
            box_mean(&gg_band, ya, nb, (h, w), r, mid.clone(), &mut var_i, tmp);
            for (v, m) in var_i.iter_mut().zip(&mean_i) {
                *v -= m * m;
            }
            let guide_inner = guide.get(first * w..last * w).unwrap_or_default();
            planes.resize_with(n_sub, Vec::new);
            // Per subset: running minimum and its neighbours, second best, the
            // previous two aggregated slices and the minimum of all slices before them.
            let m = ni * w;
            let mut best = vec![f32::INFINITY; n_sub * m];
            let mut best_k = vec![0usize; n_sub * m];
            let mut left = vec![f32::NAN; n_sub * m];
            let mut right = vec![f32::NAN; n_sub * m];
            let mut second = vec![f32::INFINITY; n_sub * m];
            let mut lag_min = vec![f32::INFINITY; n_sub * m];
            let mut prev1 = vec![f32::NAN; n_sub * m];
            let mut prev2 = vec![f32::NAN; n_sub * m];
            let mut agg = vec![0.0f32; m];
            let (mut mp, mut mip, mut a, mut b) = (
                vec![0.0f32; nm * w],
                vec![0.0f32; nm * w],
                vec![0.0f32; nm * w],
                vec![0.0f32; nm * w],
            );
            let (mut ma, mut mb) = (vec![0.0f32; m], vec![0.0f32; m]);
            let mut ip = vec![0.0f32; nb * w];
            for (kk, &s) in candidates.iter().enumerate() {
                raw_costs(
                    &feats,
                    reference,
                    offsets,
                    subsets,
                    s,
                    (h, w),
                    c,
                    ya..yb,
                    params,
                    planes,
                    scratch,
                );
                for (j, p) in planes.iter().enumerate() {
                    if r == 0 {
                        agg.copy_from_slice(
                            p.get((first - ya) * w..(last - ya) * w).unwrap_or_default(),
                        );
                    } else {
                        // Guided filter: q = mean(a) I + mean(b), a = cov(I, p) / (var(I) + eps).
                        for ((o, pv), gv) in ip.iter_mut().zip(p).zip(&g_band) {
                            *o = pv * gv;
                        }
                        box_mean(p, ya, nb, (h, w), r, mid.clone(), &mut mp, tmp);
                        box_mean(&ip, ya, nb, (h, w), r, mid.clone(), &mut mip, tmp);
                        for t in 0..nm * w {
                            let (Some(&mi), Some(&vi), Some(&mpv), Some(&mipv)) =
                                (mean_i.get(t), var_i.get(t), mp.get(t), mip.get(t))
                            else {
                                continue;
                            };
                            let av = (mipv - mi * mpv) / (vi + params.eps);
                            if let (Some(ao), Some(bo)) = (a.get_mut(t), b.get_mut(t)) {
                                *ao = av;
                                *bo = mpv - av * mi;
                            }
                        }
                        let mid0 = mid.start;
                        box_mean(&a, mid0, nm, (h, w), r, first..last, &mut ma, tmp);
                        box_mean(&b, mid0, nm, (h, w), r, first..last, &mut mb, tmp);
                        for (((o, av), bv), gv) in agg.iter_mut().zip(&ma).zip(&mb).zip(guide_inner)
                        {
                            *o = av * gv + bv;
                        }
                    }
                    let off = j * m;
                    for (t, &q) in agg.iter().enumerate() {
                        let u = off + t;
                        let (
                            Some(bst),
                            Some(bk),
                            Some(lf),
                            Some(rt),
                            Some(sc),
                            Some(lm),
                            Some(p1),
                            Some(p2),
                        ) = (
                            best.get(u).copied(),
                            best_k.get(u).copied(),
                            left.get(u).copied(),
                            right.get(u).copied(),
                            second.get(u).copied(),
                            lag_min.get(u).copied(),
                            prev1.get(u).copied(),
                            prev2.get(u).copied(),
                        )
                        else {
                            continue;
                        };
                        let lm = if kk >= 2 { lm.min(p2) } else { lm };
                        let (mut bst, mut bk, mut lf, mut rt, mut sc) = (bst, bk, lf, rt, sc);
                        if kk >= 1 && bk == kk - 1 {
                            rt = q;
                        }
                        if q < bst {
                            sc = lm;
                            bst = q;
                            bk = kk;
                            lf = p1;
                            rt = f32::NAN;
                        } else if kk >= bk + 2 {
                            sc = sc.min(q);
                        }
                        for (arr, v) in [
                            (&mut best, bst),
                            (&mut left, lf),
                            (&mut right, rt),
                            (&mut second, sc),
                            (&mut lag_min, lm),
                            (&mut prev2, p1),
                            (&mut prev1, q),
                        ] {
                            if let Some(x) = arr.get_mut(u) {
                                *x = v;
                            }
                        }
                        if let Some(x) = best_k.get_mut(u) {
                            *x = bk;
                        }
                    }
                }
            }
            // Parabola through the minimum and its neighbours.
            for (t, px) in rows_out.chunks_exact_mut(n_sub * SWEEP_OUTPUTS).enumerate() {
                for (j, o) in px.chunks_exact_mut(SWEEP_OUTPUTS).enumerate() {
                    let u = j * m + t;
                    let (Some(&bst), Some(&bk), Some(&lf), Some(&rt), Some(&sc)) = (
                        best.get(u),
                        best_k.get(u),
                        left.get(u),
                        right.get(u),
                        second.get(u),
                    ) else {
                        continue;
                    };
                    let s0 = candidates.get(bk).copied().unwrap_or(f32::NAN);
                    let curv = lf - 2.0 * bst + rt;
                    let shift = if bk == 0 || bk + 1 == k || curv.is_nan() || curv <= 0.0 {
                        0.0
                    } else {
                        (0.5 * (lf - rt) / curv).clamp(-0.5, 0.5)
                    };
                    let vals = [
                        s0 + shift * ds,
                        bst,
                        if curv.is_finite() {
                            curv / (ds * ds)
                        } else {
                            0.0
                        },
                        sc,
                    ];
                    o.copy_from_slice(&vals);
                }
            }
            Ok(())
        },
    )
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    /// A textured image shifted by a constant parallax: the sweep finds it.
    #[test]
    fn finds_a_constant_shift() {
        let (h, w, c) = (40, 48, 1);
        let tex = |x: f32, y: f32| {
            (0.37 * x).sin() * (0.23 * y).cos() + 0.5 * (0.11 * x + 0.19 * y).sin()
        };
        let offsets = [[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]];
        let s_true = 0.8f32;
        let mut views = Vec::new();
        for o in &offsets {
            for y in 0..h {
                for x in 0..w {
                    // The reference pixel p is at p + o s in view i: view_i(q) = ref(q - o s).
                    views.push(tex(
                        x as f32 - o[0] as f32 * s_true,
                        y as f32 - o[1] as f32 * s_true,
                    ));
                }
            }
        }
        let candidates: Vec<f32> = (0..21).map(|k| -1.0 + 0.1 * k as f32).collect();
        let subsets = vec![vec![1, 2, 3, 4], vec![1, 3]];
        let params = SweepParams {
            trunc_colour: 1.0,
            trunc_gradient: 1.0,
            alpha: 0.5,
            radius: 2,
            eps: 1e-4,
        };
        let mut out = vec![0.0f32; h * w * 2 * SWEEP_OUTPUTS];
        plane_sweep(
            &views,
            (5, h, w, c),
            0,
            &offsets,
            &candidates,
            &subsets,
            &params,
            &mut out,
        )
        .unwrap();
        for y in 4..h - 4 {
            for x in 4..w - 4 {
                let s = out[(y * w + x) * 2 * SWEEP_OUTPUTS];
                assert!((s - s_true).abs() < 0.03, "({x}, {y}): {s}");
            }
        }
    }

    #[test]
    fn box_mean_matches_brute_force() {
        let (h, w, r) = (9, 7, 2);
        let src: Vec<f32> = (0..h * w).map(|i| ((i * 37) % 11) as f32).collect();
        let mut dst = vec![0.0; h * w];
        box_mean(&src, 0, h, (h, w), r, 0..h, &mut dst, &mut Vec::new());
        for y in 0..h {
            for x in 0..w {
                let (mut s, mut n) = (0.0, 0.0);
                for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                    for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                        s += src[yy * w + xx];
                        n += 1.0;
                    }
                }
                assert!((dst[y * w + x] - s / n).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn rejects_bad_arguments() {
        let views = vec![0.0f32; 2 * 4 * 4];
        let offsets = [[0.0, 0.0], [1.0, 0.0]];
        let p = SweepParams {
            trunc_colour: 0.1,
            trunc_gradient: 0.1,
            alpha: 0.5,
            radius: 1,
            eps: 1e-4,
        };
        let mut out = vec![0.0f32; 4 * 4 * SWEEP_OUTPUTS];
        let call = |cands: &[f32], subs: &[Vec<usize>], out: &mut [f32]| {
            plane_sweep(&views, (2, 4, 4, 1), 0, &offsets, cands, subs, &p, out)
        };
        assert!(call(&[0.0, 1.0], &[vec![1]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 3.0], &[vec![1]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![0]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![2]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![1]], &mut out[1..]).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![1]], &mut out).is_ok());
    }
}
