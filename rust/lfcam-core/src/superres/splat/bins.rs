//! Samples sorted into bands of output rows for [`super::shift_and_add`]: a band's
//! samples as runs of consecutive sample indices, so that bands are accumulated in
//! parallel without sharing output and read their samples in order.

use super::{fine_pos, nearest};
use crate::error::{Error, Result};
use crate::parallel;
use crate::superres::positive;

/// Samples per binning chunk: fixed (not per thread), so that the order in which a
/// pixel's samples are summed, hence the result, does not depend on the thread count.
const BIN_CHUNK: usize = 1 << 16;

/// One chunk's samples sorted into bands (a counting sort), as runs of consecutive
/// sample indices: band `b`'s samples are the runs `runs[starts[b]..starts[b + 1]]`
/// (`[k0, k1)` each), in increasing order. The samples of one raw row of a view land in
/// one or two bands, so a run is usually a whole row's worth of samples: the bands read
/// positions and values in order, and the bins are small.
pub(super) struct ChunkRuns {
    pub(super) starts: Vec<u32>,
    pub(super) runs: Vec<[u32; 2]>,
}

pub(super) struct Bins {
    pub(super) band_rows: usize,
    pub(super) chunks: Vec<ChunkRuns>,
}

/// Samples sorted into bands of output rows (a sample whose kernel touches two bands
/// is in both), so that bands can be accumulated in parallel without sharing output.
/// Chunks of [`BIN_CHUNK`] samples are sorted in parallel.
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
pub(super) fn bin_samples(
    positions: &[f32],
    weights: Option<&[f32]>,
    m: usize,
    factor: f32,
    radius: usize,
    fine_h: usize,
    band_rows: usize,
) -> Result<Bins> {
    if m >= u32::MAX as usize {
        return Err(Error::invalid_argument(
            "positions",
            format!("{m} samples: fewer than {} are supported", u32::MAX),
        ));
    }
    // A kernel is at most 2 r + 1 < band_rows rows tall (checked by the caller): it
    // touches one band or two neighbours.
    debug_assert!(2 * radius < band_rows);
    let n_bands = fine_h.div_ceil(band_rows);
    let one = |c: usize| -> ChunkRuns {
        let k0 = c * BIN_CHUNK;
        let k1 = (k0 + BIN_CHUNK).min(m);
        let mut bands = BandOf::new(radius, fine_h, band_rows);
        // Runs in order of their first sample, `(band, [k0, k1))`; `open[b]`: band b's
        // last run (u32::MAX: none yet), which sample k extends if it ends at k.
        let mut seq: Vec<(u32, [u32; 2])> = Vec::new();
        let mut open = vec![u32::MAX; n_bands];
        let mut k = k0;
        while k < k1 {
            let n = (k1 - k).min(BIN_BLOCK);
            // k + n <= m < u32::MAX
            let (ka, kb) = (k as u32, (k + n) as u32);
            if let Some((b0, two)) = block_bands(positions, weights, k, n, factor, &mut bands) {
                // Every sample of the block goes to the same bands: as many additions
                // of one sample each, at once.
                for b in b0..=b0 + u32::from(two) {
                    add_run(&mut seq, &mut open, b, ka, kb);
                }
                k += n;
                continue;
            }
            for k in k..k + n {
                if weights.is_some_and(|wt| !positive(wt[k])) {
                    continue;
                }
                let Some((_, fy)) = fine_pos(positions, k, factor) else {
                    continue;
                };
                let Some((b0, two)) = bands.of(nearest(fy)) else {
                    continue;
                };
                let kk = k as u32; // k < m < u32::MAX
                for b in b0..=b0 + u32::from(two) {
                    add_run(&mut seq, &mut open, b, kk, kk + 1);
                }
            }
            k += n;
        }
        // Counting sort of the runs by band, stable: each band's runs stay in order.
        let mut starts = vec![0u32; n_bands + 1];
        for &(b, _) in &seq {
            starts[b as usize + 1] += 1;
        }
        for b in 0..n_bands {
            starts[b + 1] += starts[b];
        }
        let mut runs = vec![[0u32; 2]; seq.len()];
        let mut next = starts.clone();
        for &(b, run) in &seq {
            runs[next[b as usize] as usize] = run;
            next[b as usize] += 1;
        }
        ChunkRuns { starts, runs }
    };
    // One task per chunk (the samples' positions measure the work).
    let chunks = parallel::map_tasks(m.div_ceil(BIN_CHUNK), 8 * m, |c| Ok(one(c)))?;
    Ok(Bins { band_rows, chunks })
}

