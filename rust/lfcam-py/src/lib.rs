//! `lfcam._lfcam`: the Python extension module over `lfcam-core`.
//!
//! Thin by design: each `#[pyfunction]` borrows its numpy inputs ([`arrays`]), allocates
//! its output as a numpy array, releases the GIL, runs one core kernel inside lfcam's
//! thread pool and maps errors and panics to the `lfcam.errors` family ([`errors`]).
//! Kernels live in `lfcam-core`.

mod arrays;
mod crop;
mod errors;
mod fill;
mod fit;
mod info;
mod raster;
mod rectify;
mod remap;
mod stats;
mod superres;
mod sweep;
mod threads;
mod triangulate;

use pyo3::prelude::*;

/// Rust core of lfcam. Use the public functions of the `lfcam` package instead.
#[pymodule(name = "_lfcam")]
mod lfcam_ext {
    use pyo3::prelude::*;

    #[pymodule_export]
    use crate::crop::crop_lenslets;
    #[pymodule_export]
    use crate::fill::weighted_median_fill;
    #[pymodule_export]
    use crate::fit::fit_board_tilts;
    #[pymodule_export]
    use crate::info::simd_info;
    #[pymodule_export]
    use crate::raster::rasterize;
    #[pymodule_export]
    use crate::rectify::{RectifyPlan, rectify};
    #[pymodule_export]
    use crate::remap::remap_bilinear;
    #[pymodule_export]
    use crate::stats::nan_median;
    #[pymodule_export]
    use crate::superres::{
        btv_deblur, data_weights, invert_maps, place_samples, shift_and_add, shift_and_add_mean,
    };
    #[pymodule_export]
    use crate::sweep::plane_sweep;
    #[pymodule_export]
    use crate::threads::{get_num_threads, set_num_threads};
    #[pymodule_export]
    use crate::triangulate::triangulate;

    #[pymodule_init]
    fn init(m: &Bound<'_, PyModule>) -> PyResult<()> {
        // The test hooks are attributes only, not in `__all__`: the module exports the
        // same names with and without them, as its stub declares.
        #[cfg(feature = "test-hooks")]
        {
            use crate::errors::{_panic_for_test, _raise_core_error};
            m.setattr("_raise_core_error", wrap_pyfunction!(_raise_core_error, m)?)?;
            m.setattr("_panic_for_test", wrap_pyfunction!(_panic_for_test, m)?)?;
        }
        m.add("__version__", env!("CARGO_PKG_VERSION"))
    }
}
