//! `simd_info`: which SIMD builds of the kernels run, over `lfcam_core::simd`.

use lfcam_core::simd;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::guarded;

/// Which SIMD builds of the kernels this process runs: `setting` (`LFCAM_SIMD` in
/// effect: auto, avx2 or portable), `cpu` (the widest level the CPU has), `level` (the
/// widest the kernels run), then each kernel family with SIMD builds and the build it
/// runs (portable, avx2 or avx512).
#[pyfunction]
pub fn simd_info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    guarded(py, "simd_info", || {
        let info = simd::simd_info();
        let dict = PyDict::new(py);
        dict.set_item("setting", info.setting)?;
        dict.set_item("cpu", info.cpu.name())?;
        dict.set_item("level", info.level.name())?;
        for (kernel, level) in info.kernels {
            dict.set_item(kernel, level.name())?;
        }
        Ok(dict)
    })
}
