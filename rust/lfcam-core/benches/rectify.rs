//! Rectification of a 3x4 grid of views from an RGB u8 raw frame, as in
//! benchmarks/run.py: smooth warps, about 2/3 of each rectified frame masked. Two sizes
//! (1920x1080 raw -> 12 x 810x540, 4800x2700 raw -> 12 x 2000x1350), each interpolation
//! method, on one thread and on the default number. Throughput is output pixels.

#![allow(clippy::expect_used, clippy::indexing_slicing, missing_docs)]

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use lfcam_core::{ImageView, Interp, ViewMaps, parallel, rectify};

const GRID: (usize, usize) = (3, 4);

struct Case {
    name: &'static str,
    raw_size: (usize, usize),
    view: (usize, usize),
    rect: (usize, usize),
}

const CASES: [Case; 2] = [
    Case {
        name: "small",
        raw_size: (1920, 1080),
        view: (480, 360),
        rect: (810, 540),
    },
    Case {
        name: "full",
        raw_size: (4800, 2700),
        view: (1200, 900),
        rect: (2000, 1350),
    },
];

struct Inputs {
    raw: Vec<u8>,
    gains: Vec<f32>,
    crops: Vec<[i64; 4]>,
    warps: Vec<f32>,
    masks: Vec<u8>,
}

/// A view sees a scaled (0.9), shifted and gently distorted part of the rectified
/// frame, inside its image circle; elsewhere the warp is NaN and the mask 0.
fn inputs(case: &Case) -> Inputs {
    let (w, h) = case.raw_size;
    let (vw, vh) = case.view;
    let (rw, rh) = case.rect;
    let raw: Vec<u8> = (0..w * h * 3).map(|i| (i * 7 % 251) as u8).collect();
    let gains: Vec<f32> = (0..w * h * 3)
        .map(|i| 0.8 + 0.4 * ((i * 13 % 97) as f32 / 97.0))
        .collect();
    let n = GRID.0 * GRID.1;
    let crops: Vec<[i64; 4]> = (0..n)
        .map(|i| {
            [
                ((i % GRID.1) * vw) as i64,
                ((i / GRID.1) * vh) as i64,
                vw as i64,
                vh as i64,
            ]
        })
        .collect();
    let mut warps = vec![f32::NAN; n * rh * rw * 2];
    let mut masks = vec![0u8; n * rh * rw];
    let shift = rw as f32 * 0.06;
    for i in 0..n {
        let (r, c) = ((i / GRID.1) as f32, (i % GRID.1) as f32);
        let (dx, dy) = ((c - 1.5) * shift, (r - 1.0) * shift);
        for v in 0..rh {
            for u in 0..rw {
                let (uf, vf) = (u as f32, v as f32);
                let x =
                    (uf - rw as f32 / 2.0 - dx) * 0.9 + vw as f32 / 2.0 + 5.0 * (vf / 300.0).sin();
                let y =
                    (vf - rh as f32 / 2.0 - dy) * 0.9 + vh as f32 / 2.0 + 5.0 * (uf / 400.0).cos();
                let rad = (x - vw as f32 / 2.0).hypot(y - vh as f32 / 2.0);
                let inside = rad < 0.5 * vh as f32
                    && (0.0..=(vw - 1) as f32).contains(&x)
                    && (0.0..=(vh - 1) as f32).contains(&y);
                if inside {
                    let k = (i * rh + v) * rw + u;
                    warps[2 * k] = x;
                    warps[2 * k + 1] = y;
                    masks[k] = 1;
                }
            }
        }
    }
    Inputs {
        raw,
        gains,
        crops,
        warps,
        masks,
    }
}

fn bench(c: &mut Criterion) {
    let default_threads = parallel::num_threads();
    for case in &CASES {
        let inp = inputs(case);
        let (w, h) = case.raw_size;
        let (rw, rh) = case.rect;
        let n = inp.crops.len();
        let raw = ImageView::new(&inp.raw, h, w, 3).expect("raw");
        let gains = ImageView::new(&inp.gains, h, w, 3).expect("gains");
        let maps = ViewMaps::new(&inp.warps, Some(&inp.masks), n, rh, rw).expect("maps");
        let views: Vec<usize> = (0..n).collect();
        // Reused across iterations: this measures the kernel, not the page faults of a
        // fresh output (benchmarks/run.py measures the whole Python call).
        let mut out = vec![0.0f32; n * rh * rw * 3];
        let mut group = c.benchmark_group(format!("rectify/{}", case.name));
        group.throughput(Throughput::Elements((n * rh * rw) as u64));
        group.sample_size(10);
        for interp in [Interp::Bilinear, Interp::BilinearQ32, Interp::Bicubic] {
            for threads in [1, default_threads] {
                parallel::set_num_threads(threads).expect("threads");
                group.bench_function(
                    BenchmarkId::new(interp.name(), format!("{threads}t")),
                    |b| {
                        b.iter(|| {
                            rectify(
                                black_box(raw),
                                black_box(gains),
                                &inp.crops,
                                maps,
                                &views,
                                interp,
                                &mut out,
                            )
                            .expect("rectify");
                        });
                    },
                );
                if default_threads == 1 {
                    break;
                }
            }
        }
        parallel::set_num_threads(default_threads).expect("threads");
        group.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
