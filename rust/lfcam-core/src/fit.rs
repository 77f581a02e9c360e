//! The calibration's depth model with board poses, by nonlinear least squares
//! (docs/design.md, "Parallax fit"): the lenslet offsets `o_i`, the lenslet-centre depth
//! `Z_c`, and each calibration board's tilt, fitted jointly to the board's parallax.
//!
//! Geometry, in units of the reference distance's rectified frame: lateral positions in
//! rectified px, depth as `w = (Z - Z_c) / (Z_b - Z_c)` (lenslet centres at `w = 0`,
//! the reference board at `w = 1` where it crosses the reference lenslet's axis at the
//! frame position `c`). Lenslet `i`'s object-space centre is at `(c + o_i, 0)`. A board
//! is the plane `w = w_k + g_k . (x - c)` with `w_k = (Z_k - Z_c) / (Z_b - Z_c)` and the
//! gradient `g_k` (per px; its tilt is `atan(g_k (Z_b - Z_c) / pitch)`). The rectified
//! frame is the reference board (gradient `g_b`) itself, so a point of board `k` seen by
//! the reference view at `p` appears in view `i` where the ray from lenslet `i`'s centre
//! crosses the reference board. A lateral drift of a board moves it within its own
//! plane and changes no parallax.
//!
//! Solved by Levenberg-Marquardt on the normal equations (faer's Cholesky), with a
//! numerical Jacobian (central differences); the standard errors come from the inverse
//! of the normal matrix at the solution. With [`TiltProblem::robust`], the samples are
//! reweighted by a Cauchy loss (iteratively reweighted least squares around the
//! Levenberg-Marquardt solve): a cell whose flow locked onto a wrong match pulls the
//! least-squares fit of the gradients, and through them of `o_i` and `Z_c`.

use faer::linalg::solvers::{DenseSolveCore, Solve};
use faer::{Mat, Side};

use crate::error::{Error, Result};

/// Lateral positions are divided by this many px inside the fit, so the gradient
/// parameters are of the order of the relative depth change across the frame.
const LENGTH_PX: f64 = 1000.0;
/// Levenberg-Marquardt iterations (at most) and the relative cost change that ends them.
const MAX_ITERATIONS: usize = 100;
const COST_TOLERANCE: f64 = 1e-13;
/// Robust reweighting: the Cauchy loss's scale is this many times the median miss of the
/// samples (about 3 standard deviations of one component for Gaussian noise); at most
/// MAX_REWEIGHTS rounds, ending when no weight changes by more than WEIGHT_TOLERANCE.
const CAUCHY_SCALE: f64 = 3.5;
const MAX_REWEIGHTS: usize = 10;
const WEIGHT_TOLERANCE: f64 = 1e-3;

/// The parallax measurements: sample `j` is view `view[j]`'s median shift `parallax[j]`
/// (rectified px) of board `board[j]` over a patch of the reference view centred at
/// `pos[j]`, weighted by `weight[j]` (inverse variance).
#[derive(Debug, Clone, Copy)]
pub struct ParallaxSamples<'a> {
    /// Board index per sample, into [`TiltProblem::distances`].
    pub board: &'a [usize],
    /// View index per sample (not the reference view).
    pub view: &'a [usize],
    /// Position in the reference view's rectified frame, `[x, y]` px.
    pub pos: &'a [[f64; 2]],
    /// Measured shift from the reference view to the view, `[x, y]` px.
    pub parallax: &'a [[f64; 2]],
    /// Weight (>= 0, finite).
    pub weight: &'a [f64],
}

