//! `remap_bilinear` against a float64 reference, its NaN and edge rules, and parallel ==
//! serial.

#![allow(clippy::panic, clippy::unwrap_used, clippy::indexing_slicing)] // test helpers outside `#[test]` functions

use lfcam_core::{Error, ImageView, parallel, remap_bilinear};
use proptest::prelude::*;

/// The definition, in float64: the footprint is the pixels with non-zero weight; NaN
/// when it leaves the image or holds a NaN, in every channel.
fn reference(data: &[f32], h: usize, w: usize, c: usize, x: f32, y: f32) -> Option<Vec<f64>> {
    let axis = |v: f32, n: usize| -> Option<(usize, usize, f64)> {
        if !v.is_finite() || v < 0.0 || f64::from(v) > (n - 1) as f64 {
            return None;
        }
        let v = f64::from(v);
        let i0 = v.floor() as usize;
        let t = v - i0 as f64;
        let i1 = if t > 0.0 { i0 + 1 } else { i0 };
        (i1 < n).then_some((i0, i1, t))
    };
    let (x0, x1, tx) = axis(x, w)?;
    let (y0, y1, ty) = axis(y, h)?;
    let px = |r: usize, col: usize, k: usize| f64::from(data[(r * w + col) * c + k]);
    let v: Vec<f64> = (0..c)
        .map(|k| {
            px(y0, x0, k) * (1.0 - tx) * (1.0 - ty)
                + px(y0, x1, k) * tx * (1.0 - ty)
                + px(y1, x0, k) * (1.0 - tx) * ty
                + px(y1, x1, k) * tx * ty
        })
        .collect();
    // A NaN tap only counts if it has weight: `x1 == x0` when `tx == 0`.
    (!v.iter().any(|s| s.is_nan())).then_some(v)
}

fn check(data: &[f32], (h, w, c): (usize, usize, usize), map: &[f32], (mh, mw): (usize, usize)) {
    let src = ImageView::new(data, h, w, c).unwrap();
    let map_v = ImageView::new(map, mh, mw, 2).unwrap();
    let mut out = vec![0.0f32; mh * mw * c];
    remap_bilinear(src, map_v, &mut out).unwrap();
    for (i, (px, pt)) in out.chunks_exact(c).zip(map.chunks_exact(2)).enumerate() {
        match reference(data, h, w, c, pt[0], pt[1]) {
            None => assert!(
                px.iter().all(|v| v.is_nan()),
                "position {i} {pt:?}: expected NaN, got {px:?}"
            ),
            Some(want) => {
                for (&got, &want) in px.iter().zip(&want) {
                    // Float32 arithmetic on values of this size: a few ulp.
                    let tol = 1e-6 * want.abs().max(1.0);
                    assert!(
                        (f64::from(got) - want).abs() <= tol,
                        "position {i} {pt:?}: {got} vs {want}"
                    );
                }
            }
        }
    }
}

