//! The paths of [`triangulate`](super::triangulate) for up to [`MAX_USED_VIEWS`] used
//! views (the 3 x 4 camera has 11) on CPUs with AVX2 (module `avx2`) or AVX-512
//! (module `avx512`): a group of pixels at a time with every per-view quantity in
//! vector registers, and the sorting networks unrolled at compile time for the view
//! count.
//!
//! The general path ([`super::Setup::rows`]) keeps per-view rows of 64 pixels in
//! scratch memory and applies a network read at run time: every comparator loads and
//! stores its rows, and the loops around it cost as much again. Here the number of
//! used views `M` is a const generic (one instantiation per count), so the network
//! ([`batcher`]: the same comparators in the same order) becomes straight-line code on
//! registers, and the compiler drops the comparators whose results are never read (the
//! upper half, for the unit-weight medians). In registers the work of one pixel is a
//! long chain of dependent operations (sort, square root, division, the sums over the
//! views), so each step works on `K` registers: independent chains for the CPU to
//! overlap.
//!
//! # One estimator, two instruction sets
//! The estimator is written once, in [`estimator!`], against a small set of lane-wise
//! functions (`add`, `lt`, `select`, `keep`, ...) over `X` (`K` registers of values)
//! and `Mask` (their lane masks), which `avx2` and `avx512` each define for their
//! registers (`__m256` and vector masks; `__m512` and `__mmask16`) before expanding the
//! macro with their `#[target_feature]` list. (Safe Rust cannot make it generic
//! instead: trait methods cannot be `#[target_feature]`, and the intrinsics are safe to
//! call only in functions that are.)
//!
//! # The same numbers
//! Every per-pixel quantity is computed by the same float32 operations in the same order
//! as on the general path, and a pixel's results do not depend on the pixels it is
//! computed with (a lane that has converged keeps its `s`; the unit-weight and weighted
//! medians agree for weights 0 and 1): the outputs are the same bits
//! (`tests::few_view_paths_equal_the_general_path`). The compare-exchanges of the
//! median's keys compare their bits as integers, as the general path's AVX2 build does
//! (for keys `+0`, positive or `+inf`, the same order as floats); the start's pairs
//! compare as floats with the general path's `kb < ka`.
//!
//! # Memory
//! A row is triangulated a [`SEGMENT`] at a time: first the per-view quantities of the
//! whole segment, view by view, into a buffer (each view's flows and weights of the
//! segment are one sequential read, 12 kB for 1024 pixels), then the estimator group
//! by group from the buffer (193 kB for 11 views with AVX2: in L2), during which
//! [`Prefetcher`] fetches the next segment's flows and weights. That beats both
//! segments without prefetching and small chunks gathered from all views
//! (docs/tuning.md, "Triangulation kernel").
//!
//! # Safety
//! The functions of the estimator are `#[target_feature]`: calling them from code
//! compiled without those features is unsafe, and [`super::rows_task`] does so only
//! after checking the CPU ([`crate::simd`]). Among themselves they are safe to call,
//! and so are the arithmetic intrinsics; memory is read and written through arrays
//! only (`setr` and lane extracts, which the compiler turns into vector loads and
//! stores) and prefetched by address (a prefetch never faults).

use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};

use super::{Setup, UsedView};
use crate::error::Error;

/// Most used views (the reference excluded) these paths take; more go to the general
/// path. Batcher's network for 16 values has 63 comparators.
pub(super) const MAX_USED_VIEWS: usize = 16;

/// Room for the comparators of a network of up to [`MAX_USED_VIEWS`] values.
const MAX_COMPARATORS: usize = 64;

/// A sorting network fixed at compile time: the first `len` of `pairs`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Network {
    pub(super) pairs: [(u8, u8); MAX_COMPARATORS],
    pub(super) len: usize,
}