/// What is known before the fit.
#[derive(Debug, Clone)]
pub struct TiltProblem {
    /// Number of views `N` and the reference view's index.
    pub n_views: usize,
    /// The reference view.
    pub reference: usize,
    /// The reference board distance `Z_b`, m.
    pub z_b: f64,
    /// The other boards' distances `Z_k`, m (none equal to `Z_b`).
    pub distances: Vec<f64>,
    /// `c`: where the reference lenslet's axis crosses the rectified frame, px.
    pub centre: [f64; 2],
    /// Optional extra equations `d_i = o_i Z_b / Z_c` (the image-circle centres in the
    /// rectified frame, relative to the reference view's), with their weight.
    pub centres: Option<(Vec<[f64; 2]>, f64)>,
    /// Standard deviation of a zero-mean prior on each gradient component, per px (keeps
    /// a gradient that the views cannot see, e.g. across a one-row grid, at zero).
    pub gradient_prior: f64,
    /// Fit the reference board's own gradient too. It shows only in a second-order
    /// effect (each view's parallax turning about the frame by `g_b . o_i`), so with
    /// real flow noise it is poorly determined; without it the other boards' gradients
    /// are relative to the reference board's.
    pub fit_reference: bool,
    /// Reweight the samples by a Cauchy loss (scale from their median miss) instead of
    /// plain least squares.
    pub robust: bool,
}

/// The solution and its uncertainty.
#[derive(Debug, Clone)]
pub struct TiltFit {
    /// `o_i`, rectified px (zero for the reference view).
    pub offsets: Vec<[f64; 2]>,
    /// Standard errors of `offsets`.
    pub offsets_se: Vec<[f64; 2]>,
    /// `Z_c`, m, and its standard error.
    pub z_c: f64,
    /// Standard error of `z_c`.
    pub z_c_se: f64,
    /// The reference board's gradient (per px) and its standard error.
    pub gradient_ref: [f64; 2],
    /// Standard error of `gradient_ref`.
    pub gradient_ref_se: [f64; 2],
    /// Each other board's gradient (per px), in the order of `distances`.
    pub gradients: Vec<[f64; 2]>,
    /// Standard errors of `gradients`.
    pub gradients_se: Vec<[f64; 2]>,
    /// Weighted RMS residual per board (px), in the order of `distances` (weights
    /// including the robust ones).
    pub board_rms: Vec<f64>,
    /// Share of each board's samples the robust loss weighs at less than half (they miss
    /// the model by more than the Cauchy scale); zero without `robust`.
    pub board_downweighted: Vec<f64>,
    /// Weighted RMS residual of all samples (px).
    pub rms: f64,
    /// Levenberg-Marquardt iterations taken, over all reweighting rounds.
    pub iterations: usize,
}

/// Where a point of board `k` seen by the reference view at `p` appears in the view
/// whose centre is at offset `o` (all in the fit's scaled units): returns its shift.
#[allow(clippy::too_many_arguments)]
fn shift(p: [f64; 2], o: [f64; 2], w_k: f64, g_k: [f64; 2], g_b: [f64; 2]) -> [f64; 2] {
    // p is relative to c. The reference board's depth there, and the ray's direction.
    let w_b = 1.0 + g_b[0] * p[0] + g_b[1] * p[1];
    let d = [p[0] / w_b, p[1] / w_b];
    // The ray from the reference centre (origin) meets board k at depth w.
    let w = w_k / (1.0 - (g_k[0] * d[0] + g_k[1] * d[1]));
    let q = [w * d[0], w * d[1]];
    // The ray from lenslet i's centre (o, 0) through q meets the reference board.
    let e = [(q[0] - o[0]) / w, (q[1] - o[1]) / w];
    let w2 = (1.0 + g_b[0] * o[0] + g_b[1] * o[1]) / (1.0 - (g_b[0] * e[0] + g_b[1] * e[1]));
    [o[0] + e[0] * w2 - p[0], o[1] + e[1] * w2 - p[1]]
}

struct Layout {
    n_views: usize,
    reference: usize,
    n_boards: usize,
}

impl Layout {
    fn n_params(&self) -> usize {
        2 * (self.n_views - 1) + 1 + 2 + 2 * self.n_boards
    }
    fn offset_index(&self, view: usize) -> Option<usize> {
        match view.cmp(&self.reference) {
            std::cmp::Ordering::Less => Some(2 * view),
            std::cmp::Ordering::Equal => None,
            std::cmp::Ordering::Greater => Some(2 * (view - 1)),
        }
    }
    fn z_c_index(&self) -> usize {
        2 * (self.n_views - 1)
    }
    fn g_ref_index(&self) -> usize {
        self.z_c_index() + 1
    }
    fn g_index(&self, board: usize) -> usize {
        self.g_ref_index() + 2 + 2 * board
    }
    fn offset(&self, theta: &[f64], view: usize) -> [f64; 2] {
        self.offset_index(view)
            .and_then(|k| Some([*theta.get(k)?, *theta.get(k + 1)?]))
            .unwrap_or([0.0, 0.0])
    }
    fn pair(theta: &[f64], k: usize) -> [f64; 2] {
        [
            theta.get(k).copied().unwrap_or(0.0),
            theta.get(k + 1).copied().unwrap_or(0.0),
        ]
    }
}

