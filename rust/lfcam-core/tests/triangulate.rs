//! `triangulate` against a naive float64 reference of the same algorithm, on noisy
//! flows with outliers, holes and weights; exact flows; parallel == serial; bad inputs.

#![allow(clippy::panic, clippy::unwrap_used)] // test helpers outside `#[test]` functions

use lfcam_core::Error;
use lfcam_core::parallel;
use lfcam_core::triangulate::{
    CONFIDENCE_INFO, CONFIDENCE_TAU, LANES, MAD_TO_SIGMA, MAX_VIEWS, Outputs, Params, TOLERANCE,
    ViewStack, triangulate,
};
use proptest::prelude::*;

/// One pixel's outputs.
#[derive(Debug, Clone, Copy)]
struct Pixel {
    s: f64,
    confidence: f64,
    residual: f64,
    perpendicular: f64,
    n_used: u8,
    /// The smallest `|r_i / c - 1|` met in any pass: how near a view was to being kept
    /// or dropped the other way (float32 and float64 may decide differently below
    /// ~1e-5).
    margin: f64,
}

/// The weighted median of the module docs, by sorting.
fn wmedian(x: &[f64], v: &[f64]) -> f64 {
    let mut idx: Vec<usize> = (0..x.len()).collect();
    idx.sort_by(|&a, &b| x[a].total_cmp(&x[b]));
    let total: f64 = idx.iter().map(|&i| v[i]).sum();
    let (mut c, mut lo, mut hi) = (0.0, None, None);
    for &i in &idx {
        c += v[i];
        if lo.is_none() && 2.0 * c >= total {
            lo = Some(x[i]);
        }
        if hi.is_none() && 2.0 * c > total {
            hi = Some(x[i]);
        }
    }
    (lo.unwrap() + hi.unwrap()) / 2.0
}

/// The algorithm of the module docs for one pixel, in float64, written the obvious way
/// (residuals as 2-D norms, divisions, plain loops).
fn naive_pixel(
    u: &[[f32; 2]],
    w: Option<&[f32]>,
    offsets: &[[f64; 2]],
    reference: usize,
    p: &Params,
) -> Pixel {
    let nan = Pixel {
        s: f64::NAN,
        confidence: 0.0,
        residual: f64::NAN,
        perpendicular: f64::NAN,
        n_used: 0,
        margin: f64::INFINITY,
    };
    let total_info: f64 = offsets
        .iter()
        .enumerate()
        .filter(|&(i, _)| i != reference)
        .map(|(_, o)| o[0] * o[0] + o[1] * o[1])
        .sum();
    // Usable views: (o, u, w).
    let mut views = Vec::new();
    for (i, (&[ux, uy], &o)) in u.iter().zip(offsets).enumerate() {
        let wi = w.map_or(1.0, |w| f64::from(w[i]));
        let n = o[0] * o[0] + o[1] * o[1];
        if i != reference && n > 0.0 && ux.is_finite() && uy.is_finite() && wi > 0.0 {
            views.push((o, [f64::from(ux), f64::from(uy)], wi));
        }
    }
    if views.is_empty() {
        return nan;
    }
    let norm2 = |o: [f64; 2]| o[0] * o[0] + o[1] * o[1];
    let dot = |o: [f64; 2], u: [f64; 2]| o[0] * u[0] + o[1] * u[1];
    let si: Vec<f64> = views
        .iter()
        .map(|&(o, u, _)| dot(o, u) / norm2(o))
        .collect();
    let ai: Vec<f64> = views.iter().map(|&(o, _, w)| w * norm2(o)).collect();
    let wi: Vec<f64> = views.iter().map(|&(_, _, w)| w).collect();
    let mut margin = f64::INFINITY;
    let mut pass = |s: f64| -> (Vec<f64>, f64) {
        let r: Vec<f64> = views
            .iter()
            .map(|&(o, u, _)| (u[0] - o[0] * s).hypot(u[1] - o[1] * s))
            .collect();
        let sigma = (f64::from(MAD_TO_SIGMA) * wmedian(&r, &wi)).max(f64::from(p.sigma_floor));
        let c = f64::from(p.cutoff) * sigma;
        for &ri in &r {
            margin = margin.min((ri / c - 1.0).abs());
        }
        (r, c)
    };
    let tukey = |r: f64, c: f64| {
        if r < c {
            (1.0 - (r / c).powi(2)).powi(2)
        } else {
            0.0
        }
    };
    let mut s = wmedian(&si, &ai);
    for _ in 0..p.iterations {
        let (r, c) = pass(s);
        let (mut num, mut den) = (0.0, 0.0);
        for (k, &(o, u, w)) in views.iter().enumerate() {
            let b = w * tukey(r[k], c);
            num += b * dot(o, u);
            den += b * norm2(o);
        }
        if den <= 0.0 {
            break;
        }
        let next = num / den;
        let done = (next - s).abs() < f64::from(TOLERANCE);
        s = next;
        if done {
            break;
        }
    }
    let (r, c) = pass(s);
    let (mut n, mut sb, mut sbr, mut sq, mut info) = (0u8, 0.0, 0.0, 0.0, 0.0);
    for (k, &(o, u, w)) in views.iter().enumerate() {
        if r[k] < c {
            let b = w * tukey(r[k], c);
            let q = (o[0] * u[1] - o[1] * u[0]) / norm2(o).sqrt();
            n += 1;
            sb += b;
            sbr += b * r[k] * r[k];
            sq += q * q;
            info += w * norm2(o);
        }
    }
    if usize::from(n) < p.min_views {
        return Pixel {
            n_used: n,
            margin,
            ..nan
        };
    }
    let residual = (sbr / sb).sqrt();
    let confidence = (1.0 - (-info / total_info / f64::from(CONFIDENCE_INFO)).exp())
        * (-(residual / f64::from(CONFIDENCE_TAU)).powi(2)).exp();
    Pixel {
        s,
        confidence,
        residual,
        perpendicular: (sq / f64::from(n)).sqrt(),
        n_used: n,
        margin,
    }
}

