//! The few-view estimator ([`super::fixed`]) for AVX-512 (AVX512F): groups of 32 pixels
//! in 2 registers of 16 float32, lane masks in mask registers. Half the instructions of
//! the AVX2 build, and 32 vector registers instead of 16.

use std::arch::x86_64::{
    __m128i, __m256, __m512, __mmask16, _CMP_EQ_OQ, _CMP_GE_OQ, _CMP_GT_OQ, _CMP_LE_OQ, _CMP_LT_OQ,
    _mm_extract_epi64, _mm256_castpd_ps, _mm256_castps_si256, _mm256_extract_epi32, _mm512_abs_ps,
    _mm512_add_epi32, _mm512_add_ps, _mm512_castps_pd, _mm512_castps_si512, _mm512_castps512_ps256,
    _mm512_castsi512_ps, _mm512_cmp_ps_mask, _mm512_cvtepi32_epi8, _mm512_cvtepi32_ps,
    _mm512_cvttps_epi32, _mm512_div_ps, _mm512_extractf64x4_pd, _mm512_mask_blend_ps,
    _mm512_maskz_mov_ps, _mm512_max_epi32, _mm512_max_ps, _mm512_min_epi32, _mm512_min_ps,
    _mm512_mul_ps, _mm512_permutex2var_ps, _mm512_set1_epi32, _mm512_set1_ps, _mm512_setr_epi32,
    _mm512_setr_ps, _mm512_setzero_ps, _mm512_slli_epi32, _mm512_sqrt_ps, _mm512_sub_ps,
    _mm512_xor_si512,
};

type V = __m512;

/// Float32 per register.
const LANES: usize = 16;

/// Registers per group: 2 independent chains, as with AVX2 (docs/tuning.md,
/// "Triangulation kernel").
const K: usize = 2;

/// `K` registers of 16 float32 lanes.
#[derive(Clone, Copy)]
struct X([V; K]);

/// Lane masks of `K` registers.
#[derive(Clone, Copy)]
struct Mask([__mmask16; K]);

/// The bits of `a` as `i32` lanes, through `op`, back.
macro_rules! as_i32 {
    ($op:ident($($arg:expr),*)) => {
        _mm512_castsi512_ps($op($(_mm512_castps_si512($arg)),*))
    };
}

lanewise!("avx512f", fn add(a, b) = _mm512_add_ps(a, b));
lanewise!("avx512f", fn sub(a, b) = _mm512_sub_ps(a, b));
lanewise!("avx512f", fn mul(a, b) = _mm512_mul_ps(a, b));
lanewise!("avx512f", fn div(a, b) = _mm512_div_ps(a, b));
lanewise!("avx512f", fn sqrt(a) = _mm512_sqrt_ps(a));
lanewise!("avx512f",
    /// `a.max(b)` for `b` not NaN (`vmaxps` returns `b` if `a` is NaN, as `f32::max`).
    fn max_or(a, b) = _mm512_max_ps(a, b)
);
lanewise!("avx512f",
    /// `a.min(b)` for `b` not NaN.
    fn min_or(a, b) = _mm512_min_ps(a, b)
);
lanewise!("avx512f",
    /// The lesser of `a` and `b` with their bits read as `i32`.
    fn min_i32(a, b) = as_i32!(_mm512_min_epi32(a, b))
);
lanewise!("avx512f",
    /// The greater of `a` and `b` with their bits read as `i32`.
    fn max_i32(a, b) = as_i32!(_mm512_max_epi32(a, b))
);
lanewise!("avx512f", fn xor(a, b) = as_i32!(_mm512_xor_si512(a, b)));
lanewise!("avx512f", fn abs(a) = _mm512_abs_ps(a));
lanewise!("avx512f",
    /// `-x`, flipping the sign bit (as Rust's unary minus does, also for 0 and NaN).
    fn neg(a) = as_i32!(_mm512_xor_si512(a, _mm512_castsi512_ps(_mm512_set1_epi32(i32::MIN))))
);
lanewise!("avx512f",
    /// Truncation towards zero of lanes holding small integers, as float32.
    fn trunc(a) = _mm512_cvtepi32_ps(_mm512_cvttps_epi32(a))
);
lanewise!("avx512f",
    /// `2^k` for lanes holding integers `k` in `-126..=0`.
    fn pow2(k) = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(
        _mm512_cvttps_epi32(k),
        _mm512_set1_epi32(127),
    )))
);
lanewise!("avx512f", fn lt(a, b) -> Mask = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(a, b));
lanewise!("avx512f", fn le(a, b) -> Mask = _mm512_cmp_ps_mask::<_CMP_LE_OQ>(a, b));
lanewise!("avx512f", fn gt(a, b) -> Mask = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, b));
lanewise!("avx512f", fn ge(a, b) -> Mask = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(a, b));
lanewise!("avx512f", fn eq(a, b) -> Mask = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(a, b));