/// Samples per block of [`block_bands`].
const BIN_BLOCK: usize = 64;

/// Samples `k0..k1` added to band `b`'s runs: they extend its last run if that ends at
/// `k0`, else start a new one.
#[inline(always)]
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
fn add_run(seq: &mut Vec<(u32, [u32; 2])>, open: &mut [u32], b: u32, k0: u32, k1: u32) {
    let last = open[b as usize] as usize;
    match seq.get_mut(last) {
        Some((_, run)) if run[1] == k0 => run[1] = k1,
        _ => {
            open[b as usize] = seq.len() as u32;
            seq.push((b, [k0, k1]));
        }
    }
}

/// The bands of the samples `k..k + n` if they all go to the same ones (`n` is
/// [`BIN_BLOCK`], every sample usable, and their nearest fine rows in one range of
/// `bands`' answer), else `None` (then they are binned one by one). Straight-line
/// arithmetic over the block, which vectorises: the usual block, samples of one raw row,
/// costs no test per sample.
#[inline(always)]
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
fn block_bands(
    positions: &[f32],
    weights: Option<&[f32]>,
    k: usize,
    n: usize,
    factor: f32,
    bands: &mut BandOf,
) -> Option<(u32, bool)> {
    const B: usize = BIN_BLOCK;
    if n != B {
        return None;
    }
    let pos: &[f32; 2 * B] = positions.get(2 * k..2 * (k + B))?.try_into().ok()?;
    if let Some(wt) = weights {
        let wt: &[f32; B] = wt.get(k..k + B)?.try_into().ok()?;
        let usable = wt.iter().map(|&w| u32::from(positive(w))).sum::<u32>();
        if usable != B as u32 {
            return None;
        }
    }
    // Lane by lane over the interleaved (x, y): the fine positions as `fine_pos` forms
    // them, a sum of `0 * v` that is NaN iff one is not finite, and the odd lanes' (y)
    // least and greatest.
    let mut nan = [0f32; 8];
    let mut lo = [f32::INFINITY; 8];
    let mut hi = [f32::NEG_INFINITY; 8];
    for p in pos.chunks_exact(8) {
        for l in 0..8 {
            let v = (p[l] + 0.5) * factor - 0.5;
            nan[l] += 0.0 * v;
            lo[l] = if v < lo[l] { v } else { lo[l] };
            hi[l] = if v > hi[l] { v } else { hi[l] };
        }
    }
    if nan.iter().sum::<f32>() != 0.0 {
        return None;
    }
    let ylo = lo[1].min(lo[3]).min(lo[5]).min(lo[7]);
    let yhi = hi[1].max(hi[3]).max(hi[5]).max(hi[7]);
    // `nearest` is non-decreasing: the block's nearest rows are in `lo..=hi`.
    let (ylo, yhi) = (nearest(ylo), nearest(yhi));
    let answer = bands.of(ylo)?;
    (bands.lo <= ylo && yhi <= bands.hi).then_some(answer)
}

/// The bands that the kernel of a sample whose nearest fine row is `yc` touches:
/// `(b, two)`, band `b` and, if `two`, band `b + 1`; `None` if no row of the grid. The
/// last answer's range of `yc` is kept: samples in scan order mostly stay in it, and
/// then cost no division.
struct BandOf {
    r: i64,
    last_row: i64,
    band_rows: i64,
    /// `yc` in `lo..=hi` gives `answer`.
    lo: i64,
    hi: i64,
    answer: (u32, bool),
}

impl BandOf {
    fn new(radius: usize, fine_h: usize, band_rows: usize) -> Self {
        Self {
            r: radius as i64,
            last_row: fine_h as i64 - 1,
            band_rows: band_rows as i64,
            lo: 1,
            hi: 0,
            answer: (0, false),
        }
    }

