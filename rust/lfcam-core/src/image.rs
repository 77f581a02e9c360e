//! Borrowed image views.

use crate::error::{Error, Result};

/// A borrowed, C-contiguous `(H, W, C)` image over `&[T]`: row `y` is
/// `data[y * W * C .. (y + 1) * W * C]`, pixel `(y, x)` channel `c` is
/// `data[(y * W + x) * C + c]`. A mono image has `C == 1`.
///
/// The constructor checks that no dimension is zero and that `data.len() == H * W * C`,
/// so every accessor can be written without further checks.
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a, T> {
    data: &'a [T],
    height: usize,
    width: usize,
    channels: usize,
}

impl<'a, T> ImageView<'a, T> {
    /// Wraps `data` as an image of `height` rows, `width` columns and `channels`
    /// interleaved channels.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] (argument `"image"`) if a dimension is zero, if
    /// `height * width * channels` overflows, or if it differs from `data.len()`.
    pub fn new(data: &'a [T], height: usize, width: usize, channels: usize) -> Result<Self> {
        if height == 0 || width == 0 || channels == 0 {
            return Err(Error::invalid_argument(
                "image",
                format!(
                    "every dimension must be at least 1, got (H, W, C) = ({height}, {width}, {channels})"
                ),
            ));
        }
        let expected = height
            .checked_mul(width)
            .and_then(|n| n.checked_mul(channels))
            .ok_or_else(|| {
                Error::invalid_argument(
                    "image",
                    format!("(H, W, C) = ({height}, {width}, {channels}) is too large"),
                )
            })?;
        if data.len() != expected {
            return Err(Error::invalid_argument(
                "image",
                format!(
                    "has {} elements, but (H, W, C) = ({height}, {width}, {channels}) needs {expected}",
                    data.len()
                ),
            ));
        }
        Ok(Self {
            data,
            height,
            width,
            channels,
        })
    }

    /// Number of rows `H`.
    #[inline]
    pub fn height(&self) -> usize {
        self.height
    }

    /// Number of columns `W`.
    #[inline]
    pub fn width(&self) -> usize {
        self.width
    }

    /// Number of interleaved channels `C`.
    #[inline]
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Elements per row, `W * C`.
    #[inline]
    pub fn row_len(&self) -> usize {
        self.width * self.channels
    }

    /// The whole image, row-major.
    #[inline]
    pub fn as_slice(&self) -> &'a [T] {
        self.data
    }

    /// Row `y` (`W * C` elements), or `None` if `y >= H`.
    #[inline]
    pub fn row(&self, y: usize) -> Option<&'a [T]> {
        let len = self.row_len();
        let start = y.checked_mul(len)?;
        self.data.get(start..start.checked_add(len)?)
    }

    /// Columns `x0 .. x0 + w` of row `y` (`w * C` elements), or `None` if that span is
    /// not inside the image.
    #[inline]
    pub fn row_span(&self, y: usize, x0: usize, w: usize) -> Option<&'a [T]> {
        let x1 = x0.checked_add(w)?;
        if x1 > self.width {
            return None;
        }
        self.row(y)?.get(x0 * self.channels..x1 * self.channels)
    }

    /// Iterator over the rows, top to bottom.
    #[inline]
    pub fn rows(&self) -> std::slice::ChunksExact<'a, T> {
        self.data.chunks_exact(self.row_len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_and_spans() {
        let data: Vec<u16> = (0..24).collect();
        let img = ImageView::new(&data, 2, 4, 3).unwrap();
        assert_eq!((img.height(), img.width(), img.channels()), (2, 4, 3));
        assert_eq!(img.row_len(), 12);
        assert_eq!(img.row(1).unwrap(), &data[12..24]);
        assert!(img.row(2).is_none());
        assert!(img.row(usize::MAX).is_none());
        assert_eq!(img.row_span(1, 1, 2).unwrap(), &data[15..21]);
        assert!(img.row_span(0, 3, 2).is_none());
        assert!(img.row_span(0, usize::MAX, 2).is_none());
        assert_eq!(img.rows().count(), 2);
    }

    #[test]
    fn bad_sizes_are_invalid_arguments() {
        let data = [0u8; 12];
        for (h, w, c) in [(0, 4, 3), (1, 0, 3), (1, 4, 0), (2, 4, 3), (1, 1, 1)] {
            let err = ImageView::new(&data, h, w, c).unwrap_err();
            assert!(
                matches!(err, Error::InvalidArgument { ref arg, .. } if arg == "image"),
                "{err:?}"
            );
        }
        let err = ImageView::new(&data, usize::MAX, usize::MAX, 2).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { .. }));
        assert!(ImageView::new(&data, 1, 4, 3).is_ok());
    }
}
