//! `rectify` against a float64 reference of its definition (every interpolation, raw
//! type, channel layout, mask and NaN rule), its band / direct / fallback paths,
//! parallel == serial, and every bad input.

#![allow(clippy::panic, clippy::unwrap_used, clippy::indexing_slicing)] // test helpers outside `#[test]` functions

use lfcam_core::rectify::{RawSample, rectify_output_shape};
use lfcam_core::{Error, ImageView, Interp, ViewMaps, parallel, rectify};
use proptest::prelude::*;

/// The footprint of one axis: pixels and weights, `None` outside `n` pixels.
fn axis(interp: Interp, v: f32, n: usize) -> Option<Vec<(usize, f64)>> {
    if !v.is_finite() {
        return None;
    }
    let inside = |taps: Vec<(i64, f64)>| -> Option<Vec<(usize, f64)>> {
        taps.into_iter()
            .filter(|&(_, w)| w != 0.0)
            .map(|(i, w)| usize::try_from(i).ok().filter(|&i| i < n).map(|i| (i, w)))
            .collect()
    };
    match interp {
        Interp::BilinearQ32 => {
            // OpenCV's cvRound(v * 32): half to even.
            let s = (f64::from(v) * 32.0).round_ties_even() as i64;
            let (i, f) = (s >> 5, (s & 31) as f64 / 32.0);
            inside(vec![(i, 1.0 - f), (i + 1, f)])
        }
        Interp::Bicubic => {
            let v = f64::from(v);
            let i = v.floor() as i64;
            let t = v - i as f64;
            let a = -0.75;
            let near = |d: f64| ((a + 2.0) * d - (a + 3.0)) * d * d + 1.0;
            let far = |d: f64| ((a * d - 5.0 * a) * d + 8.0 * a) * d - 4.0 * a;
            inside(vec![
                (i - 1, far(t + 1.0)),
                (i, near(t)),
                (i + 1, near(1.0 - t)),
                (i + 2, far(2.0 - t)),
            ])
        }
        _ => {
            let v = f64::from(v);
            let i = v.floor() as i64;
            let t = v - i as f64;
            inside(vec![(i, 1.0 - t), (i + 1, t)])
        }
    }
}

struct Frame<T> {
    raw: Vec<T>,
    gains: Vec<f32>,
    h: usize,
    w: usize,
    c: usize,
    g: usize,
}

impl<T: RawSample + Into<f64>> Frame<T> {
    /// `(raw * scale) * gain` at raw `(row, col)`, channel `k`; NaN for a 0 gain.
    fn gained(&self, row: usize, col: usize, k: usize) -> f64 {
        let px = row * self.w + col;
        let gain = f64::from(self.gains[px * self.g + if self.g == 1 { 0 } else { k }]);
        if gain == 0.0 {
            return f64::NAN;
        }
        self.raw[px * self.c + k].into() * f64::from(T::SCALE) * gain
    }

    /// The definition of one output pixel.
    fn reference(&self, interp: Interp, crop: [i64; 4], x: f32, y: f32) -> Option<Vec<f64>> {
        let [x0, y0, w, h] = crop.map(|v| v as usize);
        let ax = axis(interp, x, w)?;
        let ay = axis(interp, y, h)?;
        let v: Vec<f64> = (0..self.c)
            .map(|k| {
                ay.iter()
                    .flat_map(|&(r, wy)| {
                        ax.iter()
                            .map(move |&(col, wx)| self.gained(y0 + r, x0 + col, k) * wy * wx)
                    })
                    .sum()
            })
            .collect();
        (!v.iter().any(|s| s.is_nan())).then_some(v)
    }

    fn run(
        &self,
        crops: &[[i64; 4]],
        (warps, masks, (hr, wr)): (&[f32], Option<&[u8]>, (usize, usize)),
        views: &[usize],
        interp: Interp,
    ) -> Vec<f32> {
        let raw = ImageView::new(&self.raw, self.h, self.w, self.c).unwrap();
        let gains = ImageView::new(&self.gains, self.h, self.w, self.g).unwrap();
        let maps = ViewMaps::new(warps, masks, crops.len(), hr, wr).unwrap();
        let shape = rectify_output_shape(&raw, &gains, crops, &maps, views).unwrap();
        assert_eq!(shape, [views.len(), hr, wr, self.c]);
        let mut out = vec![0.0f32; shape.iter().product()];
        rectify(raw, gains, crops, maps, views, interp, &mut out).unwrap();
        out
    }

