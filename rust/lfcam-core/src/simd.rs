//! Runtime CPU dispatch: a kernel's loops compiled a second time for AVX2 (and, for
//! one kernel, AVX-512), and run when the CPU has it (x86-64 only); the one switch
//! that forces the portable builds everywhere, [`ENV_SIMD`].
//!
//! # Which builds run
//! [`level`] is the widest [`Level`] the kernels run in this process: the CPU's
//! ([`cpu_level`], std's cached CPUID query), capped by `LFCAM_SIMD` (read once):
//! `auto` (or unset) for the widest the CPU has, `avx2` for no AVX-512, `portable` for
//! the portable builds only (other values: `auto`). Each kernel call makes a
//! [`Dispatch`] ([`Dispatch::auto`]: up to [`level`]); tests make narrower ones to run
//! a SIMD build and its portable twin side by side, and read back which ran
//! ([`Dispatch::ran`]). [`simd_info`] reports the choice per kernel family.
//!
//! # The builds
//! The kernels vectorise by the compiler (no intrinsics, but for the exceptions
//! below). The wheel targets baseline x86-64 (SSE2, 4 float lanes); most CPUs in use
//! have AVX2 (8 lanes, three-operand instructions, blends). A kernel opts in by
//! wrapping its per-task loop body, with everything it calls `#[inline(always)]`, in
//! `avx2_or_portable!` (or [`run_avx2_or_portable`] for generic code): it expands to
//! a function compiled with `#[target_feature(enable = "avx2")]` and a portable one,
//! and picks the first when the call's [`Dispatch`] selects AVX2. Floating-point
//! results are identical (Rust never contracts `a * b + c` into an FMA, and AVX2 does
//! not change IEEE arithmetic); tests compare both builds.
//!
//! # Unsafe code
//! The crate's `unsafe` is here. First, this pattern: calling a `#[target_feature]`
//! function is unsafe because running AVX2 instructions on a CPU without them is
//! undefined behaviour; a [`Dispatch`] selects a level only if [`level`] allows it,
//! which the CPU has. It is used through the macro (superres, triangulate) and written
//! out in `rectify::Job::segment`, and in `triangulate::rows_task`, which calls the
//! few-view paths `triangulate::avx2` and `triangulate::avx512`: those are written with
//! `std::arch` intrinsics (safe to call in `#[target_feature]` functions), because they
//! keep whole arrays of vectors in registers, which the compiler's vectoriser does not
//! do for arrays of floats. Second, one kernel written with intrinsics where the
//! compiler's vectorisation falls short: [`bilinear_band`], the inner loop of
//! `rectify::RectifyPlan` (raw-pointer loads at offsets clamped into the buffer, so
//! that no value of its inputs can make it read outside).
//!
//! # Portable twins
//! Every SIMD build has a portable twin that tests compare it with, bit for bit, on
//! the CPU they run on: the portable build of the same loops for the macro's kernels
//! and `rectify`; the general path of `triangulate` for its few-view paths; the
//! portable sampling loop of `RectifyPlan` (and the formula) for [`bilinear_band`].
//! Such a test fails if the SIMD build did not run where [`level`] allows it, and is
//! skipped with a printed reason where it does not (CPU without it, or `LFCAM_SIMD`).

use std::sync::OnceLock;
use std::sync::atomic::{AtomicU8, Ordering};

/// Environment variable capping the SIMD builds kernels run (read once, on first use):
/// `auto` (default), `avx2` or `portable`.
pub const ENV_SIMD: &str = "LFCAM_SIMD";

/// A width of SIMD code, narrowest first: which build of a kernel's loops runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[non_exhaustive]
pub enum Level {
    /// The portable build (baseline x86-64: SSE2; any other CPU).
    Portable,
    /// AVX2 (x86-64).
    Avx2,
    /// AVX-512 foundation (AVX512F; x86-64, with AVX2).
    Avx512,
}

impl Level {
    /// Every level, narrowest first.
    pub const ALL: [Self; 3] = [Self::Portable, Self::Avx2, Self::Avx512];

    /// `"portable"`, `"avx2"` or `"avx512"`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Portable => "portable",
            Self::Avx2 => "avx2",
            Self::Avx512 => "avx512",
        }
    }

    const fn from_u8(v: u8) -> Self {
        match v {
            0 => Self::Portable,
            1 => Self::Avx2,
            _ => Self::Avx512,
        }
    }
}