/// Sample `j`'s miss `measured - model` (px), or None past the end of the samples.
fn sample_miss(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    lay: &Layout,
    theta: &[f64],
    j: usize,
) -> Option<[f64; 2]> {
    let (&k, &i, p, m) = (
        data.board.get(j)?,
        data.view.get(j)?,
        data.pos.get(j)?,
        data.parallax.get(j)?,
    );
    let z_c = theta.get(lay.z_c_index()).copied().unwrap_or(f64::NAN);
    let h = prob.z_b - z_c;
    // Unfitted, the reference board is the frame's fronto-parallel plane (the gauge).
    let g_b = if prob.fit_reference {
        Layout::pair(theta, lay.g_ref_index())
    } else {
        [0.0; 2]
    };
    let s = 1.0 / LENGTH_PX;
    let z_k = prob.distances.get(k).copied().unwrap_or(f64::NAN);
    let g_k = Layout::pair(theta, lay.g_index(k));
    let o = lay.offset(theta, i);
    let rel = [(p[0] - prob.centre[0]) * s, (p[1] - prob.centre[1]) * s];
    let model = shift(rel, [o[0] * s, o[1] * s], (z_k - z_c) / h, g_k, g_b);
    Some([m[0] - model[0] * LENGTH_PX, m[1] - model[1] * LENGTH_PX])
}

/// Residuals `sqrt(weight robust) (measured - model)` of every equation, in a fixed
/// order: samples (x, y), then the centre equations, then the gradient priors.
fn residuals(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    lay: &Layout,
    theta: &[f64],
    robust: &[f64],
    out: &mut Vec<f64>,
) {
    out.clear();
    for j in 0..data.view.len() {
        let (Some(miss), Some(&wt)) = (sample_miss(prob, data, lay, theta, j), data.weight.get(j))
        else {
            break;
        };
        let sw = (wt * robust.get(j).copied().unwrap_or(1.0)).sqrt();
        out.push(sw * miss[0]);
        out.push(sw * miss[1]);
    }
    if let Some((d, wt)) = &prob.centres {
        let z_c = theta.get(lay.z_c_index()).copied().unwrap_or(f64::NAN);
        let sw = wt.sqrt();
        let r = prob.z_b / z_c;
        for (i, di) in d.iter().enumerate() {
            let o = lay.offset(theta, i);
            out.push(sw * (di[0] - o[0] * r));
            out.push(sw * (di[1] - o[1] * r));
        }
    }
    // Gradient priors, in the fit's units (per LENGTH_PX px).
    let inv = 1.0 / (prob.gradient_prior * LENGTH_PX);
    for k in lay.g_ref_index()..lay.n_params() {
        out.push(theta.get(k).copied().unwrap_or(0.0) * inv);
    }
}

/// Cauchy weights of the samples at `theta`, their scale CAUCHY_SCALE times the median
/// miss of the samples with a positive weight (all 1 when that median is 0: exact data).
fn cauchy_weights(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    lay: &Layout,
    theta: &[f64],
) -> Vec<f64> {
    let miss: Vec<f64> = (0..data.view.len())
        .map(|j| sample_miss(prob, data, lay, theta, j).map_or(0.0, |m| m[0].hypot(m[1])))
        .collect();
    let mut used: Vec<f64> = miss
        .iter()
        .zip(data.weight)
        .filter(|&(m, &w)| w > 0.0 && m.is_finite())
        .map(|(&m, _)| m)
        .collect();
    if used.is_empty() {
        return vec![1.0; miss.len()];
    }
    let mid = used.len() / 2;
    let median = *used.select_nth_unstable_by(mid, f64::total_cmp).1;
    let scale = CAUCHY_SCALE * median;
    if !(scale > 0.0 && scale.is_finite()) {
        return vec![1.0; miss.len()];
    }
    miss.iter()
        .map(|m| 1.0 / (1.0 + (m / scale) * (m / scale)))
        .collect()
}

