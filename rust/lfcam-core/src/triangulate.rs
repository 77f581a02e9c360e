//! Plane + parallax triangulation (docs/design.md, "Triangulation"): the parallax `s` of every
//! reference pixel from the optical flows to all views at once, robustly.
//!
//! # The estimator, per reference pixel `p`
//! `u_i = flows[i, p]` is the flow from the reference view to view `i`, which
//! estimates `o_i s` (`o_i = offsets[i]`, px per unit `s`). A view is *usable* at `p`
//! if it is not the reference, `|o_i| > 0`, both flow components are finite and its
//! weight `w_i` is positive (`w_i = 1` without weights; 0 or NaN: not usable). Over the
//! usable views:
//!
//! 1. Per-view estimates `s_i = o_i . u_i / |o_i|^2` and perpendicular components
//!    `q_i = (o_i x u_i) / |o_i|`, so that `|u_i - o_i s|^2 = |o_i|^2 (s_i - s)^2 +
//!    q_i^2`. Start: `s` = weighted median of the `s_i` with weights `a_i = w_i |o_i|^2`
//!    (it survives occluded views holding less than half of the weight).
//! 2. A *pass* at the current `s`: residuals `r_i = |u_i - o_i s|` (px), robust scale
//!    `sigma = max(sigma_floor, 1.4826 * wmedian(r_i; w_i))`, Tukey's biweight
//!    `rho_i = (1 - (r_i / c)^2)^2` for `r_i < c = cutoff * sigma`, else 0 (the view is
//!    dropped). Tukey, not Huber: its weight reaches exactly 0 at the cutoff, which is
//!    what drops an occluded view.
//! 3. Up to `iterations` times: a pass, then `s <- sum(a_i rho_i s_i) / sum(a_i rho_i)`
//!    (= `sum(w_i rho_i o_i . u_i) / sum(w_i rho_i |o_i|^2)`, weighted least squares);
//!    stop early once `s` moves by less than [`TOLERANCE`] (or if every view is dropped,
//!    leaving `s` as it is).
//! 4. A final pass at the final `s`; the *surviving* views are those with
//!    `r_i < cutoff * sigma`. Outputs: `n_used` = their number; `residual =
//!    sqrt(sum(w_i rho_i r_i^2) / sum(w_i rho_i))` (weighted RMS residual, px);
//!    `perpendicular = sqrt(mean(q_i^2))` (RMS perpendicular flow, px: pure error, a
//!    measure of calibration quality); `confidence` (below). If fewer than
//!    `min_views` views survive, `s`, `residual` and `perpendicular` are NaN and
//!    `confidence` is 0 (`n_used` still counts the survivors).
//!
//! The weighted median of values `x` with weights `v >= 0` (total `T > 0`), sorted
//! ascending with cumulative weights `C_k`, is `(x_lo + x_hi) / 2`, where `lo` is the
//! first `k` with `2 C_k >= T` and `hi` the first with `2 C_k > T` (for equal weights,
//! the ordinary median).
//!
//! # Confidence
//! `confidence = (1 - exp(-info / CONFIDENCE_INFO)) * exp(-(residual / CONFIDENCE_TAU)^2)`
//! with `info = sum(w_i |o_i|^2 over surviving views) / sum(|o_i|^2 over all views but
//! the reference)`: the share of the camera's parallax information that was measured
//! and kept (1 when every view survives with weight 1; for the variance of `s` it is
//! what counts, `var(s) = sigma_flow^2 / sum(w_i |o_i|^2)`). With
//! [`CONFIDENCE_INFO`] = 0.25 the first factor is 0.98 with every view, 0.86 with half
//! of the information and 0.30 with one view of twelve; with [`CONFIDENCE_TAU`] = 0.5 px
//! the second is 0.96 at a 0.1 px residual, 0.78 at 0.25 px and 0.02 at 1 px. Weights
//! above 1 raise `info` beyond 1 (the first factor then saturates).
//!
//! # Arithmetic and layout
//! float32 throughout (the flows' precision). Each task runs whole rows; a row is
//! processed in blocks of [`LANES`] pixels, with every quantity stored per view as a
//! row of `LANES` values (structure of arrays), so that the per-view loops vectorise
//! across pixels: the weighted medians are a sorting network (Batcher's odd-even merge
//! sort) applied lane-wise, without branches. Scratch memory is allocated once per
//! task, never per pixel; its size is bounded by [`MAX_VIEWS`].
//!
//! With at most 16 usable-offset views (the 3 x 4 camera has 11) on a CPU with AVX-512
//! or AVX2, a second implementation runs instead (module `fixed`, built for each in
//! `avx512` and `avx2`): the same operations in the same order, 32 or 16 pixels at a
//! time held in registers, with the network unrolled for the view count at compile
//! time; it gives the same bits (tested) in about a third (AVX-512) or 60% (AVX2) of
//! the instructions. The general path remains for more views and other CPUs.

use crate::error::{Error, Result};
use crate::image::ImageView;
use crate::parallel;
#[cfg(target_arch = "x86_64")]
use crate::simd::Level;
use crate::simd::{self, Dispatch};

