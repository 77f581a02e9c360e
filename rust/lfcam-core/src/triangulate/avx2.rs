//! The AVX2 path of [`triangulate`](super::triangulate) for up to [`MAX_USED_VIEWS`] used views
//! (the 3 x 4 camera has 11): [`GROUP`] pixels at a time with every per-view quantity in
//! vector registers, and the sorting networks unrolled at compile time for the view
//! count.
//!
//! The general path ([`super::Setup::rows`]) keeps per-view rows of 64 pixels in
//! scratch memory and applies a network read at run time: every comparator loads and
//! stores its rows, and the loops around it cost as much again. Here the number of
//! used views `M` is a const generic (one instantiation per count), so the network
//! ([`batcher`]: the same comparators in the same order) becomes straight-line code on
//! registers, and the compiler drops the comparators whose results are never read (the
//! upper half, for the unit-weight medians).
//!
//! In registers the work of one pixel is a long chain of dependent operations (sort,
//! square root, division, the sums over the views), so each step works on [`K`]
//! registers of 8 pixels: independent chains for the CPU to overlap.
//!
//! # The same numbers
//! Every per-pixel quantity is computed by the same float32 operations in the same order
//! as on the general path, and a pixel's results do not depend on the pixels it is
//! computed with (a lane that has converged keeps its `s`; the unit-weight and weighted
//! medians agree for weights 0 and 1): the outputs are the same bits
//! (`tests::few_view_avx2_path_equals_general_path`). The compare-exchanges of keys use
//! `vminps` / `vmaxps`, which order keys as the general path's baseline build does (its
//! AVX2 build compares the keys' bits as integers: the two differ only for NaN keys,
//! which need a residual that overflows float32).
//!
//! # Safety
//! The functions here are `#[target_feature(enable = "avx2")]`: calling them from code
//! compiled without AVX2 is unsafe, and [`super::rows_task`] does so only after
//! [`crate::simd::has_avx2`]. Among themselves they are safe to call, and so are the
//! arithmetic intrinsics; memory is read and written through arrays only (`setr` and
//! lane extracts, which the compiler turns into vector loads and stores).

use std::arch::x86_64::{
    __m256, _CMP_EQ_OQ, _CMP_GE_OQ, _CMP_GT_OQ, _CMP_LE_OQ, _CMP_LT_OQ, _MM_HINT_T0, _mm_prefetch,
    _mm256_add_epi32, _mm256_add_ps, _mm256_and_ps, _mm256_andnot_ps, _mm256_blendv_ps,
    _mm256_castpd_ps, _mm256_castps_pd, _mm256_castps_si256, _mm256_castsi256_ps, _mm256_cmp_ps,
    _mm256_cvtepi32_ps, _mm256_cvttps_epi32, _mm256_div_ps, _mm256_extract_epi32,
    _mm256_extract_epi64, _mm256_max_epi32, _mm256_max_ps, _mm256_min_epi32, _mm256_min_ps,
    _mm256_movemask_ps, _mm256_mul_ps, _mm256_or_ps, _mm256_permute4x64_pd,
    _mm256_permutevar8x32_epi32, _mm256_set1_epi32, _mm256_set1_ps, _mm256_setr_epi8,
    _mm256_setr_epi32, _mm256_setr_ps, _mm256_setzero_ps, _mm256_shuffle_epi8, _mm256_shuffle_ps,
    _mm256_slli_epi32, _mm256_sqrt_ps, _mm256_sub_ps, _mm256_xor_ps, _mm256_xor_si256,
};

use super::{CONFIDENCE_TAU, LAST, MAD_TO_SIGMA, Outputs, Params, Setup, TOLERANCE, UsedView};
use crate::error::{Error, Result};

/// Most used views (the reference excluded) this path takes; more go to the general
/// path. Batcher's network for 16 values has 63 comparators.
pub(super) const MAX_USED_VIEWS: usize = 16;

/// Pixels per register: 8 float32.
const LANES: usize = 8;

