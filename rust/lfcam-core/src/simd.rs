//! Runtime CPU dispatch: a kernel's loops compiled a second time for AVX2, and run
//! when the CPU has it (x86-64 only).
//!
//! The kernels vectorise by the compiler (no intrinsics, but for one exception below).
//! The wheel targets baseline x86-64 (SSE2, 4 float lanes); most CPUs in use have AVX2
//! (8 lanes, three-operand instructions, blends). A kernel opts in by wrapping its
//! per-task loop body, with everything it calls `#[inline(always)]`, in
//! [`avx2_or_portable!`]: it expands to a function compiled with
//! `#[target_feature(enable = "avx2")]` and a portable one, and picks the first when
//! [`has_avx2`] says so. Floating-point results are identical
//! (Rust never contracts `a * b + c` into an FMA, and AVX2 does not change IEEE
//! arithmetic); tests compare both paths.
//!
//! The crate's only `unsafe` is this pattern: calling a `#[target_feature]` function is
//! unsafe because running AVX2 instructions on a CPU without them is undefined
//! behaviour; [`has_avx2`] checks the CPU first (std's cached CPUID query). It is used
//! through the macro (triangulate) and written out in `rectify::Job::segment`, whose
//! generic parameters the macro does not take, and in `triangulate::rows_task`, which
//! calls the few-view paths `triangulate::avx2` and `triangulate::avx512` (after
//! [`has_avx512`]): those are written with `std::arch` intrinsics (safe to call in
//! `#[target_feature]` functions), because they keep whole arrays of vectors in
//! registers, which the compiler's vectoriser does not do for arrays of floats.

/// The `LFCAM_SIMD` environment variable (read once): `portable` forces the portable
/// paths, `avx2` allows AVX2 but not AVX-512, for testing and comparison.
#[cfg(target_arch = "x86_64")]
fn simd_setting() -> &'static str {
    use std::sync::OnceLock;
    static SETTING: OnceLock<String> = OnceLock::new();
    SETTING.get_or_init(|| {
        std::env::var("LFCAM_SIMD")
            .map_or_else(|_| String::new(), |v| v.trim().to_ascii_lowercase())
    })
}

/// Whether this CPU runs AVX2 code (`false` off x86-64). `LFCAM_SIMD=portable` in the
/// environment (read once) forces the portable path, for testing and comparison.
#[inline]
pub fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        simd_setting() != "portable" && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether this CPU runs AVX-512 (AVX512F) code (`false` off x86-64, and with
/// `LFCAM_SIMD=portable` or `LFCAM_SIMD=avx2` in the environment).
#[inline]
pub fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        !matches!(simd_setting(), "portable" | "avx2")
            && std::arch::is_x86_feature_detected!("avx512f")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `avx2_or_portable!(use_avx2, fn name(args) -> Ret { body })` defines `name`, which
/// runs `body` compiled for AVX2 if `use_avx2` (an expression, evaluated at each call,
/// normally [`has_avx2`]) is true and the CPU has AVX2, else compiled for the baseline.
/// `body` should call `#[inline(always)]` functions only: code it calls without
/// inlining runs as compiled for the baseline. In `body`, the constant `AVX2` says
/// which build it is, for code that should differ (see `triangulate::sort_keys`).
macro_rules! avx2_or_portable {
    (
        $use_avx2:expr,
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
            if $use_avx2 && $crate::simd::has_avx2() {
                // SAFETY: `avx2` needs only AVX2, which `has_avx2` found on this CPU.
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
pub trait Avx2Kernel {
    /// What `run` returns.
    type Output;
    /// The work.
    fn run(self) -> Self::Output;
}

/// Runs `kernel` compiled for AVX2 if `use_avx2` is true and [`has_avx2`] finds AVX2 on
/// this CPU, else compiled for the baseline: the dispatch of [`avx2_or_portable!`] for
/// code that is generic (the macro takes no type parameters), such as
/// `rectify::RectifyPlan`'s loops. (A closure would not do: closures cannot be
/// `#[inline(always)]`, and one that is not inlined runs as compiled for the baseline.)
#[inline(always)]
pub fn run_avx2_or_portable<K: Avx2Kernel>(use_avx2: bool, kernel: K) -> K::Output {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        fn avx2<K: Avx2Kernel>(kernel: K) -> K::Output {
            kernel.run()
        }
        if use_avx2 && has_avx2() {
            // SAFETY: `avx2` needs only AVX2, which `has_avx2` found on this CPU.
            #[allow(unsafe_code)]
            let result = unsafe { avx2(kernel) };
            return result;
        }
    }
    kernel.run()
}