/// Defines `fn $name(a: X, ...) -> X` (or `-> Mask`) applying `$op` register by
/// register, compiled for the target feature `$feature`: the register kernels of
/// [`avx2`] and [`avx512`] define their `X` and `Mask` and call this.
#[cfg(target_arch = "x86_64")]
macro_rules! lanewise {
    ($feature:literal, $(#[$meta:meta])* fn $name:ident($a:ident) = $op:expr) => {
        $(#[$meta])*
        #[inline]
        #[target_feature(enable = $feature)]
        fn $name(a: X) -> X {
            let mut r = a;
            for (r, &$a) in r.0.iter_mut().zip(&a.0) {
                *r = $op;
            }
            r
        }
    };
    ($feature:literal, $(#[$meta:meta])* fn $name:ident($a:ident, $b:ident) = $op:expr) => {
        $(#[$meta])*
        #[inline]
        #[target_feature(enable = $feature)]
        fn $name(a: X, b: X) -> X {
            let mut r = a;
            for (r, (&$a, &$b)) in r.0.iter_mut().zip(a.0.iter().zip(&b.0)) {
                *r = $op;
            }
            r
        }
    };
    ($feature:literal, $(#[$meta:meta])* fn $name:ident($a:ident, $b:ident) -> Mask = $op:expr) => {
        $(#[$meta])*
        #[inline]
        #[target_feature(enable = $feature)]
        fn $name(a: X, b: X) -> Mask {
            let mut r = Mask([0; K]);
            for (r, (&$a, &$b)) in r.0.iter_mut().zip(a.0.iter().zip(&b.0)) {
                *r = $op;
            }
            r
        }
    };
}

#[cfg(target_arch = "x86_64")]
mod avx2;
#[cfg(target_arch = "x86_64")]
mod avx512;
#[cfg(target_arch = "x86_64")]
mod fixed;

/// Most views (the reference included) one call accepts: it bounds the scratch memory
/// (a few kB per view per task) and keeps `n_used` in a `u8`.
pub const MAX_VIEWS: usize = 128;

/// `sigma = MAD_TO_SIGMA * median absolute residual`: the consistency factor of the
/// median absolute deviation for Gaussian noise.
pub const MAD_TO_SIGMA: f32 = 1.4826;

/// The iterations stop once `s` moves by less than this.
pub const TOLERANCE: f32 = 1e-6;

/// Information share at which the confidence's first factor is `1 - 1/e`.
pub const CONFIDENCE_INFO: f32 = 0.25;

/// Residual (px) at which the confidence's second factor is `1/e`.
pub const CONFIDENCE_TAU: f32 = 0.5;

/// Largest offset component accepted (px per unit `s`), far beyond any camera; keeps
/// `|o|^2` finite in float32.
pub const MAX_OFFSET: f64 = 1e18;

/// Pixels per block: the width of the structure-of-arrays rows. 64 float32 are a few
/// vector registers' worth, and 128 views' worth of scratch rows stay within L2.
pub const LANES: usize = 64;

/// One scratch row: a value per pixel of the block.
type Row = [f32; LANES];

/// Key of an unusable view in the sorts: above every usable one.
const LAST: f32 = f32::MAX;

// The per-lane loops below are written without `if`, `&&` and `||`: those become
// branches in the compiler's input, and a branch that may leave an element unchanged
// becomes a conditional store, which does not vectorise (measured: 3x slower). Selects
// go through bit masks instead, comparisons combine with `&` and `|`.

/// All ones if `c`, else 0.
#[inline(always)]
fn mask(c: bool) -> u32 {
    0u32.wrapping_sub(u32::from(c))
}

/// `x` if `c`, else +0.
#[inline(always)]
fn keep(c: bool, x: f32) -> f32 {
    f32::from_bits(x.to_bits() & mask(c))
}

/// `a` if `c`, else `b`.
#[inline(always)]
fn select(c: bool, a: f32, b: f32) -> f32 {
    let m = mask(c);
    f32::from_bits((a.to_bits() & m) | (b.to_bits() & !m))
}

/// 1 if `c`, else 0.
#[inline(always)]
fn one(c: bool) -> f32 {
    f32::from(u8::from(c))
}

/// `e^x` for `x <= 0`, within 2 ulp, and 0 below -87 (NaN gives `e^-87`, about 2e-38):
/// branch-free, so that it vectorises, which libm's `expf` does not. Cody-Waite
/// reduction `x = k ln 2 + r`, `|r| <= ln 2 / 2`, and the degree-6 Taylor polynomial of
/// `e^r` (truncation error below 1.3e-7 relative).
#[inline(always)]
fn exp_neg(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5 * 2^23: adding and subtracting it rounds
    const LN2_HI: f32 = 0.693_359_4; // 0.693359375, exact in 10 bits
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Not `clamp`, which keeps NaN: `max` first maps NaN to -87.
    #[allow(clippy::manual_clamp)]
    let x = x.max(-87.0).min(0.0);
    let k = (x * std::f32::consts::LOG2_E + ROUND) - ROUND;
    let r = x - k * LN2_HI - k * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // k is an integer in -126..=0, so k + 127 is a normal exponent.
    p * f32::from_bits(((k as i32 + 127) as u32) << 23)
}

/// Parameters of [`triangulate`]; see the module documentation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Fewest surviving views for a parallax (default 1).
    pub min_views: usize,
    /// Lower bound of the robust scale `sigma`, px (default 0.25).
    pub sigma_floor: f32,
    /// A view is dropped when its residual reaches `cutoff * sigma` (default 3).
    pub cutoff: f32,
    /// Most reweighting iterations (default 5); 0 keeps the weighted median.
    pub iterations: usize,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            min_views: 1,
            sigma_floor: 0.25,
            cutoff: 3.0,
            iterations: 5,
        }
    }
}

impl Params {
    fn check(&self) -> Result<()> {
        if self.min_views < 1 || self.min_views >= MAX_VIEWS {
            return Err(Error::invalid_argument(
                "min_views",
                format!(
                    "expected an integer between 1 and {}, got {}",
                    MAX_VIEWS - 1,
                    self.min_views
                ),
            ));
        }
        for (name, value) in [("sigma_floor", self.sigma_floor), ("cutoff", self.cutoff)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(Error::invalid_argument(
                    name,
                    format!("expected a finite number > 0, got {value}"),
                ));
            }
        }
        Ok(())
    }
}

/// A borrowed, C-contiguous `(N, H, W, C)` float32 stack of per-view planes (flows:
/// `C = 2`, `(x, y)`; weights: `C = 1`).
#[derive(Debug, Clone, Copy)]
pub struct ViewStack<'a> {
    /// The planes one under the other: row `i * H + y` is row `y` of view `i`.
    image: ImageView<'a, f32>,
    views: usize,
    height: usize,
}

impl<'a> ViewStack<'a> {
    /// Wraps `data` as `shape = [N, H, W, C]`.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `arg` if a dimension is zero or
    /// `data.len() != N * H * W * C`.
    pub fn new(data: &'a [f32], shape: [usize; 4], arg: &str) -> Result<Self> {
        let [views, height, width, channels] = shape;
        let elements = shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d));
        if shape.contains(&0) || elements != Some(data.len()) {
            return Err(Error::invalid_argument(
                arg,
                format!(
                    "has {} elements, but needs a non-empty (N, H, W, C) = {shape:?}",
                    data.len()
                ),
            ));
        }
        // N * H cannot overflow: N * H * W * C did not.
        let image = ImageView::new(data, views * height, width, channels)
            .map_err(|e| Error::invalid_argument(arg, e.to_string()))?;
        Ok(Self {
            image,
            views,
            height,
        })
    }

    /// `[N, H, W, C]`.
    pub fn shape(&self) -> [usize; 4] {
        [
            self.views,
            self.height,
            self.image.width(),
            self.image.channels(),
        ]
    }

    /// Columns `x0 .. x0 + w` of row `y` of view `view`, or `None` outside.
    fn span(&self, view: usize, y: usize, x0: usize, w: usize) -> Option<&'a [f32]> {
        if view >= self.views || y >= self.height {
            return None;
        }
        self.image.row_span(view * self.height + y, x0, w)
    }
}

/// The caller-owned outputs of [`triangulate`], each `(H, W)` row-major.
#[derive(Debug)]
pub struct Outputs<'a> {
    /// `s`, NaN where fewer than `min_views` views survive.
    pub parallax: &'a mut [f32],
    /// In `[0, 1]`, 0 where `s` is NaN.
    pub confidence: &'a mut [f32],
    /// Weighted RMS residual `|u_i - o_i s|` over the surviving views, px.
    pub residual: &'a mut [f32],
    /// RMS flow component perpendicular to `o_i` over the surviving views, px.
    pub perpendicular: &'a mut [f32],
    /// Number of surviving views.
    pub n_used: &'a mut [u8],
}

impl<'a> Outputs<'a> {
    /// The outputs split into consecutive pieces of `n` pixels each (the last may be
    /// shorter), all five arrays alike: rows when `n` is the width.
    pub(crate) fn chunks(self, n: usize) -> impl Iterator<Item = Outputs<'a>> {
        self.parallax
            .chunks_mut(n)
            .zip(self.confidence.chunks_mut(n))
            .zip(self.residual.chunks_mut(n))
            .zip(self.perpendicular.chunks_mut(n))
            .zip(self.n_used.chunks_mut(n))
            .map(
                |((((parallax, confidence), residual), perpendicular), n_used)| Outputs {
                    parallax,
                    confidence,
                    residual,
                    perpendicular,
                    n_used,
                },
            )
    }
}

/// A view that can contribute: not the reference, `|o| > 0`.
#[derive(Debug, Clone, Copy)]
struct UsedView {
    index: usize,
    ox: f32,
    oy: f32,
    /// `|o|^2`.
    n: f32,
    inv_n: f32,
}

/// Everything decided once per call.
#[derive(Debug)]
struct Setup<'a> {
    flows: ViewStack<'a>,
    weights: Option<ViewStack<'a>>,
    views: Vec<UsedView>,
    /// Comparators `(i, j)`, `i < j < views.len()`, sorting `views.len()` values.
    network: Vec<(usize, usize)>,
    /// The part of `network` that puts the right values in the first half (positions
    /// `0 ..= views.len() / 2`), which is all [`median_ends`] reads.
    half_network: Vec<(usize, usize)>,
    params: Params,
    /// `1 / (CONFIDENCE_INFO * sum |o_i|^2)`.
    info_scale: f32,
    /// Which builds may run (see [`crate::simd`]): of the general path's loops, and of
    /// the few-view paths (module `fixed`); x86-64 only, elsewhere the portable
    /// general path is all.
    #[cfg(target_arch = "x86_64")]
    simd: &'a Dispatch,
    /// Whether the few-view paths (x86-64) may run (tests turn them off, to compare).
    #[cfg(target_arch = "x86_64")]
    few_view: bool,
}