/// Registers per quantity in the estimator: 2 independent chains (measured on the
/// 11-view benchmark: 1 register is latency-bound, 3 spill more than they gain).
const K: usize = 2;

/// Pixels the estimator works on at once.
const GROUP: usize = K * LANES;

/// Room for the comparators of a network of up to [`MAX_USED_VIEWS`] values.
const MAX_COMPARATORS: usize = 64;

type V = __m256;

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
struct Fixed<const M: usize>;

impl<const M: usize> Fixed<M> {
    const NETWORK: Network = batcher(M);
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

// --- lane-wise operations on K registers --------------------------------------------

/// `K` registers of 8 float32 lanes (or of lane masks: all ones or all zeros).
#[derive(Clone, Copy)]
struct X([V; K]);

/// Defines `fn $name(a: X, ...) -> X` applying `$op` register by register.
macro_rules! lanewise {
    ($(#[$meta:meta])* fn $name:ident($a:ident) = $op:expr) => {
        $(#[$meta])*
        #[inline]
        #[target_feature(enable = "avx2")]
        fn $name(a: X) -> X {
            let mut r = a;
            for (r, &$a) in r.0.iter_mut().zip(&a.0) {
                *r = $op;
            }
            r
        }
    };
    ($(#[$meta:meta])* fn $name:ident($a:ident, $b:ident) = $op:expr) => {
        $(#[$meta])*
        #[inline]
        #[target_feature(enable = "avx2")]
        fn $name(a: X, b: X) -> X {
            let mut r = a;
            for (r, (&$a, &$b)) in r.0.iter_mut().zip(a.0.iter().zip(&b.0)) {
                *r = $op;
            }
            r
        }
    };
}

lanewise!(fn add(a, b) = _mm256_add_ps(a, b));
lanewise!(fn sub(a, b) = _mm256_sub_ps(a, b));
lanewise!(fn mul(a, b) = _mm256_mul_ps(a, b));
lanewise!(fn div(a, b) = _mm256_div_ps(a, b));
lanewise!(
    /// `a.max(b)` for `b` not NaN (`vmaxps` returns `b` if `a` is NaN, as `f32::max`).
    fn max_or(a, b) = _mm256_max_ps(a, b)
);
lanewise!(
    /// `a.min(b)` for `b` not NaN.
    fn min_or(a, b) = _mm256_min_ps(a, b)
);
lanewise!(fn lt(a, b) = _mm256_cmp_ps::<_CMP_LT_OQ>(a, b));
lanewise!(fn le(a, b) = _mm256_cmp_ps::<_CMP_LE_OQ>(a, b));
lanewise!(fn gt(a, b) = _mm256_cmp_ps::<_CMP_GT_OQ>(a, b));
lanewise!(fn ge(a, b) = _mm256_cmp_ps::<_CMP_GE_OQ>(a, b));
lanewise!(fn eq(a, b) = _mm256_cmp_ps::<_CMP_EQ_OQ>(a, b));
lanewise!(fn and(a, b) = _mm256_and_ps(a, b));
lanewise!(fn xor(a, b) = _mm256_xor_ps(a, b));
lanewise!(
    /// The lesser of `a` and `b` with their bits read as `i32`.
    fn min_i32(a, b) = _mm256_castsi256_ps(_mm256_min_epi32(
        _mm256_castps_si256(a),
        _mm256_castps_si256(b),
    ))
);
lanewise!(
    /// The greater of `a` and `b` with their bits read as `i32`.
    fn max_i32(a, b) = _mm256_castsi256_ps(_mm256_max_epi32(
        _mm256_castps_si256(a),
        _mm256_castps_si256(b),
    ))
);
lanewise!(fn or(a, b) = _mm256_or_ps(a, b));
lanewise!(
    /// `a & !b`.
    fn and_not(a, b) = _mm256_andnot_ps(b, a)
);
lanewise!(
    /// `x` where the mask `m` is set, else +0.
    fn keep(m, x) = _mm256_and_ps(m, x)
);
lanewise!(fn sqrt(a) = _mm256_sqrt_ps(a));
lanewise!(fn abs(a) = _mm256_andnot_ps(_mm256_set1_ps(-0.0), a));
lanewise!(
    /// `-x`, flipping the sign bit (as Rust's unary minus does, also for 0 and NaN).
    fn neg(a) = _mm256_castsi256_ps(_mm256_xor_si256(
        _mm256_castps_si256(a),
        _mm256_set1_epi32(i32::MIN),
    ))
);
lanewise!(
    /// Truncation towards zero of lanes holding small integers, as float32.
    fn trunc(a) = _mm256_cvtepi32_ps(_mm256_cvttps_epi32(a))
);
#[inline]
#[target_feature(enable = "avx2")]
fn splat(x: f32) -> X {
    X([_mm256_set1_ps(x); K])
}

#[inline]
#[target_feature(enable = "avx2")]
fn zero() -> X {
    X([_mm256_setzero_ps(); K])
}

/// `a` where the mask `m` is set, else `b`.
#[inline]
#[target_feature(enable = "avx2")]
fn select(m: X, a: X, b: X) -> X {
    let mut r = a;
    for ((r, &m), (&a, &b)) in r.0.iter_mut().zip(&m.0).zip(a.0.iter().zip(&b.0)) {
        *r = _mm256_blendv_ps(b, a, m);
    }
    r
}

/// Whether the mask `m` is set in some lane.
#[inline]
#[target_feature(enable = "avx2")]
fn any(m: X) -> bool {
    m.0.iter().any(|&v| _mm256_movemask_ps(v) != 0)
}

/// Whether the mask `m` is set in every lane.
#[inline]
#[target_feature(enable = "avx2")]
fn all(m: X) -> bool {
    m.0.iter().all(|&v| _mm256_movemask_ps(v) == 0xff)
}

/// [`super::exp_neg`], lane-wise, by the same operations.
#[inline]
#[target_feature(enable = "avx2")]
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
    let mut scale = k;
    for s in scale.0.iter_mut() {
        let exponent = _mm256_add_epi32(_mm256_cvttps_epi32(*s), _mm256_set1_epi32(127));
        *s = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(exponent));
    }
    mul(p, scale)
}

// --- memory ------------------------------------------------------------------------

#[inline]
#[target_feature(enable = "avx2")]
fn load(a: &[f32; LANES]) -> V {
    let [a0, a1, a2, a3, a4, a5, a6, a7] = *a;
    _mm256_setr_ps(a0, a1, a2, a3, a4, a5, a6, a7)
}

#[inline]
#[target_feature(enable = "avx2")]
fn to_array(v: V) -> [f32; LANES] {
    let i = _mm256_castps_si256(v);
    let f = |bits: i32| f32::from_bits(bits as u32);
    [
        f(_mm256_extract_epi32::<0>(i)),
        f(_mm256_extract_epi32::<1>(i)),
        f(_mm256_extract_epi32::<2>(i)),
        f(_mm256_extract_epi32::<3>(i)),
        f(_mm256_extract_epi32::<4>(i)),
        f(_mm256_extract_epi32::<5>(i)),
        f(_mm256_extract_epi32::<6>(i)),
        f(_mm256_extract_epi32::<7>(i)),
    ]
}

/// The `x` and `y` components of 8 interleaved flow vectors.
#[inline]
#[target_feature(enable = "avx2")]
fn load_flow(f: &[f32; 2 * LANES]) -> (V, V) {
    let [
        a0,
        a1,
        a2,
        a3,
        a4,
        a5,
        a6,
        a7,
        b0,
        b1,
        b2,
        b3,
        b4,
        b5,
        b6,
        b7,
    ] = *f;
    let lo = _mm256_setr_ps(a0, a1, a2, a3, a4, a5, a6, a7);
    let hi = _mm256_setr_ps(b0, b1, b2, b3, b4, b5, b6, b7);
    // Per 128-bit half: x0 x1 x4 x5 | x2 x3 x6 x7 (and y), then the 64-bit pairs in order.
    let xs = _mm256_shuffle_ps::<0b10_00_10_00>(lo, hi);
    let ys = _mm256_shuffle_ps::<0b11_01_11_01>(lo, hi);
    let order =
        |v: V| _mm256_castpd_ps(_mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_castps_pd(v)));
    (order(xs), order(ys))
}

/// `v` into `dst` (8 values, or the first `dst.len()` of them).
#[inline]
#[target_feature(enable = "avx2")]
fn put(dst: &mut [f32], v: V) {
    let values = to_array(v);
    match dst.first_chunk_mut::<LANES>() {
        Some(d) => *d = values,
        None => dst.iter_mut().zip(values).for_each(|(d, x)| *d = x),
    }
}

/// Counts `v` (integers in `0..=255` as float32) into `dst` as bytes.
#[inline]
#[target_feature(enable = "avx2")]
fn put_counts(dst: &mut [u8], v: V) {
    // Each 32-bit lane's low byte to the bottom of its 128-bit half, then the halves'
    // first 4 bytes together.
    let bytes = _mm256_shuffle_epi8(
        _mm256_cvttps_epi32(v),
        _mm256_setr_epi8(
            0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8, 12, -1, -1, -1,
            -1, -1, -1, -1, -1, -1, -1, -1, -1,
        ),
    );
    let packed = _mm256_permutevar8x32_epi32(bytes, _mm256_setr_epi32(0, 4, 1, 1, 1, 1, 1, 1));
    let values = (_mm256_extract_epi64::<0>(packed) as u64).to_le_bytes();
    match dst.first_chunk_mut::<LANES>() {
        Some(d) => *d = values,
        None => dst.iter_mut().zip(values).for_each(|(d, x)| *d = x),
    }
}

// --- the estimator ----------------------------------------------------------------

/// Pixels per segment: a row is triangulated a segment at a time, first the per-view
/// quantities of the whole segment, view by view, into a [`Buffer`] (each view's flows
/// and weights of the segment are one sequential read, 12 kB for 1024 pixels), then the
/// estimator group by group from the buffer (193 kB for 11 views: in L2), during which
/// [`Prefetcher`] fetches the next segment's flows and weights. Measured against
/// 64-pixel chunks gathered from all views with each chunk prefetched two ahead (CPU
/// time, full-size benchmark, 1 thread, medians of 12 rounds): 45.6 ms; segments
/// without prefetching, 51.8 ms; segments with, 43.9 ms.
const SEGMENT: usize = 1024;

/// The per-view quantities of the groups of a segment, group after group: for each,
/// `s_i`, `a_i`, `w_i`, `q_i^2` of every view (module docs of [`super`]; unusable lanes
/// as there). Kept by the task's scratch, so that it is allocated once per task
/// sequence, not per row.
#[derive(Default)]
pub(super) struct Buffer(Vec<X>);

impl std::fmt::Debug for Buffer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Buffer({} registers)", self.0.len() * K)
    }
}