fn image(h: usize, w: usize, c: usize, seed: u64) -> Vec<f32> {
    (0..h * w * c)
        .map(|i| {
            let v = (i as u64)
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(seed);
            (v >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn matches_float64_reference(
        (h, w, c) in (1usize..20, 1usize..20, 1usize..=4),
        seed in any::<u64>(),
        points in prop::collection::vec(
            prop_oneof![
                8 => (-2.0f32..22.0, -2.0f32..22.0),
                1 => (0u8..22, 0u8..22).prop_map(|(x, y)| (f32::from(x), f32::from(y))),
                1 => Just((f32::NAN, 1.0)),
            ],
            1..200,
        ),
    ) {
        let data = image(h, w, c, seed);
        let map: Vec<f32> = points.iter().flat_map(|&(x, y)| [x, y]).collect();
        check(&data, (h, w, c), &map, (1, points.len()));
    }

    #[test]
    fn nan_sources_poison_only_samples_that_weigh_them(
        seed in any::<u64>(),
        nan_at in 0usize..30,
        points in prop::collection::vec((0.0f32..5.0, 0.0f32..4.0), 1..100),
    ) {
        let mut data = image(5, 6, 2, seed);
        data[nan_at * 2 + 1] = f32::NAN;
        let map: Vec<f32> = points.iter().flat_map(|&(x, y)| [x, y]).collect();
        check(&data, (5, 6, 2), &map, (1, points.len()));
    }
}

#[test]
fn whole_number_positions_and_the_last_row_and_column() {
    // A 3x4 RGB image whose last column and row are read exactly, never beyond.
    let data = image(3, 4, 3, 7);
    let mut map = Vec::new();
    for y in 0..3 {
        for x in 0..4 {
            map.extend([x as f32, y as f32]);
        }
    }
    map.extend([3.0, 1.5, 2.5, 2.0, 3.0, 2.0]);
    let src = ImageView::new(&data, 3, 4, 3).unwrap();
    let n = map.len() / 2;
    let mut out = vec![0.0f32; n * 3];
    remap_bilinear(src, ImageView::new(&map, 1, n, 2).unwrap(), &mut out).unwrap();
    assert_eq!(
        out[..36],
        data[..],
        "whole-number positions reproduce the image"
    );
    check(&data, (3, 4, 3), &map, (1, n));
    // Just outside: NaN.
    let outside = [
        3.0001f32,
        0.0,
        0.0,
        2.0001,
        -0.0001,
        0.0,
        f32::INFINITY,
        0.0,
    ];
    let mut out = vec![0.0f32; 12];
    remap_bilinear(src, ImageView::new(&outside, 1, 4, 2).unwrap(), &mut out).unwrap();
    assert!(out.iter().all(|v| v.is_nan()), "{out:?}");
}

#[test]
fn composes_maps() {
    // Sampling a map (2 channels) at displaced positions.
    let (h, w) = (40usize, 50usize);
    let map_a: Vec<f32> = (0..h * w)
        .flat_map(|i| {
            let (y, x) = ((i / w) as f32, (i % w) as f32);
            [2.0 * x + 1.0, 0.5 * y - 3.0]
        })
        .collect();
    let pts = [10.25f32, 7.5, 49.0, 39.0, 0.0, 0.0];
    let mut out = [0.0f32; 6];
    remap_bilinear(
        ImageView::new(&map_a, h, w, 2).unwrap(),
        ImageView::new(&pts, 1, 3, 2).unwrap(),
        &mut out,
    )
    .unwrap();
    // An affine map is reproduced exactly by bilinear interpolation.
    assert_eq!(out, [21.5, 0.75, 99.0, 16.5, 1.0, -3.0]);
}

#[test]
fn parallel_equals_serial() {
    let (h, w, c) = (300usize, 400usize, 3usize);
    let data = image(h, w, c, 1);
    let (mh, mw) = (500usize, 600usize);
    let map: Vec<f32> = (0..mh * mw)
        .flat_map(|i| {
            let (r, col) = ((i / mw) as f32, (i % mw) as f32);
            [col * 0.7 - 5.0 + (r * 0.01).sin(), r * 0.6 - 2.0]
        })
        .collect();
    let src = ImageView::new(&data, h, w, c).unwrap();
    let map_v = ImageView::new(&map, mh, mw, 2).unwrap();
    let before = parallel::num_threads();
    let mut outs = Vec::new();
    for threads in [1, 3] {
        parallel::set_num_threads(threads).unwrap();
        let mut out = vec![0.0f32; mh * mw * c];
        remap_bilinear(src, map_v, &mut out).unwrap();
        outs.push(out);
    }
    parallel::set_num_threads(before).unwrap();
    assert!(outs[0].len() * 4 >= 4 * parallel::SERIAL_BELOW_BYTES);
    let same = outs[0]
        .iter()
        .zip(&outs[1])
        .all(|(a, b)| a.to_bits() == b.to_bits());
    assert!(same, "parallel and serial results differ");
}

#[test]
fn bad_arguments_name_themselves() {
    let data = [0.0f32; 12];
    let src = ImageView::new(&data, 2, 2, 3).unwrap();
    let map3 = ImageView::new(&data, 2, 2, 3).unwrap();
    let map2 = ImageView::new(&data[..8], 2, 2, 2).unwrap();
    let arg = |e: Error| match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("{other:?}"),
    };
    assert_eq!(
        arg(remap_bilinear(src, map3, &mut [0.0; 12]).unwrap_err()),
        "map"
    );
    assert_eq!(
        arg(remap_bilinear(src, map2, &mut [0.0; 13]).unwrap_err()),
        "out"
    );
    let wide = ImageView::new(&data, 1, 1, 12).unwrap();
    assert_eq!(
        arg(remap_bilinear(wide, map2, &mut [0.0; 48]).unwrap_err()),
        "src"
    );
}