    /// Runs `rectify` and compares every output pixel with the definition.
    fn check(
        &self,
        crops: &[[i64; 4]],
        maps: (&[f32], Option<&[u8]>, (usize, usize)),
        views: &[usize],
        interp: Interp,
    ) {
        let out = self.run(crops, maps, views, interp);
        let (warps, masks, (hr, wr)) = maps;
        let per_view = hr * wr;
        for (j, &view) in views.iter().enumerate() {
            for p in 0..per_view {
                let q = view * per_view + p;
                let got = &out[(j * per_view + p) * self.c..][..self.c];
                let kept = masks.is_none_or(|m| m[q] != 0);
                let (x, y) = (warps[2 * q], warps[2 * q + 1]);
                match kept
                    .then(|| self.reference(interp, crops[view], x, y))
                    .flatten()
                {
                    None => assert!(
                        got.iter().all(|v| v.is_nan()),
                        "{interp:?} view {view} pixel {p} ({x}, {y}): expected NaN, got {got:?}"
                    ),
                    Some(want) => {
                        for (&g, &w) in got.iter().zip(&want) {
                            assert!(
                                (f64::from(g) - w).abs() <= 1e-5,
                                "{interp:?} view {view} pixel {p} ({x}, {y}): {g} vs {w}"
                            );
                        }
                    }
                }
            }
        }
    }
}

/// Deterministic pseudo-random values in `[0, 1)`.
fn noise(n: usize, seed: u64) -> impl Iterator<Item = f64> {
    (0..n as u64).map(move |i| {
        let v = (i ^ seed.rotate_left(17))
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (v >> 11) as f64 / (1u64 << 53) as f64
    })
}

fn frame_u8(h: usize, w: usize, c: usize, g: usize, seed: u64) -> Frame<u8> {
    let raw = noise(h * w * c, seed).map(|v| (v * 256.0) as u8).collect();
    let gains = noise(h * w * g, seed + 1)
        .map(|v| if v < 0.03 { 0.0 } else { 0.5 + v as f32 })
        .collect();
    Frame {
        raw,
        gains,
        h,
        w,
        c,
        g,
    }
}

/// Smooth warps: each view sees its crop scaled by 0.9 with a gentle bend, and a
/// margin of positions outside it.
fn smooth_warps(crops: &[[i64; 4]], hr: usize, wr: usize) -> Vec<f32> {
    let mut warps = Vec::with_capacity(crops.len() * hr * wr * 2);
    for (i, &[_, _, w, h]) in crops.iter().enumerate() {
        for v in 0..hr {
            for u in 0..wr {
                let (uf, vf) = (u as f32, v as f32);
                let x = (uf - wr as f32 / 2.0) * 0.9 + w as f32 / 2.0 + (vf / 9.0).sin() + i as f32;
                let y = (vf - hr as f32 / 2.0) * 0.9 + h as f32 / 2.0 + 0.5 * (uf / 7.0).cos();
                warps.extend([x, y]);
            }
        }
    }
    warps
}

fn grid(rows: i64, cols: i64, vw: i64, vh: i64) -> Vec<[i64; 4]> {
    (0..rows * cols)
        .map(|i| [1 + (i % cols) * vw, 2 + (i / cols) * vh, vw, vh])
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Warps anywhere in and around the crops (the direct path), with masks.
    #[test]
    fn random_warps_match_the_definition(
        seed in any::<u64>(),
        (c, g) in prop_oneof![Just((1usize, 1usize)), Just((3, 3)), Just((3, 1)), Just((4, 4)), Just((2, 1))],
        interp in prop::sample::select(Interp::ALL.to_vec()),
        points in prop::collection::vec(
            prop_oneof![
                6 => (-3.0f32..14.0, -3.0f32..12.0),
                1 => (0u8..13, 0u8..11).prop_map(|(x, y)| (f32::from(x), f32::from(y))),
                1 => (0u8..13, 0u8..11).prop_map(|(x, y)| (f32::from(x) + 0.015625, f32::from(y) - 0.015625)),
                1 => Just((f32::NAN, 2.0)),
            ],
            2 * 3 * 5,
        ),
        keep in prop::collection::vec(prop::bool::weighted(0.8), 2 * 3 * 5),
        views in prop::collection::vec(0usize..2, 1..4),
    ) {
        let frame = frame_u8(30, 40, c, g, seed);
        let crops = [[3, 4, 12, 10], [20, 15, 13, 11]];
        let warps: Vec<f32> = points.iter().flat_map(|&(x, y)| [x, y]).collect();
        let masks: Vec<u8> = keep.iter().map(|&k| u8::from(k)).collect();
        frame.check(&crops, (&warps, Some(&masks), (3, 5)), &views, interp);
        frame.check(&crops, (&warps, None, (3, 5)), &views, interp);
    }
}