/// A group's per-view quantities (in a [`Buffer`]) and their totals over the views.
struct Group<'b, const M: usize> {
    s: &'b [X; M],
    a: &'b [X; M],
    w: &'b [X; M],
    q2: &'b [X; M],
    /// Sums of `a_i`, `w_i` and `1 if w_i > 0`, in the order of the views as on the
    /// general path; all ones where every weight is 0 or 1.
    total_a: X,
    total_w: X,
    count: X,
    unit_mask: X,
}

impl<'b, const M: usize> Group<'b, M> {
    /// The group stored in `data` (`4 M` registers), and its totals.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn new(data: &'b [X]) -> Option<Self> {
        let part =
            |i: usize| -> Option<&'b [X; M]> { data.get(i * M..(i + 1) * M)?.try_into().ok() };
        let (s, a, w, q2) = (part(0)?, part(1)?, part(2)?, part(3)?);
        let (one, zeros) = (splat(1.0), zero());
        let (mut total_a, mut total_w, mut count) = (zero(), zero(), zero());
        let mut unit_mask = eq(zeros, zeros);
        for (&a, &w) in a.iter().zip(w) {
            total_a = add(total_a, a);
            total_w = add(total_w, w);
            count = add(count, and(gt(w, zeros), one));
            unit_mask = and(unit_mask, or(eq(w, zeros), eq(w, one)));
        }
        Some(Self {
            s,
            a,
            w,
            q2,
            total_a,
            total_w,
            count,
            unit_mask,
        })
    }
}