/// [`super::sorting_network`] as a `const fn`, for `n <= MAX_USED_VIEWS`: the same
/// comparators in the same order (so that pairs with equal keys end up in the same
/// order as on the general path).
// Evaluated at compile time only (see `Fixed`): an index out of range is a compile error.
#[allow(clippy::indexing_slicing)]
pub(super) const fn batcher(n: usize) -> Network {
    let mut out = Network {
        pairs: [(0, 0); MAX_COMPARATORS],
        len: 0,
    };
    let mut p = 1;
    while p < n {
        let mut k = p;
        while k >= 1 {
            let mut j = k % p;
            while j + k < n {
                let limit = if k < n - j - k { k } else { n - j - k };
                let mut i = 0;
                while i < limit {
                    if (i + j) / (2 * p) == (i + j + k) / (2 * p) {
                        out.pairs[out.len] = ((i + j) as u8, (i + j + k) as u8);
                        out.len += 1;
                    }
                    i += 1;
                }
                j += 2 * k;
            }
            k /= 2;
        }
        p *= 2;
    }
    out
}

/// The compile-time constants of `M` used views.
pub(super) struct Fixed<const M: usize>;

impl<const M: usize> Fixed<M> {
    pub(super) const NETWORK: Network = batcher(M);
}

/// Runs `$body` with `$i`, `$j` bound to each comparator of `$net` in order, unrolled:
/// the network is a constant, so the indices are too and the keys stay in registers.
macro_rules! for_each_comparator {
    ($net:expr, |$i:ident, $j:ident| $body:block) => {
        for_each_comparator!(@ $net, $i, $j, $body;
            0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16 17 18 19 20 21 22 23 24 25 26 27 28 29
            30 31 32 33 34 35 36 37 38 39 40 41 42 43 44 45 46 47 48 49 50 51 52 53 54 55 56
            57 58 59 60 61 62 63)
    };
    (@ $net:expr, $i:ident, $j:ident, $body:block; $($c:literal)*) => {
        $(
            if $c < $net.len {
                let ($i, $j) = $net.pairs[$c];
                let ($i, $j) = (usize::from($i), usize::from($j));
                $body
            }
        )*
    };
}

/// Sorts the `[X; M]` `$keys` lane-wise ascending, carrying `$payload` along
/// ([`super::sort_pairs`]), with the lane-wise functions in scope. A macro, not a
/// function: called from several places, a function is not inlined, and its arrays
/// then go through memory.
///
/// `kb < ka ? kb : ka` is `min_or(kb, ka)` and `kb < ka ? ka : kb` is `max_or(ka, kb)`
/// (`vminps` / `vmaxps`), also for NaN and zeros of either sign; the payload is swapped
/// with XORs, which run on more of the CPU's vector pipes than blends.
macro_rules! sort_pairs {
    ($m:ident, $keys:expr, $payload:expr) => {
        for_each_comparator!(Fixed::<$m>::NETWORK, |i, j| {
            if let (Ok([x, y]), Ok([px, py])) = (
                $keys.get_disjoint_mut([i, j]),
                $payload.get_disjoint_mut([i, j]),
            ) {
                let (ka, kb) = (*x, *y);
                let swap = lt(kb, ka);
                *x = min_or(kb, ka);
                *y = max_or(ka, kb);
                let d = keep(swap, xor(*px, *py));
                *px = xor(*px, d);
                *py = xor(*py, d);
            }
        })
    };
}

pub(super) use {for_each_comparator, sort_pairs};

/// Pixels per segment (module docs).
pub(super) const SEGMENT: usize = 1024;

/// Bytes per cache line (of the x86-64 CPUs with AVX2).
const CACHE_LINE: usize = 64;

/// Whether these paths take `setup` (its number of used views).
pub(super) fn takes(setup: &Setup<'_>) -> bool {
    (1..=MAX_USED_VIEWS).contains(&setup.views.len())
}

/// Asks the CPU to fetch a segment's flows and weights into its cache, a part at each
/// [`Self::step`], so that the memory is read while the previous segment is computed
/// (the task's next rows are mostly computed by the same thread).
pub(super) struct Prefetcher {
    /// Start and length in cache lines of each view's flows and weights (the first
    /// `count`).
    spans: [(*const f32, usize); 2 * MAX_USED_VIEWS],
    count: usize,
    /// Lines per step, and the position: span, line.
    per_step: usize,
    span: usize,
    line: usize,
}