impl<'a> Setup<'a> {
    fn new(
        flows: ViewStack<'a>,
        weights: Option<ViewStack<'a>>,
        offsets: &[[f64; 2]],
        reference: usize,
        params: &Params,
        simd: &'a Dispatch,
    ) -> Result<Self> {
        // Off x86-64 there is no SIMD build to choose: the portable one runs.
        #[cfg(not(target_arch = "x86_64"))]
        let _ = simd;
        let [n, h, w, c] = flows.shape();
        if c != 2 {
            return Err(Error::invalid_argument(
                "flows",
                format!(
                    "expected (N, H, W, 2) flow vectors, got shape {:?}",
                    flows.shape()
                ),
            ));
        }
        if !(2..=MAX_VIEWS).contains(&n) {
            return Err(Error::invalid_argument(
                "flows",
                format!(
                    "expected between 2 and {MAX_VIEWS} views (the reference and at least one \
                     other), got N = {n}"
                ),
            ));
        }
        if let Some(wt) = &weights
            && wt.shape() != [n, h, w, 1]
        {
            let [wn, wh, ww, _] = wt.shape();
            return Err(Error::invalid_argument(
                "weights",
                format!(
                    "expected shape (N, H, W) = ({n}, {h}, {w}) like flows, got ({wn}, {wh}, {ww})"
                ),
            ));
        }
        if offsets.len() != n {
            return Err(Error::invalid_argument(
                "offsets",
                format!(
                    "expected (N, 2) = ({n}, 2), one per view of flows, got ({}, 2)",
                    offsets.len()
                ),
            ));
        }
        if reference >= n {
            return Err(Error::invalid_argument(
                "reference",
                format!(
                    "expected a view index between 0 and {}, got {reference}",
                    n - 1
                ),
            ));
        }
        params.check()?;
        let mut views = Vec::with_capacity(n);
        let mut total = 0f64;
        for (index, &[ox, oy]) in offsets.iter().enumerate() {
            if !(ox.is_finite()
                && oy.is_finite()
                && ox.abs() <= MAX_OFFSET
                && oy.abs() <= MAX_OFFSET)
            {
                return Err(Error::invalid_item(
                    "offsets",
                    index,
                    format!("({ox}, {oy}) must be finite and at most {MAX_OFFSET:e} in magnitude"),
                ));
            }
            if index == reference {
                if (ox, oy) != (0.0, 0.0) {
                    return Err(Error::invalid_item(
                        "offsets",
                        index,
                        format!(
                            "the reference view's offset must be (0, 0), got ({ox}, {oy}); is \
                             reference = {reference} the view the offsets are relative to?"
                        ),
                    ));
                }
                continue;
            }
            let (ox, oy) = (ox as f32, oy as f32);
            let norm2 = ox * ox + oy * oy;
            if norm2.is_normal() {
                total += f64::from(norm2);
                views.push(UsedView {
                    index,
                    ox,
                    oy,
                    n: norm2,
                    inv_n: 1.0 / norm2,
                });
            }
        }
        if views.is_empty() {
            return Err(Error::invalid_argument(
                "offsets",
                "every view's offset is zero: there is no parallax to triangulate",
            ));
        }
        let network = sorting_network(views.len());
        let half_network = prune_network(&network, views.len() / 2 + 1);
        Ok(Self {
            flows,
            weights,
            views,
            network,
            half_network,
            params: *params,
            info_scale: (1.0 / (f64::from(CONFIDENCE_INFO) * total)) as f32,
            #[cfg(target_arch = "x86_64")]
            simd,
            #[cfg(target_arch = "x86_64")]
            few_view: true,
        })
    }

    fn height(&self) -> usize {
        self.flows.shape()[1]
    }

    fn width(&self) -> usize {
        self.flows.shape()[2]
    }
}