/// Lane-wise `op` of two masks.
fn masks(a: Mask, b: Mask, op: impl Fn(__mmask16, __mmask16) -> __mmask16) -> Mask {
    let mut r = a;
    for (r, (&a, &b)) in r.0.iter_mut().zip(a.0.iter().zip(&b.0)) {
        *r = op(a, b);
    }
    r
}

#[inline]
fn and(a: Mask, b: Mask) -> Mask {
    masks(a, b, |a, b| a & b)
}

#[inline]
fn or(a: Mask, b: Mask) -> Mask {
    masks(a, b, |a, b| a | b)
}

/// `a & !b`.
#[inline]
fn and_not(a: Mask, b: Mask) -> Mask {
    masks(a, b, |a, b| a & !b)
}

/// The mask set in every lane.
#[inline]
fn all_lanes() -> Mask {
    Mask([__mmask16::MAX; K])
}

/// Whether the mask `m` is set in some lane.
#[inline]
fn any(m: Mask) -> bool {
    m.0.iter().any(|&k| k != 0)
}

/// Whether the mask `m` is set in every lane.
#[inline]
fn all(m: Mask) -> bool {
    m.0.iter().all(|&k| k == __mmask16::MAX)
}

/// `x` where the mask `m` is set, else +0.
#[inline]
#[target_feature(enable = "avx512f")]
fn keep(m: Mask, x: X) -> X {
    let mut r = x;
    for (r, (&m, &x)) in r.0.iter_mut().zip(m.0.iter().zip(&x.0)) {
        *r = _mm512_maskz_mov_ps(m, x);
    }
    r
}

/// `a` where the mask `m` is set, else `b`.
#[inline]
#[target_feature(enable = "avx512f")]
fn select(m: Mask, a: X, b: X) -> X {
    let mut r = a;
    for ((r, &m), (&a, &b)) in r.0.iter_mut().zip(&m.0).zip(a.0.iter().zip(&b.0)) {
        *r = _mm512_mask_blend_ps(m, b, a);
    }
    r
}

#[inline]
#[target_feature(enable = "avx512f")]
fn splat(x: f32) -> X {
    X([_mm512_set1_ps(x); K])
}

#[inline]
#[target_feature(enable = "avx512f")]
fn zero() -> X {
    X([_mm512_setzero_ps(); K])
}

#[inline]
#[target_feature(enable = "avx512f")]
fn load(a: &[f32; LANES]) -> V {
    let [
        a0,
        a1,
        a2,
        a3,
        a4,
        a5,
        a6,
        a7,
        a8,
        a9,
        a10,
        a11,
        a12,
        a13,
        a14,
        a15,
    ] = *a;
    _mm512_setr_ps(
        a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12, a13, a14, a15,
    )
}

/// The `x` and `y` components of 16 interleaved flow vectors.
#[inline]
#[target_feature(enable = "avx512f")]
fn load_flow(f: &[f32; 2 * LANES]) -> (V, V) {
    let (lo, hi) = f.split_at(LANES);
    let (Ok(lo), Ok(hi)) = (lo.try_into(), hi.try_into()) else {
        return (_mm512_set1_ps(f32::NAN), _mm512_set1_ps(f32::NAN));
    };
    let (lo, hi) = (load(lo), load(hi));
    let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    (
        _mm512_permutex2var_ps(lo, even, hi),
        _mm512_permutex2var_ps(lo, odd, hi),
    )
}

/// The 8 lanes of `h`.
#[inline]
#[target_feature(enable = "avx512f")]
fn half(h: __m256) -> [f32; 8] {
    let i = _mm256_castps_si256(h);
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

/// `v` into `dst` (16 values, or the first `dst.len()` of them).
#[inline]
#[target_feature(enable = "avx512f")]
fn put(dst: &mut [f32], v: V) {
    let (lo, hi) = (
        half(_mm512_castps512_ps256(v)),
        half(_mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(
            _mm512_castps_pd(v),
        ))),
    );
    match dst.split_first_chunk_mut::<8>() {
        Some((d_lo, rest)) => {
            *d_lo = lo;
            match rest.first_chunk_mut::<8>() {
                Some(d_hi) => *d_hi = hi,
                None => rest.iter_mut().zip(hi).for_each(|(d, x)| *d = x),
            }
        }
        None => dst.iter_mut().zip(lo).for_each(|(d, x)| *d = x),
    }
}

/// Counts `v` (integers in `0..=255` as float32) into `dst` as bytes.
#[inline]
#[target_feature(enable = "avx512f")]
fn put_counts(dst: &mut [u8], v: V) {
    let bytes: __m128i = _mm512_cvtepi32_epi8(_mm512_cvttps_epi32(v));
    let lo = (_mm_extract_epi64::<0>(bytes) as u64).to_le_bytes();
    let hi = (_mm_extract_epi64::<1>(bytes) as u64).to_le_bytes();
    for (d, x) in dst.iter_mut().zip(lo.into_iter().chain(hi)) {
        *d = x;
    }
}

super::fixed::estimator!("avx512f");
