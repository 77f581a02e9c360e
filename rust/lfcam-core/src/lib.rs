//! `lfcam-core`: the per-pixel kernels of lfcam, in pure Rust.
//!
//! Kernels take borrowed input views and a caller-owned output, check every size
//! first and return [`Result`]; they never panic on user data. Threading is decided in
//! one place, [`parallel`]. Nothing here knows about Python: the bindings live in the
//! `lfcam-py` crate.

// One audited exception, in `simd`: calling AVX2 code after checking the CPU.
#![deny(unsafe_code)]
// Kernels must not panic on user data: no unchecked indexing outside tests.
#![warn(clippy::indexing_slicing)]

pub mod crop;
pub mod error;
pub mod fill;
pub mod fit;
pub mod image;
pub mod parallel;
pub mod raster;
pub mod rectify;
pub mod remap;
pub mod simd;
pub mod stats;
pub mod superres;
pub mod sweep;
pub mod triangulate;

pub use crate::crop::crop_lenslets;
pub use crate::error::{Error, Result};
pub use crate::fill::{FillParams, weighted_median_fill};
pub use crate::image::ImageView;
pub use crate::raster::{ProjectedMesh, Target, rasterize};
pub use crate::rectify::{Interp, ViewMaps, rectify};
pub use crate::remap::remap_bilinear;
pub use crate::stats::nan_median;
pub use crate::sweep::{SweepParams, plane_sweep};
pub use crate::triangulate::triangulate;