/// Comparators of Batcher's odd-even merge sort for `n` values (any `n`, not only
/// powers of two): applying `(i, j)` as "put the smaller of `x[i]`, `x[j]` in `x[i]`"
/// in order sorts any input. For 11 values: 38 comparators (the best known: 35).
fn sorting_network(n: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut p = 1;
    while p < n {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < n {
                for i in 0..k.min(n - j - k) {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        out.push((i + j, i + j + k));
                    }
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    out
}

/// The comparators of `network` that the first `outputs` positions depend on: the
/// others only order the positions after them, which are then not sorted.
fn prune_network(network: &[(usize, usize)], outputs: usize) -> Vec<(usize, usize)> {
    let wires = network
        .iter()
        .map(|&(_, j)| j + 1)
        .max()
        .unwrap_or(0)
        .max(outputs);
    let mut needed: Vec<bool> = (0..wires).map(|i| i < outputs).collect();
    let mut kept: Vec<(usize, usize)> = network
        .iter()
        .rev()
        .filter(|&&(i, j)| {
            let (ni, nj) = (needed.get(i).copied(), needed.get(j).copied());
            let use_it = ni == Some(true) || nj == Some(true);
            if use_it {
                needed
                    .iter_mut()
                    .enumerate()
                    .for_each(|(k, v)| *v |= k == i || k == j);
            }
            use_it
        })
        .copied()
        .collect();
    kept.reverse();
    kept
}

/// Sorts each lane of `keys` (rows = values, lanes = independent problems) ascending.
/// Every key must be `+0`, positive or `+inf` (squared residuals).
///
/// In the AVX2 build, a select that may store an element's own value back (as a
/// compare-exchange does) becomes a masked store, which is microcoded and slow on AMD
/// (measured: the whole kernel 1.5x slower than the baseline build). There the keys'
/// bits are compared as integers instead (for such keys, integer and float order
/// agree), with `vpminsd` / `vpmaxsd`; in the baseline build (SSE2 has no `pminsd`)
/// the select becomes `minps` / `maxps`. The sorted keys are the same bits.
#[inline(always)]
fn sort_keys<const AVX2: bool>(keys: &mut [Row], network: &[(usize, usize)]) {
    for &(i, j) in network {
        if let Ok([x, y]) = keys.get_disjoint_mut([i, j]) {
            for (a, b) in x.iter_mut().zip(y.iter_mut()) {
                if AVX2 {
                    let (ka, kb) = (a.to_bits() as i32, b.to_bits() as i32);
                    *a = f32::from_bits(ka.min(kb) as u32);
                    *b = f32::from_bits(ka.max(kb) as u32);
                } else {
                    let (ka, kb) = (*a, *b);
                    let swap = kb < ka;
                    *a = select(swap, kb, ka);
                    *b = select(swap, ka, kb);
                }
            }
        }
    }
}

/// Sorts each lane of `keys` ascending, carrying `payload` along. No key may be NaN;
/// every payload value must be `+0` or positive (weights).
#[inline(always)]
fn sort_pairs<const AVX2: bool>(keys: &mut [Row], payload: &mut [Row], network: &[(usize, usize)]) {
    // In the AVX2 build, `+ 0.0` on the value a select keeps keeps the compiler from
    // making a masked store of it (see `sort_keys`); it maps -0 to +0 (a key -0 and a
    // key +0 compare equal, and a weight is never -0).
    let same = |v: f32| if AVX2 { v + 0.0 } else { v };
    for &(i, j) in network {
        if let (Ok([x, y]), Ok([px, py])) = (
            keys.get_disjoint_mut([i, j]),
            payload.get_disjoint_mut([i, j]),
        ) {
            for (((a, b), pa), pb) in x
                .iter_mut()
                .zip(y.iter_mut())
                .zip(px.iter_mut())
                .zip(py.iter_mut())
            {
                let (ka, kb, va, vb) = (*a, *b, *pa, *pb);
                let swap = kb < ka;
                *a = select(swap, kb, same(ka));
                *b = select(swap, ka, same(kb));
                *pa = select(swap, vb, same(va));
                *pb = select(swap, va, same(vb));
            }
        }
    }
}

/// For sorted `keys` with weights `payload` (sorted along) and per-lane totals
/// `total`, the `lo` and `hi` of the weighted median (module docs). Exactly one key of
/// a lane meets each condition if its total is positive (cumulative weights do not
/// decrease); 0 in lanes with a total of 0.
#[inline(always)]
fn weighted_median_ends(keys: &[Row], payload: &[Row], total: &Row, lo: &mut Row, hi: &mut Row) {
    let mut cum = [0f32; LANES];
    lo.fill(0.0);
    hi.fill(0.0);
    for (k, v) in keys.iter().zip(payload) {
        for (((((c, &t), l), h), &x), &wt) in cum
            .iter_mut()
            .zip(total)
            .zip(lo.iter_mut())
            .zip(hi.iter_mut())
            .zip(k)
            .zip(v)
        {
            let before = 2.0 * *c;
            let now = *c + wt;
            *c = now;
            let after = 2.0 * now;
            *l += keep((after >= t) & (before < t), x);
            *h += keep((after > t) & (before <= t), x);
        }
    }
}

/// [`weighted_median_ends`] for weights 1 on the first `K` sorted keys of each lane
/// (the unusable views' keys are +inf, sorted last) and 0 on the others: `lo` is
/// the key at position `(K - 1) / 2` and `hi` the one at `K / 2` (rounded down; given
/// as `positions`, -1 for `K = 0`). Only the first half of the rows can hold them.
#[inline(always)]
fn median_ends(keys: &[Row], positions: &(Row, Row), lo: &mut Row, hi: &mut Row) {
    lo.fill(0.0);
    hi.fill(0.0);
    let (lo_pos, hi_pos) = positions;
    let mut k = 0.0f32;
    for key in keys.iter().take(keys.len() / 2 + 1) {
        for ((((l, h), &x), &pl), &ph) in lo
            .iter_mut()
            .zip(hi.iter_mut())
            .zip(key)
            .zip(lo_pos)
            .zip(hi_pos)
        {
            *l += keep(k == pl, x);
            *h += keep(k == ph, x);
        }
        k += 1.0;
    }
}

/// Per-task scratch: per-view rows of one block.
#[derive(Debug)]
struct Scratch {
    /// `s_i` (0 where unusable).
    s: Vec<Row>,
    /// `a_i = w_i |o_i|^2` (0 where unusable).
    a: Vec<Row>,
    /// `w_i` (0 where unusable).
    w: Vec<Row>,
    /// `q_i^2` (+inf where unusable: the residual is then +inf, which sorts last and
    /// gets Tukey weight 0, with no test).
    q2: Vec<Row>,
    /// `r_i^2` at the current `s`.
    r2: Vec<Row>,
    /// Sort keys and payload.
    key: Vec<Row>,
    pay: Vec<Row>,
    /// Per lane: current `s`, totals of `a` and `w`, the median positions of
    /// [`median_ends`], whether still iterating, `1 / (cutoff sigma)^2`, weighted-median
    /// ends.
    s_cur: Row,
    total_a: Row,
    total_w: Row,
    positions: (Row, Row),
    active: [bool; LANES],
    inv_c2: Row,
    lo: Row,
    hi: Row,
    /// The few-view paths' buffers (empty until one runs).
    #[cfg(target_arch = "x86_64")]
    avx2: avx2::Buffer,
    #[cfg(target_arch = "x86_64")]
    avx512: avx512::Buffer,
}

impl Scratch {
    fn new(m: usize) -> Self {
        let rows = || vec![[0f32; LANES]; m];
        Self {
            s: rows(),
            a: rows(),
            w: rows(),
            q2: rows(),
            r2: rows(),
            key: rows(),
            pay: rows(),
            s_cur: [0.0; LANES],
            total_a: [0.0; LANES],
            total_w: [0.0; LANES],
            positions: ([0.0; LANES], [0.0; LANES]),
            active: [false; LANES],
            inv_c2: [0.0; LANES],
            lo: [0.0; LANES],
            hi: [0.0; LANES],
            #[cfg(target_arch = "x86_64")]
            avx2: avx2::Buffer::default(),
            #[cfg(target_arch = "x86_64")]
            avx512: avx512::Buffer::default(),
        }
    }
}

/// The per-view quantities of `view` at one block: `s_i`, `a_i`, `w_i`, `q_i^2` for
/// `flow` (`len` vectors) and `weights`; in unusable lanes (and lanes past `len`), 0
/// and `q_i^2` = +inf.
/// Returns whether a weight is negative or infinite.
#[inline(always)]
fn gather_view(
    view: &UsedView,
    flow: &[[f32; 2]],
    weights: impl Iterator<Item = f32>,
    rows: (&mut Row, &mut Row, &mut Row, &mut Row),
) -> bool {
    let (s_row, a_row, w_row, q_row) = rows;
    let mut bad = false;
    for (((((u, wt), s), a), w), q) in flow
        .iter()
        .zip(weights)
        .zip(s_row.iter_mut())
        .zip(a_row.iter_mut())
        .zip(w_row.iter_mut())
        .zip(q_row.iter_mut())
    {
        let [ux, uy] = *u;
        let si = (view.ox * ux + view.oy * uy) * view.inv_n;
        let cross = view.ox * uy - view.oy * ux;
        let qi = cross * cross * view.inv_n;
        let ai = wt * view.n;
        bad |= (wt < 0.0) | (wt == f32::INFINITY);
        let ok = (wt > 0.0) & (ai > 0.0) & si.is_finite() & qi.is_finite();
        *s = keep(ok, si);
        *q = select(ok, qi, f32::INFINITY);
        *w = keep(ok, wt);
        *a = keep(ok, ai);
    }
    let len = flow.len();
    for row in [s_row, a_row, w_row] {
        row.iter_mut().skip(len).for_each(|v| *v = 0.0);
    }
    q_row.iter_mut().skip(len).for_each(|v| *v = f32::INFINITY);
    bad
}

impl Setup<'_> {
    /// Fills the scratch rows for the block of `len` pixels at `(y, x0)`. Returns
    /// whether any lane has a usable view and whether every usable weight is 1.
    #[inline(always)]
    fn gather(&self, sc: &mut Scratch, y: usize, x0: usize, len: usize) -> Result<(bool, bool)> {
        let internal = || Error::internal("triangulate", format!("row {y} out of range"));
        let rows =
            sc.s.iter_mut()
                .zip(sc.a.iter_mut())
                .zip(sc.w.iter_mut())
                .zip(sc.q2.iter_mut());
        for (view, (((s, a), w), q)) in self.views.iter().zip(rows) {
            let span = self
                .flows
                .span(view.index, y, x0, len)
                .ok_or_else(internal)?;
            let (flow, _) = span.as_chunks::<2>();
            match &self.weights {
                None => {
                    gather_view(view, flow, std::iter::repeat(1.0), (s, a, w, q));
                }
                Some(wt) => {
                    let wrow = wt.span(view.index, y, x0, len).ok_or_else(internal)?;
                    if gather_view(view, flow, wrow.iter().copied(), (s, a, w, q)) {
                        let (x, value) = wrow
                            .iter()
                            .enumerate()
                            .find(|&(_, &v)| v < 0.0 || v == f32::INFINITY)
                            .map_or((0, 0.0), |(i, &v)| (i, v));
                        return Err(Error::invalid_item(
                            "weights",
                            view.index,
                            format!(
                                "weight {value} at row {y}, column {} is negative or infinite; \
                                 expected a finite value >= 0 (0 or NaN: do not use)",
                                x0 + x
                            ),
                        ));
                    }
                }
            }
        }
        sc.total_a.fill(0.0);
        sc.total_w.fill(0.0);
        let mut count = [0f32; LANES];
        let mut unit = true;
        for (a, w) in sc.a.iter().zip(&sc.w) {
            for ((((ta, tw), cnt), &ai), &wi) in sc
                .total_a
                .iter_mut()
                .zip(sc.total_w.iter_mut())
                .zip(count.iter_mut())
                .zip(a)
                .zip(w)
            {
                *ta += ai;
                *tw += wi;
                *cnt += one(wi > 0.0);
                unit &= (wi == 0.0) | (wi == 1.0);
            }
        }
        let (lo_pos, hi_pos) = &mut sc.positions;
        for ((pl, ph), &k) in lo_pos.iter_mut().zip(hi_pos.iter_mut()).zip(&count) {
            // Rounding down by truncation, which is exact for k >= 1 (`floor` is a libm
            // call without SSE4.1).
            *pl = select(k > 0.0, ((k - 1.0) * 0.5) as i32 as f32, -1.0);
            *ph = select(k > 0.0, (k * 0.5) as i32 as f32, -1.0);
        }
        let any = sc.total_a.iter().any(|&t| t > 0.0);
        Ok((any, unit))
    }

    /// The weighted median of the `s_i` (weights `a_i`) into `s_cur`; lanes without a
    /// usable view get NaN and are inactive.
    #[inline(always)]
    fn start<const AVX2: bool>(&self, sc: &mut Scratch) {
        for ((key, pay), (s, a)) in sc
            .key
            .iter_mut()
            .zip(sc.pay.iter_mut())
            .zip(sc.s.iter().zip(&sc.a))
        {
            for (((k, p), &si), &ai) in key.iter_mut().zip(pay.iter_mut()).zip(s).zip(a) {
                *k = select(ai > 0.0, si, LAST);
                *p = ai;
            }
        }
        sort_pairs::<AVX2>(&mut sc.key, &mut sc.pay, &self.network);
        weighted_median_ends(&sc.key, &sc.pay, &sc.total_a, &mut sc.lo, &mut sc.hi);
        for ((((s, act), &l), &h), &t) in sc
            .s_cur
            .iter_mut()
            .zip(sc.active.iter_mut())
            .zip(&sc.lo)
            .zip(&sc.hi)
            .zip(&sc.total_a)
        {
            *s = (l + h) * 0.5;
            *act = t > 0.0;
        }
    }

    /// A pass at `s_cur`: `r2` and `inv_c2 = 1 / (cutoff sigma)^2`.
    #[inline(always)]
    fn pass<const AVX2: bool>(&self, sc: &mut Scratch, unit: bool) {
        if unit {
            self.residuals::<false>(sc);
        } else {
            self.residuals::<true>(sc);
        }
        if unit {
            sort_keys::<AVX2>(&mut sc.key, &self.half_network);
            median_ends(&sc.key, &sc.positions, &mut sc.lo, &mut sc.hi);
        } else {
            sort_pairs::<AVX2>(&mut sc.key, &mut sc.pay, &self.network);
            weighted_median_ends(&sc.key, &sc.pay, &sc.total_w, &mut sc.lo, &mut sc.hi);
        }
        let Params {
            sigma_floor,
            cutoff,
            ..
        } = self.params;
        for ((ic, &l), &h) in sc.inv_c2.iter_mut().zip(&sc.lo).zip(&sc.hi) {
            let median = (l.sqrt() + h.sqrt()) * 0.5;
            let c = cutoff * (MAD_TO_SIGMA * median).max(sigma_floor);
            *ic = 1.0 / (c * c);
        }
    }

    /// `r2` at `s_cur` and a copy to sort (+inf for unusable views), and the payload
    /// `w` too if `PAYLOAD`.
    #[inline(always)]
    fn residuals<const PAYLOAD: bool>(&self, sc: &mut Scratch) {
        for ((((view, r2), key), pay), ((s, q2), w)) in self
            .views
            .iter()
            .zip(sc.r2.iter_mut())
            .zip(sc.key.iter_mut())
            .zip(sc.pay.iter_mut())
            .zip(sc.s.iter().zip(&sc.q2).zip(&sc.w))
        {
            for ((((r, k), &si), &qi), &cur) in r2
                .iter_mut()
                .zip(key.iter_mut())
                .zip(s)
                .zip(q2)
                .zip(&sc.s_cur)
            {
                let d = si - cur;
                let ri = view.n * d * d + qi;
                *r = ri;
                *k = ri;
            }
            if PAYLOAD {
                pay.copy_from_slice(w);
            }
        }
    }

    /// One reweighted least-squares step for the active lanes; returns whether any lane
    /// is still active.
    #[inline(always)]
    fn update(&self, sc: &mut Scratch) -> bool {
        let mut num = [0f32; LANES];
        let mut den = [0f32; LANES];
        for ((r2, a), s) in sc.r2.iter().zip(&sc.a).zip(&sc.s) {
            for (((((nu, de), &ri), &ai), &si), &ic) in num
                .iter_mut()
                .zip(den.iter_mut())
                .zip(r2)
                .zip(a)
                .zip(s)
                .zip(&sc.inv_c2)
            {
                // Tukey's weight: 0 from the cutoff (x >= 1) on, and for r2 = +inf.
                let t = (1.0 - ri * ic).max(0.0);
                let b = ai * t * t;
                *nu += b * si;
                *de += b;
            }
        }
        let mut any = false;
        for (((cur, act), &nu), &de) in sc
            .s_cur
            .iter_mut()
            .zip(sc.active.iter_mut())
            .zip(&num)
            .zip(&den)
        {
            let next = select(de > 0.0, nu / de, *cur);
            let done = (de <= 0.0) | ((next - *cur).abs() < TOLERANCE);
            *cur = select(*act, next, *cur);
            *act &= !done;
            any |= *act;
        }
        any
    }

    /// The outputs at the final `s_cur` (after a final [`Self::pass`]).
    #[inline(always)]
    fn finish(&self, sc: &Scratch, out: Outputs<'_>) {
        let mut n = [0f32; LANES];
        let mut sum_b = [0f32; LANES];
        let mut sum_br = [0f32; LANES];
        let mut sum_q = [0f32; LANES];
        let mut info = [0f32; LANES];
        for (((r2, w), q2), a) in sc.r2.iter().zip(&sc.w).zip(&sc.q2).zip(&sc.a) {
            for (((((((((cnt, sb), sbr), sq), inf), &ri), &wi), &qi), &ai), &ic) in n
                .iter_mut()
                .zip(sum_b.iter_mut())
                .zip(sum_br.iter_mut())
                .zip(sum_q.iter_mut())
                .zip(info.iter_mut())
                .zip(r2)
                .zip(w)
                .zip(q2)
                .zip(a)
                .zip(&sc.inv_c2)
            {
                let x = ri * ic;
                let kept = (wi > 0.0) & (x < 1.0);
                let t = (1.0 - x).max(0.0);
                let b = wi * t * t;
                *cnt += one(kept);
                *sb += b;
                *sbr += keep(kept, b * ri); // 0 * inf is NaN
                *sq += keep(kept, qi);
                *inf += keep(kept, ai);
            }
        }
        let min_views = self.params.min_views as f32;
        let mut parallax = [0f32; LANES];
        let mut confidence = [0f32; LANES];
        let mut residual = [0f32; LANES];
        let mut perpendicular = [0f32; LANES];
        let lanes = parallax
            .iter_mut()
            .zip(confidence.iter_mut())
            .zip(residual.iter_mut())
            .zip(perpendicular.iter_mut());
        for (((((par, conf), res), perp), (&cnt, &s)), ((&sb, &sbr), (&sq, &inf))) in lanes
            .zip(n.iter().zip(&sc.s_cur))
            .zip(sum_b.iter().zip(&sum_br).zip(sum_q.iter().zip(&info)))
        {
            let ok = cnt >= min_views;
            let rms = (sbr / sb).sqrt();
            let z = rms * (1.0 / CONFIDENCE_TAU);
            let c = (1.0 - exp_neg(-inf * self.info_scale)) * exp_neg(-z * z);
            *par = select(ok, s, f32::NAN);
            *res = select(ok, rms, f32::NAN);
            *perp = select(ok, (sq / cnt).sqrt(), f32::NAN);
            // Not `clamp`, which keeps NaN: `max` first maps NaN to 0.
            #[allow(clippy::manual_clamp)]
            let c = c.max(0.0).min(1.0);
            *conf = keep(ok, c);
        }
        let outputs = out
            .parallax
            .iter_mut()
            .zip(out.confidence.iter_mut())
            .zip(out.residual.iter_mut())
            .zip(out.perpendicular.iter_mut())
            .zip(out.n_used.iter_mut());
        for ((((((((par, conf), res), perp), used), &p), &c), &r), (&q, &cnt)) in outputs
            .zip(&parallax)
            .zip(&confidence)
            .zip(&residual)
            .zip(perpendicular.iter().zip(&n))
        {
            *par = p;
            *conf = c;
            *res = r;
            *perp = q;
            // At most MAX_VIEWS - 1 = 127 views: exact in f32 and in u8.
            *used = cnt as u8;
        }
    }

    /// Triangulates the block of `out`'s length at `(y, x0)`.
    #[inline(always)]
    fn block<const AVX2: bool>(
        &self,
        sc: &mut Scratch,
        y: usize,
        x0: usize,
        out: Outputs<'_>,
    ) -> Result<()> {
        let len = out.parallax.len();
        let (any, unit) = self.gather(sc, y, x0, len)?;
        if !any {
            out.parallax.fill(f32::NAN);
            out.residual.fill(f32::NAN);
            out.perpendicular.fill(f32::NAN);
            out.confidence.fill(0.0);
            out.n_used.fill(0);
            return Ok(());
        }
        self.start::<AVX2>(sc);
        for _ in 0..self.params.iterations {
            self.pass::<AVX2>(sc, unit);
            if !self.update(sc) {
                break;
            }
        }
        self.pass::<AVX2>(sc, unit);
        self.finish(sc, out);
        Ok(())
    }

    /// Triangulates rows `first_row ..` into `out` (whole rows).
    #[inline(always)]
    fn rows<const AVX2: bool>(
        &self,
        sc: &mut Scratch,
        first_row: usize,
        out: Outputs<'_>,
    ) -> Result<()> {
        let w = self.width();
        for (k, row) in out.chunks(w).enumerate() {
            for (b, block) in row.chunks(LANES).enumerate() {
                self.block::<AVX2>(sc, first_row + k, b * LANES, block)?;
            }
        }
        Ok(())
    }
}

/// Triangulates rows `first_row ..` into `out`: on a few-view path (module `fixed`)
/// if `setup.simd` selects AVX-512 or AVX2, else on the general path.
fn rows_task(
    setup: &Setup<'_>,
    sc: &mut Scratch,
    first_row: usize,
    out: Outputs<'_>,
) -> Result<()> {
    #[cfg(target_arch = "x86_64")]
    if setup.few_view && fixed::takes(setup) {
        if setup.simd.select(Level::Avx512) {
            // SAFETY: `avx512::rows` needs only AVX512F, which this CPU has: a
            // `Dispatch` selects only levels `simd::level` allows.
            #[allow(unsafe_code)]
            let result = unsafe { avx512::rows(setup, first_row, out, &mut sc.avx512) };
            return result;
        }
        if setup.simd.select(Level::Avx2) {
            // SAFETY: `avx2::rows` needs only AVX2, which this CPU has (as above).
            #[allow(unsafe_code)]
            let result = unsafe { avx2::rows(setup, first_row, out, &mut sc.avx2) };
            return result;
        }
    }
    general_rows_task(setup, sc, first_row, out)
}

simd::avx2_or_portable!(
    setup.simd,
    /// [`Setup::rows`], compiled for AVX2 and for the baseline.
    fn general_rows_task(
        setup: &Setup<'_>,
        sc: &mut Scratch,
        first_row: usize,
        out: Outputs<'_>,
    ) -> Result<()> {
        setup.rows::<AVX2>(sc, first_row, out)
    }
);

/// Input bytes per row (flows and weights of the used views): the measure of work the
/// chunking policy is given, since this kernel reads ~5x more than it writes.
fn row_cost(setup: &Setup<'_>) -> usize {
    let per_pixel = if setup.weights.is_some() { 12 } else { 8 };
    setup
        .views
        .len()
        .saturating_mul(setup.width())
        .saturating_mul(per_pixel)
}

/// The robust parallax `s` of every reference pixel, with its confidence, residual,
/// perpendicular error and number of views (see the module documentation).
///
/// `flows` is `(N, H, W, 2)`: the flow `(x, y)` from the reference view to view `i`
/// (non-finite: no measurement; the reference's own plane is not read). `weights`,
/// if given, is `(N, H, W)`: a weight `>= 0` per flow vector (0 or NaN: do not use).
/// `offsets[i]` is `o_i` in px per unit `s`, `offsets[reference] = (0, 0)`. Every
/// output is `(H, W)`. Runs in lfcam's pool over tasks of whole rows (see
/// [`parallel`]); the result does not depend on the number of threads.
///
/// # Errors
/// - [`Error::InvalidArgument`] `"flows"` if `C != 2` or `N` is not in
///   `2..=`[`MAX_VIEWS`]; `"weights"` if its shape is not `(N, H, W)`; `"offsets"` if
///   it does not have `N` rows or every non-reference offset is zero; `"reference"` if
///   it is not below `N`; `"min_views"`, `"sigma_floor"`, `"cutoff"` for parameters
///   out of range (see [`Params`]); `"out"` if an output is not `H * W` long;
/// - [`Error::InvalidItem`] `"offsets"` for a non-finite or huge offset, or a
///   non-zero offset of the reference view; `"weights"` (view index) for a negative
///   or infinite weight (found while computing: outputs are then partly written).
pub fn triangulate(
    flows: ViewStack<'_>,
    weights: Option<ViewStack<'_>>,
    offsets: &[[f64; 2]],
    reference: usize,
    params: &Params,
    out: Outputs<'_>,
) -> Result<()> {
    let simd = Dispatch::auto();
    triangulate_with(flows, weights, offsets, reference, params, out, &simd, true)
}

/// [`triangulate`] with the builds `simd` allows, and the few-view paths if
/// `few_view` (tests compare them).
#[allow(clippy::too_many_arguments)]
fn triangulate_with(
    flows: ViewStack<'_>,
    weights: Option<ViewStack<'_>>,
    offsets: &[[f64; 2]],
    reference: usize,
    params: &Params,
    out: Outputs<'_>,
    simd: &Dispatch,
    few_view: bool,
) -> Result<()> {
    // Off x86-64 there are no few-view paths to turn off.
    #[cfg(not(target_arch = "x86_64"))]
    let _ = few_view;
    let setup = Setup {
        #[cfg(target_arch = "x86_64")]
        few_view,
        ..Setup::new(flows, weights, offsets, reference, params, simd)?
    };
    let (h, w) = (setup.height(), setup.width());
    let pixels = h * w;
    let lens = [
        out.parallax.len(),
        out.confidence.len(),
        out.residual.len(),
        out.perpendicular.len(),
        out.n_used.len(),
    ];
    if lens.iter().any(|&len| len != pixels) {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "outputs of {lens:?} elements (parallax, confidence, residual, perpendicular, \
                 n_used), but (H, W) = ({h}, {w}) needs {pixels} each"
            ),
        ));
    }
    let threads = parallel::num_threads();
    let row_bytes = row_cost(&setup);
    let rows = parallel::rows_per_task(h, row_bytes, threads);
    let chunk = rows * w;
    let tasks: Vec<(usize, Outputs<'_>)> = out
        .chunks(chunk)
        .enumerate()
        .map(|(i, out)| (i * rows, out))
        .collect();
    let m = setup.views.len();
    parallel::for_each_task_init(
        tasks,
        row_bytes.saturating_mul(h),
        || Scratch::new(m),
        |sc, _, (first, out)| rows_task(&setup, sc, first, out),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::Level;

    #[test]
    fn networks_sort_every_zero_one_input() {
        // The 0-1 principle: a network that sorts every 0/1 sequence sorts everything.
        for n in 0..=14usize {
            let net = sorting_network(n);
            assert!(net.iter().all(|&(i, j)| i < j && j < n));
            for bits in 0u32..(1 << n) {
                let mut v: Vec<u8> = (0..n).map(|i| ((bits >> i) & 1) as u8).collect();
                for &(i, j) in &net {
                    if v[j] < v[i] {
                        v.swap(i, j);
                    }
                }
                assert!(v.windows(2).all(|p| p[0] <= p[1]), "n = {n}, bits {bits:b}");
            }
        }
        assert_eq!(sorting_network(11).len(), 38);
    }

    #[test]
    fn pruned_networks_sort_the_first_half() {
        for n in 1..=14usize {
            let keep = n / 2 + 1;
            let net = prune_network(&sorting_network(n), keep);
            assert!(net.len() <= sorting_network(n).len());
            for bits in 0u32..(1 << n) {
                let mut v: Vec<u8> = (0..n).map(|i| ((bits >> i) & 1) as u8).collect();
                let mut want = v.clone();
                want.sort_unstable();
                for &(i, j) in &net {
                    if v[j] < v[i] {
                        v.swap(i, j);
                    }
                }
                let k = keep.min(n);
                assert_eq!(v[..k], want[..k], "n = {n}, bits {bits:b}");
            }
        }
        assert_eq!(prune_network(&sorting_network(11), 6).len(), 35);
    }

    #[test]
    fn exp_neg_is_accurate() {
        let mut x = 0.0f32;
        while x > -90.0 {
            let (got, want) = (exp_neg(x), f64::from(x).exp());
            let err = (f64::from(got) - want).abs() / want;
            assert!(
                err < 3e-7 || (x < -87.0 && got < 2e-38),
                "{x}: {got} vs {want}"
            );
            x -= 0.0137;
        }
        assert_eq!(exp_neg(0.0), 1.0);
        assert!(exp_neg(f32::NAN) < 1e-37);
        assert!(exp_neg(f32::NEG_INFINITY) < 1e-37);
    }

    #[test]
    fn networks_sort_random_inputs_up_to_max_views() {
        let mut state = 12345u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32 % 1000
        };
        for n in 15..MAX_VIEWS {
            let net = sorting_network(n);
            for _ in 0..200 {
                let mut v: Vec<u32> = (0..n).map(|_| next()).collect();
                let mut want = v.clone();
                want.sort_unstable();
                for &(i, j) in &net {
                    if v[j] < v[i] {
                        v.swap(i, j);
                    }
                }
                assert_eq!(v, want, "n = {n}");
            }
        }
    }

    fn lanes(values: &[f32]) -> Row {
        let mut row = [LAST; LANES];
        row[..values.len()].copy_from_slice(values);
        row
    }

    /// Weighted median of one lane through the lane-wise functions.
    fn wmedian(x: &[f32], v: &[f32]) -> f32 {
        let n = x.len();
        let mut keys: Vec<Row> = x.iter().map(|&k| [k; LANES]).collect();
        let mut pay: Vec<Row> = v.iter().map(|&k| [k; LANES]).collect();
        // Both builds' variants sort alike (here compiled for the baseline).
        let (mut keys2, mut pay2) = (keys.clone(), pay.clone());
        sort_pairs::<false>(&mut keys, &mut pay, &sorting_network(n));
        sort_pairs::<true>(&mut keys2, &mut pay2, &sorting_network(n));
        assert_eq!((&keys, &pay), (&keys2, &pay2));
        let total = [v.iter().sum::<f32>(); LANES];
        let (mut lo, mut hi) = ([0.0; LANES], [0.0; LANES]);
        weighted_median_ends(&keys, &pay, &total, &mut lo, &mut hi);
        (lo[0] + hi[0]) / 2.0
    }

    #[test]
    fn weighted_medians() {
        assert_eq!(wmedian(&[3.0, 1.0, 2.0], &[1.0, 1.0, 1.0]), 2.0);
        assert_eq!(wmedian(&[4.0, 1.0, 3.0, 2.0], &[1.0, 1.0, 1.0, 1.0]), 2.5);
        assert_eq!(wmedian(&[1.0, 2.0, 10.0], &[1.0, 1.0, 5.0]), 10.0);
        assert_eq!(wmedian(&[1.0, 2.0, 10.0], &[2.0, 1.0, 3.0]), 6.0);
        assert_eq!(wmedian(&[5.0, 1.0, 7.0], &[0.0, 1.0, 0.0]), 1.0);
        assert_eq!(wmedian(&[7.0], &[2.0]), 7.0);
        // No weight: 0 (the lane has no usable view and is not used).
        assert_eq!(wmedian(&[7.0], &[0.0]), 0.0);
    }

    #[test]
    fn unit_weight_medians_match_weighted_ones() {
        let x = [5.0, 1.0, 4.0, 2.0, 3.0, 9.0];
        for count in 0..=x.len() {
            let vals: Vec<f32> = x[..count].to_vec();
            let mut keys: Vec<Row> = (0..x.len())
                .map(|i| lanes(&[vals.get(i).copied().unwrap_or(LAST)]))
                .collect();
            let mut keys2 = keys.clone();
            sort_keys::<false>(&mut keys, &sorting_network(x.len()));
            sort_keys::<true>(&mut keys2, &sorting_network(x.len()));
            assert_eq!(keys, keys2);
            let k = count as f32;
            let hi_pos = if count == 0 { -1.0 } else { (k / 2.0).floor() };
            let positions = ([((k - 1.0) / 2.0).floor(); LANES], [hi_pos; LANES]);
            let (mut lo, mut hi) = ([0.0; LANES], [0.0; LANES]);
            median_ends(&keys, &positions, &mut lo, &mut hi);
            let got = (lo[0] + hi[0]) / 2.0;
            if count == 0 {
                assert_eq!(got, 0.0);
            } else {
                assert_eq!(got, wmedian(&vals, &vec![1.0; count]), "{count}");
            }
        }
    }

    #[test]
    fn avx2_and_baseline_builds_agree() {
        if !simd::runs_or_skip(Level::Avx2, "triangulate avx2_and_baseline_builds_agree") {
            return;
        }
        // Noisy flows with outliers, holes and fractional weights, 3 rows of 2.5
        // blocks; weights 0/1 too (the unit path).
        let (n, h, w) = (12usize, 3usize, 2 * LANES + 37);
        let offsets: Vec<[f64; 2]> = (0..n)
            .map(|i| [10.0 * (i % 4) as f64 - 10.0, 10.0 * (i / 4) as f64 - 10.0])
            .collect();
        let reference = 5;
        let mut seed = 7u64;
        let mut rnd = move || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut flows = vec![0f32; n * h * w * 2];
        let mut frac = vec![0f32; n * h * w];
        for (i, &[ox, oy]) in offsets.iter().enumerate() {
            for p in 0..h * w {
                let k = i * h * w + p;
                let s = (p as f32 * 0.01).sin() * 0.5;
                let roll = rnd();
                let bad = if roll < 0.1 { 5.0 } else { 0.0 };
                flows[2 * k] = ox as f32 * s + rnd() - 0.5 + bad;
                flows[2 * k + 1] = oy as f32 * s + rnd() - 0.5;
                if roll > 0.95 {
                    flows[2 * k] = f32::NAN;
                }
                frac[k] = if roll > 0.9 { 0.0 } else { 0.25 + rnd() };
            }
        }
        let unit: Vec<f32> = frac.iter().map(|&v| f32::from(u8::from(v > 0.0))).collect();
        let fs = ViewStack::new(&flows, [n, h, w, 2], "flows").unwrap();
        for weights in [None, Some(&frac), Some(&unit)] {
            let ws = weights.map(|v| ViewStack::new(v, [n, h, w, 1], "weights").unwrap());
            let results = [Path::General, Path::Portable]
                .map(|path| run(fs, ws, &offsets, reference, &Params::default(), path).unwrap());
            let [a, b] = &results;
            assert_eq!((a.5, b.5), (Level::Avx2, Level::Portable));
            // Equal as numbers (a zero's sign may differ), NaN where NaN.
            let same = |x: &[f32], y: &[f32]| {
                x.iter()
                    .zip(y)
                    .all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
            };
            assert!(same(&a.0, &b.0) && same(&a.1, &b.1) && same(&a.2, &b.2));
            assert!(same(&a.3, &b.3) && a.4 == b.4);
            assert!(a.0.iter().filter(|v| v.is_finite()).count() > h * w / 2);
        }
    }

    /// Which code a test runs.
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    enum Path {
        /// What [`triangulate`] runs: the widest builds this process runs.
        Auto,
        /// The few-view AVX2 path (never the AVX-512 one) where it takes the views.
        Avx2,
        /// The general path's AVX2 build, never a few-view path.
        General,
        /// The general path's baseline build.
        Portable,
    }

    /// Outputs of one call on `path` and the widest build that ran, or the error
    /// message.
    type Run =
        std::result::Result<(Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<u8>, Level), String>;

    fn run(
        flows: ViewStack<'_>,
        weights: Option<ViewStack<'_>>,
        offsets: &[[f64; 2]],
        reference: usize,
        params: &Params,
        path: Path,
    ) -> Run {
        let [_, h, w, _] = flows.shape();
        let px = h * w;
        let (mut p, mut c, mut r, mut q) = (
            vec![0f32; px],
            vec![0f32; px],
            vec![0f32; px],
            vec![0f32; px],
        );
        let mut u = vec![0u8; px];
        let out = Outputs {
            parallax: &mut p,
            confidence: &mut c,
            residual: &mut r,
            perpendicular: &mut q,
            n_used: &mut u,
        };
        let (cap, few_view) = match path {
            Path::Auto => (Level::Avx512, true),
            Path::Avx2 => (Level::Avx2, true),
            Path::General => (Level::Avx2, false),
            Path::Portable => (Level::Portable, false),
        };
        let simd = Dispatch::at_most(cap);
        triangulate_with(
            flows, weights, offsets, reference, params, out, &simd, few_view,
        )
        .map_err(|e| e.to_string())?;
        Ok((p, c, r, q, u, simd.ran()))
    }

    /// The same bits (any NaN for NaN).
    #[cfg(target_arch = "x86_64")]
    fn same_bits(a: &[f32], b: &[f32]) -> bool {
        a.iter()
            .zip(b)
            .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn few_view_paths_equal_the_general_path() {
        // Every view count the AVX2 path takes and one more, rows with a partial chunk
        // and a partial block, no / unit / fractional weights with holes, outliers,
        // pixels without any usable view, a zero offset, and several parameter sets.
        let name = "few_view_paths_equal_the_general_path";
        if !simd::runs_or_skip(Level::Avx2, name) {
            return;
        }
        // The AVX-512 path is compared where it runs (`Path::Auto`).
        simd::runs_or_skip(Level::Avx512, name);
        let mut seed = 11u64;
        let mut rnd = move || {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        let params = [
            Params::default(),
            Params {
                iterations: 0,
                ..Params::default()
            },
            Params {
                min_views: 2,
                sigma_floor: 0.1,
                cutoff: 2.0,
                iterations: 9,
            },
        ];
        let mut checked = 0;
        // Rows longer than the AVX2 path's segment (1024 pixels) for a few view counts.
        let sizes = (2..=18usize)
            .map(|n| (n, 3usize, 2 * 64 + 37))
            .chain([4, 12, 17].map(|n| (n, 2, 1024 + 64 + 37)));
        for (n, h, w) in sizes {
            let reference = n / 3;
            let offsets: Vec<[f64; 2]> = (0..n)
                .map(|i| {
                    if i == reference || (n > 4 && i == n - 1) {
                        [0.0, 0.0] // the reference, and a view without parallax
                    } else {
                        let a = 2.4 * i as f64;
                        let len = 3.0 + 37.0 * f64::from(rnd());
                        [len * a.cos(), len * a.sin()]
                    }
                })
                .collect();
            let mut flows = vec![0f32; n * h * w * 2];
            let mut frac = vec![0f32; n * h * w];
            for (i, &[ox, oy]) in offsets.iter().enumerate() {
                for p in 0..h * w {
                    let k = i * h * w + p;
                    let s = (p as f32 * 0.013).sin() * 0.9;
                    let roll = rnd();
                    let bad = if roll < 0.12 { 2.0 + 8.0 * rnd() } else { 0.0 };
                    flows[2 * k] = ox as f32 * s + 0.4 * (rnd() - 0.5) + bad;
                    flows[2 * k + 1] = oy as f32 * s + 0.4 * (rnd() - 0.5) - 0.5 * bad;
                    if (0.12..0.17).contains(&roll) {
                        flows[2 * k + (p % 2)] = if p % 3 == 0 { f32::INFINITY } else { f32::NAN };
                    }
                    // Pixels 40..56 of row 1: no usable view at all.
                    if p >= w + 40 && p < w + 56 {
                        flows[2 * k] = f32::NAN;
                    }
                    frac[k] = match roll {
                        r if r > 0.93 => 0.0,
                        r if r > 0.9 => f32::NAN,
                        _ => 0.05 + 2.0 * rnd(),
                    };
                }
            }
            let unit: Vec<f32> = frac.iter().map(|&v| f32::from(u8::from(v > 0.0))).collect();
            let fs = ViewStack::new(&flows, [n, h, w, 2], "flows").unwrap();
            // The few-view paths take every view count up to their maximum.
            let simd = Dispatch::auto();
            let setup = Setup::new(fs, None, &offsets, reference, &params[0], &simd).unwrap();
            let takes = fixed::takes(&setup);
            assert_eq!(takes, setup.views.len() <= fixed::MAX_USED_VIEWS, "n = {n}");
            for weights in [None, Some(&unit), Some(&frac)] {
                let ws = weights.map(|v| ViewStack::new(v, [n, h, w, 1], "weights").unwrap());
                for p in &params {
                    if p.min_views >= n {
                        continue;
                    }
                    let b = run(fs, ws, &offsets, reference, p, Path::General).unwrap();
                    assert_eq!(b.5, Level::Avx2);
                    for path in [Path::Auto, Path::Avx2] {
                        let a = run(fs, ws, &offsets, reference, p, path).unwrap();
                        let what =
                            format!("{path:?}, n = {n}, weights {}, {p:?}", weights.is_some());
                        // The few-view path ran: AVX-512 where this process runs it.
                        let widest = if path == Path::Auto && takes {
                            simd::level()
                        } else {
                            Level::Avx2
                        };
                        assert_eq!(a.5, widest, "{what}");
                        assert!(same_bits(&a.0, &b.0), "parallax, {what}");
                        assert!(same_bits(&a.1, &b.1), "confidence, {what}");
                        assert!(same_bits(&a.2, &b.2), "residual, {what}");
                        assert!(same_bits(&a.3, &b.3), "perpendicular, {what}");
                        assert_eq!(a.4, b.4, "n_used, {what}");
                        assert!(a.0.iter().any(|v| v.is_finite()), "{what}");
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 100);
    }

    #[test]
    fn few_view_paths_report_a_bad_weight_as_the_general_path() {
        let name = "few_view_paths_report_a_bad_weight_as_the_general_path";
        if !simd::runs_or_skip(Level::Avx2, name) {
            return;
        }
        let (n, h, w) = (12usize, 2usize, 1150usize);
        let offsets: Vec<[f64; 2]> = (0..n)
            .map(|i| [10.0 * (i % 4) as f64 - 10.0, 10.0 * (i / 4) as f64 - 10.0])
            .collect();
        let flows = vec![0.5f32; n * h * w * 2];
        for bad in [
            (3, 1, 70),
            (0, 0, 3),
            (11, 1, 149),
            (7, 0, 64),
            (2, 1, 1100),
        ] {
            let mut weights = vec![1f32; n * h * w];
            let (v, y, x) = bad;
            weights[(v * h + y) * w + x] = -1.0;
            // A second bad weight in a later view of the same chunk: the first is named.
            weights[((v + 1).min(n - 1) * h + y) * w + (x / 64) * 64] = f32::INFINITY;
            let fs = ViewStack::new(&flows, [n, h, w, 2], "flows").unwrap();
            let ws = ViewStack::new(&weights, [n, h, w, 1], "weights").unwrap();
            let p = Params::default();
            let b = run(fs, Some(ws), &offsets, 5, &p, Path::General).unwrap_err();
            for path in [Path::Auto, Path::Avx2] {
                let a = run(fs, Some(ws), &offsets, 5, &p, path).unwrap_err();
                assert_eq!(a, b, "{path:?}");
            }
        }
    }

    #[test]
    fn const_networks_equal_the_runtime_ones() {
        #[cfg(target_arch = "x86_64")]
        for n in 0..=fixed::MAX_USED_VIEWS {
            let net = fixed::batcher(n);
            let pairs: Vec<(usize, usize)> = net
                .pairs
                .iter()
                .take(net.len)
                .map(|&(i, j)| (usize::from(i), usize::from(j)))
                .collect();
            assert_eq!(pairs, sorting_network(n), "n = {n}");
        }
    }

    #[test]
    fn params_are_checked() {
        assert!(Params::default().check().is_ok());
        let bad = [
            Params {
                min_views: 0,
                ..Params::default()
            },
            Params {
                sigma_floor: 0.0,
                ..Params::default()
            },
            Params {
                cutoff: f32::NAN,
                ..Params::default()
            },
            Params {
                cutoff: f32::INFINITY,
                ..Params::default()
            },
        ];
        for (p, name) in bad
            .iter()
            .zip(["min_views", "sigma_floor", "cutoff", "cutoff"])
        {
            let err = p.check().unwrap_err();
            assert!(
                matches!(err, Error::InvalidArgument { ref arg, .. } if arg == name),
                "{err:?}"
            );
        }
    }
}