#[test]
fn smooth_warps_match_the_definition_for_every_raw_type() {
    // 3x4 views, rectified frames larger than the crops: the band path, with
    // footprints leaving the crops all around.
    let crops = grid(3, 4, 30, 24);
    let (hr, wr) = (40usize, 45usize);
    let warps = smooth_warps(&crops, hr, wr);
    let masks: Vec<u8> = noise(warps.len() / 2, 5)
        .map(|v| u8::from(v > 0.2))
        .collect();
    let views: Vec<usize> = (0..12).collect();
    for interp in Interp::ALL {
        let f8 = frame_u8(80, 130, 3, 3, 9);
        f8.check(&crops, (&warps, Some(&masks), (hr, wr)), &views, interp);
        let f16 = Frame {
            raw: noise(80 * 130, 3).map(|v| (v * 65536.0) as u16).collect(),
            gains: noise(80 * 130, 4).map(|v| 0.5 + v as f32).collect(),
            h: 80,
            w: 130,
            c: 1,
            g: 1,
        };
        f16.check(&crops, (&warps, None, (hr, wr)), &[11, 0, 5, 5], interp);
        let mut raw: Vec<f32> = noise(80 * 130 * 4, 6).map(|v| v as f32).collect();
        raw[(30 * 130 + 40) * 4 + 2] = f32::NAN; // a NaN raw value poisons its samples
        let f32s = Frame {
            raw,
            gains: noise(80 * 130, 8)
                .map(|v| if v < 0.01 { 0.0 } else { 1.0 })
                .collect(),
            h: 80,
            w: 130,
            c: 4,
            g: 1,
        };
        f32s.check(&crops, (&warps, Some(&masks), (hr, wr)), &views, interp);
    }
}

#[test]
fn outlying_positions_fall_back_to_the_raw_frame() {
    // Smooth warps over the middle of each crop (a band is used), and isolated
    // positions elsewhere in the crop that the band estimate, which looks at every
    // fourth position, does not see: they are read from the raw frame.
    let crops = grid(1, 2, 120, 100);
    let (hr, wr) = (64usize, 70usize);
    let mut warps = Vec::new();
    for _ in &crops {
        for v in 0..hr {
            for u in 0..wr {
                let (uf, vf) = (u as f32, v as f32);
                warps.extend([40.0 + 0.5 * uf + (vf / 9.0).sin(), 30.0 + 0.6 * vf]);
            }
        }
    }
    for (k, i) in (0..warps.len() / 2)
        .filter(|i| i % 4 == 2)
        .enumerate()
        .step_by(37)
    {
        warps[2 * i] = (k * 7 % 120) as f32 + 0.3;
        warps[2 * i + 1] = (k * 3 % 100) as f32 * 0.99;
    }
    let frame = frame_u8(110, 250, 3, 1, 2);
    for interp in Interp::ALL {
        frame.check(&crops, (&warps, None, (hr, wr)), &[0, 1], interp);
    }
}

#[test]
fn scattered_positions_read_the_raw_frame_directly() {
    // Few positions scattered over large crops: computing the band of gained pixels
    // would cost more than it saves, so every tap is read from the raw frame.
    let crops = [[0, 0, 200, 150], [200, 50, 180, 150]];
    let (hr, wr) = (12usize, 16usize);
    let warps: Vec<f32> = noise(2 * hr * wr * 2, 3)
        .enumerate()
        .map(|(i, v)| (v * if i % 2 == 0 { 203.0 } else { 153.0 }) as f32 - 1.5)
        .collect();
    let frame = frame_u8(210, 400, 3, 3, 8);
    for interp in Interp::ALL {
        frame.check(&crops, (&warps, None, (hr, wr)), &[1, 0], interp);
    }
}

#[test]
fn bilinear_names_agree_and_quantised_differs() {
    let crops = grid(1, 1, 50, 40);
    let warps = smooth_warps(&crops, 30, 30);
    let frame = frame_u8(45, 55, 3, 3, 1);
    let maps = (&warps[..], None, (30, 30));
    let a = frame.run(&crops, maps, &[0], Interp::Bilinear);
    let b = frame.run(&crops, maps, &[0], Interp::BilinearExact);
    let q = frame.run(&crops, maps, &[0], Interp::BilinearQ32);
    assert!(a.iter().zip(&b).all(|(a, b)| a.to_bits() == b.to_bits()));
    let differ = a.iter().zip(&q).filter(|(a, q)| a != q).count();
    assert!(differ > a.len() / 2, "only {differ} of {} differ", a.len());
}

#[test]
fn parallel_equals_serial() {
    let crops = grid(3, 4, 120, 90);
    let (hr, wr) = (150usize, 170usize);
    let warps = smooth_warps(&crops, hr, wr);
    let masks: Vec<u8> = noise(warps.len() / 2, 1)
        .map(|v| u8::from(v > 0.1))
        .collect();
    let frame = frame_u8(300, 500, 3, 3, 4);
    let views: Vec<usize> = (0..12).collect();
    let before = parallel::num_threads();
    for interp in Interp::ALL {
        let mut outs = Vec::new();
        for threads in [1, 3] {
            parallel::set_num_threads(threads).unwrap();
            outs.push(frame.run(&crops, (&warps, Some(&masks), (hr, wr)), &views, interp));
        }
        assert!(outs[0].len() * 4 > 4 * parallel::SERIAL_BELOW_BYTES);
        let same = outs[0]
            .iter()
            .zip(&outs[1])
            .all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "{interp:?}: parallel and serial results differ");
    }
    parallel::set_num_threads(before).unwrap();
}

