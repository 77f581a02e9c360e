//! Robust statistics over a stack of images or maps (e.g. the same calibration map
//! measured on several captures).

use crate::error::{Error, Result};
use crate::parallel;

/// Below this many values per element, sorting them is faster than selecting.
const SORT_BELOW: usize = 32;

/// The median of `values` (no NaN among them) as numpy computes it: the middle value,
/// or for an even count the float32 mean `(lo + hi) / 2` of the two middle ones. NaN
/// for no values. Reorders `values`.
fn median_of(values: &mut [f32]) -> f32 {
    let n = values.len();
    let half = n / 2;
    let (hi, lo) = if n < SORT_BELOW {
        values.sort_unstable_by(f32::total_cmp);
        let hi = values.get(half).copied();
        let lo = half.checked_sub(1).and_then(|i| values.get(i)).copied();
        (hi, lo)
    } else {
        let (left, hi, _) = values.select_nth_unstable_by(half, f32::total_cmp);
        let lo = left.iter().copied().max_by(f32::total_cmp);
        (Some(*hi), lo)
    };
    match (hi, lo) {
        (Some(hi), Some(lo)) if n.is_multiple_of(2) => (lo + hi) / 2.0,
        (Some(hi), _) => hi,
        (None, _) => f32::NAN,
    }
}

/// Per-element median over the `k` planes of `stack`, ignoring NaN, and the number of
/// values it was taken over.
///
/// `stack` holds `k` planes of `m = median.len()` values each, plane after plane
/// (a C-contiguous `(K, ...)` array): element `e` has the values `stack[i * m + e]` for
/// `i in 0..k`. `median[e]` is their median ignoring NaN, equal to `numpy.nanmedian`
/// (for an even count, the float32 mean of the two middle values), or NaN if all are
/// NaN; `count[e]` is how many are not NaN. Infinities are values like any other, as in
/// numpy. Runs in lfcam's pool.
///
/// # Errors
/// - [`Error::InvalidArgument`] `"stack"` if `k == 0` or `stack.len() != k * m`;
/// - [`Error::InvalidArgument`] `"count"` if `count.len() != m`, or if `k` does not fit
///   in the count type `N`.
pub fn nan_median<N>(stack: &[f32], k: usize, median: &mut [f32], count: &mut [N]) -> Result<()>
where
    N: Copy + Send + Sync + TryFrom<usize>,
{
    if k == 0 {
        return Err(Error::invalid_argument(
            "stack",
            "needs at least one value per element (K >= 1), got K = 0",
        ));
    }
    if N::try_from(k).is_err() {
        return Err(Error::invalid_argument(
            "count",
            format!("K = {k} values per element do not fit in the count's integer type"),
        ));
    }
    let m = median.len();
    if count.len() != m {
        return Err(Error::invalid_argument(
            "count",
            format!("has {} elements, the median {m}", count.len()),
        ));
    }
    if k.checked_mul(m) != Some(stack.len()) {
        return Err(Error::invalid_argument(
            "stack",
            format!(
                "has {} elements, but K = {k} planes of {m} need {}",
                stack.len(),
                k.checked_mul(m)
                    .map_or_else(|| "more than usize::MAX".to_owned(), |n| n.to_string())
            ),
        ));
    }
    if m == 0 {
        return Ok(());
    }
    let planes: Vec<&[f32]> = stack.chunks_exact(m).collect();
    parallel::for_each_row_chunk_pair(median, count, 1, 1, |first, med, cnt| {
        let len = med.len();
        // This task's part of every plane.
        let parts = planes
            .iter()
            .map(|p| p.get(first..first + len))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| Error::internal("nan_median", "plane too short"))?;
        let mut values = Vec::with_capacity(k);
        for (e, (mo, co)) in med.iter_mut().zip(cnt.iter_mut()).enumerate() {
            values.clear();
            values.extend(
                parts
                    .iter()
                    .filter_map(|p| p.get(e).copied())
                    .filter(|v| !v.is_nan()),
            );
            *mo = median_of(&mut values);
            *co = N::try_from(values.len())
                .map_err(|_| Error::internal("nan_median", "count overflow"))?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_of_small_sets() {
        assert!(median_of(&mut []).is_nan());
        assert_eq!(median_of(&mut [3.0]), 3.0);
        assert_eq!(median_of(&mut [3.0, 1.0]), 2.0);
        assert_eq!(median_of(&mut [5.0, 1.0, 3.0]), 3.0);
        assert_eq!(median_of(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median_of(&mut [f32::INFINITY, 1.0]), f32::INFINITY);
        let mut many: Vec<f32> = (0..101).rev().map(|v| v as f32).collect();
        assert_eq!(median_of(&mut many), 50.0);
        let mut even: Vec<f32> = (0..100).map(|v| v as f32).collect();
        assert_eq!(median_of(&mut even), 49.5);
    }

    #[test]
    fn stack_of_three_planes() {
        let nan = f32::NAN;
        let stack = [1.0, nan, nan, 4.0, 3.0, 3.0, nan, nan, 2.0, nan, nan, 6.0];
        let mut med = [0.0f32; 4];
        let mut cnt = [0u8; 4];
        nan_median(&stack, 3, &mut med, &mut cnt).unwrap();
        assert_eq!(med[0], 2.0);
        assert_eq!(med[1], 3.0);
        assert!(med[2].is_nan());
        assert_eq!(med[3], 5.0);
        assert_eq!(cnt, [3, 1, 0, 2]);
    }

    #[test]
    fn bad_sizes() {
        let mut med = [0.0f32; 2];
        let mut cnt = [0u8; 2];
        assert!(nan_median(&[0.0; 4], 0, &mut med, &mut cnt).is_err());
        assert!(nan_median(&[0.0; 5], 2, &mut med, &mut cnt).is_err());
        assert!(nan_median(&[0.0; 4], 2, &mut med, &mut [0u8; 3]).is_err());
        let big = vec![0.0f32; 256 * 2];
        let err = nan_median(&big, 256, &mut med, &mut cnt).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "count"));
        assert!(nan_median(&big, 256, &mut med, &mut [0u16; 2]).is_ok());
    }
}