/// Inputs of one call.
#[derive(Debug, Clone)]
struct Case {
    n: usize,
    h: usize,
    w: usize,
    flows: Vec<f32>,
    weights: Option<Vec<f32>>,
    offsets: Vec<[f64; 2]>,
    reference: usize,
    params: Params,
}

/// All outputs of one call, as vectors.
#[derive(Debug, Clone, PartialEq)]
struct Result5 {
    parallax: Vec<f32>,
    confidence: Vec<f32>,
    residual: Vec<f32>,
    perpendicular: Vec<f32>,
    n_used: Vec<u8>,
}

impl Result5 {
    fn bits(&self) -> Vec<u32> {
        [
            &self.parallax,
            &self.confidence,
            &self.residual,
            &self.perpendicular,
        ]
        .iter()
        .flat_map(|v| v.iter().map(|x| x.to_bits()))
        .chain(self.n_used.iter().map(|&x| u32::from(x)))
        .collect()
    }
}

fn run(c: &Case) -> Result<Result5, Error> {
    let px = c.h * c.w;
    let mut r = Result5 {
        parallax: vec![-7.0; px],
        confidence: vec![-7.0; px],
        residual: vec![-7.0; px],
        perpendicular: vec![-7.0; px],
        n_used: vec![200; px],
    };
    let flows = ViewStack::new(&c.flows, [c.n, c.h, c.w, 2], "flows")?;
    let weights = match &c.weights {
        Some(w) => Some(ViewStack::new(w, [c.n, c.h, c.w, 1], "weights")?),
        None => None,
    };
    triangulate(
        flows,
        weights,
        &c.offsets,
        c.reference,
        &c.params,
        Outputs {
            parallax: &mut r.parallax,
            confidence: &mut r.confidence,
            residual: &mut r.residual,
            perpendicular: &mut r.perpendicular,
            n_used: &mut r.n_used,
        },
    )?;
    Ok(r)
}

/// splitmix64, for structured random data from one proptest seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Roughly Gaussian (sum of four uniforms), unit variance.
    fn normal(&mut self) -> f64 {
        (0..4).map(|_| self.unit() - 0.5).sum::<f64>() * 3f64.sqrt()
    }
}