/// The cap a value of [`ENV_SIMD`] sets: `None` for `auto` (and anything not
/// understood), else the widest level allowed.
fn parse_setting(value: &str) -> Option<Level> {
    match value.trim().to_ascii_lowercase().as_str() {
        "portable" => Some(Level::Portable),
        "avx2" => Some(Level::Avx2),
        _ => None,
    }
}

/// The cap [`ENV_SIMD`] sets in this process (read once).
fn setting() -> Option<Level> {
    static SETTING: OnceLock<Option<Level>> = OnceLock::new();
    *SETTING.get_or_init(|| {
        std::env::var(ENV_SIMD)
            .ok()
            .as_deref()
            .and_then(parse_setting)
    })
}

/// The widest level this CPU runs: AVX-512 needs AVX512F and AVX2, AVX2 needs AVX2
/// (`Portable` off x86-64).
pub fn cpu_level() -> Level {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::arch::is_x86_feature_detected!("avx2");
        if avx2 && std::arch::is_x86_feature_detected!("avx512f") {
            Level::Avx512
        } else if avx2 {
            Level::Avx2
        } else {
            Level::Portable
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        Level::Portable
    }
}

/// The widest level kernels run in this process: [`cpu_level`] capped by
/// [`ENV_SIMD`] (decided once).
#[inline]
pub fn level() -> Level {
    static LEVEL: OnceLock<Level> = OnceLock::new();
    *LEVEL.get_or_init(|| cpu_level().min(setting().unwrap_or(Level::Avx512)))
}

/// Whether kernels run AVX2 code here ([`level`] at least [`Level::Avx2`]).
#[inline]
pub fn has_avx2() -> bool {
    level() >= Level::Avx2
}

/// Whether kernels run AVX-512 code here ([`level`] is [`Level::Avx512`]).
#[inline]
pub fn has_avx512() -> bool {
    level() >= Level::Avx512
}

/// One kernel call's choice of builds: levels up to [`Dispatch::allowed`] may run.
/// It records the widest that did ([`Dispatch::ran`]), so that a test comparing a
/// SIMD build with its portable twin can check the SIMD build ran.
#[derive(Debug)]
pub struct Dispatch {
    allowed: Level,
    ran: AtomicU8,
}

impl Dispatch {
    /// The widest builds this process runs ([`level`]): what kernels use.
    pub fn auto() -> Self {
        Self::at_most(Level::Avx512)
    }

    /// Builds up to `cap`, and up to [`level`].
    pub fn at_most(cap: Level) -> Self {
        Self {
            allowed: cap.min(level()),
            ran: AtomicU8::new(Level::Portable as u8),
        }
    }

    /// The widest level this call may run.
    pub fn allowed(&self) -> Level {
        self.allowed
    }

    /// Whether to run the build for `level` (this CPU has it when `true`); records
    /// that it runs.
    #[inline]
    pub fn select(&self, level: Level) -> bool {
        if self.allowed < level {
            return false;
        }
        if self.ran.load(Ordering::Relaxed) < level as u8 {
            self.ran.fetch_max(level as u8, Ordering::Relaxed);
        }
        true
    }

    /// The widest level a [`Self::select`] chose so far ([`Level::Portable`] if none).
    pub fn ran(&self) -> Level {
        Level::from_u8(self.ran.load(Ordering::Relaxed))
    }
}

/// The kernel families with SIMD builds and the widest build each has (the general
/// path of `triangulate` and its few-view paths counted apart).
const KERNELS: [(&str, Level); 5] = [
    ("rectify", Level::Avx2),
    ("rectify_plan", Level::Avx2),
    ("superres", Level::Avx2),
    ("triangulate", Level::Avx2),
    ("triangulate_few_views", Level::Avx512),
];

/// What [`simd_info`] reports.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SimdInfo {
    /// [`ENV_SIMD`]'s setting in effect: `"auto"`, `"avx2"` or `"portable"`.
    pub setting: &'static str,
    /// The widest level this CPU has ([`cpu_level`]).
    pub cpu: Level,
    /// The widest level kernels run ([`level`]).
    pub level: Level,
    /// Each kernel family with SIMD builds and the build it runs.
    pub kernels: Vec<(&'static str, Level)>,
}

