//! Plane sweep along the calibrated parallax lines: a photo-consistency cost of the
//! reference view against every other view at candidate parallaxes, aggregated
//! edge-aware, with occlusion-aware subsets of the views
//! (docs/design.md, "Depth refinement").
//!
//! For a candidate `s`, the reference pixel `p` is compared with view `i` at
//! `p + o_i s` (bilinear or bicubic). The per-view cost mixes a truncated colour
//! difference and a truncated difference of grey gradients (the gradients survive
//! vignetting and exposure differences between views). A subset's raw cost is the mean
//! over its views that see the sample; it is aggregated over the window of a guided
//! filter (He, Sun, Tang 2013) guided by the grey reference, so that windows do not mix
//! the two sides of an image edge. Each subset keeps its minimum over the candidates, a
//! parabola through the minimum and its neighbours (sub-candidate position), the
//! curve's curvature there, the lowest cost at least two candidates away from the
//! minimum (confidence) and the cost at the candidate nearest 0. Occlusion-aware view
//! selection (Wang, Efros, Ramamoorthi 2015): near an occluding edge the views on one
//! side of the reference see the same point, so the caller passes subsets such as
//! half-planes of the views and picks one per pixel.
//!
//! With a per-pixel base map the candidates are offsets from it (`s = base(p) + c_k`):
//! a narrow band around an initial estimate, whose aggregation windows then follow
//! that estimate's surface instead of a fronto-parallel plane. An `active` mask limits
//! the work to the pixels wanted (and their windows' reach).

use crate::error::{Error, Result};
use crate::parallel;

/// Outputs per subset and pixel: parallax, cost, curvature, second-best cost, cost at
/// the candidate nearest 0 (with a base map: the base's own cost).
pub const SWEEP_OUTPUTS: usize = 5;

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
    /// Bicubic samples of the views (OpenCV's `INTER_CUBIC` kernel, a = -0.75, edge
    /// taps clamped) instead of bilinear ones.
    pub cubic: bool,
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
/// into `dst` (`out_rows.len() * w`). Direct sums of shifted rows (vectorised; a
/// window's `2 r + 1` values per axis, so float32 keeps about 1e-7 of the mean).
/// `tmp`: scratch.
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
    let (first, last) = (out_rows.start, out_rows.end);
    if first >= last || w == 0 {
        return;
    }
    // Horizontal window sums of the rows the output's windows reach.
    let ha = first.saturating_sub(r).max(y0);
    let hb = (last + r).min(h).min(y0 + n);
    tmp.clear();
    tmp.resize((hb - ha) * w, 0.0);
    let rows_in = src.get((ha - y0) * w..(hb - y0) * w).unwrap_or_default();
    for (row_in, row_out) in rows_in.chunks_exact(w).zip(tmp.chunks_exact_mut(w)) {
        for d in 0..=2 * r {
            // out[x] += in[x + d - r] where both lie in the row.
            let (xa, sa) = if d < r { (r - d, 0) } else { (0, d - r) };
            let len = w.saturating_sub(xa.max(sa));
            if let (Some(o), Some(i)) = (row_out.get_mut(xa..xa + len), row_in.get(sa..sa + len)) {
                for (ov, iv) in o.iter_mut().zip(i) {
                    *ov += iv;
                }
            }
        }
    }
    // Vertical sums, divided by the clipped window's pixel count.
    let inv_x: Vec<f32> = (0..w)
        .map(|x| 1.0 / ((x + r + 1).min(w) - x.saturating_sub(r)) as f32)
        .collect();
    for (y, row_out) in (first..last).zip(dst.chunks_exact_mut(w)) {
        let (ya, yb) = (y.saturating_sub(r).max(ha), (y + r + 1).min(hb));
        row_out.fill(0.0);
        for yy in ya..yb {
            if let Some(row) = tmp.get((yy - ha) * w..(yy - ha + 1) * w) {
                for (o, v) in row_out.iter_mut().zip(row) {
                    *o += v;
                }
            }
        }
        let inv_y = 1.0 / ((y + r + 1).min(h) - y.saturating_sub(r)) as f32;
        for (o, ix) in row_out.iter_mut().zip(&inv_x) {
            *o *= ix * inv_y;
        }
    }
}