fn cost(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

fn check(prob: &TiltProblem, data: &ParallaxSamples<'_>, start: &[[f64; 2]]) -> Result<()> {
    let m = data.view.len();
    for (name, len) in [
        ("board", data.board.len()),
        ("pos", data.pos.len()),
        ("parallax", data.parallax.len()),
        ("weight", data.weight.len()),
    ] {
        if len != m {
            return Err(Error::invalid_argument(
                name,
                format!("has {len} samples, view has {m}"),
            ));
        }
    }
    if prob.n_views < 2 || prob.reference >= prob.n_views {
        return Err(Error::invalid_argument(
            "reference",
            format!(
                "view {} of {} views (need >= 2 views)",
                prob.reference, prob.n_views
            ),
        ));
    }
    if start.len() != prob.n_views {
        return Err(Error::invalid_argument(
            "offsets",
            format!("has {} views, expected {}", start.len(), prob.n_views),
        ));
    }
    if !(prob.z_b.is_finite() && prob.z_b > 0.0) {
        return Err(Error::invalid_argument(
            "z_b",
            "must be a finite distance > 0",
        ));
    }
    if !(prob.gradient_prior.is_finite() && prob.gradient_prior > 0.0) {
        return Err(Error::invalid_argument(
            "gradient_prior",
            "must be finite and > 0",
        ));
    }
    for (k, &z) in prob.distances.iter().enumerate() {
        if !(z.is_finite() && z > 0.0) || z == prob.z_b {
            return Err(Error::invalid_item(
                "distances",
                k,
                format!("{z} is not a finite distance > 0 other than z_b"),
            ));
        }
    }
    if let Some((d, wt)) = &prob.centres
        && (d.len() != prob.n_views || !(wt.is_finite() && *wt >= 0.0))
    {
        return Err(Error::invalid_argument(
            "centres",
            "need one finite centre per view and a weight >= 0",
        ));
    }
    for j in 0..m {
        let ok = data.board.get(j).is_some_and(|&k| k < prob.distances.len())
            && data
                .view
                .get(j)
                .is_some_and(|&i| i < prob.n_views && i != prob.reference)
            && data
                .pos
                .get(j)
                .is_some_and(|p| p.iter().all(|v| v.is_finite()))
            && data
                .parallax
                .get(j)
                .is_some_and(|p| p.iter().all(|v| v.is_finite()))
            && data
                .weight
                .get(j)
                .is_some_and(|w| w.is_finite() && *w >= 0.0);
        if !ok {
            return Err(Error::invalid_item(
                "samples",
                j,
                "needs a board and a non-reference view in range, finite values and weight >= 0",
            ));
        }
    }
    Ok(())
}

/// Fits `o_i`, `Z_c` and the boards' gradients to the parallax samples, starting from
/// `start` (`o_i` from a fronto-parallel fit) and `z_c0`.
///
/// # Errors
/// - [`Error::InvalidArgument`] / [`Error::InvalidItem`] for inconsistent sizes or
///   non-finite values;
/// - [`Error::Numerical`] if the normal equations are singular or the fit leaves the
///   region where the model is defined (`0 < Z_c < min(Z_k, Z_b)`).
pub fn fit_board_tilts(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    start: &[[f64; 2]],
    z_c0: f64,
) -> Result<TiltFit> {
    check(prob, data, start)?;
    let z_max = prob.distances.iter().copied().fold(prob.z_b, f64::min);
    if !(z_c0.is_finite() && z_c0 > 0.0 && z_c0 < z_max) {
        return Err(Error::invalid_argument(
            "z_c",
            format!("start {z_c0} is not between 0 and the nearest board, {z_max} m"),
        ));
    }
    let lay = Layout {
        n_views: prob.n_views,
        reference: prob.reference,
        n_boards: prob.distances.len(),
    };
    let n = lay.n_params();
    let mut theta = vec![0.0; n];
    for (i, o) in start.iter().enumerate() {
        if let Some(k) = lay.offset_index(i)
            && let Some(t) = theta.get_mut(k..k + 2)
        {
            t.copy_from_slice(o);
        }
    }
    if let Some(t) = theta.get_mut(lay.z_c_index()) {
        *t = z_c0;
    }
    let mut robust = vec![1.0; data.view.len()];
    let mut iterations = levenberg_marquardt(prob, data, &lay, &robust, z_max, &mut theta);
    if prob.robust {
        for _ in 0..MAX_REWEIGHTS {
            let next = cauchy_weights(prob, data, &lay, &theta);
            let change = next
                .iter()
                .zip(&robust)
                .fold(0.0_f64, |acc, (a, b)| acc.max((a - b).abs()));
            robust = next;
            iterations += levenberg_marquardt(prob, data, &lay, &robust, z_max, &mut theta);
            if change <= WEIGHT_TOLERANCE {
                break;
            }
        }
    }

    let mut r = Vec::new();
    residuals(prob, data, &lay, &theta, &robust, &mut r);
    let m_eq = r.len();
    let c = cost(&r);
    let mut jac = Mat::<f64>::zeros(m_eq, n);
    let mut rp = Vec::new();
    let mut rm = Vec::new();
    jacobian(
        prob, data, &lay, &theta, &robust, &mut jac, &mut rp, &mut rm,
    );
    let normal = jac.transpose() * &jac;
    let cov = normal
        .llt(Side::Lower)
        .map_err(|_| {
            Error::Numerical(
                "the parallax fit's normal equations are singular (too few views or boards)".into(),
            )
        })?
        .inverse();
    let dof = (m_eq as f64 - n as f64).max(1.0);
    let sigma2 = c / dof;
    let se = |k: usize| (sigma2 * cov[(k, k)]).max(0.0).sqrt();

    let mut offsets = vec![[0.0; 2]; prob.n_views];
    let mut offsets_se = vec![[0.0; 2]; prob.n_views];
    for i in 0..prob.n_views {
        if let (Some(k), Some(o), Some(s)) = (
            lay.offset_index(i),
            offsets.get_mut(i),
            offsets_se.get_mut(i),
        ) {
            *o = Layout::pair(&theta, k);
            *s = [se(k), se(k + 1)];
        }
    }
    let g = |k: usize| {
        let p = Layout::pair(&theta, k);
        [p[0] / LENGTH_PX, p[1] / LENGTH_PX]
    };
    let g_se = |k: usize| [se(k) / LENGTH_PX, se(k + 1) / LENGTH_PX];
    let n_samples = data.view.len();
    let mut acc = vec![(0.0, 0.0); prob.distances.len()];
    let mut low = vec![(0usize, 0usize); prob.distances.len()];
    for j in 0..n_samples {
        if let (Some(&k), Some(&w), Some(&rw), Some(rx), Some(ry)) = (
            data.board.get(j),
            data.weight.get(j),
            robust.get(j),
            r.get(2 * j),
            r.get(2 * j + 1),
        ) && let (Some(a), Some(l)) = (acc.get_mut(k), low.get_mut(k))
        {
            a.0 += rx * rx + ry * ry;
            a.1 += 2.0 * w * rw;
            l.0 += usize::from(rw < 0.5);
            l.1 += 1;
        }
    }
    let total: (f64, f64) = acc.iter().fold((0.0, 0.0), |s, a| (s.0 + a.0, s.1 + a.1));
    let rms_of = |a: (f64, f64)| {
        if a.1 > 0.0 {
            (a.0 / a.1).sqrt()
        } else {
            f64::NAN
        }
    };
    Ok(TiltFit {
        offsets,
        offsets_se,
        z_c: theta.get(lay.z_c_index()).copied().unwrap_or(f64::NAN),
        z_c_se: se(lay.z_c_index()),
        gradient_ref: g(lay.g_ref_index()),
        gradient_ref_se: g_se(lay.g_ref_index()),
        gradients: (0..lay.n_boards).map(|k| g(lay.g_index(k))).collect(),
        gradients_se: (0..lay.n_boards).map(|k| g_se(lay.g_index(k))).collect(),
        board_rms: acc.iter().map(|&a| rms_of(a)).collect(),
        board_downweighted: low
            .iter()
            .map(|&(d, m)| if m > 0 { d as f64 / m as f64 } else { 0.0 })
            .collect(),
        rms: rms_of(total),
        iterations,
    })
}

/// Levenberg-Marquardt from `theta` (updated in place) with the samples' robust weights
/// fixed; `Z_c` is kept inside `(0, z_max)`. Returns the iterations taken.
fn levenberg_marquardt(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    lay: &Layout,
    robust: &[f64],
    z_max: f64,
    theta: &mut Vec<f64>,
) -> usize {
    let n = lay.n_params();
    let valid = |th: &[f64]| {
        th.get(lay.z_c_index())
            .is_some_and(|&z| z > 0.0 && z < z_max)
    };
    let mut r = Vec::new();
    residuals(prob, data, lay, theta, robust, &mut r);
    let m_eq = r.len();
    let mut c = cost(&r);
    let mut lambda = 1e-3;
    let mut jac = Mat::<f64>::zeros(m_eq, n);
    let mut rp = Vec::new();
    let mut rm = Vec::new();
    let mut iterations = 0;
    for it in 0..MAX_ITERATIONS {
        iterations = it + 1;
        jacobian(prob, data, lay, theta, robust, &mut jac, &mut rp, &mut rm);
        // Normal equations J^T J d = -J^T r (r = measured - model, so J is of -model).
        let normal = jac.transpose() * &jac;
        let rhs = Mat::<f64>::from_fn(n, 1, |a, _| {
            -(0..m_eq)
                .map(|e| jac[(e, a)] * r.get(e).copied().unwrap_or(0.0))
                .sum::<f64>()
        });
        let mut improved = false;
        for _ in 0..20 {
            let mut damped = normal.clone();
            for a in 0..n {
                damped[(a, a)] += lambda * normal[(a, a)].max(1e-12);
            }
            let Ok(llt) = damped.llt(Side::Lower) else {
                lambda *= 10.0;
                continue;
            };
            let step = llt.solve(&rhs);
            let trial: Vec<f64> = theta
                .iter()
                .enumerate()
                .map(|(a, t)| t + step[(a, 0)])
                .collect();
            if !valid(&trial) {
                lambda *= 10.0;
                continue;
            }
            residuals(prob, data, lay, &trial, robust, &mut rp);
            let ct = cost(&rp);
            if ct.is_finite() && ct <= c {
                let done = (c - ct) <= COST_TOLERANCE * c.max(f64::MIN_POSITIVE);
                *theta = trial;
                std::mem::swap(&mut r, &mut rp);
                c = ct;
                lambda = (lambda / 3.0).max(1e-12);
                improved = !done;
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
    }
    iterations
}

/// Central-difference Jacobian of the residuals.
#[allow(clippy::too_many_arguments)]
fn jacobian(
    prob: &TiltProblem,
    data: &ParallaxSamples<'_>,
    lay: &Layout,
    theta: &[f64],
    robust: &[f64],
    jac: &mut Mat<f64>,
    rp: &mut Vec<f64>,
    rm: &mut Vec<f64>,
) {
    let mut t = theta.to_vec();
    for a in 0..theta.len() {
        let base = theta.get(a).copied().unwrap_or(0.0);
        let step = 1e-6 * base.abs().max(if a == lay.z_c_index() { 0.1 } else { 1.0 });
        if let Some(v) = t.get_mut(a) {
            *v = base + step;
        }
        residuals(prob, data, lay, &t, robust, rp);
        if let Some(v) = t.get_mut(a) {
            *v = base - step;
        }
        residuals(prob, data, lay, &t, robust, rm);
        if let Some(v) = t.get_mut(a) {
            *v = base;
        }
        for (e, (p, m)) in rp.iter().zip(rm.iter()).enumerate() {
            jac[(e, a)] = (p - m) / (2.0 * step);
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing, clippy::unwrap_used)]
mod tests {
    use super::*;

    /// Samples of an exactly known camera: 3 x 4 views, boards at 0.7 and 1.5 m with
    /// tilts, the reference board at 1 m tilted too.
    fn synthetic(g_b: [f64; 2], g: &[[f64; 2]]) -> (TiltProblem, Vec<[f64; 2]>, f64, Samples) {
        let (rows, cols, reference) = (3usize, 4usize, 5usize);
        let mut offsets = Vec::new();
        for r in 0..rows {
            for c in 0..cols {
                let (dr, dc) = (r as f64 - 1.0, c as f64 - 1.0);
                offsets.push([31.0 * dc + 0.7 * dr, 29.5 * dr - 0.4 * dc]);
            }
        }
        let z_c = 0.1833;
        let prob = TiltProblem {
            n_views: rows * cols,
            reference,
            z_b: 1.0,
            distances: vec![0.7, 1.5],
            centre: [310.0, 228.0],
            centres: None,
            gradient_prior: 1e-3,
            fit_reference: true,
            robust: false,
        };
        let mut s = Samples::default();
        let l = LENGTH_PX;
        for (k, &z_k) in prob.distances.iter().enumerate() {
            for (i, o) in offsets.iter().enumerate() {
                if i == reference {
                    continue;
                }
                for y in (20..440).step_by(40) {
                    for x in (20..600).step_by(40) {
                        let p = [x as f64, y as f64];
                        let rel = [(p[0] - prob.centre[0]) / l, (p[1] - prob.centre[1]) / l];
                        let w_k = (z_k - z_c) / (prob.z_b - z_c);
                        let gk = [g[k][0] * l, g[k][1] * l];
                        let gb = [g_b[0] * l, g_b[1] * l];
                        let d = shift(rel, [o[0] / l, o[1] / l], w_k, gk, gb);
                        s.board.push(k);
                        s.view.push(i);
                        s.pos.push(p);
                        s.parallax.push([d[0] * l, d[1] * l]);
                        s.weight.push(1.0);
                    }
                }
            }
        }
        (prob, offsets, z_c, s)
    }

    #[derive(Default)]
    struct Samples {
        board: Vec<usize>,
        view: Vec<usize>,
        pos: Vec<[f64; 2]>,
        parallax: Vec<[f64; 2]>,
        weight: Vec<f64>,
    }

    impl Samples {
        fn view(&self) -> ParallaxSamples<'_> {
            ParallaxSamples {
                board: &self.board,
                view: &self.view,
                pos: &self.pos,
                parallax: &self.parallax,
                weight: &self.weight,
            }
        }
    }

    #[test]
    fn fronto_parallel_shift_is_o_times_s() {
        let d = shift([0.2, -0.1], [0.03, 0.01], 0.5, [0.0; 2], [0.0; 2]);
        // s = 1 - 1 / w_k = -1
        assert!((d[0] + 0.03).abs() < 1e-15 && (d[1] + 0.01).abs() < 1e-15);
    }

    #[test]
    fn recovers_offsets_z_c_and_tilts() {
        // 1e-5 per px: about 2 degrees for a 0.25 mm pitch 0.8 m from the lenslets.
        let g_b = [1.2e-5, -0.6e-5];
        let g = [[-0.8e-5, 1.1e-5], [0.5e-5, 0.9e-5]];
        let (prob, offsets, z_c, s) = synthetic(g_b, &g);
        let mut start = offsets.clone();
        for o in &mut start {
            o[0] *= 1.02;
            o[1] *= 0.98;
        }
        let fit = fit_board_tilts(&prob, &s.view(), &start, 0.2).unwrap();
        assert!((fit.z_c - z_c).abs() < 1e-7, "{}", fit.z_c);
        for (a, b) in fit.offsets.iter().zip(&offsets) {
            assert!((a[0] - b[0]).abs() < 1e-5 && (a[1] - b[1]).abs() < 1e-5);
        }
        // Within 0.05%: the (wide) prior pulls the gradients towards zero a little.
        let close =
            |a: [f64; 2], b: [f64; 2]| (0..2).all(|c| (a[c] - b[c]).abs() < 5e-4 * b[c].abs());
        assert!(close(fit.gradient_ref, g_b));
        assert!(fit.gradients.iter().zip(&g).all(|(a, b)| close(*a, *b)));
        assert!(fit.rms < 1e-4, "{}", fit.rms);
    }

    #[test]
    fn without_the_reference_gradient_a_fronto_parallel_reference_is_exact() {
        let g = [[-0.8e-5, 1.1e-5], [0.5e-5, 0.9e-5]];
        let (mut prob, offsets, z_c, s) = synthetic([0.0; 2], &g);
        prob.fit_reference = false;
        let fit = fit_board_tilts(&prob, &s.view(), &offsets, 0.2).unwrap();
        assert_eq!(fit.gradient_ref, [0.0; 2]);
        let close =
            |a: [f64; 2], b: [f64; 2]| (0..2).all(|c| (a[c] - b[c]).abs() < 5e-4 * b[c].abs());
        assert!(fit.gradients.iter().zip(&g).all(|(a, b)| close(*a, *b)));
        for (a, b) in fit.offsets.iter().zip(&offsets) {
            assert!((a[0] - b[0]).abs() < 1e-5 && (a[1] - b[1]).abs() < 1e-5);
        }
        assert!((fit.z_c - z_c).abs() < 1e-7, "{}", fit.z_c);
    }

    #[test]
    fn robust_fit_ignores_cells_that_locked_onto_wrong_matches() {
        let g = [[-0.8e-5, 1.1e-5], [0.5e-5, 0.9e-5]];
        let (mut prob, offsets, z_c, mut s) = synthetic([0.0; 2], &g);
        prob.fit_reference = false;
        // Flow noise of up to 0.03 px (a fixed pseudo-random sequence), and one cell in
        // 25, all at one side of the frame, off by 1-3 px: it tilts a least-squares fit.
        let mut state = 12345_u64;
        for p in &mut s.parallax {
            for v in p.iter_mut() {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                *v += ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.06;
            }
        }
        let mut bad = 0;
        for j in (0..s.view.len()).step_by(25) {
            if s.pos[j][0] > 400.0 {
                s.parallax[j][0] += 1.0 + (j % 5) as f64 * 0.5;
                bad += 1;
            }
        }
        assert!(bad > 10);
        let plain = fit_board_tilts(&prob, &s.view(), &offsets, 0.2).unwrap();
        prob.robust = true;
        let fit = fit_board_tilts(&prob, &s.view(), &offsets, 0.2).unwrap();
        let worst = |f: &TiltFit| {
            f.offsets
                .iter()
                .zip(&offsets)
                .map(|(a, b)| (a[0] - b[0]).hypot(a[1] - b[1]) / b[0].hypot(b[1]).max(1e-9))
                .fold(0.0_f64, f64::max)
        };
        assert!(worst(&plain) > 5e-4, "{}", worst(&plain));
        assert!(worst(&fit) < 3e-4, "{}", worst(&fit));
        assert!((plain.z_c - z_c).abs() > 2e-4, "{}", plain.z_c);
        assert!((fit.z_c - z_c).abs() < 5e-5, "{}", fit.z_c);
        let close =
            |a: [f64; 2], b: [f64; 2]| (0..2).all(|c| (a[c] - b[c]).abs() < 0.1 * b[c].abs());
        assert!(fit.gradients.iter().zip(&g).all(|(a, b)| close(*a, *b)));
        let share = bad as f64 / s.view.len() as f64;
        assert!(
            fit.board_downweighted
                .iter()
                .all(|&d| d > 0.5 * share && d < 0.1),
            "{:?} {share}",
            fit.board_downweighted
        );
    }

    #[test]
    fn bad_sizes_are_argument_errors() {
        let (prob, offsets, _, mut s) = synthetic([0.0; 2], &[[0.0; 2]; 2]);
        s.weight.pop();
        let e = fit_board_tilts(&prob, &s.view(), &offsets, 0.2).unwrap_err();
        assert!(matches!(e, Error::InvalidArgument { .. }), "{e}");
        let (prob, offsets, _, s) = synthetic([0.0; 2], &[[0.0; 2]; 2]);
        let e = fit_board_tilts(&prob, &s.view(), &offsets, 0.9).unwrap_err();
        assert!(e.to_string().starts_with("z_c:"), "{e}");
    }
}