/// Which builds this process runs: the setting, the CPU's level, and per kernel family
/// the build it runs.
pub fn simd_info() -> SimdInfo {
    let level = level();
    SimdInfo {
        setting: setting().map_or("auto", Level::name),
        cpu: cpu_level(),
        level,
        kernels: KERNELS
            .iter()
            .map(|&(name, widest)| (name, widest.min(level)))
            .collect(),
    }
}

/// For a test comparing a SIMD build at `level` with its portable twin: whether this
/// process runs that level (the test must then see it run), else `false` after
/// printing, past the test harness's capture, why the comparison is skipped.
#[cfg(test)]
pub(crate) fn runs_or_skip(level: Level, test: &str) -> bool {
    use std::io::Write;
    if self::level() >= level {
        return true;
    }
    let why = if cpu_level() < level {
        "this CPU lacks it".to_owned()
    } else {
        format!(
            "{ENV_SIMD}={} caps it",
            setting().map_or("auto", Level::name)
        )
    };
    // Written to stderr directly: `eprintln!` output is shown only for failing tests.
    let _ = writeln!(
        std::io::stderr(),
        "SKIPPED {test}: the {} build does not run here ({why})",
        level.name()
    );
    false
}

/// `avx2_or_portable!(dispatch, fn name(args) -> Ret { body })` defines `name`, which
/// runs `body` compiled for AVX2 if `dispatch` (an expression of type [`Dispatch`] or a
/// reference to one, evaluated at each call, in which the arguments are in scope)
/// selects [`Level::Avx2`], else compiled for the baseline. `body` should call
/// `#[inline(always)]` functions only: code it calls without inlining runs as compiled
/// for the baseline. In `body`, the constant `AVX2` says which build it is, for code
/// that should differ (see `triangulate::sort_keys`).
macro_rules! avx2_or_portable {
    (
        $dispatch:expr,
        $(#[$meta:meta])*
        $vis:vis fn $name:ident$(<$($lt:lifetime),*>)?($($arg:ident : $ty:ty),* $(,)?) -> $ret:ty $body:block
    ) => {
        $(#[$meta])*
        $vis fn $name$(<$($lt),*>)?($($arg: $ty),*) -> $ret {
            #[inline(always)]
            fn body<$($($lt,)*)? const AVX2: bool>($($arg: $ty),*) -> $ret $body

            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            fn avx2$(<$($lt),*>)?($($arg: $ty),*) -> $ret {
                body::<true>($($arg),*)
            }

            #[cfg(target_arch = "x86_64")]
            if $dispatch.select($crate::simd::Level::Avx2) {
                // SAFETY: `avx2` needs only AVX2, which this CPU has: a `Dispatch`
                // selects only levels `simd::level` allows.
                #[allow(unsafe_code)]
                let result = unsafe { avx2($($arg),*) };
                return result;
            }
            body::<false>($($arg),*)
        }
    };
}

pub(crate) use avx2_or_portable;

/// Code that [`run_avx2_or_portable`] runs: `run` must be `#[inline(always)]` and call
/// only `#[inline(always)]` code, so that all of it is compiled into each build.
/// `AVX2` says which build runs (as in the macro `avx2_or_portable!`).
pub trait Avx2Kernel {
    /// What `run` returns.
    type Output;
    /// The work.
    fn run<const AVX2: bool>(self) -> Self::Output;
}

/// Runs `kernel` compiled for AVX2 if `dispatch` selects [`Level::Avx2`], else
/// compiled for the baseline: the dispatch of `avx2_or_portable!` for code that is
/// generic (the macro takes no type parameters), such as `rectify::RectifyPlan`'s
/// loops. (A closure would not do: closures cannot be `#[inline(always)]`, and one
/// that is not inlined runs as compiled for the baseline.)
#[inline(always)]
pub fn run_avx2_or_portable<K: Avx2Kernel>(dispatch: &Dispatch, kernel: K) -> K::Output {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        fn avx2<K: Avx2Kernel>(kernel: K) -> K::Output {
            kernel.run::<true>()
        }
        if dispatch.select(Level::Avx2) {
            // SAFETY: `avx2` needs only AVX2, which this CPU has: a `Dispatch` selects
            // only levels `simd::level` allows.
            #[allow(unsafe_code)]
            let result = unsafe { avx2(kernel) };
            return result;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = dispatch;
    kernel.run::<false>()
}

/// The taps of [`bilinear_band`], one per output pixel, as parallel slices: the index
/// `at` of the top-left pixel of its footprint in a `w`-pixel-wide image (`row * w +
/// col`), and its fractions `tx`, `ty` along x and y (the footprint has a second column
/// when `tx > 0`, a second row when `ty > 0`).
#[derive(Debug, Clone, Copy)]
pub struct BandTaps<'a> {
    /// Footprint's top-left pixel, `row * w + col`.
    pub at: &'a [u32],
    /// Fraction along x.
    pub tx: &'a [f32],
    /// Fraction along y.
    pub ty: &'a [f32],
}

/// Bilinear interpolation of `C`-channel pixels (`C` 3 or 4) from `band`, in OpenCV's
/// order: `v0 = p00 + tx (p01 - p00)`, `v1 = p10 + tx (p11 - p10)`, `v = v0 + ty (v1 -
/// v0)` lane by lane in float32 (bit for bit `remap::lerp_lanes`), no NaN test, tap `k`
/// into `dst[k * C..k * C + C]`. Pixel `(row, col)` of the image, `C` values, is at
/// `band[(row * w + col - base) * C..]`, rows `stride` values apart (`stride >= w C`);
/// `p01` is `C` values after `p00` if `tx > 0` (else `p00` itself), `p10` `stride`
/// after if `ty > 0`.
///
/// Runs only where [`has_avx2`] (AVX2 on this CPU, allowed by [`ENV_SIMD`]); `None` is
/// nothing done (also when the lengths disagree: `taps` slices of one length `n`, `dst`
/// of `n * C`, `C` not 3 or 4, or a band too short to hold one footprint). The caller
/// then interpolates with portable code. Every read is inside `band` whatever the taps (a
/// footprint that would leave the band is moved inside it: a wrong value, never a read
/// outside); the callers' band holds every footprint, plus `stride + C + 4` values of
/// slack after the last pixel read.
#[inline(always)]
pub fn bilinear_band<const C: usize>(
    band: &[f32],
    stride: usize,
    base: usize,
    taps: BandTaps<'_>,
    dst: &mut [f32],
) -> Option<()> {
    #[cfg(target_arch = "x86_64")]
    {
        if !has_avx2() {
            return None;
        }
        // SAFETY: `bilinear_band_avx2` needs only AVX2, which this CPU has when
        // `has_avx2` says so.
        #[allow(unsafe_code)]
        return unsafe { bilinear_band_avx2::<C>(band, stride, base, taps, dst) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (band, stride, base, taps, dst);
        None
    }
}

/// [`bilinear_band`] for AVX2: eight taps' offsets at a time in vectors, then pairs
/// of pixels in 256-bit registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(unsafe_code)]
fn bilinear_band_avx2<const C: usize>(
    band: &[f32],
    stride: usize,
    base: usize,
    taps: BandTaps<'_>,
    dst: &mut [f32],
) -> Option<()> {
    use std::arch::x86_64::{
        _CMP_GT_OQ, _mm_loadu_ps, _mm_set1_ps, _mm_storeu_ps, _mm256_add_epi32, _mm256_and_si256,
        _mm256_castps_si256, _mm256_castps256_ps128, _mm256_cmp_ps, _mm256_extractf128_ps,
        _mm256_loadu_ps, _mm256_loadu_si256, _mm256_min_epu32, _mm256_mullo_epi32,
        _mm256_permutevar8x32_ps, _mm256_set1_epi32, _mm256_setr_epi32, _mm256_setzero_ps,
        _mm256_storeu_si256, _mm256_sub_epi32,
    };
    let n = taps.at.len();
    if !(C == 3 || C == 4)
        || n == 0
        || taps.tx.len() != n
        || taps.ty.len() != n
        || dst.len() != n.checked_mul(C)?
    {
        return None;
    }
    // Every read is at `top + down + right + lane` with `top <= limit`, `down <=
    // stride`, `right <= C`, `lane < 4`: below `limit + stride + C + 4 <= band.len()`.
    let limit = band.len().checked_sub(stride.checked_add(C + 4)?)?;
    let (Ok(limit32), Ok(stride32)) = (u32::try_from(limit), u32::try_from(stride)) else {
        return None;
    };
    // Offsets are computed modulo 2^32, then clamped to `limit`: any value is safe.
    let (base32, c32) = (base as u32, C as u32);
    let src = band.as_ptr();
    let out = dst.as_mut_ptr();
    // A four-lane store at pixel `k` ends at `k C + 4`: inside `dst` for `k < n - 1`
    // (and for `k = n - 1` too when `C == 4`).
    let four_lanes = if C == 4 { n } else { n - 1 };

    let mut k = 0;
    // Blocks of 8 taps whose pixels all take four-lane stores.
    let (vbase, vc) = (
        _mm256_set1_epi32(base32 as i32),
        _mm256_set1_epi32(c32 as i32),
    );
    let (vlimit, vstride) = (
        _mm256_set1_epi32(limit32 as i32),
        _mm256_set1_epi32(stride32 as i32),
    );
    // Lane `i` of a pair's fractions: tap `2 j` in the low half, `2 j + 1` in the high.
    let pairs = [
        _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1),
        _mm256_setr_epi32(2, 2, 2, 2, 3, 3, 3, 3),
        _mm256_setr_epi32(4, 4, 4, 4, 5, 5, 5, 5),
        _mm256_setr_epi32(6, 6, 6, 6, 7, 7, 7, 7),
    ];
    let zero = _mm256_setzero_ps();
    while k + 8 <= four_lanes {
        let mut offs = [[0u32; 8]; 4];
        // SAFETY: `k + 8 <= n`, the length of the three tap slices: the loads read
        // their elements `k..k + 8`; the stores write the local `offs`.
        let (tx, ty) = unsafe {
            (
                _mm256_loadu_ps(taps.tx.as_ptr().add(k)),
                _mm256_loadu_ps(taps.ty.as_ptr().add(k)),
            )
        };
        // SAFETY: as above.
        let at = unsafe { _mm256_loadu_si256(taps.at.as_ptr().add(k).cast()) };
        let top = _mm256_min_epu32(_mm256_mullo_epi32(_mm256_sub_epi32(at, vbase), vc), vlimit);
        let gt0 = |v| _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(v, zero));
        let right = _mm256_and_si256(gt0(tx), vc);
        let bottom = _mm256_add_epi32(top, _mm256_and_si256(gt0(ty), vstride));
        // SAFETY: each store writes one `[u32; 8]` of `offs`.
        unsafe {
            _mm256_storeu_si256(offs[0].as_mut_ptr().cast(), top);
            _mm256_storeu_si256(offs[1].as_mut_ptr().cast(), _mm256_add_epi32(top, right));
            _mm256_storeu_si256(offs[2].as_mut_ptr().cast(), bottom);
            _mm256_storeu_si256(offs[3].as_mut_ptr().cast(), _mm256_add_epi32(bottom, right));
        }
        let [o00, o01, o10, o11] = offs.map(pairs_of);
        let quads = o00.into_iter().zip(o01).zip(o10).zip(o11);
        for (j, (&pair, (((q00, q01), q10), q11))) in pairs.iter().zip(quads).enumerate() {
            let (a, b) = (2 * j, 2 * j + 1);
            // SAFETY: every offset is at most `limit + stride + C` (`top <= limit`,
            // `right <= C`, `down <= stride`), so each four-lane load ends inside
            // `band`.
            let (p00, p01, p10, p11) = unsafe {
                (
                    load2(src, q00),
                    load2(src, q01),
                    load2(src, q10),
                    load2(src, q11),
                )
            };
            let tx2 = _mm256_permutevar8x32_ps(tx, pair);
            let ty2 = _mm256_permutevar8x32_ps(ty, pair);
            let v = lerp2(lerp2(p00, p01, tx2), lerp2(p10, p11, tx2), ty2);
            // SAFETY: pixels `k + a < k + b < four_lanes`: their four-lane stores end
            // inside `dst`, in this order (the second overwrites the first's fourth).
            unsafe {
                _mm_storeu_ps(out.add((k + a) * C), _mm256_castps256_ps128(v));
                _mm_storeu_ps(out.add((k + b) * C), _mm256_extractf128_ps::<1>(v));
            }
        }
        k += 8;
    }
    // The rest, one pixel at a time.
    while k < n {
        let (at, tx, ty) = (*taps.at.get(k)?, *taps.tx.get(k)?, *taps.ty.get(k)?);
        let top = (at.wrapping_sub(base32).wrapping_mul(c32)).min(limit32) as usize;
        let right = if tx > 0.0 { C } else { 0 };
        let bottom = top + if ty > 0.0 { stride } else { 0 };
        // SAFETY: as in the blocks, the offsets are at most `limit + stride + C`.
        let (p00, p01, p10, p11) = unsafe {
            (
                _mm_loadu_ps(src.add(top)),
                _mm_loadu_ps(src.add(top + right)),
                _mm_loadu_ps(src.add(bottom)),
                _mm_loadu_ps(src.add(bottom + right)),
            )
        };
        let (tx, ty) = (_mm_set1_ps(tx), _mm_set1_ps(ty));
        let v = lerp(lerp(p00, p01, tx), lerp(p10, p11, tx), ty);
        let mut lanes = [0.0f32; 4];
        // SAFETY: `lanes` holds four values.
        unsafe { _mm_storeu_ps(lanes.as_mut_ptr(), v) };
        // SAFETY: `k < n`, so values `k C .. k C + C` are inside `dst`; `lanes` holds
        // `4 >= C` values and does not overlap it.
        unsafe { std::ptr::copy_nonoverlapping(lanes.as_ptr(), out.add(k * C), C) };
        k += 1;
    }
    Some(())
}

/// Eight offsets as four pairs.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn pairs_of([a0, a1, a2, a3, a4, a5, a6, a7]: [u32; 8]) -> [(usize, usize); 4] {
    let u = |v: u32| v as usize;
    [
        (u(a0), u(a1)),
        (u(a2), u(a3)),
        (u(a4), u(a5)),
        (u(a6), u(a7)),
    ]
}