impl Prefetcher {
    /// For the segment at `(y, x0)` (nothing if outside), over `steps` steps.
    pub(super) fn new(
        setup: &Setup<'_>,
        views: &[UsedView],
        y: usize,
        x0: usize,
        steps: usize,
    ) -> Self {
        let len = SEGMENT.min(setup.width().saturating_sub(x0));
        let lines = |s: &[f32]| (s.as_ptr(), size_of_val(s).div_ceil(CACHE_LINE));
        let mut spans = [(std::ptr::null(), 0); 2 * MAX_USED_VIEWS];
        let mut count = 0;
        let mut push = |span: Option<&[f32]>| {
            if let (Some(span), Some(slot)) = (span, spans.get_mut(count)) {
                *slot = lines(span);
                count += 1;
            }
        };
        for view in views {
            push(setup.flows.span(view.index, y, x0, len));
            if let Some(ws) = &setup.weights {
                push(ws.span(view.index, y, x0, len));
            }
        }
        let total: usize = spans.iter().map(|&(_, n)| n).sum();
        Self {
            spans,
            count,
            per_step: total.div_ceil(steps.max(1)),
            span: 0,
            line: 0,
        }
    }

    /// Prefetches the next part.
    #[inline]
    #[target_feature(enable = "sse")]
    pub(super) fn step(&mut self) {
        let mut left = self.per_step;
        while left > 0 {
            let Some(&(start, n)) = self.spans.get(self.span).filter(|_| self.span < self.count)
            else {
                return;
            };
            let take = left.min(n - self.line);
            for line in self.line..self.line + take {
                // An address only: a prefetch never faults.
                let p = start.wrapping_add(line * CACHE_LINE / size_of::<f32>());
                _mm_prefetch::<_MM_HINT_T0>(p.cast::<i8>());
            }
            left -= take;
            self.line += take;
            if self.line == n {
                (self.span, self.line) = (self.span + 1, 0);
            }
        }
    }
}

/// The error for the first negative or infinite weight of the segment at `(y, x0)`:
/// in the first 64-pixel block holding one, the first view with one, as on the general
/// path.
#[cold]
pub(super) fn bad_weight(
    setup: &Setup<'_>,
    views: &[UsedView],
    y: usize,
    x0: usize,
    len: usize,
) -> Error {
    const BLOCK: usize = super::LANES;
    for b in (x0..x0 + len).step_by(BLOCK) {
        let n = BLOCK.min(x0 + len - b);
        for view in views {
            let found = (setup.weights.as_ref())
                .and_then(|ws| ws.span(view.index, y, b, n))
                .and_then(|ws| {
                    ws.iter()
                        .enumerate()
                        .find(|&(_, &v)| v < 0.0 || v == f32::INFINITY)
                });
            if let Some((x, &value)) = found {
                return Error::invalid_item(
                    "weights",
                    view.index,
                    format!(
                        "weight {value} at row {y}, column {} is negative or infinite; \
                         expected a finite value >= 0 (0 or NaN: do not use)",
                        b + x
                    ),
                );
            }
        }
    }
    Error::internal("triangulate", "no bad weight found")
}