/// OpenCV's bicubic weights (a = -0.75) for a tap offset `t` in 0..1.
#[inline]
fn cubic_weights(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let x = t + 1.0;
    let w0 = ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    let w1 = ((A + 2.0) * t - (A + 3.0)) * t * t + 1.0;
    let u = 1.0 - t;
    let w2 = ((A + 2.0) * u - (A + 3.0)) * u * u + 1.0;
    [w0, w1, w2, 1.0 - w0 - w1 - w2]
}

/// Adds `wy` times the `wx`-weighted taps of the row of `feat` starting at `at` (`K`
/// consecutive taps of `F` features) to `acc`; None if the row is out of range.
#[inline(always)]
fn add_row<const F: usize, const K: usize>(
    feat: &[f32],
    at: usize,
    wx: &[f32; K],
    wy: f32,
    acc: &mut [f32; F],
) -> Option<()> {
    let row = feat.get(at..at + K * F)?;
    let mut racc = [0.0f32; F];
    for (tap, &wxv) in row.chunks_exact(F).zip(wx) {
        for (a, v) in racc.iter_mut().zip(tap) {
            *a += wxv * v;
        }
    }
    for (a, r) in acc.iter_mut().zip(&racc) {
        *a += wy * r;
    }
    Some(())
}

/// Sample of `F` features at `(x, y)` of a `h x w` image (bilinear, or bicubic with
/// edge taps clamped; rows combined first, then the row sums); None if the position
/// is outside the image or a tap is not finite.
#[inline]
fn sample<const F: usize>(
    feat: &[f32],
    (h, w): (usize, usize),
    x: f32,
    y: f32,
    cubic: bool,
) -> Option<[f32; F]> {
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
        return None;
    }
    // Truncation is the floor for non-negative positions.
    let (x0, y0) = (x as usize, y as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let mut acc = [0.0f32; F];
    if cubic {
        let (wx, wy) = (cubic_weights(fx), cubic_weights(fy));
        let ys = [
            y0.saturating_sub(1),
            y0,
            (y0 + 1).min(h - 1),
            (y0 + 2).min(h - 1),
        ];
        if x0 >= 1 && x0 + 2 < w {
            for (&yy, &wyv) in ys.iter().zip(&wy) {
                add_row::<F, 4>(feat, (yy * w + x0 - 1) * F, &wx, wyv, &mut acc)?;
            }
        } else {
            // Edge columns: one tap at a time, clamped.
            let xs = [
                x0.saturating_sub(1),
                x0,
                (x0 + 1).min(w - 1),
                (x0 + 2).min(w - 1),
            ];
            for (&yy, &wyv) in ys.iter().zip(&wy) {
                for (&xx, &wxv) in xs.iter().zip(&wx) {
                    add_row::<F, 1>(feat, (yy * w + xx) * F, &[wxv], wyv, &mut acc)?;
                }
            }
        }
    } else {
        let y1 = (y0 + 1).min(h - 1);
        if x0 + 1 < w {
            let wx = [1.0 - fx, fx];
            add_row::<F, 2>(feat, (y0 * w + x0) * F, &wx, 1.0 - fy, &mut acc)?;
            add_row::<F, 2>(feat, (y1 * w + x0) * F, &wx, fy, &mut acc)?;
        } else {
            add_row::<F, 1>(feat, (y0 * w + x0) * F, &[1.0], 1.0 - fy, &mut acc)?;
            add_row::<F, 1>(feat, (y1 * w + x0) * F, &[1.0], fy, &mut acc)?;
        }
    }
    acc.iter().all(|v| v.is_finite()).then_some(acc)
}

/// Cost of one view's sample against the reference's features (see [`SweepParams`]):
/// `wc min(colour, tc) + wg min(gradient, tg)` with `wc = (1 - alpha) / (c tc)` over
/// the colour differences' sum and `wg = alpha / tg`.
#[inline]
fn view_cost<const F: usize>(
    reference: &[f32; F],
    sampled: &[f32; F],
    [tc, tg, wc, wg]: [f32; 4],
) -> f32 {
    let c = F - 2;
    let mut colour = 0.0f32;
    let mut gradient = 0.0f32;
    for (k, (a, b)) in sampled.iter().zip(reference).enumerate() {
        let d = (a - b).abs();
        if k < c {
            colour += d;
        } else {
            gradient += d;
        }
    }
    wc * colour.min(tc) + wg * gradient.min(tg)
}

