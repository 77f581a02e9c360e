//! The few-view estimator ([`super::fixed`]) for AVX2: groups of 16 pixels in 2
//! registers of 8 float32, lane masks as vectors (all ones or all zeros).

use std::arch::x86_64::{
    __m256, _CMP_EQ_OQ, _CMP_GE_OQ, _CMP_GT_OQ, _CMP_LE_OQ, _CMP_LT_OQ, _mm256_add_epi32,
    _mm256_add_ps, _mm256_and_ps, _mm256_andnot_ps, _mm256_blendv_ps, _mm256_castpd_ps,
    _mm256_castps_pd, _mm256_castps_si256, _mm256_castsi256_ps, _mm256_cmp_ps, _mm256_cvtepi32_ps,
    _mm256_cvttps_epi32, _mm256_div_ps, _mm256_extract_epi32, _mm256_extract_epi64,
    _mm256_max_epi32, _mm256_max_ps, _mm256_min_epi32, _mm256_min_ps, _mm256_movemask_ps,
    _mm256_mul_ps, _mm256_or_ps, _mm256_permute4x64_pd, _mm256_permutevar8x32_epi32,
    _mm256_set1_epi32, _mm256_set1_ps, _mm256_setr_epi8, _mm256_setr_epi32, _mm256_setr_ps,
    _mm256_setzero_ps, _mm256_shuffle_epi8, _mm256_shuffle_ps, _mm256_slli_epi32, _mm256_sqrt_ps,
    _mm256_sub_ps, _mm256_xor_ps, _mm256_xor_si256,
};

type V = __m256;

/// Float32 per register.
const LANES: usize = 8;

/// Registers per group: 2 independent chains (with one the chains' latency shows, with
/// four the spills; docs/tuning.md, "Triangulation kernel").
const K: usize = 2;

/// `K` registers of 8 float32 lanes.
#[derive(Clone, Copy)]
struct X([V; K]);

/// Lane masks of `K` registers: all ones or all zeros per lane.
type Mask = X;

