//! Profiling driver for `RectifyPlan::rectify` at the full size of benchmarks/run.py
//! (4800x2700x3 u8 raw -> 12 x 2000x1350x3 f32, ~29% kept), output reused:
//! `cargo run --profile bench --example rect_profile -- [iters] [threads] [masked]`.
//! Prints the median wall time (and CPU time of the process) per call.

#![allow(clippy::expect_used, clippy::indexing_slicing, missing_docs)]

use std::time::Instant;

use lfcam_core::rectify::RectifyPlan;
use lfcam_core::{ImageView, Interp, ViewMaps, parallel};

fn cpu_seconds() -> f64 {
    // utime + stime of this process, from /proc (Linux only; 0 elsewhere).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|s| s.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let iters: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(20);
    let threads: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(2);
    let masked = args.get(3).is_some_and(|s| s == "masked");
    parallel::set_num_threads(threads).expect("threads");
    let (w, h, vw, vh, rw, rh) = (
        4800usize, 2700usize, 1200usize, 900usize, 2000usize, 1350usize,
    );
    let raw: Vec<u8> = (0..w * h * 3)
        .map(|i| ((i * 2_654_435_761) >> 7) as u8)
        .collect();
    let gains: Vec<f32> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = ((i % w % vw) as f32, (i / w % vh) as f32);
            let g = 1.0
                + 0.5 * ((x - vw as f32 / 2.0).powi(2) + (y - vh as f32 / 2.0).powi(2))
                    / (vw * vw) as f32;
            let g = if i % 10_007 == 0 { 0.0 } else { g };
            [g, g, g]
        })
        .collect();
    let n = 12;
    let (ox, oy) = ((w - 4 * vw) / 2, (h - 3 * vh) / 2);
    let crops: Vec<[i64; 4]> = (0..n)
        .map(|i| {
            [
                (ox + (i % 4) * vw) as i64,
                (oy + (i / 4) * vh) as i64,
                vw as i64,
                vh as i64,
            ]
        })
        .collect();
    let mut warps = vec![f32::NAN; n * rh * rw * 2];
    let mut masks = vec![0u8; n * rh * rw];
    for i in 0..n {
        let (r, c) = ((i / 4) as f32, (i % 4) as f32);
        for v in 0..rh {
            for u in 0..rw {
                let (uf, vf) = (u as f32, v as f32);
                let x = (uf - rw as f32 / 2.0 - (c - 1.5) * 120.0) * 0.9
                    + vw as f32 / 2.0
                    + 5.0 * (vf / 300.0).sin();
                let y = (vf - rh as f32 / 2.0 - (r - 1.0) * 120.0) * 0.9
                    + vh as f32 / 2.0
                    + 5.0 * (uf / 400.0).cos();
                let inside = (x - vw as f32 / 2.0).hypot(y - vh as f32 / 2.0) < 0.5 * vh as f32
                    && (0.0..=(vw - 1) as f32).contains(&x)
                    && (0.0..=(vh - 1) as f32).contains(&y);
                if inside && !masked {
                    let k = (i * rh + v) * rw + u;
                    warps[2 * k] = x;
                    warps[2 * k + 1] = y;
                    masks[k] = 1;
                }
            }
        }
    }
    let raw_v = ImageView::new(&raw, h, w, 3).expect("raw");
    let gains_v = ImageView::new(&gains, h, w, 3).expect("gains");
    let maps = ViewMaps::new(&warps, Some(&masks), n, rh, rw).expect("maps");
    let plan = RectifyPlan::new(gains_v, &crops, maps, Interp::Bilinear).expect("plan");
    let views: Vec<usize> = (0..n).collect();
    let mut out = vec![0.0f32; n * rh * rw * 3];
    for _ in 0..2 {
        plan.rectify(raw_v, &views, &mut out).expect("rectify");
    }
    let mut wall = Vec::new();
    let cpu0 = cpu_seconds();
    for _ in 0..iters {
        let t = Instant::now();
        plan.rectify(raw_v, &views, &mut out).expect("rectify");
        wall.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cpu = (cpu_seconds() - cpu0) * 1e3 / iters as f64;
    wall.sort_by(f64::total_cmp);
    let sum: f64 = out
        .iter()
        .filter(|v| v.is_finite())
        .map(|&v| f64::from(v))
        .sum();
    println!(
        "{} kept {:.1}%: median {:.2} ms, min {:.2} ms, cpu {:.1} ms/call ({threads} threads); checksum {sum:.6e}",
        if masked { "masked" } else { "rectify" },
        100.0 * plan.kept() as f64 / (n * rh * rw) as f64,
        wall[iters / 2],
        wall[0],
        cpu
    );
}