/// A random capture: `n` views with offsets of 3 to 40 px, noisy flows, outliers
/// (occlusions), holes and optionally weights.
fn random_case(seed: u64, n: usize, h: usize, w: usize, weighted: bool) -> Case {
    let mut rng = Rng(seed);
    let reference = (rng.next() % n as u64) as usize;
    let offsets: Vec<[f64; 2]> = (0..n)
        .map(|i| {
            if i == reference {
                [0.0, 0.0]
            } else {
                let (len, angle) = (rng.range(3.0, 40.0), rng.range(0.0, std::f64::consts::TAU));
                [len * angle.cos(), len * angle.sin()]
            }
        })
        .collect();
    let noise = rng.range(0.02, 0.4);
    let mut flows = vec![0f32; n * h * w * 2];
    let mut weights = vec![0f32; n * h * w];
    for p in 0..h * w {
        let s = rng.range(-1.5, 0.9);
        for (i, o) in offsets.iter().enumerate() {
            let k = i * h * w + p;
            let (mut ux, mut uy) = (
                o[0] * s + noise * rng.normal(),
                o[1] * s + noise * rng.normal(),
            );
            let roll = rng.unit();
            if roll < 0.15 {
                // An occlusion: the flow locked onto something else.
                let (e, a) = (rng.range(3.0, 30.0), rng.range(0.0, std::f64::consts::TAU));
                ux += e * a.cos();
                uy += e * a.sin();
            } else if roll < 0.22 {
                ux = f64::NAN;
            } else if roll < 0.25 {
                uy = f64::INFINITY;
            }
            flows[2 * k] = ux as f32;
            flows[2 * k + 1] = uy as f32;
            let wr = rng.unit();
            weights[k] = if wr < 0.1 {
                0.0
            } else if wr < 0.15 {
                f32::NAN
            } else {
                rng.range(0.05, 2.0) as f32
            };
        }
    }
    Case {
        n,
        h,
        w,
        flows,
        weights: weighted.then_some(weights),
        offsets,
        reference,
        params: Params::default(),
    }
}

/// Error of `got` against `want`, relative above 1 (float32 arithmetic on values up to
/// tens of px); 0 if both are NaN, infinite if only one is.
fn error(want: f64, got: f32) -> f64 {
    match (want.is_nan(), got.is_nan()) {
        (true, true) => 0.0,
        (false, false) => (want - f64::from(got)).abs() / want.abs().max(1.0),
        _ => f64::INFINITY,
    }
}

/// A view whose residual is within this fraction of the cutoff may be kept by one
/// implementation and dropped by the other; such pixels are not compared.
const AMBIGUOUS: f64 = 1e-4;

/// Every pixel of `c` against [`naive_pixel`]: the largest [`error`] of s, residual,
/// perpendicular and confidence; `Err` if an `n_used` differs. Pixels where a view
/// came within [`AMBIGUOUS`] of the cutoff are skipped (see [`Pixel::margin`]).
fn errors_against_naive(c: &Case) -> Result<[f64; 4], String> {
    let got = run(c).map_err(|e| e.to_string())?;
    let px = c.h * c.w;
    let mut worst = [0f64; 4];
    let mut skipped = 0;
    for p in 0..px {
        let u: Vec<[f32; 2]> = (0..c.n)
            .map(|i| {
                let k = (i * px + p) * 2;
                [c.flows[k], c.flows[k + 1]]
            })
            .collect();
        let w: Option<Vec<f32>> = c
            .weights
            .as_ref()
            .map(|w| (0..c.n).map(|i| w[i * px + p]).collect());
        let want = naive_pixel(&u, w.as_deref(), &c.offsets, c.reference, &c.params);
        if want.margin < AMBIGUOUS {
            skipped += 1;
            continue;
        }
        if want.n_used != got.n_used[p] {
            return Err(format!(
                "pixel {p}: want {want:?}, got n_used {}",
                got.n_used[p]
            ));
        }
        let errs = [
            error(want.s, got.parallax[p]),
            error(want.residual, got.residual[p]),
            error(want.perpendicular, got.perpendicular[p]),
            error(want.confidence, got.confidence[p]),
        ];
        for (w, e) in worst.iter_mut().zip(errs) {
            *w = w.max(e);
        }
    }
    // About 1 pixel in 10^4 comes that close to the cutoff.
    if skipped > 1 + px / 100 {
        return Err(format!(
            "{skipped} of {px} pixels within {AMBIGUOUS} of the cutoff"
        ));
    }
    Ok(worst)
}

/// [`errors_against_naive`] within `tol` for each of s, residual, perpendicular,
/// confidence.
fn check_against_naive(c: &Case, tol: [f64; 4]) -> Result<(), String> {
    let worst = errors_against_naive(c)?;
    if worst.iter().zip(&tol).all(|(e, t)| e <= t) {
        Ok(())
    } else {
        Err(format!("errors {worst:?} exceed {tol:?}"))
    }
}

