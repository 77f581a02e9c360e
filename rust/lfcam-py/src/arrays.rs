//! Borrowing numpy arrays as core views, with errors that name the argument.

use lfcam_core::ImageView;
use numpy::{
    Element, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::errors::{input_error, to_pyerr};

/// `obj` as a numpy array, or `InputError` naming `arg`.
pub fn as_untyped<'a, 'py>(
    obj: &'a Bound<'py, PyAny>,
    arg: &str,
) -> PyResult<&'a Bound<'py, PyUntypedArray>> {
    obj.cast::<PyUntypedArray>().map_err(|_| {
        let type_name = obj
            .get_type()
            .name()
            .map_or_else(|_| "?".to_owned(), |n| n.to_string());
        input_error(
            obj.py(),
            arg,
            format!("expected a numpy.ndarray, got {type_name}"),
        )
    })
}

/// The dtype of `arr` as numpy prints it (`uint8`, `>u2`, ...).
pub fn dtype_name(arr: &Bound<'_, PyUntypedArray>) -> String {
    arr.dtype()
        .str()
        .map_or_else(|_| "?".to_owned(), |s| s.to_string())
}

/// Borrows `arr` (whose dtype the caller has checked is `T`) read-only.
pub fn readonly<'py, T: Element>(
    arr: &Bound<'py, PyUntypedArray>,
    arg: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let py = arr.py();
    let typed = arr
        .cast::<PyArrayDyn<T>>()
        .map_err(|_| input_error(py, arg, format!("unexpected dtype {}", dtype_name(arr))))?;
    typed
        .try_readonly()
        .map_err(|e| input_error(py, arg, format!("cannot be borrowed: {e}")))
}

/// A 2-D `(H, W)` or 3-D `(H, W, C)` C-contiguous, non-empty array as an
/// [`ImageView`] (a 2-D array has `C == 1`).
pub fn image_view<'a, T: Element>(
    arr: &'a PyReadonlyArrayDyn<'_, T>,
    arg: &str,
) -> PyResult<ImageView<'a, T>> {
    let py = arr.py();
    let shape = arr.shape();
    let (h, w, c) = match *shape {
        [h, w] => (h, w, 1),
        [h, w, c] => (h, w, c),
        _ => {
            return Err(input_error(
                py,
                arg,
                format!(
                    "expected a 2-D (H, W) or 3-D (H, W, C) image, got {} dimensions, shape {shape:?}",
                    shape.len()
                ),
            ));
        }
    };
    if h == 0 || w == 0 || c == 0 {
        return Err(input_error(
            py,
            arg,
            format!("image is empty, shape {shape:?}"),
        ));
    }
    if !arr.is_c_contiguous() {
        // `as_slice` alone would also accept a Fortran-ordered array.
        return Err(input_error(
            py,
            arg,
            "must be C-contiguous (use numpy.ascontiguousarray)",
        ));
    }
    let data = arr
        .as_slice()
        .map_err(|_| input_error(py, arg, "must be C-contiguous and aligned"))?;
    ImageView::new(data, h, w, c).map_err(|e| to_pyerr(py, e))
}
