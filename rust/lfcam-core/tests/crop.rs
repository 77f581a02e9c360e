//! `crop_lenslets` against a naive reference, and every bad input.

#![allow(clippy::panic)] // test helpers outside `#[test]` functions

use lfcam_core::{Error, ImageView, crop::crop_output_shape, crop_lenslets, parallel};
use proptest::prelude::*;

/// The obvious triple loop, indexing `data` directly.
fn naive<T: Copy + Default>(
    data: &[T],
    width: usize,
    channels: usize,
    rects: &[[i64; 4]],
) -> Vec<T> {
    let mut out = Vec::new();
    for &[x0, y0, w, h] in rects {
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                for k in 0..channels {
                    out.push(data[(y as usize * width + x as usize) * channels + k]);
                }
            }
        }
    }
    out
}

/// A frame of `h x w x c` distinct-ish values, rectangles of one size inside it.
fn case() -> impl Strategy<Value = (usize, usize, usize, Vec<[i64; 4]>)> {
    (1usize..300, 1usize..300, 1usize..5).prop_flat_map(|(h, w, c)| {
        (1..=w, 1..=h).prop_flat_map(move |(rw, rh)| {
            let origin = (0..=(w - rw) as i64, 0..=(h - rh) as i64);
            let rects = prop::collection::vec(
                origin.prop_map(move |(x0, y0)| [x0, y0, rw as i64, rh as i64]),
                1..16,
            );
            (Just(h), Just(w), Just(c), rects)
        })
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn matches_naive_reference((h, w, c, rects) in case()) {
        let data: Vec<u32> = (0..(h * w * c) as u32).collect();
        let src = ImageView::new(&data, h, w, c).unwrap();
        let shape = crop_output_shape(&src, &rects).unwrap();
        let mut out = vec![u32::MAX; shape.iter().product()];
        crop_lenslets(src, &rects, &mut out).unwrap();
        prop_assert_eq!(out, naive(&data, w, c, &rects));
    }

    #[test]
    fn arbitrary_rects_never_panic(
        rects in prop::collection::vec(prop::array::uniform4(any::<i64>()), 0..4),
        len in 0usize..64,
    ) {
        let data = vec![1u8; 6 * 5 * 2];
        let src = ImageView::new(&data, 6, 5, 2).unwrap();
        let mut out = vec![0u8; len];
        let _ = crop_lenslets(src, &rects, &mut out);
        let _ = crop_output_shape(&src, &rects);
    }
}

/// Large enough to take the parallel path, on several thread counts.
#[test]
fn parallel_equals_naive_on_a_3x4_grid() {
    let (hh, ww, c) = (1080usize, 1920usize, 3usize);
    let data: Vec<u8> = (0..hh * ww * c).map(|v| (v * 7 % 251) as u8).collect();
    let src = ImageView::new(&data, hh, ww, c).unwrap();
    let rects: Vec<[i64; 4]> = (0..12)
        .map(|i| [(i % 4) * 480, (i / 4) * 360, 480, 360])
        .collect();
    let want = naive(&data, ww, c, &rects);
    assert!(want.len() >= 4 * parallel::SERIAL_BELOW_BYTES);
    for threads in [1, 2, 3] {
        parallel::set_num_threads(threads).unwrap();
        let mut out = vec![0u8; want.len()];
        crop_lenslets(src, &rects, &mut out).unwrap();
        assert!(out == want, "{threads} threads");
    }
}

fn item_error(err: Error) -> (String, usize, String) {
    match err {
        Error::InvalidItem { arg, index, reason } => (arg, index, reason),
        other => panic!("expected InvalidItem, got {other:?}"),
    }
}

#[test]
fn bad_rects_are_invalid_items_naming_the_index() {
    let data = vec![0u16; 40 * 30];
    let src = ImageView::new(&data, 30, 40, 1).unwrap();
    let ok = [0, 0, 10, 10];
    let cases: [([i64; 4], &str); 9] = [
        ([-1, 0, 10, 10], "lies outside the 40x30 frame"),
        ([0, -1, 10, 10], "lies outside the 40x30 frame"),
        ([31, 0, 10, 10], "lies outside the 40x30 frame"),
        ([0, 21, 10, 10], "lies outside the 40x30 frame"),
        ([i64::MAX, 0, 10, 10], "lies outside"),
        ([i64::MIN, i64::MIN, 10, 10], "lies outside"),
        ([0, 0, 0, 10], "at least 1"),
        ([0, 0, 10, -5], "at least 1"),
        ([1, 1, 11, 10], "differs from that of rects[0], (10, 10)"),
    ];
    for (bad, needle) in cases {
        let mut out = vec![0u16; 300];
        let (arg, index, reason) =
            item_error(crop_lenslets(src, &[ok, ok, bad], &mut out).unwrap_err());
        assert_eq!((arg.as_str(), index), ("rects", 2), "{bad:?}");
        assert!(reason.contains(needle), "{bad:?}: {reason}");
        assert!(
            out.iter().all(|&v| v == 0),
            "nothing written before validation"
        );
    }
    let (_, index, reason) =
        item_error(crop_lenslets(src, &[[30, 20, 11, 10], ok], &mut vec![0u16; 220]).unwrap_err());
    assert_eq!(index, 0);
    assert_eq!(
        reason,
        "rectangle (x0, y0, w, h) = (30, 20, 11, 10) lies outside the 40x30 frame"
    );
}

#[test]
fn no_rects_and_wrong_output_are_invalid_arguments() {
    let data = vec![0f32; 8 * 8 * 3];
    let src = ImageView::new(&data, 8, 8, 3).unwrap();
    assert!(matches!(
        crop_lenslets(src, &[], &mut []),
        Err(Error::InvalidArgument { ref arg, .. }) if arg == "rects"
    ));
    for len in [0usize, 2 * 4 * 4 * 3 - 1, 2 * 4 * 4 * 3 + 1] {
        let mut out = vec![0f32; len];
        let err = crop_lenslets(src, &[[0, 0, 4, 4], [4, 4, 4, 4]], &mut out).unwrap_err();
        assert!(
            matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "out"),
            "{len}: {err:?}"
        );
    }
    let mut out = vec![0f32; 2 * 4 * 4 * 3];
    crop_lenslets(src, &[[0, 0, 4, 4], [4, 4, 4, 4]], &mut out).unwrap();
}