/// [`super::gather_view`] for view `k` (`view`) over a segment into `groups` (the
/// buffer, `4 M` registers per group): `flows` gives 16 values (8 pixels) per register,
/// `weights` (if `WEIGHTED`, else 1) 8. Registers past `flows` are left as they are.
/// Returns whether a weight is negative or infinite.
#[inline]
#[target_feature(enable = "avx2")]
fn gather_view<'f, const M: usize, const WEIGHTED: bool>(
    k: usize,
    view: &UsedView,
    mut flows: impl Iterator<Item = &'f [f32; 2 * LANES]>,
    mut weights: impl Iterator<Item = &'f [f32; LANES]>,
    groups: &mut [X],
) -> bool {
    let v = |x: f32| _mm256_set1_ps(x);
    let (zero, one, inf) = (v(0.0), v(1.0), v(f32::INFINITY));
    let (ox, oy, n, inv_n) = (v(view.ox), v(view.oy), v(view.n), v(view.inv_n));
    let mut bad = zero;
    'groups: for g in groups.chunks_exact_mut(4 * M) {
        for j in 0..K {
            let Some(flow) = flows.next() else {
                break 'groups;
            };
            let weight = weights.next();
            let (ux, uy) = load_flow(flow);
            let wt = match weight {
                Some(w) if WEIGHTED => load(w),
                _ => one,
            };
            let si = _mm256_mul_ps(
                _mm256_add_ps(_mm256_mul_ps(ox, ux), _mm256_mul_ps(oy, uy)),
                inv_n,
            );
            let cross = _mm256_sub_ps(_mm256_mul_ps(ox, uy), _mm256_mul_ps(oy, ux));
            let qi = _mm256_mul_ps(_mm256_mul_ps(cross, cross), inv_n);
            let ai = _mm256_mul_ps(wt, n);
            let finite = |x: V| _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(v(-0.0), x), inf);
            if WEIGHTED {
                let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(wt, zero);
                let infinite = _mm256_cmp_ps::<_CMP_EQ_OQ>(wt, inf);
                bad = _mm256_or_ps(bad, _mm256_or_ps(negative, infinite));
            }
            let ok = _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GT_OQ>(wt, zero),
                    _mm256_cmp_ps::<_CMP_GT_OQ>(ai, zero),
                ),
                _mm256_and_ps(finite(si), finite(qi)),
            );
            let values = [
                _mm256_and_ps(ok, si),
                _mm256_and_ps(ok, ai),
                _mm256_and_ps(ok, wt),
                _mm256_blendv_ps(inf, qi, ok),
            ];
            for (i, value) in values.into_iter().enumerate() {
                if let Some(r) = g.get_mut(i * M + k).and_then(|x| x.0.get_mut(j)) {
                    *r = value;
                }
            }
        }
    }
    _mm256_movemask_ps(bad) != 0
}