fn err(
    raw: (&[u8], usize, usize, usize),
    gains: (&[f32], usize, usize, usize),
    crops: &[[i64; 4]],
    maps: ViewMaps<'_>,
    views: &[usize],
    out_len: usize,
) -> Error {
    let raw = ImageView::new(raw.0, raw.1, raw.2, raw.3).unwrap();
    let gains = ImageView::new(gains.0, gains.1, gains.2, gains.3).unwrap();
    let mut out = vec![7.0f32; out_len];
    let e = rectify(raw, gains, crops, maps, views, Interp::Bilinear, &mut out).unwrap_err();
    assert!(
        out.iter().all(|&v| v == 7.0),
        "nothing written before validation"
    );
    e
}

#[test]
fn bad_inputs_name_the_argument() {
    let raw = vec![0u8; 20 * 30 * 3];
    let gains3 = vec![1.0f32; 20 * 30 * 3];
    let gains5 = vec![1.0f32; 20 * 30 * 5];
    let warps = vec![0.0f32; 2 * 4 * 5 * 2];
    let maps = ViewMaps::new(&warps, None, 2, 4, 5).unwrap();
    let ok = [[0, 0, 10, 10], [10, 10, 10, 10]];
    let r = (&raw[..], 20, 30, 3);
    let n = 2 * 4 * 5 * 3;
    let msg = |e: Error| e.to_string();

    let e = err(r, (&gains3[..900], 30, 30, 1), &ok, maps, &[0], n);
    assert_eq!(
        msg(e),
        "gains: (H, W) = (30, 30) differs from raw's (20, 30)"
    );
    let e = err(r, (&gains5, 20, 30, 5), &ok, maps, &[0], n);
    assert!(msg(e).starts_with("gains: has 5 channels but raw has 3"));
    let mono = (&raw[..600], 20, 30, 1);
    let e = err(mono, (&gains3, 20, 30, 3), &ok, maps, &[0], n / 3);
    assert!(msg(e).starts_with("gains: has 3 channels but raw has 1"));
    let e = err(r, (&gains3, 20, 30, 3), &ok[..1], maps, &[0], n);
    assert_eq!(
        msg(e),
        "crops: has 1 rectangles but warps has 2 views; one rectangle per view is needed"
    );
    let e = err(
        r,
        (&gains3, 20, 30, 3),
        &[ok[0], [25, 5, 10, 10]],
        maps,
        &[0],
        n,
    );
    assert_eq!(
        msg(e),
        "crops[1]: rectangle (x0, y0, w, h) = (25, 5, 10, 10) lies outside the 30x20 raw frame"
    );
    let e = err(
        r,
        (&gains3, 20, 30, 3),
        &[[0, 0, 0, 3], ok[1]],
        maps,
        &[0],
        n,
    );
    assert!(msg(e).starts_with("crops[0]: rectangle (x0, y0, w, h) = (0, 0, 0, 3) must have"));
    let e = err(r, (&gains3, 20, 30, 3), &ok, maps, &[], 0);
    assert_eq!(
        msg(e),
        "views: at least one view must be selected, got none"
    );
    let e = err(r, (&gains3, 20, 30, 3), &ok, maps, &[1, 2], n);
    assert_eq!(msg(e), "views[1]: view index 2 is out of range for 2 views");
    let e = err(r, (&gains3, 20, 30, 3), &ok, maps, &[1, 0], n + 1);
    assert!(matches!(e, Error::InvalidArgument { ref arg, .. } if arg == "out"));
    let wide = (&raw[..], 20, 6, 15);
    let e = err(
        wide,
        (&gains3[..120], 20, 6, 1),
        &[[0, 0, 1, 1]; 2],
        maps,
        &[0],
        300,
    );
    assert_eq!(msg(e), "raw: has 15 channels; 1 to 4 are supported");

    let e = ViewMaps::new(&warps[1..], None, 2, 4, 5).unwrap_err();
    assert!(matches!(e, Error::InvalidArgument { ref arg, .. } if arg == "warps"));
    let e = ViewMaps::new(&warps, Some(&[1u8; 39]), 2, 4, 5).unwrap_err();
    assert!(matches!(e, Error::InvalidArgument { ref arg, .. } if arg == "masks"));
    let e = ViewMaps::new(&[], None, 0, 4, 5).unwrap_err();
    assert!(matches!(e, Error::InvalidArgument { ref arg, .. } if arg == "warps"));
}