/// The estimator, for the `#[target_feature]` list `$features`, in a module that defines
/// (module docs): `V` (a register), `LANES` (float32 per register), `K` (registers per
/// group), `X` (`K` registers: `struct X([V; K])`), `Mask`; lane-wise `splat`, `zero`,
/// `add`, `sub`, `mul`, `div`, `sqrt`, `max_or`, `min_or` (`vmaxps` / `vminps`),
/// `min_i32`, `max_i32` (the bits as `i32`), `xor`, `abs`, `neg` (sign bit), `trunc`,
/// `pow2` (`2^k` for integral `k` in `-126..=0`); comparisons `lt`, `le`, `gt`, `ge`,
/// `eq` giving a `Mask`; `and`, `or`, `and_not` of masks, `all_lanes()`, `any`, `all`;
/// `keep(m, x)` (`x` or +0), `select(m, a, b)`; and for one register `load`,
/// `load_flow` (8 or 16 interleaved flow vectors to `x`, `y`), `put` and `put_counts`
/// (to the first `dst.len()` of a register's lanes).
macro_rules! estimator {
    ($features:literal) => {
        use $crate::error::{Error, Result};
        use $crate::triangulate::fixed::{
            Fixed, MAX_USED_VIEWS, Prefetcher, SEGMENT, bad_weight, for_each_comparator, sort_pairs,
        };
        use $crate::triangulate::{
            CONFIDENCE_TAU, LAST, MAD_TO_SIGMA, Outputs, Params, Setup, TOLERANCE, UsedView,
        };

        /// Pixels the estimator works on at once.
        const GROUP: usize = K * LANES;

        /// [`super::exp_neg`], lane-wise, by the same operations.
        #[inline]
        #[target_feature(enable = $features)]
        fn exp_neg(x: X) -> X {
            const ROUND: f32 = 12_582_912.0;
            const LN2_HI: f32 = 0.693_359_4;
            const LN2_LO: f32 = -2.121_944_4e-4;
            let x = min_or(max_or(x, splat(-87.0)), zero());
            let k = sub(
                add(mul(x, splat(std::f32::consts::LOG2_E)), splat(ROUND)),
                splat(ROUND),
            );
            let r = sub(sub(x, mul(k, splat(LN2_HI))), mul(k, splat(LN2_LO)));
            // 1 + r (1 + r (1/2 + r (1/6 + r (1/24 + r (1/120 + r / 720))))), inside out.
            let mut p = splat(1.0 / 720.0);
            for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
                p = add(splat(c), mul(r, p));
            }
            mul(p, pow2(k))
        }

        /// The per-view quantities of the groups of a segment, group after group: for
        /// each, `s_i`, `a_i`, `w_i`, `q_i^2` of every view (module docs of
        /// [`super`]; unusable lanes as there). Kept by the task's scratch,
        /// so that it is allocated once per task sequence, not per row.
        #[derive(Default)]
        pub(super) struct Buffer(Vec<X>);

        impl std::fmt::Debug for Buffer {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "Buffer({} registers)", self.0.len() * K)
            }
        }

        /// A group's per-view quantities (in a [`Buffer`]) and their totals.
        struct Group<'b, const M: usize> {
            s: &'b [X; M],
            a: &'b [X; M],
            w: &'b [X; M],
            q2: &'b [X; M],
            /// Sums of `a_i`, `w_i` and `1 if w_i > 0`, in the order of the views as on
            /// the general path; set where every weight is 0 or 1.
            total_a: X,
            total_w: X,
            count: X,
            unit: Mask,
        }

        impl<'b, const M: usize> Group<'b, M> {
            /// The group stored in `data` (`4 M` registers), and its totals.
            #[inline]
            #[target_feature(enable = $features)]
            fn new(data: &'b [X]) -> Option<Self> {
                let part = |i: usize| -> Option<&'b [X; M]> {
                    data.get(i * M..(i + 1) * M)?.try_into().ok()
                };
                let (s, a, w, q2) = (part(0)?, part(1)?, part(2)?, part(3)?);
                let (one, zeros) = (splat(1.0), zero());
                let (mut total_a, mut total_w, mut count) = (zero(), zero(), zero());
                let mut unit = all_lanes();
                for (&a, &w) in a.iter().zip(w) {
                    total_a = add(total_a, a);
                    total_w = add(total_w, w);
                    count = add(count, keep(gt(w, zeros), one));
                    unit = and(unit, or(eq(w, zeros), eq(w, one)));
                }
                Some(Self {
                    s,
                    a,
                    w,
                    q2,
                    total_a,
                    total_w,
                    count,
                    unit,
                })
            }
        }

        /// Flows and weights of the lanes past the end of a row: unusable.
        const NO_FLOW: [f32; 2 * LANES] = [f32::NAN; 2 * LANES];
        const NO_WEIGHT: [f32; LANES] = [0.0; LANES];

        /// [`super::gather_view`] for view `k` (`view`) over a segment into
        /// `groups` (the buffer, `4 M` registers per group): `flows` gives the flow
        /// vectors of a register's pixels, `weights` (if `WEIGHTED`, else 1) their
        /// weights, a whole number of groups. Returns whether a weight is negative or
        /// infinite.
        #[inline]
        #[target_feature(enable = $features)]
        fn gather_view<'f, const M: usize, const WEIGHTED: bool>(
            k: usize,
            view: &UsedView,
            mut flows: impl Iterator<Item = &'f [f32; 2 * LANES]>,
            mut weights: impl Iterator<Item = &'f [f32; LANES]>,
            groups: &mut [X],
        ) -> bool {
            let (zeros, one, inf) = (zero(), splat(1.0), splat(f32::INFINITY));
            let (ox, oy) = (splat(view.ox), splat(view.oy));
            let (n, inv_n) = (splat(view.n), splat(view.inv_n));
            let mut bad = and_not(all_lanes(), all_lanes());
            for g in groups.chunks_exact_mut(4 * M) {
                let (mut ux, mut uy, mut wt) = (zero(), zero(), one);
                for ((x, y), w) in ux.0.iter_mut().zip(uy.0.iter_mut()).zip(wt.0.iter_mut()) {
                    let Some(flow) = flows.next() else {
                        return any(bad);
                    };
                    (*x, *y) = load_flow(flow);
                    if let Some(weight) = weights.next().filter(|_| WEIGHTED) {
                        *w = load(weight);
                    }
                }
                let si = mul(add(mul(ox, ux), mul(oy, uy)), inv_n);
                let cross = sub(mul(ox, uy), mul(oy, ux));
                let qi = mul(mul(cross, cross), inv_n);
                let ai = mul(wt, n);
                if WEIGHTED {
                    bad = or(bad, or(lt(wt, zeros), eq(wt, inf)));
                }
                let finite = |x: X| lt(abs(x), inf);
                let ok = and(
                    and(gt(wt, zeros), gt(ai, zeros)),
                    and(finite(si), finite(qi)),
                );
                let values = [
                    keep(ok, si),
                    keep(ok, ai),
                    keep(ok, wt),
                    select(ok, qi, inf),
                ];
                for (i, value) in values.into_iter().enumerate() {
                    if let Some(slot) = g.get_mut(i * M + k) {
                        *slot = value;
                    }
                }
            }
            any(bad)
        }

        /// Sorts `keys` lane-wise ascending ([`super::sort_keys`]); the
        /// compiler keeps only the comparators that the positions read afterwards
        /// depend on. The keys' bits are compared as integers (module docs).
        #[inline]
        #[target_feature(enable = $features)]
        fn sort_keys<const M: usize>(keys: &mut [X; M]) {
            for_each_comparator!(Fixed::<M>::NETWORK, |i, j| {
                if let Ok([x, y]) = keys.get_disjoint_mut([i, j]) {
                    let (ka, kb) = (*x, *y);
                    *x = min_i32(ka, kb);
                    *y = max_i32(ka, kb);
                }
            });
        }

        /// [`super::weighted_median_ends`].
        #[inline]
        #[target_feature(enable = $features)]
        fn weighted_median_ends<const M: usize>(
            keys: &[X; M],
            payload: &[X; M],
            total: X,
        ) -> (X, X) {
            let two = splat(2.0);
            let (mut cum, mut lo, mut hi) = (zero(), zero(), zero());
            for (&x, &wt) in keys.iter().zip(payload) {
                let before = mul(two, cum);
                let now = add(cum, wt);
                cum = now;
                let after = mul(two, now);
                lo = add(lo, keep(and(ge(after, total), lt(before, total)), x));
                hi = add(hi, keep(and(gt(after, total), le(before, total)), x));
            }
            (lo, hi)
        }

        /// [`super::median_ends`]: the keys at positions `lo_pos` and
        /// `hi_pos`, 0 if none. One position matches at most, so the sum there is a
        /// select here, which is the same (the keys are squared residuals, never -0)
        /// and shorter: it follows the sort on the critical path.
        #[inline]
        #[target_feature(enable = $features)]
        fn median_ends<const M: usize>(keys: &[X; M], lo_pos: X, hi_pos: X) -> (X, X) {
            let (mut lo, mut hi) = (zero(), zero());
            let mut k = 0.0f32;
            for &x in keys.iter().take(M / 2 + 1) {
                let at = splat(k);
                lo = select(eq(at, lo_pos), x, lo);
                hi = select(eq(at, hi_pos), x, hi);
                k += 1.0;
            }
            (lo, hi)
        }

        /// [`super::Setup::pass`]: the residuals `r2` at `cur` and
        /// `1 / (cutoff sigma)^2`.
        #[inline]
        #[target_feature(enable = $features)]
        fn pass<const M: usize, const UNIT: bool>(
            views: &[UsedView; M],
            g: &Group<'_, M>,
            positions: (X, X),
            params: &Params,
            cur: X,
            r2: &mut [X; M],
        ) -> X {
            let mut key = [zero(); M];
            for (((r, k), view), (&s, &q2)) in r2
                .iter_mut()
                .zip(key.iter_mut())
                .zip(views)
                .zip(g.s.iter().zip(g.q2))
            {
                let d = sub(s, cur);
                let ri = add(mul(mul(splat(view.n), d), d), q2);
                *r = ri;
                *k = ri;
            }
            let (lo, hi) = if UNIT {
                sort_keys(&mut key);
                median_ends(&key, positions.0, positions.1)
            } else {
                let mut pay = *g.w;
                sort_pairs!(M, key, pay);
                weighted_median_ends(&key, &pay, g.total_w)
            };
            let median = mul(add(sqrt(lo), sqrt(hi)), splat(0.5));
            let c = mul(
                splat(params.cutoff),
                max_or(mul(splat(MAD_TO_SIGMA), median), splat(params.sigma_floor)),
            );
            div(splat(1.0), mul(c, c))
        }

        /// The outputs of a group: parallax, confidence, residual, perpendicular,
        /// `n_used`.
        struct Solved {
            parallax: X,
            confidence: X,
            residual: X,
            perpendicular: X,
            n_used: X,
        }

        /// [`super::Setup::block`] after the gather: start, iterations,
        /// final pass, outputs.
        #[inline]
        #[target_feature(enable = $features)]
        fn solve<const M: usize, const UNIT: bool>(
            setup: &Setup<'_>,
            views: &[UsedView; M],
            g: &Group<'_, M>,
        ) -> Solved {
            let params = &setup.params;
            // The positions of the unit-weight median's ends
            // ([`super::Setup::gather`]).
            let (one, half) = (splat(1.0), splat(0.5));
            let some = gt(g.count, zero());
            let positions = (
                select(some, trunc(mul(sub(g.count, one), half)), splat(-1.0)),
                select(some, trunc(mul(g.count, half)), splat(-1.0)),
            );
            // The start: the weighted median of the s_i with weights a_i.
            let mut key = [zero(); M];
            let mut pay = *g.a;
            for (k, (&s, &a)) in key.iter_mut().zip(g.s.iter().zip(g.a)) {
                *k = select(gt(a, zero()), s, splat(LAST));
            }
            sort_pairs!(M, key, pay);
            let (lo, hi) = weighted_median_ends(&key, &pay, g.total_a);
            let mut cur = mul(add(lo, hi), half);
            let mut active = gt(g.total_a, zero());

            let mut r2 = [zero(); M];
            // `iterations` times a pass and an update (stopping once no lane is
            // active), then a final pass; one call of `pass`, so that it is inlined.
            let mut ic;
            let mut iteration = 0;
            loop {
                ic = pass::<M, UNIT>(views, g, positions, params, cur, &mut r2);
                if iteration == params.iterations {
                    break;
                }
                iteration += 1;
                // [`super::Setup::update`].
                let (mut num, mut den) = (zero(), zero());
                for ((&ri, &ai), &si) in r2.iter().zip(g.a).zip(g.s) {
                    let t = max_or(sub(one, mul(ri, ic)), zero());
                    let bw = mul(mul(ai, t), t);
                    num = add(num, mul(bw, si));
                    den = add(den, bw);
                }
                let next = select(gt(den, zero()), div(num, den), cur);
                let done = or(le(den, zero()), lt(abs(sub(next, cur)), splat(TOLERANCE)));
                cur = select(active, next, cur);
                active = and_not(active, done);
                if !any(active) {
                    // As on the general path: the final pass comes next.
                    iteration = params.iterations;
                }
            }

            // [`super::Setup::finish`].
            let (mut n, mut sum_b, mut sum_br, mut sum_q, mut info) =
                (zero(), zero(), zero(), zero(), zero());
            for (((&ri, &wi), &qi), &ai) in r2.iter().zip(g.w).zip(g.q2).zip(g.a) {
                let x = mul(ri, ic);
                let kept = and(gt(wi, zero()), lt(x, one));
                let t = max_or(sub(one, x), zero());
                let bw = mul(mul(wi, t), t);
                n = add(n, keep(kept, one));
                sum_b = add(sum_b, bw);
                sum_br = add(sum_br, keep(kept, mul(bw, ri)));
                sum_q = add(sum_q, keep(kept, qi));
                info = add(info, keep(kept, ai));
            }
            let ok = ge(n, splat(params.min_views as f32));
            let rms = sqrt(div(sum_br, sum_b));
            let z = mul(rms, splat(1.0 / CONFIDENCE_TAU));
            let confidence = mul(
                sub(one, exp_neg(mul(neg(info), splat(setup.info_scale)))),
                exp_neg(mul(neg(z), z)),
            );
            let confidence = min_or(max_or(confidence, zero()), one);
            let nan = splat(f32::NAN);
            Solved {
                parallax: select(ok, cur, nan),
                confidence: keep(ok, confidence),
                residual: select(ok, rms, nan),
                perpendicular: select(ok, sqrt(div(sum_q, n)), nan),
                n_used: n,
            }
        }

        /// Up to [`GROUP`] pixels of the outputs.
        struct GroupOut<'b> {
            parallax: &'b mut [f32],
            confidence: &'b mut [f32],
            residual: &'b mut [f32],
            perpendicular: &'b mut [f32],
            n_used: &'b mut [u8],
        }

        impl GroupOut<'_> {
            /// No usable view anywhere in the group.
            fn fill_empty(self) {
                self.parallax.fill(f32::NAN);
                self.residual.fill(f32::NAN);
                self.perpendicular.fill(f32::NAN);
                self.confidence.fill(0.0);
                self.n_used.fill(0);
            }

            #[inline]
            #[target_feature(enable = $features)]
            fn store(self, solved: &Solved) {
                let registers = (solved.parallax.0.iter().zip(&solved.confidence.0))
                    .zip(solved.residual.0.iter().zip(&solved.perpendicular.0))
                    .zip(&solved.n_used.0);
                let outs = (self.parallax.chunks_mut(LANES))
                    .zip(self.confidence.chunks_mut(LANES))
                    .zip(
                        self.residual
                            .chunks_mut(LANES)
                            .zip(self.perpendicular.chunks_mut(LANES)),
                    )
                    .zip(self.n_used.chunks_mut(LANES));
                for ((((p, c), (r, q)), n), (((&pv, &cv), (&rv, &qv)), &nv)) in outs.zip(registers)
                {
                    put(p, pv);
                    put(c, cv);
                    put(r, rv);
                    put(q, qv);
                    // At most MAX_USED_VIEWS views: exact in f32 and in u8.
                    put_counts(n, nv);
                }
            }
        }

        /// The rows of `out` (whole rows from `first_row` on) for `M` used views.
        #[target_feature(enable = $features)]
        fn rows_of<const M: usize>(
            setup: &Setup<'_>,
            first_row: usize,
            out: Outputs<'_>,
            buffer: &mut Buffer,
        ) -> Result<()> {
            let internal = || Error::internal("triangulate", "view count or row out of range");
            let views: &[UsedView; M] =
                setup.views.as_slice().try_into().map_err(|_| internal())?;
            let w = setup.width();
            let stride = 4 * M;
            let size = SEGMENT.min(w).div_ceil(GROUP) * stride;
            if buffer.0.len() < size {
                buffer.0.resize(size, zero());
            }
            for (k, row) in out.chunks(w).enumerate() {
                let y = first_row + k;
                for (c, segment) in row.chunks(SEGMENT).enumerate() {
                    let Outputs {
                        parallax: par,
                        confidence: conf,
                        residual: res,
                        perpendicular: perp,
                        n_used: used,
                    } = segment;
                    let (x0, len) = (c * SEGMENT, par.len());
                    let groups = buffer
                        .0
                        .get_mut(..len.div_ceil(GROUP) * stride)
                        .ok_or_else(internal)?;
                    // The per-view quantities, view by view.
                    let mut bad = false;
                    for (i, view) in views.iter().enumerate() {
                        let flow = setup
                            .flows
                            .span(view.index, y, x0, len)
                            .ok_or_else(internal)?;
                        let weight = match &setup.weights {
                            Some(ws) => Some(ws.span(view.index, y, x0, len).ok_or_else(internal)?),
                            None => None,
                        };
                        let (full, rest) = flow.as_chunks::<{ 2 * LANES }>();
                        let (full_w, rest_w) = weight.map_or((&[][..], &[][..]), |w| w.as_chunks());
                        // The pixels left over, padded with unusable lanes to a whole
                        // group.
                        let mut pad_flow = [NO_FLOW; K];
                        let mut pad_weight = [NO_WEIGHT; K];
                        for (d, &v) in pad_flow.as_flattened_mut().iter_mut().zip(rest) {
                            *d = v;
                        }
                        for (d, &v) in pad_weight.as_flattened_mut().iter_mut().zip(rest_w) {
                            *d = v;
                        }
                        let tail = len.div_ceil(GROUP) * K - full.len();
                        let (pf, pw) = (
                            pad_flow.get(..tail).ok_or_else(internal)?,
                            pad_weight.get(..tail).ok_or_else(internal)?,
                        );
                        let (flows, weights) = (full.iter().chain(pf), full_w.iter().chain(pw));
                        bad |= if weight.is_some() {
                            gather_view::<M, true>(i, view, flows, weights, groups)
                        } else {
                            gather_view::<M, false>(i, view, flows, weights, groups)
                        };
                    }
                    if bad {
                        return Err(bad_weight(setup, views, y, x0, len));
                    }
                    // The estimator, group by group, while the next segment's flows and
                    // weights are fetched.
                    let (ny, nx) = if x0 + SEGMENT < w {
                        (y, x0 + SEGMENT)
                    } else {
                        (y + 1, 0)
                    };
                    let mut prefetcher = Prefetcher::new(setup, views, ny, nx, len.div_ceil(GROUP));
                    let outs = par
                        .chunks_mut(GROUP)
                        .zip(conf.chunks_mut(GROUP))
                        .zip(res.chunks_mut(GROUP))
                        .zip(perp.chunks_mut(GROUP))
                        .zip(used.chunks_mut(GROUP));
                    for (data, ((((parallax, confidence), residual), perpendicular), n_used)) in
                        groups.chunks_exact(stride).zip(outs)
                    {
                        let out = GroupOut {
                            parallax,
                            confidence,
                            residual,
                            perpendicular,
                            n_used,
                        };
                        prefetcher.step();
                        let g = Group::<M>::new(data).ok_or_else(internal)?;
                        if !any(gt(g.total_a, zero())) {
                            out.fill_empty();
                        } else if all(g.unit) {
                            out.store(&solve::<M, true>(setup, views, &g));
                        } else {
                            out.store(&solve::<M, false>(setup, views, &g));
                        }
                    }
                }
            }
            Ok(())
        }

        /// The rows of `out` from `first_row` on, for a `setup` that
        /// [`super::fixed::takes`].
        ///
        /// # Errors
        /// As [`super::Setup::rows`].
        #[target_feature(enable = $features)]
        pub(super) fn rows(
            setup: &Setup<'_>,
            first_row: usize,
            out: Outputs<'_>,
            buffer: &mut Buffer,
        ) -> Result<()> {
            const _: () = assert!(MAX_USED_VIEWS == 16);
            match setup.views.len() {
                1 => rows_of::<1>(setup, first_row, out, buffer),
                2 => rows_of::<2>(setup, first_row, out, buffer),
                3 => rows_of::<3>(setup, first_row, out, buffer),
                4 => rows_of::<4>(setup, first_row, out, buffer),
                5 => rows_of::<5>(setup, first_row, out, buffer),
                6 => rows_of::<6>(setup, first_row, out, buffer),
                7 => rows_of::<7>(setup, first_row, out, buffer),
                8 => rows_of::<8>(setup, first_row, out, buffer),
                9 => rows_of::<9>(setup, first_row, out, buffer),
                10 => rows_of::<10>(setup, first_row, out, buffer),
                11 => rows_of::<11>(setup, first_row, out, buffer),
                12 => rows_of::<12>(setup, first_row, out, buffer),
                13 => rows_of::<13>(setup, first_row, out, buffer),
                14 => rows_of::<14>(setup, first_row, out, buffer),
                15 => rows_of::<15>(setup, first_row, out, buffer),
                16 => rows_of::<16>(setup, first_row, out, buffer),
                m => Err(Error::internal(
                    "triangulate",
                    format!("{m} used views on the few-view path"),
                )),
            }
        }
    };
}

pub(super) use estimator;
