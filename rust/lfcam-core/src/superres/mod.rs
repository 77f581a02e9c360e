//! Super-resolution kernels (docs/design.md, "Super-resolution"): warp-map inversion, placement of raw
//! samples in the reference view's rectified frame, robust shift-and-add onto an
//! r-times finer grid, and bilateral-TV deblurring (Farsiu, Robinson, Elad, Milanfar
//! 2004, "Fast and robust multiframe super resolution").
//!
//! # Conventions
//! Positions follow OpenCV: `(x, y)`, `x` the column, pixel centres at integers. A
//! rectified position `x` lands on the `r`-times finer grid at `X = (x + 0.5) r - 0.5`
//! (docs/design.md, "Pixel centres": fine pixel `U` sits at rectified `(U + 0.5) / r - 0.5`).
//!
//! # Indexing
//! Every function checks all sizes up front; the inner loops then index slices whose
//! lengths those checks guarantee, with explicit bounds tests on every computed index.
//! The functions that index say so, one by one (`#[allow(clippy::indexing_slicing)]`).
//!
//! # Modules
//! One algorithm each, in the order the data flows: `invert` (warp maps inverted: raw
//! pixel -> rectified position in its view), `place` (samples moved into the reference
//! view's frame along the parallax), `splat` (robust shift-and-add onto the fine grid)
//! and `btv` (bilateral-TV deblurring of the fused image).

use crate::error::{Error, Result};

mod btv;
mod invert;
mod place;
mod splat;

pub use btv::{BtvParams, btv_deblur, data_weights};
pub use invert::{invert_map, invert_maps};
pub use place::{PlaceParams, place_samples};
pub use splat::{SplatParams, shift_and_add, shift_and_add_mean};

/// Largest super-resolution factor (and channel count) the kernels accept.
pub const MAX_FACTOR: f32 = 16.0;
/// Largest number of interleaved channels.
pub const MAX_CHANNELS: usize = 4;
/// Largest splat kernel radius, fine px.
pub const MAX_RADIUS: usize = 16;

/// `v > 0` (false for NaN): written as a function so that `!positive(v)` reads as
/// "not a usable positive number".
#[inline(always)]
fn positive(v: f32) -> bool {
    v > 0.0
}

fn check_len(arg: &str, got: usize, want: usize, what: &str) -> Result<()> {
    if got == want {
        Ok(())
    } else {
        Err(Error::invalid_argument(
            arg,
            format!("has {got} elements, {what} needs {want}"),
        ))
    }
}

fn mul(arg: &str, dims: &[usize]) -> Result<usize> {
    dims.iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| Error::invalid_argument(arg, format!("shape {dims:?} is too large")))
}