/// Tolerances of s, residual, perpendicular and confidence. Heavy outliers that survive
/// the cutoff make the residual sensitive to the last bits of s (a lever of `|o_i| |s -
/// s_i|`, up to 100 px): there float32 agrees to about 1e-4 relative.
const TOL: [f64; 4] = [1e-4, 1e-3, 1e-5, 1e-3];

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn matches_naive_reference(
        seed in any::<u64>(),
        n in 2usize..17,
        h in 1usize..4,
        w in 1usize..150,
        weighted in any::<bool>(),
        iterations in 0usize..8,
        min_views in 1usize..4,
        cutoff in 1.5f32..5.0,
        sigma_floor in 0.05f32..1.0,
    ) {
        let mut c = random_case(seed, n, h, w, weighted);
        c.params = Params { min_views, sigma_floor, cutoff, iterations };
        let errs = errors_against_naive(&c);
        if std::env::var_os("LFCAM_PRINT_ERRORS").is_some() {
            println!("ERR {errs:?} {seed} {n} {h} {w} {weighted} {iterations} {min_views} {cutoff} {sigma_floor}");
        }
        prop_assert_eq!(check_against_naive(&c, TOL), Ok(()));
    }

    #[test]
    fn arbitrary_inputs_never_panic(
        flows in prop::collection::vec(any::<f32>(), 0..80),
        weights in prop::option::of(prop::collection::vec(any::<f32>(), 0..40)),
        offsets in prop::collection::vec(prop::array::uniform2(any::<f64>()), 0..6),
        n in 0usize..6,
        h in 0usize..4,
        w in 0usize..4,
        reference in 0usize..7,
        out_len in 0usize..20,
    ) {
        let Ok(fs) = ViewStack::new(&flows, [n, h, w, 2], "flows") else { return Ok(()) };
        let ws = weights.as_deref().and_then(|w8| ViewStack::new(w8, [n, h, w, 1], "weights").ok());
        let (mut a, mut b, mut c, mut d) =
            (vec![0f32; out_len], vec![0f32; out_len], vec![0f32; out_len], vec![0f32; out_len]);
        let mut e = vec![0u8; out_len];
        let out = Outputs {
            parallax: &mut a, confidence: &mut b, residual: &mut c, perpendicular: &mut d,
            n_used: &mut e,
        };
        let _ = triangulate(fs, ws, &offsets, reference, &Params::default(), out);
    }
}

#[test]
fn exact_flows_are_recovered() {
    let (n, h, w) = (12, 5, 130);
    let mut c = random_case(7, n, h, w, false);
    for p in 0..h * w {
        let s = -1.0 + 2.0 * p as f64 / (h * w) as f64;
        for i in 0..n {
            let k = (i * h * w + p) * 2;
            c.flows[k] = (c.offsets[i][0] * s) as f32;
            c.flows[k + 1] = (c.offsets[i][1] * s) as f32;
        }
    }
    let r = run(&c).unwrap();
    for p in 0..h * w {
        let s = -1.0 + 2.0 * p as f64 / (h * w) as f64;
        assert!((f64::from(r.parallax[p]) - s).abs() < 1e-5, "{p}");
        assert!(r.residual[p] < 1e-4 && r.perpendicular[p] < 1e-4, "{p}");
        assert_eq!(usize::from(r.n_used[p]), n - 1);
        assert!(r.confidence[p] > 0.98, "{}", r.confidence[p]);
    }
}

#[test]
fn parallel_equals_serial() {
    // 12 views of 300 x 200: well above the serial threshold.
    let c = random_case(3, 12, 200, 300, true);
    let default_threads = parallel::num_threads();
    parallel::set_num_threads(1).unwrap();
    let serial = run(&c).unwrap();
    for threads in [2, 3] {
        parallel::set_num_threads(threads).unwrap();
        assert!(
            run(&c).unwrap().bits() == serial.bits(),
            "{threads} threads"
        );
    }
    parallel::set_num_threads(default_threads).unwrap();
    assert_eq!(check_against_naive(&c, TOL), Ok(()));
}

#[test]
fn holes_reference_and_zero_weights() {
    let mut c = random_case(11, 4, 1, LANES + 3, true);
    let px = c.h * c.w;
    let reference = c.reference;
    let wts = c.weights.as_mut().unwrap();
    for p in 0..px {
        for i in 0..c.n {
            match p % 4 {
                // Every flow NaN but the reference's, which is never read.
                0 if i != reference => c.flows[(i * px + p) * 2] = f32::NAN,
                // Every weight 0 but the reference's.
                1 if i != reference => wts[i * px + p] = 0.0,
                _ => {}
            }
        }
        wts[reference * px + p] = -1.0; // the reference's weight is not read either
    }
    let r = run(&c).unwrap();
    for p in 0..px {
        if p % 4 < 2 {
            assert!(r.parallax[p].is_nan() && r.residual[p].is_nan(), "{p}");
            assert!(r.perpendicular[p].is_nan(), "{p}");
            assert_eq!((r.confidence[p], r.n_used[p]), (0.0, 0), "{p}");
        }
    }
    assert_eq!(check_against_naive(&c, TOL), Ok(()));
}