    #[inline(always)]
    fn of(&mut self, yc: i64) -> Option<(u32, bool)> {
        if yc >= self.lo && yc <= self.hi {
            return Some(self.answer);
        }
        let (r, br) = (self.r, self.band_rows);
        let lo = (yc - r).max(0);
        let hi = (yc + r).min(self.last_row);
        if lo > hi {
            return None;
        }
        let (b0, b1) = (lo / br, hi / br);
        self.answer = (b0 as u32, b1 > b0);
        // The same bands for yc' with b0 br <= yc' - r, yc' + r < (b1 + 1) br (away
        // from the grid's edges, where the clamps above act) and, for one band,
        // yc' + r < (b0 + 1) br; for two, yc' + r >= b1 br and yc' - r < b1 br.
        let (mut l, mut h) = (b0 * br + r, (b1 + 1) * br - 1 - r);
        if b1 > b0 {
            l = l.max(b1 * br - r);
            h = h.min(b1 * br - 1 + r);
        }
        self.lo = l.max(r);
        self.hi = h.min(self.last_row - r);
        Some(self.answer)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// The runs of [`bin_samples`] formed one sample at a time, as documented.
    fn bin_naive(
        positions: &[f32],
        weights: Option<&[f32]>,
        radius: usize,
        factor: f32,
        fine_h: usize,
        band_rows: usize,
    ) -> Vec<(Vec<u32>, Vec<[u32; 2]>)> {
        let m = positions.len() / 2;
        let n_bands = fine_h.div_ceil(band_rows);
        (0..m.div_ceil(BIN_CHUNK))
            .map(|c| {
                let mut runs: Vec<Vec<[u32; 2]>> = vec![Vec::new(); n_bands];
                for k in c * BIN_CHUNK..((c + 1) * BIN_CHUNK).min(m) {
                    if weights.is_some_and(|wt| !positive(wt[k])) {
                        continue;
                    }
                    let Some((_, fy)) = fine_pos(positions, k, factor) else {
                        continue;
                    };
                    let yc = nearest(fy);
                    let r = radius as i64;
                    let (lo, hi) = ((yc - r).max(0), (yc + r).min(fine_h as i64 - 1));
                    if lo > hi {
                        continue;
                    }
                    let kk = k as u32;
                    for b in lo / band_rows as i64..=hi / band_rows as i64 {
                        let band = &mut runs[b as usize];
                        match band.last_mut() {
                            Some(run) if run[1] == kk => run[1] = kk + 1,
                            _ => band.push([kk, kk + 1]),
                        }
                    }
                }
                let mut starts = vec![0u32];
                for band in &runs {
                    starts.push(starts.last().unwrap() + band.len() as u32);
                }
                (starts, runs.concat())
            })
            .collect()
    }

    #[test]
    fn binning_by_blocks_equals_one_by_one() {
        let mut seed = 7u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        // Raw rows of 300 samples in scan order, slightly rotated, with jitter, over
        // more rows than the grid has (samples off it), past one chunk.
        let m = BIN_CHUNK + 10_000;
        let mut pos = Vec::with_capacity(2 * m);
        for k in 0..m {
            let (i, j) = ((k % 300) as f32, (k / 300) as f32);
            pos.push(0.5 * i + 0.01 * j + 0.2 * rnd());
            pos.push(-3.0 + 0.5 * j + 0.03 * i + 0.2 * rnd());
        }
        // Unusable and extreme samples, alone and in runs.
        for k in [5usize, 700, 701, 4000, 30_000] {
            pos[2 * k + k % 2] = f32::NAN;
        }
        pos[2 * 1000 + 1] = f32::INFINITY;
        pos[2 * 1200 + 1] = 1e30;
        pos[2 * 1300] = -1e38;
        pos[2 * 1400 + 1] = -3e9;
        let wts: Vec<f32> = (0..m)
            .map(|k| match k % 997 {
                0 => 0.0,
                1 => f32::NAN,
                _ => 0.5 + rnd(),
            })
            .collect();
        for (factor, radius, fine_h, band_rows) in [
            (2.0f32, 1usize, 250usize, 48usize),
            (2.0, 1, 250, 17),
            (1.0, 0, 100, 4),
            (3.0, 2, 400, 80),
        ] {
            for weights in [None, Some(&wts[..])] {
                let want = bin_naive(&pos, weights, radius, factor, fine_h, band_rows);
                let got = bin_samples(&pos, weights, m, factor, radius, fine_h, band_rows).unwrap();
                assert_eq!(got.chunks.len(), want.len());
                for (g, (starts, runs)) in got.chunks.iter().zip(&want) {
                    assert_eq!(&g.starts, starts, "{factor} {radius} {band_rows}");
                    assert_eq!(&g.runs, runs, "{factor} {radius} {band_rows}");
                }
            }
        }
    }
}
