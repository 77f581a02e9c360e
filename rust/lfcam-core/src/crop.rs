//! Cutting the lenslet sub-images ("views") out of a raw frame.

use crate::error::{Error, Result};
use crate::image::ImageView;
use crate::parallel;

/// A crop rectangle that passed validation, in `usize`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Rect {
    x0: usize,
    y0: usize,
}

/// Checks `rects` against a `width x height` frame and returns the common view size
/// `(w, h)` and the rectangles' origins.
fn validate_rects(
    rects: &[[i64; 4]],
    width: usize,
    height: usize,
) -> Result<(usize, usize, Vec<Rect>)> {
    let Some(&[_, _, w0, h0]) = rects.first() else {
        return Err(Error::invalid_argument(
            "rects",
            "at least one rectangle is needed, got none",
        ));
    };
    let frame_w = i64::try_from(width).unwrap_or(i64::MAX);
    let frame_h = i64::try_from(height).unwrap_or(i64::MAX);
    let mut origins = Vec::with_capacity(rects.len());
    for (index, &[x0, y0, w, h]) in rects.iter().enumerate() {
        if w < 1 || h < 1 {
            return Err(Error::invalid_item(
                "rects",
                index,
                format!(
                    "rectangle (x0, y0, w, h) = ({x0}, {y0}, {w}, {h}) must have a width and \
                     height of at least 1"
                ),
            ));
        }
        let inside = x0 >= 0
            && y0 >= 0
            && x0.checked_add(w).is_some_and(|x1| x1 <= frame_w)
            && y0.checked_add(h).is_some_and(|y1| y1 <= frame_h);
        if !inside {
            return Err(Error::invalid_item(
                "rects",
                index,
                format!(
                    "rectangle (x0, y0, w, h) = ({x0}, {y0}, {w}, {h}) lies outside the \
                     {width}x{height} frame"
                ),
            ));
        }
        if (w, h) != (w0, h0) {
            return Err(Error::invalid_item(
                "rects",
                index,
                format!(
                    "rectangle size (w, h) = ({w}, {h}) differs from that of rects[0], \
                     ({w0}, {h0}); all rectangles must have one size"
                ),
            ));
        }
        // Inside the frame, so all four are in 0..=usize::MAX.
        let (Ok(x0), Ok(y0)) = (usize::try_from(x0), usize::try_from(y0)) else {
            return Err(Error::invalid_item(
                "rects",
                index,
                "origin does not fit in usize",
            ));
        };
        origins.push(Rect { x0, y0 });
    }
    let (Ok(w), Ok(h)) = (usize::try_from(w0), usize::try_from(h0)) else {
        return Err(Error::invalid_item(
            "rects",
            0,
            "size does not fit in usize",
        ));
    };
    Ok((w, h, origins))
}

/// The output shape `(N, h, w, C)` of [`crop_lenslets`] for `src` and `rects`, after
/// validating both exactly as [`crop_lenslets`] does. Use it to allocate the output.
///
/// # Errors
/// As [`crop_lenslets`], except for the check of `out`; also
/// [`Error::InvalidArgument`] (`"rects"`) if the output's element count overflows.
pub fn crop_output_shape<T>(src: &ImageView<'_, T>, rects: &[[i64; 4]]) -> Result<[usize; 4]> {
    let (w, h, _) = validate_rects(rects, src.width(), src.height())?;
    let shape = [rects.len(), h, w, src.channels()];
    shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| {
            Error::invalid_argument(
                "rects",
                format!("the output shape {shape:?} has too many elements"),
            )
        })?;
    Ok(shape)
}

