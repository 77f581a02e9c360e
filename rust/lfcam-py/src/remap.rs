//! `remap_bilinear`.

use lfcam_core::remap;
use numpy::PyUntypedArrayMethods;
use pyo3::prelude::*;

use crate::arrays::{fill, image_view, output_array, typed};
use crate::errors::{guarded, input_error};

/// Samples an image at the positions of a map (exact bilinear, NaN for no data).
///
/// src: (H, W) or (H, W, C) float32, C-contiguous, C <= 4.
/// map: (H', W', 2) float32, C-contiguous, positions (x, y) in src.
/// out: None, or a float32 C-contiguous array of the output's shape to write into.
/// Returns a new (H', W') or (H', W', C) float32 array, or `out`.
#[pyfunction]
#[pyo3(signature = (src, map, out=None))]
pub fn remap_bilinear<'py>(
    py: Python<'py>,
    src: &Bound<'py, PyAny>,
    map: &Bound<'py, PyAny>,
    out: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(py, "remap_bilinear", || {
        let src_ro = typed::<f32>(src, "src", "float32")?;
        let map_ro = typed::<f32>(map, "map", "float32")?;
        if map_ro.ndim() != 3 || map_ro.shape().get(2) != Some(&2) {
            return Err(input_error(
                py,
                "map",
                format!(
                    "expected shape (H', W', 2) of positions (x, y), got {:?}",
                    map_ro.shape()
                ),
            ));
        }
        let src_v = image_view(&src_ro, "src")?;
        let map_v = image_view(&map_ro, "map")?;
        let mut shape = vec![map_v.height(), map_v.width()];
        if src_ro.ndim() == 3 {
            shape.push(src_v.channels());
        }
        let out = output_array::<f32>(py, out, &shape, "float32")?;
        fill(&out, "remap_bilinear", |slice| {
            remap::remap_bilinear(src_v, map_v, slice)
        })?;
        Ok(out.into_any())
    })
}
