//! Lenslet cropping: a 3x4 grid of views, u8 RGB and u16 mono, two view sizes, on the
//! default number of threads and on one. Throughput is output elements.

#![allow(clippy::expect_used, missing_docs)]

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use lfcam_core::{ImageView, crop_lenslets, parallel};

const GRID: (i64, i64) = (3, 4);

fn grid_rects(view_w: i64, view_h: i64) -> Vec<[i64; 4]> {
    (0..GRID.0 * GRID.1)
        .map(|i| [(i % GRID.1) * view_w, (i / GRID.1) * view_h, view_w, view_h])
        .collect()
}

fn bench_one<T: Copy + Default + From<u8> + Send + Sync>(
    c: &mut Criterion,
    name: &str,
    channels: usize,
    view: (i64, i64),
) {
    let (vw, vh) = view;
    // The raw frame is the grid plus a margin, like a real sensor.
    let (w, h) = ((vw * GRID.1) as usize + 64, (vh * GRID.0) as usize + 36);
    // Not zeros: an all-zero frame may be backed by the shared zero page and read from
    // cache, which flatters the copy.
    let data: Vec<T> = (0..w * h * channels)
        .map(|i| T::from((i % 251) as u8))
        .collect();
    let src = ImageView::new(&data, h, w, channels).expect("frame");
    let rects = grid_rects(vw, vh);
    let len = rects.len() * (vw * vh) as usize * channels;
    // The output is reused across iterations, so this measures the copy, not the page
    // faults of a fresh allocation (benchmarks/run.py measures the whole Python call).
    let mut out = vec![T::default(); len];
    let default_threads = parallel::num_threads();

    let mut group = c.benchmark_group(format!("crop_lenslets/{name}"));
    group.throughput(Throughput::Elements(len as u64));
    for threads in [1, default_threads] {
        parallel::set_num_threads(threads).expect("threads");
        group.bench_with_input(
            BenchmarkId::new(format!("{vw}x{vh}"), format!("{threads}t")),
            &rects,
            |b, rects| {
                b.iter(|| crop_lenslets(black_box(src), black_box(rects), &mut out).expect("crop"));
            },
        );
        if default_threads == 1 {
            break;
        }
    }
    parallel::set_num_threads(default_threads).expect("threads");
    group.finish();
}

fn crop(c: &mut Criterion) {
    for view in [(480, 360), (1200, 900)] {
        bench_one::<u8>(c, "u8_rgb", 3, view);
        bench_one::<u16>(c, "u16_mono", 1, view);
    }
}

criterion_group!(benches, crop);
criterion_main!(benches);
