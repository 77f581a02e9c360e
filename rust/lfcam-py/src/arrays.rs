//! Borrowing numpy arrays as core views, with errors that name the argument.

use lfcam_core::ImageView;
use numpy::{
    Element, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn,
    PyReadwriteArrayDyn, PyUntypedArray, PyUntypedArrayMethods, dtype,
};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyTuple;

use crate::errors::{input_error, internal_error, to_pyerr};

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

/// `obj` borrowed read-only as an array of dtype `T` (`name`, as numpy spells it, for
/// the message), or `InputError` naming `arg`.
pub fn typed<'py, T: Element>(
    obj: &Bound<'py, PyAny>,
    arg: &str,
    name: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let py = obj.py();
    let arr = as_untyped(obj, arg)?;
    if !arr.dtype().is_equiv_to(&dtype::<T>(py)) {
        return Err(input_error(
            py,
            arg,
            format!("expected dtype {name}, got {}", dtype_name(arr)),
        ));
    }
    readonly::<T>(arr, arg)
}

/// The elements of a C-contiguous array, or `InputError` naming `arg`.
pub fn c_slice<'a, T: Element>(arr: &'a PyReadonlyArrayDyn<'_, T>, arg: &str) -> PyResult<&'a [T]> {
    let py = arr.py();
    if !arr.is_c_contiguous() {
        return Err(input_error(
            py,
            arg,
            "must be C-contiguous (use numpy.ascontiguousarray)",
        ));
    }
    arr.as_slice()
        .map_err(|_| input_error(py, arg, "must be C-contiguous and aligned"))
}

/// `obj` as `(N, 4)` rows `(x0, y0, w, h)`, copied out of an int64 C-contiguous array.
pub fn rect_rows(obj: &Bound<'_, PyAny>, arg: &str) -> PyResult<Vec<[i64; 4]>> {
    let py = obj.py();
    let ro = typed::<i64>(obj, arg, "int64")?;
    let shape = ro.shape();
    if !matches!(shape, [_, 4]) {
        return Err(input_error(
            py,
            arg,
            format!("expected shape (N, 4) of rows (x0, y0, w, h), got {shape:?}"),
        ));
    }
    let (rows, _) = c_slice(&ro, arg)?.as_chunks::<4>();
    Ok(rows.to_vec())
}

/// `numpy.empty`, imported once.
fn numpy_empty(py: Python<'_>) -> PyResult<&Bound<'_, PyAny>> {
    static EMPTY: PyOnceLock<Py<PyAny>> = PyOnceLock::new();
    EMPTY.import(py, "numpy", "empty")
}

/// A new C-contiguous array of `shape` and dtype `T`, from `numpy.empty`.
///
/// Allocated by numpy rather than as a Rust `Vec` moved out with `into_pyarray`: numpy
/// madvises large allocations for transparent huge pages, which makes the first-touch
/// page faults (the dominant cost of filling a fresh output of tens of MB) several
/// times cheaper; and `empty`, unlike `zeros` (calloc), does not zero memory the
/// allocator reuses. Measured with benchmarks/run.py (crop_lenslets, full size, 2
/// threads): ~9 ms, against 24 ms for a `Vec`. Callers must write every element (the
/// kernels check `out.len()` and cover every row); on error the array is dropped.
/// Called through Python, not `PyArray::new`, so that a failed allocation raises
/// numpy's `MemoryError` instead of panicking (and no `unsafe` is needed).
pub fn new_array<'py, T: Element>(
    py: Python<'py>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    Ok(numpy_empty(py)?
        .call1((PyTuple::new(py, shape)?, dtype::<T>(py)))?
        .cast_into::<PyArrayDyn<T>>()?)
}

/// The array a kernel writes: the caller's `out` after checking its dtype (`name`, as
/// numpy spells it), shape and contiguity, or a fresh one from [`new_array`].
pub fn output_array<'py, T: Element>(
    py: Python<'py>,
    out: Option<&Bound<'py, PyAny>>,
    shape: &[usize],
    name: &str,
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    output_arg(py, out, shape, name, "out")
}

/// [`output_array`] for the output argument `arg` (named in errors: `"out[1]"`, ...).
pub fn output_arg<'py, T: Element>(
    py: Python<'py>,
    out: Option<&Bound<'py, PyAny>>,
    shape: &[usize],
    name: &str,
    arg: &str,
) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let Some(out) = out else {
        return new_array::<T>(py, shape);
    };
    let arr = as_untyped(out, arg)?;
    if !arr.dtype().is_equiv_to(&dtype::<T>(py)) {
        return Err(input_error(
            py,
            arg,
            format!("expected dtype {name}, got {}", dtype_name(arr)),
        ));
    }
    if arr.shape() != shape {
        return Err(input_error(
            py,
            arg,
            format!("expected shape {shape:?}, got {:?}", arr.shape()),
        ));
    }
    if !arr.is_c_contiguous() {
        return Err(input_error(py, arg, "must be C-contiguous"));
    }
    Ok(arr.cast::<PyArrayDyn<T>>()?.clone())
}

/// `out` (from [`output_arg`]) borrowed for writing. A fresh array is always writeable;
/// a caller's may be read-only or share memory with an input (which is borrowed
/// read-only meanwhile) or another output: an error naming `arg`.
pub fn writable<'py, T: Element>(
    out: &Bound<'py, PyArrayDyn<T>>,
    arg: &str,
) -> PyResult<PyReadwriteArrayDyn<'py, T>> {
    out.try_readwrite().map_err(|e| {
        input_error(
            out.py(),
            arg,
            format!(
                "cannot be written ({e}): is it read-only, or does it share memory with an \
                 input or another output?"
            ),
        )
    })
}

/// Runs `kernel` on the elements of `out` (from [`output_array`]) with the GIL
/// released, inside lfcam's pool; core errors become exceptions.
pub fn fill<T, F>(out: &Bound<'_, PyArrayDyn<T>>, function: &str, kernel: F) -> PyResult<()>
where
    T: Element + Send,
    F: FnOnce(&mut [T]) -> lfcam_core::Result<()> + Send,
{
    let py = out.py();
    let mut rw = writable(out, "out")?;
    let slice = rw
        .as_slice_mut()
        .map_err(|e| internal_error(py, function, format!("output slice: {e}")))?;
    py.detach(|| lfcam_core::parallel::install(|| kernel(slice)))
        .and_then(|inner| inner)
        .map_err(|e| to_pyerr(py, e))
}
