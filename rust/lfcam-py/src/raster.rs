//! `rasterize`.

use lfcam_core::raster::{self as core, ProjectedMesh, Target};
use numpy::{PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use crate::arrays::{c_slice, new_array, typed};
use crate::errors::{guarded, input_error, internal_error, to_pyerr};

/// Z-buffered rasterisation of a projected triangle mesh (see lfcam-core's `raster`).
///
/// vertices: (M, 3) float32, C-contiguous: x (column, px), y (row, px), z (depth > 0).
/// colours: (M, C) float32, C-contiguous.
/// faces: (K, 3) int32, C-contiguous: vertex indices.
/// Returns (image, depth, mask): new arrays (H, W, C) float32 and (H, W) float32 (NaN
/// where nothing was drawn), and (H, W) uint8 (1 where something was drawn).
#[pyfunction]
pub fn rasterize<'py>(
    py: Python<'py>,
    vertices: &Bound<'py, PyAny>,
    colours: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    height: i64,
    width: i64,
) -> PyResult<Bound<'py, PyTuple>> {
    guarded(py, "rasterize", || {
        let side = |value: i64, arg: &str| {
            usize::try_from(value)
                .ok()
                .filter(|&v| v > 0)
                .ok_or_else(|| {
                    input_error(py, arg, format!("expected an integer >= 1, got {value}"))
                })
        };
        let (h, w) = (side(height, "height")?, side(width, "width")?);

        let v_ro = typed::<f32>(vertices, "vertices", "float32")?;
        if !matches!(v_ro.shape(), [_, 3]) {
            return Err(input_error(
                py,
                "vertices",
                format!("expected shape (M, 3), got {:?}", v_ro.shape()),
            ));
        }
        let (verts, _) = c_slice(&v_ro, "vertices")?.as_chunks::<3>();

        let c_ro = typed::<f32>(colours, "colours", "float32")?;
        let ch = match *c_ro.shape() {
            [m, c] if m == verts.len() && c > 0 => c,
            ref shape => {
                return Err(input_error(
                    py,
                    "colours",
                    format!(
                        "expected shape ({}, C) with C >= 1 (one row per vertex), got {shape:?}",
                        verts.len()
                    ),
                ));
            }
        };
        let cols = c_slice(&c_ro, "colours")?;

        let f_ro = typed::<i32>(faces, "faces", "int32")?;
        if !matches!(f_ro.shape(), [_, 3]) {
            return Err(input_error(
                py,
                "faces",
                format!("expected shape (K, 3), got {:?}", f_ro.shape()),
            ));
        }
        let (face_rows, _) = c_slice(&f_ro, "faces")?.as_chunks::<3>();

        let image = new_array::<f32>(py, &[h, w, ch])?;
        let depth = new_array::<f32>(py, &[h, w])?;
        let mask = new_array::<u8>(py, &[h, w])?;
        {
            let mut img_rw = readwrite(&image)?;
            let mut dep_rw = readwrite(&depth)?;
            let mut mask_rw = readwrite(&mask)?;
            let target = Target {
                image: slice_mut(&mut img_rw)?,
                depth: slice_mut(&mut dep_rw)?,
                mask: slice_mut(&mut mask_rw)?,
                height: h,
                width: w,
            };
            let mesh = ProjectedMesh {
                vertices: verts,
                colours: cols,
                channels: ch,
                faces: face_rows,
            };
            py.detach(|| lfcam_core::parallel::install(|| core::rasterize(&mesh, target)))
                .and_then(|inner| inner)
                .map_err(|e| to_pyerr(py, e))?;
        }
        PyTuple::new(py, [image.into_any(), depth.into_any(), mask.into_any()])
    })
}

/// A fresh output array borrowed for writing.
fn readwrite<'py, T: numpy::Element>(
    arr: &Bound<'py, PyArrayDyn<T>>,
) -> PyResult<numpy::PyReadwriteArrayDyn<'py, T>> {
    arr.try_readwrite()
        .map_err(|e| internal_error(arr.py(), "rasterize", format!("output borrow: {e}")))
}

/// The elements of a fresh (C-contiguous) output array.
fn slice_mut<'a, T: numpy::Element>(
    rw: &'a mut numpy::PyReadwriteArrayDyn<'_, T>,
) -> PyResult<&'a mut [T]> {
    let py = rw.py();
    rw.as_slice_mut()
        .map_err(|e| internal_error(py, "rasterize", format!("output slice: {e}")))
}