lanewise!("avx2", fn add(a, b) = _mm256_add_ps(a, b));
lanewise!("avx2", fn sub(a, b) = _mm256_sub_ps(a, b));
lanewise!("avx2", fn mul(a, b) = _mm256_mul_ps(a, b));
lanewise!("avx2", fn div(a, b) = _mm256_div_ps(a, b));
lanewise!("avx2", fn sqrt(a) = _mm256_sqrt_ps(a));
lanewise!("avx2",
    /// `a.max(b)` for `b` not NaN (`vmaxps` returns `b` if `a` is NaN, as `f32::max`).
    fn max_or(a, b) = _mm256_max_ps(a, b)
);
lanewise!("avx2",
    /// `a.min(b)` for `b` not NaN.
    fn min_or(a, b) = _mm256_min_ps(a, b)
);
lanewise!("avx2",
    /// The lesser of `a` and `b` with their bits read as `i32`.
    fn min_i32(a, b) = _mm256_castsi256_ps(_mm256_min_epi32(
        _mm256_castps_si256(a),
        _mm256_castps_si256(b),
    ))
);
lanewise!("avx2",
    /// The greater of `a` and `b` with their bits read as `i32`.
    fn max_i32(a, b) = _mm256_castsi256_ps(_mm256_max_epi32(
        _mm256_castps_si256(a),
        _mm256_castps_si256(b),
    ))
);
lanewise!("avx2", fn xor(a, b) = _mm256_xor_ps(a, b));
lanewise!("avx2", fn abs(a) = _mm256_andnot_ps(_mm256_set1_ps(-0.0), a));
lanewise!("avx2",
    /// `-x`, flipping the sign bit (as Rust's unary minus does, also for 0 and NaN).
    fn neg(a) = _mm256_castsi256_ps(_mm256_xor_si256(
        _mm256_castps_si256(a),
        _mm256_set1_epi32(i32::MIN),
    ))
);
lanewise!("avx2",
    /// Truncation towards zero of lanes holding small integers, as float32.
    fn trunc(a) = _mm256_cvtepi32_ps(_mm256_cvttps_epi32(a))
);
lanewise!("avx2",
    /// `2^k` for lanes holding integers `k` in `-126..=0`.
    fn pow2(k) = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
        _mm256_cvttps_epi32(k),
        _mm256_set1_epi32(127),
    )))
);
lanewise!("avx2", fn lt(a, b) = _mm256_cmp_ps::<_CMP_LT_OQ>(a, b));
lanewise!("avx2", fn le(a, b) = _mm256_cmp_ps::<_CMP_LE_OQ>(a, b));
lanewise!("avx2", fn gt(a, b) = _mm256_cmp_ps::<_CMP_GT_OQ>(a, b));
lanewise!("avx2", fn ge(a, b) = _mm256_cmp_ps::<_CMP_GE_OQ>(a, b));
lanewise!("avx2", fn eq(a, b) = _mm256_cmp_ps::<_CMP_EQ_OQ>(a, b));
lanewise!("avx2", fn and(a, b) = _mm256_and_ps(a, b));
lanewise!("avx2", fn or(a, b) = _mm256_or_ps(a, b));
lanewise!("avx2",
    /// `a & !b`.
    fn and_not(a, b) = _mm256_andnot_ps(b, a)
);
lanewise!("avx2",
    /// `x` where the mask `m` is set, else +0.
    fn keep(m, x) = _mm256_and_ps(m, x)
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

/// The mask set in every lane.
#[inline]
#[target_feature(enable = "avx2")]
fn all_lanes() -> Mask {
    X([_mm256_castsi256_ps(_mm256_set1_epi32(-1)); K])
}

/// `a` where the mask `m` is set, else `b`.
#[inline]
#[target_feature(enable = "avx2")]
fn select(m: Mask, a: X, b: X) -> X {
    let mut r = a;
    for ((r, &m), (&a, &b)) in r.0.iter_mut().zip(&m.0).zip(a.0.iter().zip(&b.0)) {
        *r = _mm256_blendv_ps(b, a, m);
    }
    r
}

/// Whether the mask `m` is set in some lane.
#[inline]
#[target_feature(enable = "avx2")]
fn any(m: Mask) -> bool {
    m.0.iter().any(|&v| _mm256_movemask_ps(v) != 0)
}

/// Whether the mask `m` is set in every lane.
#[inline]
#[target_feature(enable = "avx2")]
fn all(m: Mask) -> bool {
    m.0.iter().all(|&v| _mm256_movemask_ps(v) == 0xff)
}

#[inline]
#[target_feature(enable = "avx2")]
fn load(a: &[f32; LANES]) -> V {
    let [a0, a1, a2, a3, a4, a5, a6, a7] = *a;
    _mm256_setr_ps(a0, a1, a2, a3, a4, a5, a6, a7)
}

/// The `x` and `y` components of 8 interleaved flow vectors.
#[inline]
#[target_feature(enable = "avx2")]
fn load_flow(f: &[f32; 2 * LANES]) -> (V, V) {
    let (lo, hi) = f.split_at(LANES);
    let (Ok(lo), Ok(hi)) = (lo.try_into(), hi.try_into()) else {
        return (_mm256_set1_ps(f32::NAN), _mm256_set1_ps(f32::NAN));
    };
    let (lo, hi) = (load(lo), load(hi));
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
    let i = _mm256_castps_si256(v);
    let f = |bits: i32| f32::from_bits(bits as u32);
    let values = [
        f(_mm256_extract_epi32::<0>(i)),
        f(_mm256_extract_epi32::<1>(i)),
        f(_mm256_extract_epi32::<2>(i)),
        f(_mm256_extract_epi32::<3>(i)),
        f(_mm256_extract_epi32::<4>(i)),
        f(_mm256_extract_epi32::<5>(i)),
        f(_mm256_extract_epi32::<6>(i)),
        f(_mm256_extract_epi32::<7>(i)),
    ];
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

super::fixed::estimator!("avx2");