/// Copies the `N` rectangles `rects` (each `(x0, y0, w, h)` in raw pixels, all of one
/// size) out of `src` into `out`, laid out `(N, h, w, C)` C-contiguous: view `i`, row
/// `r`, column `c`, channel `k` is `out[((i * h + r) * w + c) * C + k]` and equals
/// `src` at row `y0 + r`, column `x0 + c`, channel `k`.
///
/// Every input is checked before anything is written. Runs in lfcam's pool over
/// (view, row) tasks; small outputs run serially (see [`parallel`]).
///
/// # Errors
/// - [`Error::InvalidArgument`] `"rects"` if `rects` is empty;
/// - [`Error::InvalidItem`] `"rects"` naming the first rectangle that has a width or
///   height below 1, lies (partly) outside the frame, or differs in size from
///   `rects[0]`;
/// - [`Error::InvalidArgument`] `"out"` if `out.len() != N * h * w * C`.
pub fn crop_lenslets<T: Copy + Send + Sync>(
    src: ImageView<'_, T>,
    rects: &[[i64; 4]],
    out: &mut [T],
) -> Result<()> {
    let (w, h, origins) = validate_rects(rects, src.width(), src.height())?;
    let c = src.channels();
    let expected = [origins.len(), h, w, c]
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d));
    if expected != Some(out.len()) {
        return Err(Error::invalid_argument(
            "out",
            format!(
                "has {} elements, but the output (N, h, w, C) = ({}, {h}, {w}, {c}) needs {}",
                out.len(),
                origins.len(),
                expected.map_or_else(|| "more than usize::MAX".to_owned(), |n| n.to_string()),
            ),
        ));
    }
    let row_len = w * c;
    parallel::for_each_row_chunk(out, row_len, |first_row, rows| {
        for (k, out_row) in rows.chunks_exact_mut(row_len).enumerate() {
            let g = first_row + k;
            let (view, r) = (g / h, g % h);
            let src_row = origins
                .get(view)
                .and_then(|o| src.row_span(o.y0 + r, o.x0, w))
                .filter(|s| s.len() == out_row.len())
                .ok_or_else(|| {
                    Error::internal("crop_lenslets", format!("row {r} of view {view}"))
                })?;
            out_row.copy_from_slice(src_row);
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(h: usize, w: usize, c: usize) -> Vec<u16> {
        (0..h * w * c).map(|v| (v % 65_521) as u16).collect()
    }

    #[test]
    fn crops_a_grid_of_rgb_views() {
        let (hh, ww, c) = (6, 8, 3);
        let data = frame(hh, ww, c);
        let src = ImageView::new(&data, hh, ww, c).unwrap();
        let rects = [[0, 0, 4, 3], [4, 0, 4, 3], [0, 3, 4, 3], [4, 3, 4, 3]];
        assert_eq!(crop_output_shape(&src, &rects).unwrap(), [4, 3, 4, 3]);
        let mut out = vec![0u16; 4 * 3 * 4 * 3];
        crop_lenslets(src, &rects, &mut out).unwrap();
        for (i, rect) in rects.iter().enumerate() {
            let [x0, y0, w, h] = rect.map(|v| v as usize);
            for r in 0..h {
                for col in 0..w {
                    for k in 0..c {
                        let got = out[((i * h + r) * w + col) * c + k];
                        let want = data[((y0 + r) * ww + x0 + col) * c + k];
                        assert_eq!(got, want);
                    }
                }
            }
        }
    }

    #[test]
    fn whole_frame_and_single_pixel() {
        let data = frame(5, 7, 1);
        let src = ImageView::new(&data, 5, 7, 1).unwrap();
        let mut out = vec![0u16; 35];
        crop_lenslets(src, &[[0, 0, 7, 5]], &mut out).unwrap();
        assert_eq!(out, data);
        let mut one = [0u16; 1];
        crop_lenslets(src, &[[6, 4, 1, 1]], &mut one).unwrap();
        assert_eq!(one[0], data[34]);
    }

    #[test]
    fn outside_rect_names_index_and_frame() {
        let data = vec![0u8; 1920 * 1080];
        let src = ImageView::new(&data, 1080, 1920, 1).unwrap();
        let rects = [[0, 0, 100, 100], [1900, 10, 100, 100]];
        let err = crop_lenslets(src, &rects, &mut vec![0u8; 20_000]).unwrap_err();
        assert_eq!(
            err,
            Error::invalid_item(
                "rects",
                1,
                "rectangle (x0, y0, w, h) = (1900, 10, 100, 100) lies outside the 1920x1080 frame"
            )
        );
    }
}