fn arg_of(err: Error) -> String {
    match err {
        Error::InvalidArgument { arg, .. } => arg,
        Error::InvalidItem { arg, index, .. } => format!("{arg}[{index}]"),
        other => panic!("unexpected {other:?}"),
    }
}

#[test]
fn bad_inputs_name_the_argument() {
    let good = random_case(5, 3, 2, 4, true);
    let reference = good.reference;
    let mut cases: Vec<(Case, String)> = Vec::new();
    let mut c = good.clone();
    c.offsets.pop();
    cases.push((c, "offsets".into()));
    let mut c = good.clone();
    c.offsets[(reference + 1) % 3] = [f64::NAN, 0.0];
    cases.push((c, format!("offsets[{}]", (reference + 1) % 3)));
    let mut c = good.clone();
    c.offsets[reference] = [0.5, 0.0];
    cases.push((c, format!("offsets[{reference}]")));
    let mut c = good.clone();
    for (i, o) in c.offsets.iter_mut().enumerate() {
        if i != reference {
            *o = [0.0, 0.0];
        }
    }
    cases.push((c, "offsets".into()));
    let mut c = good.clone();
    c.reference = 3;
    cases.push((c, "reference".into()));
    let mut c = good.clone();
    c.weights.as_mut().unwrap()[((reference + 1) % 3) * 8 + 5] = -0.5;
    cases.push((c, format!("weights[{}]", (reference + 1) % 3)));
    let mut c = good.clone();
    c.weights.as_mut().unwrap()[((reference + 2) % 3) * 8] = f32::INFINITY;
    cases.push((c, format!("weights[{}]", (reference + 2) % 3)));
    for (field, name) in [
        (
            Params {
                min_views: 0,
                ..Params::default()
            },
            "min_views",
        ),
        (
            Params {
                sigma_floor: -1.0,
                ..Params::default()
            },
            "sigma_floor",
        ),
        (
            Params {
                cutoff: 0.0,
                ..Params::default()
            },
            "cutoff",
        ),
    ] {
        let mut c = good.clone();
        c.params = field;
        cases.push((c, name.into()));
    }
    for (c, want) in cases {
        assert_eq!(arg_of(run(&c).unwrap_err()), want);
    }
    // Too few or too many views.
    for n in [1, MAX_VIEWS + 1] {
        let c = Case {
            n,
            flows: vec![0.0; n * 2],
            weights: None,
            offsets: vec![[0.0, 0.0]; n],
            reference: 0,
            h: 1,
            w: 1,
            params: Params::default(),
        };
        assert_eq!(arg_of(run(&c).unwrap_err()), "flows");
    }
    // Wrong output length.
    let flows = ViewStack::new(&good.flows, [3, 2, 4, 2], "flows").unwrap();
    let mut v = vec![0f32; 7];
    let (mut a, mut b, mut d) = (vec![0f32; 8], vec![0f32; 8], vec![0f32; 8]);
    let mut e = vec![0u8; 8];
    let out = Outputs {
        parallax: &mut a,
        confidence: &mut b,
        residual: &mut v,
        perpendicular: &mut d,
        n_used: &mut e,
    };
    let err = triangulate(
        flows,
        None,
        &good.offsets,
        reference,
        &Params::default(),
        out,
    );
    assert_eq!(arg_of(err.unwrap_err()), "out");
    // Shapes.
    assert_eq!(
        arg_of(ViewStack::new(&good.flows, [3, 2, 4, 3], "flows").unwrap_err()),
        "flows"
    );
    let wrong = ViewStack::new(&good.flows, [3, 2, 4, 2], "weights").unwrap();
    let mut r = vec![vec![0f32; 8]; 4];
    let mut e = vec![0u8; 8];
    let [a, b, c, d] = &mut r[..] else {
        unreachable!()
    };
    let out = Outputs {
        parallax: a,
        confidence: b,
        residual: c,
        perpendicular: d,
        n_used: &mut e,
    };
    let err = triangulate(
        flows,
        Some(wrong),
        &good.offsets,
        reference,
        &Params::default(),
        out,
    );
    assert_eq!(arg_of(err.unwrap_err()), "weights");
}