/// Sorts `keys` lane-wise ascending, carrying `payload` along ([`super::sort_pairs`]).
/// A macro, not a function: called from several places, a function is not inlined,
/// and its arrays then go through memory.
///
/// `kb < ka ? kb : ka` is `vminps(kb, ka)` and `kb < ka ? ka : kb` is `vmaxps(ka, kb)`,
/// also for NaN and zeros of either sign; the payload is swapped with XORs, which run
/// on more of the CPU's vector pipes than blends.
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
                let d = and(swap, xor(*px, *py));
                *px = xor(*px, d);
                *py = xor(*py, d);
            }
        })
    };
}

/// Sorts `keys` lane-wise ascending ([`super::sort_keys`]); the compiler keeps only the
/// comparators that the positions read afterwards depend on. As in the general path's
/// AVX2 build, the keys' bits are compared as integers (`vpminsd` / `vpmaxsd`, which
/// run on other pipes than the float arithmetic around them): for keys `+0`, positive
/// or `+inf`, integer and float order agree.
#[inline]
#[target_feature(enable = "avx2")]
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
#[target_feature(enable = "avx2")]
fn weighted_median_ends<const M: usize>(keys: &[X; M], payload: &[X; M], total: X) -> (X, X) {
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

/// [`super::median_ends`]: the keys at positions `lo_pos` and `hi_pos`, 0 if none. One
/// position matches at most, so the sum there is an OR here, which is the same (the keys
/// are squared residuals, never -0) and shorter: it follows the sort on the critical
/// path.
#[inline]
#[target_feature(enable = "avx2")]
fn median_ends<const M: usize>(keys: &[X; M], lo_pos: X, hi_pos: X) -> (X, X) {
    let (mut lo, mut hi) = (zero(), zero());
    let mut k = 0.0f32;
    for &x in keys.iter().take(M / 2 + 1) {
        let at = splat(k);
        lo = or(lo, keep(eq(at, lo_pos), x));
        hi = or(hi, keep(eq(at, hi_pos), x));
        k += 1.0;
    }
    (lo, hi)
}

/// [`super::Setup::pass`]: the residuals `r2` at `cur` and `1 / (cutoff sigma)^2`.
#[inline]
#[target_feature(enable = "avx2")]
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

/// The outputs of a group: parallax, confidence, residual, perpendicular, `n_used`.
struct Solved {
    parallax: X,
    confidence: X,
    residual: X,
    perpendicular: X,
    n_used: X,
}

/// [`super::Setup::block`] after the gather: start, iterations, final pass, outputs.
#[inline]
#[target_feature(enable = "avx2")]
fn solve<const M: usize, const UNIT: bool>(
    setup: &Setup<'_>,
    views: &[UsedView; M],
    g: &Group<'_, M>,
) -> Solved {
    let params = &setup.params;
    // The positions of the unit-weight median's ends ([`super::Setup::gather`]).
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
    // `iterations` times a pass and an update (stopping once no lane is active), then
    // a final pass; one call of `pass`, so that it is inlined.
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
        n = add(n, and(kept, one));
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

/// Flows and weights of the lanes past the end of a row: unusable.
const NO_FLOW: [f32; 2 * LANES] = [f32::NAN; 2 * LANES];
const NO_WEIGHT: [f32; LANES] = [0.0; LANES];

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
    #[target_feature(enable = "avx2")]
    fn store(self, solved: &Solved) {
        let registers = (solved.parallax.0.iter().zip(&solved.confidence.0))
            .zip(solved.residual.0.iter().zip(&solved.perpendicular.0))
            .zip(&solved.n_used.0);
        let outs = (self
            .parallax
            .chunks_mut(LANES)
            .zip(self.confidence.chunks_mut(LANES)))
        .zip(
            self.residual
                .chunks_mut(LANES)
                .zip(self.perpendicular.chunks_mut(LANES)),
        )
        .zip(self.n_used.chunks_mut(LANES));
        for ((((p, c), (r, q)), n), (((&pv, &cv), (&rv, &qv)), &nv)) in outs.zip(registers) {
            put(p, pv);
            put(c, cv);
            put(r, rv);
            put(q, qv);
            // At most MAX_USED_VIEWS views: exact in f32 and in u8.
            put_counts(n, nv);
        }
    }
}

/// Asks the CPU to fetch a segment's flows and weights into its cache, a part at each
/// [`Self::step`], so that the memory is read while the previous segment is computed
/// (the task's next rows are mostly computed by the same thread).
struct Prefetcher {
    /// Start and length in cache lines of each view's flows and weights (the first
    /// `count`).
    spans: [(*const f32, usize); 2 * MAX_USED_VIEWS],
    count: usize,
    /// Lines per step, and the position: span, line.
    per_step: usize,
    span: usize,
    line: usize,
}

/// Bytes per cache line (of the x86-64 CPUs with AVX2).
const CACHE_LINE: usize = 64;

impl Prefetcher {
    /// For the segment at `(y, x0)` (nothing if outside), over `steps` steps.
    fn new<const M: usize>(
        setup: &Setup<'_>,
        views: &[UsedView; M],
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
    #[target_feature(enable = "avx2")]
    fn step(&mut self) {
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

/// The rows of `out` (whole rows from `first_row` on) for `M` used views.
#[target_feature(enable = "avx2")]
fn rows_of<const M: usize>(
    setup: &Setup<'_>,
    first_row: usize,
    out: Outputs<'_>,
    buffer: &mut Buffer,
) -> Result<()> {
    let internal = || Error::invalid_argument("flows", "internal: view count or row out of range");
    let views: &[UsedView; M] = setup.views.as_slice().try_into().map_err(|_| internal())?;
    let w = setup.width();
    let stride = 4 * M;
    let size = SEGMENT.min(w).div_ceil(GROUP) * stride;
    if buffer.0.len() < size {
        buffer.0.resize(size, zero());
    }
    let rows = out
        .parallax
        .chunks_mut(w)
        .zip(out.confidence.chunks_mut(w))
        .zip(out.residual.chunks_mut(w))
        .zip(out.perpendicular.chunks_mut(w))
        .zip(out.n_used.chunks_mut(w));
    for (k, ((((par, conf), res), perp), used)) in rows.enumerate() {
        let y = first_row + k;
        let segments = par
            .chunks_mut(SEGMENT)
            .zip(conf.chunks_mut(SEGMENT))
            .zip(res.chunks_mut(SEGMENT))
            .zip(perp.chunks_mut(SEGMENT))
            .zip(used.chunks_mut(SEGMENT));
        for (c, ((((par, conf), res), perp), used)) in segments.enumerate() {
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
                // The pixels left over, padded with unusable lanes to a whole group.
                let mut pad_flow = [NO_FLOW; K];
                let mut pad_weight = [NO_WEIGHT; K];
                pad_flow
                    .as_flattened_mut()
                    .iter_mut()
                    .zip(rest)
                    .for_each(|(d, &v)| *d = v);
                pad_weight
                    .as_flattened_mut()
                    .iter_mut()
                    .zip(rest_w)
                    .for_each(|(d, &v)| *d = v);
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
            // The estimator, group by group, while the next segment's flows and weights
            // are fetched.
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
                } else if all(g.unit_mask) {
                    out.store(&solve::<M, true>(setup, views, &g));
                } else {
                    out.store(&solve::<M, false>(setup, views, &g));
                }
            }
        }
    }
    Ok(())
}

/// The error for the first negative or infinite weight of the segment at `(y, x0)`:
/// in the first 64-pixel block holding one, the first view with one, as on the general
/// path.
#[cold]
fn bad_weight<const M: usize>(
    setup: &Setup<'_>,
    views: &[UsedView; M],
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
    Error::invalid_argument("weights", "internal: no bad weight found")
}

/// Whether this path takes `setup` (its number of used views).
pub(super) fn takes(setup: &Setup<'_>) -> bool {
    (1..=MAX_USED_VIEWS).contains(&setup.views.len())
}

/// The rows of `out` from `first_row` on, for a `setup` that [`takes`].
///
/// # Errors
/// As [`super::Setup::rows`].
#[target_feature(enable = "avx2")]
pub(super) fn rows(
    setup: &Setup<'_>,
    first_row: usize,
    out: Outputs<'_>,
    buffer: &mut Buffer,
) -> Result<()> {
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
        m => Err(Error::invalid_argument(
            "flows",
            format!("internal: {m} used views on the AVX2 path"),
        )),
    }
}