/// Four lanes at `src + lo` and four at `src + hi`, as one vector.
///
/// # Safety
/// Both four-value reads must be inside one allocation.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(unsafe_code)]
#[inline]
unsafe fn load2(src: *const f32, (lo, hi): (usize, usize)) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::{_mm_loadu_ps, _mm256_castps128_ps256, _mm256_insertf128_ps};
    // SAFETY: the caller's contract.
    unsafe {
        _mm256_insertf128_ps::<1>(
            _mm256_castps128_ps256(_mm_loadu_ps(src.add(lo))),
            _mm_loadu_ps(src.add(hi)),
        )
    }
}

/// `a + t (b - a)` lane by lane (`remap::lerp_lanes`), four lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn lerp(
    a: std::arch::x86_64::__m128,
    b: std::arch::x86_64::__m128,
    t: std::arch::x86_64::__m128,
) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::{_mm_add_ps, _mm_mul_ps, _mm_sub_ps};
    _mm_add_ps(a, _mm_mul_ps(t, _mm_sub_ps(b, a)))
}

/// [`lerp`] on eight lanes (two pixels).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn lerp2(
    a: std::arch::x86_64::__m256,
    b: std::arch::x86_64::__m256,
    t: std::arch::x86_64::__m256,
) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::{_mm256_add_ps, _mm256_mul_ps, _mm256_sub_ps};
    _mm256_add_ps(a, _mm256_mul_ps(t, _mm256_sub_ps(b, a)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `a + t (b - a)`, as `remap::lerp_lanes` on one lane.
    fn lerp1(a: f32, b: f32, t: f32) -> f32 {
        a + t * (b - a)
    }

    #[test]
    fn bilinear_band_equals_scalar_and_stays_inside() {
        if !runs_or_skip(Level::Avx2, "bilinear_band_equals_scalar_and_stays_inside") {
            return;
        }
        for c in [3usize, 4] {
            let (w, rows) = (37usize, 6usize);
            let stride = w * c + 5;
            let band: Vec<f32> = (0..(rows + 1) * stride + 8)
                .map(|i| ((i * 7919) % 1000) as f32 / 999.0 - 0.25)
                .collect();
            let base = 2 * w;
            // Footprints anywhere in the first `rows - 1` rows: whole-number positions
            // (tx or ty 0) included; a run long enough for blocks and a tail.
            for n in [1usize, 2, 7, 8, 9, 17, 40] {
                let mut at = Vec::new();
                let (mut tx, mut ty) = (Vec::new(), Vec::new());
                for k in 0..n {
                    let (r, col) = (2 + k * 5 % (rows - 1), k * 11 % (w - 1));
                    at.push(u32::try_from(r * w + col).unwrap());
                    tx.push(if k % 3 == 0 {
                        0.0
                    } else {
                        (k % 7) as f32 / 7.5
                    });
                    ty.push(if k % 4 == 1 {
                        0.0
                    } else {
                        (k % 5) as f32 / 5.5
                    });
                }
                let taps = BandTaps {
                    at: &at,
                    tx: &tx,
                    ty: &ty,
                };
                let mut got = vec![f32::NAN; n * c];
                let sub = &band[..];
                bilinear_band_dispatch(c, sub, stride, base, taps, &mut got).unwrap();
                for k in 0..n {
                    let top = (at[k] as usize - base) * c;
                    let right = if tx[k] > 0.0 { c } else { 0 };
                    let down = if ty[k] > 0.0 { stride } else { 0 };
                    for ch in 0..c {
                        let p = |o: usize| band[o + ch];
                        let v0 = lerp1(p(top), p(top + right), tx[k]);
                        let v1 = lerp1(p(top + down), p(top + down + right), tx[k]);
                        let want = lerp1(v0, v1, ty[k]);
                        assert_eq!(got[k * c + ch].to_bits(), want.to_bits(), "{c} {n} {k}");
                    }
                }
                // Taps anywhere (indices below `base`, past the band): read inside it.
                let wild: Vec<u32> = (0..n as u32).map(|k| k.wrapping_mul(0x9e37_79b9)).collect();
                let taps = BandTaps {
                    at: &wild,
                    tx: &tx,
                    ty: &ty,
                };
                bilinear_band_dispatch(c, sub, stride, base, taps, &mut got).unwrap();
                // Lengths that disagree: nothing done.
                let short = BandTaps {
                    at: &at[..n - 1],
                    tx: &tx,
                    ty: &ty,
                };
                assert!(bilinear_band_dispatch(c, sub, stride, base, short, &mut got).is_none());
                assert!(
                    bilinear_band_dispatch(c, &band[..stride], stride, base, taps, &mut got)
                        .is_none()
                );
            }
        }
    }

    #[test]
    fn settings_cap_the_cpu_level() {
        assert_eq!(parse_setting("portable"), Some(Level::Portable));
        assert_eq!(parse_setting(" AVX2\n"), Some(Level::Avx2));
        for auto in ["", "auto", "avx512", "sse"] {
            assert_eq!(parse_setting(auto), None, "{auto:?}");
        }
        let cap = std::env::var(ENV_SIMD)
            .ok()
            .as_deref()
            .and_then(parse_setting);
        assert_eq!(setting(), cap);
        assert_eq!(level(), cpu_level().min(cap.unwrap_or(Level::Avx512)));
        let info = simd_info();
        assert_eq!((info.cpu, info.level), (cpu_level(), level()));
        assert!(info.kernels.iter().all(|&(_, l)| l <= level()));
        // On this CPU, with no cap, the dispatcher picks what the CPU has.
        #[cfg(target_arch = "x86_64")]
        if cap.is_none() {
            let avx2 = std::arch::is_x86_feature_detected!("avx2");
            let avx512 = avx2 && std::arch::is_x86_feature_detected!("avx512f");
            assert_eq!(has_avx2(), avx2);
            assert_eq!(has_avx512(), avx512);
            assert_eq!(info.setting, "auto");
        }
        if cap == Some(Level::Portable) {
            assert!(!has_avx2() && info.kernels.iter().all(|&(_, l)| l == Level::Portable));
        }
    }

    #[test]
    fn dispatch_selects_up_to_its_cap_and_records_it() {
        for cap in Level::ALL {
            let d = Dispatch::at_most(cap);
            assert_eq!(d.allowed(), cap.min(level()));
            assert_eq!(d.ran(), Level::Portable);
            for l in Level::ALL {
                assert_eq!(d.select(l), l <= d.allowed(), "{cap:?} {l:?}");
            }
            assert_eq!(d.ran(), d.allowed());
        }
        assert_eq!(Dispatch::auto().allowed(), level());
    }

    fn bilinear_band_dispatch(
        c: usize,
        band: &[f32],
        stride: usize,
        base: usize,
        taps: BandTaps<'_>,
        dst: &mut [f32],
    ) -> Option<()> {
        match c {
            3 => bilinear_band::<3>(band, stride, base, taps, dst),
            _ => bilinear_band::<4>(band, stride, base, taps, dst),
        }
    }
}
