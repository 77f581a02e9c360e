//! `nan_median` against a sort-based reference, and parallel == serial.

#![allow(clippy::panic, clippy::unwrap_used, clippy::indexing_slicing)] // test helpers outside `#[test]` functions

use lfcam_core::{Error, nan_median, parallel};
use proptest::prelude::*;

/// Sort the non-NaN values; the middle one, or the float32 mean of the two middle ones.
fn reference(values: &[f32]) -> (f32, usize) {
    let mut v: Vec<f32> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    v.sort_by(f32::total_cmp);
    let n = v.len();
    let m = match n {
        0 => f32::NAN,
        _ if n % 2 == 1 => v[n / 2],
        _ => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    };
    (m, n)
}

fn check(stack: &[f32], k: usize) {
    let m = stack.len() / k;
    let mut med = vec![0.0f32; m];
    let mut cnt = vec![0u16; m];
    nan_median(stack, k, &mut med, &mut cnt).unwrap();
    for e in 0..m {
        let column: Vec<f32> = (0..k).map(|i| stack[i * m + e]).collect();
        let (want, n) = reference(&column);
        assert_eq!(usize::from(cnt[e]), n, "element {e}: {column:?}");
        assert!(
            med[e] == want || (med[e].is_nan() && want.is_nan()),
            "element {e}: {} vs {want} for {column:?}",
            med[e]
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn matches_sorting(
        k in 1usize..70,
        m in 1usize..40,
        values in prop::collection::vec(
            prop_oneof![
                4 => -1e3f32..1e3,
                1 => Just(f32::NAN),
                1 => (0i8..4).prop_map(f32::from),
                1 => Just(f32::INFINITY),
            ],
            70 * 40,
        ),
    ) {
        check(&values[..k * m], k);
    }
}

#[test]
fn all_nan_even_and_single() {
    let nan = f32::NAN;
    check(&[nan, nan, nan, 1.0, nan, nan], 3);
    check(&[4.0, 1.0, 2.0, 8.0], 4);
    check(&[4.0, 1.0, 2.0, 8.0], 1);
    check(&[4.0, nan, 2.0, 8.0, 3.0, 5.0], 2);
}

#[test]
fn parallel_equals_serial() {
    let (k, m) = (5usize, 400_000usize);
    let stack: Vec<f32> = (0..k * m)
        .map(|i| {
            if i % 7 == 3 {
                f32::NAN
            } else {
                ((i * 7919) % 1000) as f32 * 0.01
            }
        })
        .collect();
    let before = parallel::num_threads();
    let mut outs = Vec::new();
    for threads in [1, 3] {
        parallel::set_num_threads(threads).unwrap();
        let mut med = vec![0.0f32; m];
        let mut cnt = vec![0u8; m];
        nan_median(&stack, k, &mut med, &mut cnt).unwrap();
        outs.push((med, cnt));
    }
    parallel::set_num_threads(before).unwrap();
    assert!(
        outs[0]
            .0
            .iter()
            .zip(&outs[1].0)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    assert_eq!(outs[0].1, outs[1].1);
    check(&stack[..k * 1000], k); // spot check of the definition
}

#[test]
fn bad_sizes_name_the_argument() {
    let arg = |e: Error| match e {
        Error::InvalidArgument { arg, .. } => arg,
        other => panic!("{other:?}"),
    };
    let (mut med, mut cnt) = (vec![0.0f32; 3], vec![0u8; 3]);
    assert_eq!(
        arg(nan_median(&[0.0; 6], 0, &mut med, &mut cnt).unwrap_err()),
        "stack"
    );
    assert_eq!(
        arg(nan_median(&[0.0; 7], 2, &mut med, &mut cnt).unwrap_err()),
        "stack"
    );
    assert_eq!(
        arg(nan_median(&[0.0; 6], 2, &mut med, &mut [0u8; 2]).unwrap_err()),
        "count"
    );
    let big = vec![0.0f32; 300 * 3];
    assert_eq!(
        arg(nan_median(&big, 300, &mut med, &mut cnt).unwrap_err()),
        "count"
    );
    nan_median(&big, 300, &mut med, &mut [0u16; 3]).unwrap();
    // No elements: nothing to do.
    nan_median(&[], 4, &mut [], &mut [0u8; 0]).unwrap();
}
