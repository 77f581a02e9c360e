//! Triangulation of 11 flows (a 3x4 grid, reference at row 1, column 1) as in
//! benchmarks/run.py: a smooth parallax field, 0.2 px flow noise, 10% occluded flow
//! vectors (a 2-8 px error) and 5% holes (NaN). Two sizes (480x360, 1000x1000), without
//! weights, with 0/1 weights (what the forward-backward check gives) and with fractional
//! weights, on one thread and on the default number. Throughput is reference pixels.

#![allow(clippy::expect_used, clippy::indexing_slicing, missing_docs)]

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use lfcam_core::parallel;
use lfcam_core::triangulate::{Outputs, Params, ViewStack, triangulate};

const GRID: (usize, usize) = (3, 4);
const REFERENCE: usize = 5;

struct Inputs {
    n: usize,
    flows: Vec<f32>,
    binary: Vec<f32>,
    fractional: Vec<f32>,
    offsets: Vec<[f64; 2]>,
}

/// A small deterministic generator (splitmix64): uniform in [0, 1).
fn uniform(state: &mut u64) -> f64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
}

fn inputs(h: usize, w: usize) -> Inputs {
    let n = GRID.0 * GRID.1;
    let (rr, rc) = (REFERENCE / GRID.1, REFERENCE % GRID.1);
    let offsets: Vec<[f64; 2]> = (0..n)
        .map(|i| {
            let (r, c) = (i / GRID.1, i % GRID.1);
            [25.0 * (c as f64 - rc as f64), 25.0 * (r as f64 - rr as f64)]
        })
        .collect();
    let mut state = 1u64;
    let mut flows = vec![0f32; n * h * w * 2];
    let mut binary = vec![0f32; n * h * w];
    let mut fractional = vec![0f32; n * h * w];
    for y in 0..h {
        for x in 0..w {
            let s = 0.4 * ((x as f64 / 97.0).sin() * (y as f64 / 61.0).cos());
            for (i, o) in offsets.iter().enumerate() {
                let k = (i * h + y) * w + x;
                let mut noise = || 0.2 * 3f64.sqrt() * (2.0 * uniform(&mut state) - 1.0);
                let (mut ux, mut uy) = (o[0] * s + noise(), o[1] * s + noise());
                let roll = uniform(&mut state);
                if roll < 0.10 {
                    let e = 2.0 + 6.0 * uniform(&mut state);
                    ux += e;
                    uy -= 0.5 * e;
                }
                let hole = (0.10..0.15).contains(&roll);
                if hole {
                    ux = f64::NAN;
                }
                flows[2 * k] = ux as f32;
                flows[2 * k + 1] = uy as f32;
                binary[k] = if hole || i == REFERENCE { 0.0 } else { 1.0 };
                fractional[k] = if hole { 0.0 } else { 0.3 + 0.7 * roll as f32 };
            }
        }
    }
    Inputs {
        n,
        flows,
        binary,
        fractional,
        offsets,
    }
}

fn bench(c: &mut Criterion) {
    let default_threads = parallel::num_threads();
    for (h, w) in [(360, 480), (1000, 1000)] {
        let inp = inputs(h, w);
        let px = h * w;
        let (mut par, mut conf, mut res, mut perp) = (
            vec![0f32; px],
            vec![0f32; px],
            vec![0f32; px],
            vec![0f32; px],
        );
        let mut used = vec![0u8; px];
        let flows = ViewStack::new(&inp.flows, [inp.n, h, w, 2], "flows").expect("flows");
        let mut group = c.benchmark_group(format!("triangulate/{}x{}", w, h));
        group.throughput(Throughput::Elements(px as u64));
        group.sample_size(20);
        for (name, weights) in [
            ("none", None),
            ("binary", Some(&inp.binary)),
            ("fractional", Some(&inp.fractional)),
        ] {
            let weights =
                weights.map(|d| ViewStack::new(d, [inp.n, h, w, 1], "weights").expect("weights"));
            for threads in [1, default_threads] {
                parallel::set_num_threads(threads).expect("threads");
                group.bench_function(BenchmarkId::new(name, format!("{threads}t")), |b| {
                    b.iter(|| {
                        let out = Outputs {
                            parallax: &mut par,
                            confidence: &mut conf,
                            residual: &mut res,
                            perpendicular: &mut perp,
                            n_used: &mut used,
                        };
                        triangulate(
                            black_box(flows),
                            black_box(weights),
                            &inp.offsets,
                            REFERENCE,
                            &Params::default(),
                            out,
                        )
                        .expect("triangulate")
                    });
                });
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