/// What [`raw_costs`] reads: every view's features, where to look and which pixels.
struct Scene<'a> {
    feats: &'a [Vec<f32>],
    reference: usize,
    offsets: &'a [[f64; 2]],
    subsets: &'a [Vec<usize>],
    base: Option<&'a [f32]>,
    need: Option<&'a [u8]>,
    dims: (usize, usize),
}

/// Raw (not aggregated) cost of every subset at candidate `s` (added to the base map,
/// if any) for the image rows `rows`, per subset as planes:
/// `out[j][(y - rows.start) * w + x]`. A subset none of whose views sees the sample
/// costs 1 (the maximum), as does a reference pixel without data or outside `need`.
fn raw_costs<const F: usize>(
    sc: &Scene<'_>,
    s: f32,
    rows: std::ops::Range<usize>,
    p: &SweepParams,
    out: &mut [Vec<f32>],
    per_view: &mut Vec<f32>,
) {
    let (h, w) = sc.dims;
    let n = sc.feats.len();
    let n_rows = rows.len();
    for plane in out.iter_mut() {
        plane.clear();
        plane.resize(n_rows * w, 1.0);
    }
    let Some(ref_feat) = sc.feats.get(sc.reference) else {
        return;
    };
    per_view.clear();
    per_view.resize(n, f32::NAN);
    // The colour difference is the channels' sum: its truncation scales by c.
    let c = (F - 2) as f32;
    let weights = [
        p.trunc_colour * c,
        p.trunc_gradient,
        (1.0 - p.alpha) / (p.trunc_colour * c),
        p.alpha / p.trunc_gradient,
    ];
    for (row_i, y) in rows.enumerate() {
        for x in 0..w {
            let at = y * w + x;
            if sc.need.is_some_and(|m| m.get(at).is_none_or(|&v| v == 0)) {
                continue;
            }
            let s_px = match sc.base {
                Some(b) => b.get(at).copied().unwrap_or(f32::NAN) + s,
                None => s,
            };
            let Some(r) = ref_feat
                .get(at * F..(at + 1) * F)
                .and_then(|r| <&[f32; F]>::try_from(r).ok())
            else {
                continue;
            };
            if !(s_px.is_finite() && r.iter().all(|v| v.is_finite())) {
                continue;
            }
            for (i, ((cost, feat), o)) in per_view
                .iter_mut()
                .zip(sc.feats)
                .zip(sc.offsets)
                .enumerate()
            {
                *cost = f32::NAN;
                if i == sc.reference {
                    continue;
                }
                let (dx, dy) = (
                    (o[0] * f64::from(s_px)) as f32,
                    (o[1] * f64::from(s_px)) as f32,
                );
                if let Some(sampled) =
                    sample::<F>(feat, (h, w), x as f32 + dx, y as f32 + dy, p.cubic)
                {
                    *cost = view_cost(r, &sampled, weights);
                }
            }
            for (views, plane) in sc.subsets.iter().zip(out.iter_mut()) {
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

/// A pixel-subset's running state over the candidates.
#[derive(Debug, Clone, Copy)]
struct Track {
    best: f32,
    best_k: usize,
    left: f32,
    right: f32,
    second: f32,
    /// Minimum of the slices before the previous two.
    lag_min: f32,
    prev1: f32,
    prev2: f32,
    at_zero: f32,
}

impl Track {
    const NEW: Self = Self {
        best: f32::INFINITY,
        best_k: 0,
        left: f32::NAN,
        right: f32::NAN,
        second: f32::INFINITY,
        lag_min: f32::INFINITY,
        prev1: f32::NAN,
        prev2: f32::NAN,
        at_zero: f32::NAN,
    };

    /// Takes the aggregated cost `q` of candidate `kk`.
    #[inline]
    fn push(&mut self, kk: usize, q: f32, zero_k: usize) {
        if kk >= 2 {
            self.lag_min = self.lag_min.min(self.prev2);
        }
        if kk >= 1 && self.best_k + 1 == kk {
            self.right = q;
        }
        if q < self.best {
            self.second = self.lag_min;
            self.best = q;
            self.best_k = kk;
            self.left = self.prev1;
            self.right = f32::NAN;
        } else if kk >= self.best_k + 2 {
            self.second = self.second.min(q);
        }
        if kk == zero_k {
            self.at_zero = q;
        }
        self.prev2 = self.prev1;
        self.prev1 = q;
    }

    /// The outputs (see [`plane_sweep`]) for candidates `cands` spaced `ds`, plus `base`.
    fn outputs(&self, cands: &[f32], ds: f32, base: f32) -> [f32; SWEEP_OUTPUTS] {
        let k = cands.len();
        let s0 = cands.get(self.best_k).copied().unwrap_or(f32::NAN);
        let curv = self.left - 2.0 * self.best + self.right;
        let shift = if self.best_k == 0 || self.best_k + 1 == k || curv.is_nan() || curv <= 0.0 {
            0.0
        } else {
            (0.5 * (self.left - self.right) / curv).clamp(-0.5, 0.5)
        };
        [
            base + s0 + shift * ds,
            self.best,
            if curv.is_finite() {
                curv / (ds * ds)
            } else {
                0.0
            },
            self.second,
            self.at_zero,
        ]
    }
}

/// `mask` grown by `r` px (square): where any pixel within `r` is set.
fn dilate(mask: &[u8], (h, w): (usize, usize), r: usize) -> Vec<u8> {
    let mut rows = vec![0u8; h * w];
    for (src, dst) in mask.chunks_exact(w).zip(rows.chunks_exact_mut(w)) {
        for (x, d) in dst.iter_mut().enumerate() {
            let lo = x.saturating_sub(r);
            let hi = (x + r + 1).min(w);
            *d = u8::from(src.get(lo..hi).is_some_and(|s| s.iter().any(|&v| v != 0)));
        }
    }
    let mut out = vec![0u8; h * w];
    for (y, dst) in out.chunks_exact_mut(w).enumerate() {
        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
            if let Some(src) = rows.get(yy * w..(yy + 1) * w) {
                for (d, s) in dst.iter_mut().zip(src) {
                    *d |= s;
                }
            }
        }
    }
    out
}

/// Plane sweep of `views` along their parallax vectors over `candidates`.
///
/// `views`: `n` images `h x w x c`, row-major, one after the other (NaN: no data);
/// `offsets[i]`: view `i`'s parallax vector (px per unit parallax; the reference
/// pixel `p` is seen at `p + o_i s`); `base`: none, or an `h x w` map added to every
/// candidate (`s = base(p) + c_k`; NaN: the pixel is skipped); `candidates`:
/// increasing, equally spaced parallaxes (at least 3); `subsets`: the view index lists
/// whose mean costs are swept (the reference is ignored in them); `active`: none, or
/// an `h x w` mask of the pixels wanted (others get NaN outputs; their costs are
/// computed only within the aggregation's reach of a wanted pixel, so wanted pixels
/// get the same values as without the mask). `out` holds `h x w x subsets x`
/// [`SWEEP_OUTPUTS`] values: per pixel and subset the parallax at the aggregated
/// cost's minimum (parabola through it and its neighbours; the end candidate itself at
/// either end of the range), that minimum cost, the parabola's curvature (cost per
/// unit parallax squared), the lowest cost at least two candidates from the minimum
/// (infinite if none) and the cost at the candidate nearest 0. Runs in lfcam's pool,
/// in bands of rows.
///
/// # Errors
/// [`Error::InvalidArgument`] naming the argument if sizes disagree, `reference` is
/// not a view, a subset names a view out of range or is empty, the candidates are not
/// finite, increasing and equally spaced, or a parameter is out of range.
#[allow(clippy::too_many_arguments, clippy::too_many_lines)]
pub fn plane_sweep(
    views: &[f32],
    (n, h, w, c): (usize, usize, usize, usize),
    reference: usize,
    offsets: &[[f64; 2]],
    base: Option<&[f32]>,
    candidates: &[f32],
    subsets: &[Vec<usize>],
    active: Option<&[u8]>,
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
    for (name, len) in [
        ("base", base.map(<[f32]>::len)),
        ("active", active.map(<[u8]>::len)),
    ] {
        if let Some(len) = len
            && len != h * w
        {
            return Err(Error::invalid_argument(
                name,
                format!("has {len} elements, expected {h} x {w}"),
            ));
        }
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
    let args = (views, (n, h, w, c), reference, offsets, base);
    match c {
        1 => sweep_bands::<3>(args, candidates, subsets, active, params, out),
        2 => sweep_bands::<4>(args, candidates, subsets, active, params, out),
        3 => sweep_bands::<5>(args, candidates, subsets, active, params, out),
        4 => sweep_bands::<6>(args, candidates, subsets, active, params, out),
        _ => Err(Error::invalid_argument(
            "views",
            format!("expected 1 to 4 channels, got {c}"),
        )),
    }
}

/// A task's buffers: box-filter scratch, per-view costs, subset planes, tracks.
type Scratch = (Vec<f32>, Vec<f32>, Vec<Vec<f32>>, Vec<Track>);

/// The views, their layout, the reference, the offsets and the base map.
type Views<'a> = (
    &'a [f32],
    (usize, usize, usize, usize),
    usize,
    &'a [[f64; 2]],
    Option<&'a [f32]>,
);

/// [`plane_sweep`] after its checks, for `F = c + 2` features per pixel.
#[allow(clippy::too_many_arguments, clippy::too_many_lines)]
fn sweep_bands<const F: usize>(
    (views, (n, h, w, c), reference, offsets, base): Views<'_>,
    candidates: &[f32],
    subsets: &[Vec<usize>],
    active: Option<&[u8]>,
    params: &SweepParams,
    out: &mut [f32],
) -> Result<()> {
    let plane = h * w * c;
    let n_sub = subsets.len();
    let row_len = w * n_sub * SWEEP_OUTPUTS;
    let ds = candidates.get(1).copied().unwrap_or(1.0) - candidates.first().copied().unwrap_or(0.0);
    let zero_k = candidates
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .map_or(0, |(i, _)| i);
    let r = params.radius;
    // The pixels whose costs are needed: the wanted ones and their windows' reach
    // (the guided filter's two box passes: 2 r).
    let need = active.map(|m| dilate(m, (h, w), 2 * r));
    // Every view's features once (colour, grey gradients), then the guide.
    let feats: Vec<Vec<f32>> = parallel::map_tasks(n, plane.saturating_mul(n * 4), |i| {
        Ok(views
            .get(i * plane..(i + 1) * plane)
            .map_or_else(Vec::new, |v| features(v, h, w, c)))
    })?;
    let guide: Vec<f32> = feats
        .get(reference)
        .map(|ft| {
            ft.chunks_exact(F)
                .map(|px| {
                    let g = px.iter().take(c).sum::<f32>() / c as f32;
                    if g.is_finite() { g } else { 0.0 }
                })
                .collect()
        })
        .unwrap_or_default();
    let scene = Scene {
        feats: &feats,
        reference,
        offsets,
        subsets,
        base,
        need: need.as_deref(),
        dims: (h, w),
    };
    // A band's tasks recompute a halo of 2 r rows on each side: bands of a sixth of the
    // image per thread (at least 8 r rows) keep that a small share of the work while
    // leaving tasks to balance.
    let threads = parallel::num_threads().max(1);
    let min_rows = (8 * r).max(h.div_ceil(3 * threads)).max(8);
    parallel::for_each_row_chunk_init(
        out,
        row_len,
        min_rows,
        || (Vec::new(), Vec::new(), Vec::new(), Vec::new()),
        |(tmp, per_view, planes, tracks): &mut Scratch, first, rows_out| {
            let last = first + rows_out.len() / row_len;
            if let Some(m) = active
                && !m
                    .get(first * w..last * w)
                    .is_some_and(|a| a.iter().any(|&v| v != 0))
            {
                rows_out.fill(f32::NAN);
                return Ok(());
            }
            let ya = first.saturating_sub(2 * r);
            let yb = (last + 2 * r).min(h);
            let nb = yb - ya;
            let mid = first.saturating_sub(r)..(last + r).min(h); // stage-1 rows
            let nm = mid.len();
            let ni = last - first;
            let g_band = guide.get(ya * w..yb * w).unwrap_or_default();
            let gg_band: Vec<f32> = g_band.iter().map(|v| v * v).collect();
            // The guide's window means and variances over the stage-1 rows.
            let mut mean_i = vec![0.0f32; nm * w];
            let mut var_i = vec![0.0f32; nm * w];
            box_mean(g_band, ya, nb, (h, w), r, mid.clone(), &mut mean_i, tmp);
            box_mean(&gg_band, ya, nb, (h, w), r, mid.clone(), &mut var_i, tmp);
            // 1 / (var(I) + eps), the same for every candidate.
            for (v, m) in var_i.iter_mut().zip(&mean_i) {
                *v = 1.0 / (*v - m * m + params.eps);
            }
            let guide_inner = guide.get(first * w..last * w).unwrap_or_default();
            planes.resize_with(n_sub, Vec::new);
            let m = ni * w;
            tracks.clear();
            tracks.resize(n_sub * m, Track::NEW);
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
                raw_costs::<F>(&scene, s, ya..yb, params, planes, per_view);
                for (j, p) in planes.iter().enumerate() {
                    if r == 0 {
                        agg.copy_from_slice(
                            p.get((first - ya) * w..(last - ya) * w).unwrap_or_default(),
                        );
                    } else {
                        // Guided filter: q = mean(a) I + mean(b), a = cov(I, p) / (var(I) + eps).
                        for ((o, pv), gv) in ip.iter_mut().zip(p).zip(g_band) {
                            *o = pv * gv;
                        }
                        box_mean(p, ya, nb, (h, w), r, mid.clone(), &mut mp, tmp);
                        box_mean(&ip, ya, nb, (h, w), r, mid.clone(), &mut mip, tmp);
                        for (((((ao, bo), mi), vi), mpv), mipv) in a
                            .iter_mut()
                            .zip(b.iter_mut())
                            .zip(&mean_i)
                            .zip(&var_i)
                            .zip(&mp)
                            .zip(&mip)
                        {
                            let av = (mipv - mi * mpv) * vi;
                            *ao = av;
                            *bo = mpv - av * mi;
                        }
                        let mid0 = mid.start;
                        box_mean(&a, mid0, nm, (h, w), r, first..last, &mut ma, tmp);
                        box_mean(&b, mid0, nm, (h, w), r, first..last, &mut mb, tmp);
                        for (((o, av), bv), gv) in agg.iter_mut().zip(&ma).zip(&mb).zip(guide_inner)
                        {
                            *o = av * gv + bv;
                        }
                    }
                    if let Some(tr) = tracks.get_mut(j * m..(j + 1) * m) {
                        for (t, &q) in tr.iter_mut().zip(&agg) {
                            t.push(kk, q, zero_k);
                        }
                    }
                }
            }
            for (t, px) in rows_out.chunks_exact_mut(n_sub * SWEEP_OUTPUTS).enumerate() {
                let at = first * w + t;
                let wanted = active.is_none_or(|m| m.get(at).is_some_and(|&v| v != 0));
                let b0 = base.map_or(0.0, |b| b.get(at).copied().unwrap_or(f32::NAN));
                for (j, o) in px.chunks_exact_mut(SWEEP_OUTPUTS).enumerate() {
                    match tracks.get(j * m + t) {
                        Some(tr) if wanted && b0.is_finite() => {
                            o.copy_from_slice(&tr.outputs(candidates, ds, b0));
                        }
                        _ => o.fill(f32::NAN),
                    }
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

    /// Views of `tex` at a constant parallax `s`: the reference pixel p is at p + o s in
    /// view i, so view_i(q) = tex(q - o s).
    fn shifted_views(
        tex: impl Fn(f32, f32) -> f32,
        offsets: &[[f64; 2]],
        s: f32,
        (h, w): (usize, usize),
    ) -> Vec<f32> {
        let mut views = Vec::new();
        for o in offsets {
            for y in 0..h {
                for x in 0..w {
                    views.push(tex(x as f32 - o[0] as f32 * s, y as f32 - o[1] as f32 * s));
                }
            }
        }
        views
    }

    /// A textured image shifted by a constant parallax: the sweep finds it.
    #[test]
    fn finds_a_constant_shift() {
        let (h, w, c) = (40, 48, 1);
        let tex = |x: f32, y: f32| {
            (0.37 * x).sin() * (0.23 * y).cos() + 0.5 * (0.11 * x + 0.19 * y).sin()
        };
        let offsets = [[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]];
        let s_true = 0.8f32;
        let views = shifted_views(tex, &offsets, s_true, (h, w));
        let candidates: Vec<f32> = (0..21).map(|k| -1.0 + 0.1 * k as f32).collect();
        let subsets = vec![vec![1, 2, 3, 4], vec![1, 3]];
        let params = SweepParams {
            trunc_colour: 1.0,
            trunc_gradient: 1.0,
            alpha: 0.5,
            radius: 2,
            eps: 1e-4,
            cubic: false,
        };
        let mut out = vec![0.0f32; h * w * 2 * SWEEP_OUTPUTS];
        plane_sweep(
            &views,
            (5, h, w, c),
            0,
            &offsets,
            None,
            &candidates,
            &subsets,
            None,
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

    /// A base map moves the candidates; a mask leaves the wanted pixels' values as
    /// they are; bicubic samples find the shift too.
    #[test]
    fn base_mask_and_cubic() {
        let (h, w) = (36, 44);
        let tex = |x: f32, y: f32| (0.41 * x).sin() * (0.29 * y).cos() + 0.4 * (0.13 * x).cos();
        let offsets = [[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]];
        let s_true = 0.6f32;
        let views = shifted_views(tex, &offsets, s_true, (h, w));
        let subsets = vec![vec![1, 2, 3], vec![1, 3]];
        let mut params = SweepParams {
            trunc_colour: 1.0,
            trunc_gradient: 1.0,
            alpha: 0.5,
            radius: 2,
            eps: 1e-4,
            cubic: false,
        };
        let run = |base: Option<&[f32]>, cands: &[f32], active: Option<&[u8]>, p: &SweepParams| {
            let mut out = vec![0.0f32; h * w * 2 * SWEEP_OUTPUTS];
            plane_sweep(
                &views,
                (4, h, w, 1),
                0,
                &offsets,
                base,
                cands,
                &subsets,
                active,
                p,
                &mut out,
            )
            .unwrap();
            out
        };
        let abs: Vec<f32> = (0..9).map(|k| 0.2 + 0.1 * k as f32).collect();
        let rel: Vec<f32> = abs.iter().map(|v| v - 0.5).collect();
        let base = vec![0.5f32; h * w];
        let a = run(None, &abs, None, &params);
        let b = run(Some(&base), &rel, None, &params);
        let mut mask = vec![0u8; h * w];
        for y in 10..14 {
            for x in 5..30 {
                mask[y * w + x] = 1;
            }
        }
        let m = run(Some(&base), &rel, Some(&mask), &params);
        for i in 0..h * w {
            for o in 0..2 * SWEEP_OUTPUTS {
                let (va, vb, vm) = (
                    a[i * 2 * SWEEP_OUTPUTS + o],
                    b[i * 2 * SWEEP_OUTPUTS + o],
                    m[i * 2 * SWEEP_OUTPUTS + o],
                );
                // The last output is the cost at the candidate nearest 0: 0.2 vs the base.
                if o % SWEEP_OUTPUTS != SWEEP_OUTPUTS - 1 {
                    assert!((va - vb).abs() <= 1e-5, "{i} {o}: {va} {vb}");
                }
                if mask[i] == 1 {
                    assert!(
                        vm == vb || (vm.is_nan() && vb.is_nan()),
                        "{i} {o}: {vm} {vb}"
                    );
                } else {
                    assert!(vm.is_nan());
                }
            }
            // The base's own cost is the cost at candidate 0.5 (index 3).
            let at_base = b[i * 2 * SWEEP_OUTPUTS + SWEEP_OUTPUTS - 1];
            assert!(at_base >= b[i * 2 * SWEEP_OUTPUTS + 1]);
        }
        params.cubic = true;
        let c = run(Some(&base), &rel, None, &params);
        for y in 4..h - 4 {
            for x in 4..w - 4 {
                let s = c[(y * w + x) * 2 * SWEEP_OUTPUTS];
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
            cubic: false,
        };
        let mut out = vec![0.0f32; 4 * 4 * SWEEP_OUTPUTS];
        let call = |cands: &[f32], subs: &[Vec<usize>], out: &mut [f32]| {
            plane_sweep(
                &views,
                (2, 4, 4, 1),
                0,
                &offsets,
                None,
                cands,
                subs,
                None,
                &p,
                out,
            )
        };
        assert!(call(&[0.0, 1.0], &[vec![1]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 3.0], &[vec![1]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![0]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![2]], &mut out).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![1]], &mut out[1..]).is_err());
        assert!(call(&[0.0, 1.0, 2.0], &[vec![1]], &mut out).is_ok());
    }
}
