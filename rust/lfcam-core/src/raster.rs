//! Z-buffered triangle rasterisation with perspective-correct interpolation: the
//! renderer of depth meshes (novel views, DESIGN.md section 5).
//!
//! # Conventions
//! - Vertices arrive already projected: `(x, y, z)` with `x` the column and `y` the row
//!   of the target image in pixels, `z > 0` the depth along the viewing axis (any unit).
//!   Pixel `(u, v)` is centred at integer coordinates `(u, v)` (DESIGN.md section 2).
//! - A pixel centre is inside a triangle when all three edge functions are positive, or
//!   zero on an edge the triangle owns. Edge functions are evaluated exactly on vertex
//!   positions snapped to 1/[`SUBPIXEL`] px (integer arithmetic), and an edge is owned
//!   by exactly one of the two triangles sharing it (a top-left-style rule on the edge's
//!   direction), so a shared edge is never drawn twice and never leaves a crack.
//! - Colour and depth are interpolated perspective-correctly: barycentric weights
//!   divided by each vertex's `z`, renormalised. Depth is the interpolated `z` itself
//!   (`1 / sum(l_k / z_k)`), the nearest one wins (z-buffer).
//! - Triangles are two-sided (no culling). A triangle is skipped (not an error) if a
//!   vertex is not finite, has `z <= 0`, or lies farther than [`MAX_COORD`] px from the
//!   image origin, or if its snapped area is zero.
//! - Pixels no triangle covers are NaN in the image and the depth, and 0 in the mask.
//!
//! # Parallelism
//! Sort-last: the triangles are split into consecutive ranges, one per thread (at most
//! [`MAX_PARTS`]); the first range is drawn into the target, each other one into a
//! frame buffer of its own, and the buffers are merged in range order keeping the
//! strictly nearer surface. Each triangle is set up once (a depth mesh of 1 Mpx has
//! 2 M triangles of half a pixel each: per-triangle work dominates, so binning them by
//! rows first cost more than it saved), and the result equals the serial one exactly,
//! ties included (a later triangle wins only when strictly nearer, as in one pass).

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::parallel;

/// Sub-pixel resolution of vertex positions: 1/256 px.
pub const SUBPIXEL: i64 = 256;

/// Vertex coordinates beyond this many pixels from the origin make a triangle skipped:
/// with image sides of at most [`MAX_SIDE`] px, keeps the integer edge functions (sums
/// of products of coordinate differences in sub-pixel units, below 2^59) inside `i64`.
pub const MAX_COORD: f32 = 1_048_576.0;

/// Largest image side accepted (pixels), for the same reason as [`MAX_COORD`].
pub const MAX_SIDE: usize = 1 << 20;

/// Most triangle ranges drawn in parallel (each beyond the first costs a frame buffer).
pub const MAX_PARTS: usize = 8;

/// Fewest triangles per range: below this, a frame buffer costs more than it saves.
pub const MIN_TRIANGLES_PER_PART: usize = 64 * 1024;

/// A borrowed triangle mesh whose vertices are projected to the target image.
#[derive(Debug, Clone, Copy)]
pub struct ProjectedMesh<'a> {
    /// `(x, y, z)` per vertex: column, row (px) and depth (> 0).
    pub vertices: &'a [[f32; 3]],
    /// `channels` values per vertex, vertex after vertex.
    pub colours: &'a [f32],
    /// Number of colour channels (>= 1).
    pub channels: usize,
    /// Vertex indices of each triangle.
    pub faces: &'a [[i32; 3]],
}

/// The outputs of [`rasterize`], `height * width` pixels each.
#[derive(Debug)]
pub struct Target<'a> {
    /// `(H, W, C)` interleaved colour; NaN where nothing was drawn.
    pub image: &'a mut [f32],
    /// `(H, W)` depth of the nearest surface; NaN where nothing was drawn.
    pub depth: &'a mut [f32],
    /// `(H, W)`: 1 where a triangle was drawn, else 0.
    pub mask: &'a mut [u8],
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
}

/// A triangle after setup: snapped vertices (counter-clockwise in the edge-function
/// sense), their `1/z`, and the pixel rows and columns its bounding box covers.
#[derive(Debug, Clone, Copy)]
struct Setup {
    x: [i64; 3],
    y: [i64; 3],
    inv_z: [f64; 3],
    /// Original vertex indices in the order of `x`, `y`.
    idx: [usize; 3],
    rows: (usize, usize),
    cols: (usize, usize),
    area: i64,
}

/// `v` px in sub-pixel units, rounded half away from zero. (`f64::round` is a libm
/// call on baseline x86-64, several times slower than this truncating conversion.)
/// `|v| <= MAX_COORD`, so the result fits in `i32`.
fn snap(v: f32) -> i32 {
    let s = f64::from(v) * SUBPIXEL as f64;
    (s + if s >= 0.0 { 0.5 } else { -0.5 }) as i32
}

/// The first integer `>= v / SUBPIXEL`, for `v` in sub-pixel units.
fn ceil_px<T: Into<i64>>(v: T) -> i64 {
    let v: i64 = v.into();
    v.div_euclid(SUBPIXEL) + i64::from(v.rem_euclid(SUBPIXEL) != 0)
}

/// The snapped `(x, y)` of the vertices of `face`, or `None` if a vertex is unusable.
fn snapped(mesh: &ProjectedMesh<'_>, face: &[i32; 3]) -> Option<([i32; 3], [i32; 3], [f32; 3])> {
    let mut x = [0i32; 3];
    let mut y = [0i32; 3];
    let mut z = [0f32; 3];
    for (((&vi, xo), yo), zo) in face.iter().zip(&mut x).zip(&mut y).zip(&mut z) {
        let &[px, py, pz] = mesh.vertices.get(usize::try_from(vi).ok()?)?;
        // `!(a <= b)` is also true for NaN.
        if !(px.abs() <= MAX_COORD && py.abs() <= MAX_COORD && pz > 0.0 && pz.is_finite()) {
            return None;
        }
        *xo = snap(px);
        *yo = snap(py);
        *zo = pz;
    }
    Some((x, y, z))
}

/// Sets up triangle `t` for a `height x width` image: `None` if it is skipped (see the
/// module docs), has zero snapped area, or its bounding box holds no pixel centre.
fn setup(mesh: &ProjectedMesh<'_>, t: usize, height: usize, width: usize) -> Option<Setup> {
    let face = mesh.faces.get(t)?;
    let (xs, ys, zs) = snapped(mesh, face)?;
    let mut x = xs.map(i64::from);
    let mut y = ys.map(i64::from);
    let [x0, x1, x2] = x;
    let [y0, y1, y2] = y;
    let c0 = ceil_px(x0.min(x1).min(x2)).max(0);
    let c1 = x0
        .max(x1)
        .max(x2)
        .div_euclid(SUBPIXEL)
        .min(width as i64 - 1);
    let r0 = ceil_px(y0.min(y1).min(y2)).max(0);
    let r1 = y0
        .max(y1)
        .max(y2)
        .div_euclid(SUBPIXEL)
        .min(height as i64 - 1);
    if c0 > c1 || r0 > r1 {
        return None;
    }
    let mut area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0);
    if area == 0 {
        return None;
    }
    let mut inv_z = zs.map(|z| 1.0 / f64::from(z));
    let mut idx = [0usize; 3];
    for (&vi, io) in face.iter().zip(&mut idx) {
        *io = usize::try_from(vi).ok()?;
    }
    if area < 0 {
        x.swap(1, 2);
        y.swap(1, 2);
        inv_z.swap(1, 2);
        idx.swap(1, 2);
        area = -area;
    }
    Some(Setup {
        x,
        y,
        inv_z,
        idx,
        rows: (usize::try_from(r0).ok()?, usize::try_from(r1).ok()?),
        cols: (usize::try_from(c0).ok()?, usize::try_from(c1).ok()?),
        area,
    })
}

/// Draws the triangles `range` into a full-frame `image` and `depth`, in order.
fn draw_range(
    mesh: &ProjectedMesh<'_>,
    range: std::ops::Range<usize>,
    height: usize,
    width: usize,
    image: &mut [f32],
    depth: &mut [f32],
) {
    for t in range {
        if let Some(s) = setup(mesh, t, height, width) {
            draw(&s, mesh, width, 0, image, depth);
        }
    }
}

/// Whether the edge from `(ax, ay)` to `(bx, by)` owns the pixel centres exactly on it.
/// For the reversed edge the answer is the opposite, so of two triangles sharing an
/// edge (traversed in opposite directions once both are counter-clockwise) exactly one
/// owns it.
fn owns(ax: i64, ay: i64, bx: i64, by: i64) -> bool {
    let (dx, dy) = (bx - ax, by - ay);
    dy < 0 || (dy == 0 && dx > 0)
}

/// Draws triangle `s` into the rows `first..first + rows` of the task's outputs.
#[allow(clippy::too_many_arguments)]
fn draw(
    s: &Setup,
    mesh: &ProjectedMesh<'_>,
    width: usize,
    first: usize,
    image: &mut [f32],
    depth: &mut [f32],
) {
    let n_rows = depth.len() / width.max(1);
    let r0 = s.rows.0.max(first);
    let r1 = s.rows.1.min(first + n_rows.saturating_sub(1));
    if n_rows == 0 || r0 > r1 {
        return;
    }
    let ch = mesh.channels;
    let ([x0, x1, x2], [y0, y1, y2]) = (s.x, s.y);
    // Edge k is opposite vertex k: from vertex k+1 to vertex k+2.
    // E(p) = (bx - ax)(py - ay) - (by - ay)(px - ax), p in sub-pixel units; per pixel
    // step it changes by `step_x` along a row and `step_y` down a column.
    let edges = [(x1, y1, x2, y2), (x2, y2, x0, y0), (x0, y0, x1, y1)];
    let step_x = edges.map(|(_, ay, _, by)| -(by - ay) * SUBPIXEL);
    let step_y = edges.map(|(ax, _, bx, _)| (bx - ax) * SUBPIXEL);
    let base = edges.map(|(ax, ay, bx, by)| -(bx - ax) * ay + (by - ay) * ax);
    let bias = edges.map(|(ax, ay, bx, by)| i64::from(owns(ax, ay, bx, by)));
    let inv_area = 1.0 / s.area as f64;
    let (c0, c1) = s.cols;
    let col = |vi: usize, c: usize| -> f64 {
        mesh.colours
            .get(vi * ch + c)
            .map_or(f64::NAN, |v| f64::from(*v))
    };
    for r in r0..=r1 {
        let (ri, ci) = (r as i64, c0 as i64);
        let [b0, b1, b2] = base;
        let [sx0, sx1, sx2] = step_x;
        let [sy0, sy1, sy2] = step_y;
        let [bias0, bias1, bias2] = bias;
        let (mut e0, mut e1, mut e2) = (
            b0 + sx0 * ci + sy0 * ri,
            b1 + sx1 * ci + sy1 * ri,
            b2 + sx2 * ci + sy2 * ri,
        );
        let row = (r - first) * width;
        for c in c0..=c1 {
            if e0 + bias0 > 0 && e1 + bias1 > 0 && e2 + bias2 > 0 {
                let [iz0, iz1, iz2] = s.inv_z;
                let w0 = e0 as f64 * inv_area * iz0;
                let w1 = e1 as f64 * inv_area * iz1;
                let w2 = e2 as f64 * inv_area * iz2;
                let sum = w0 + w1 + w2;
                if sum > 0.0 {
                    let z = (1.0 / sum) as f32;
                    let p = row + c;
                    if let Some(zb) = depth.get_mut(p)
                        && (z < *zb || zb.is_nan())
                    {
                        *zb = z;
                        let inv = 1.0 / sum;
                        if let Some(px) = image.get_mut(p * ch..(p + 1) * ch) {
                            for (cc, out) in px.iter_mut().enumerate() {
                                let [i0, i1, i2] = s.idx;
                                let v =
                                    (w0 * col(i0, cc) + w1 * col(i1, cc) + w2 * col(i2, cc)) * inv;
                                *out = v as f32;
                            }
                        }
                    }
                }
            }
            e0 += sx0;
            e1 += sx1;
            e2 += sx2;
        }
    }
}

/// Renders `mesh` into `target` with a z-buffer (see the module docs for the
/// conventions). Every output element is written. Runs in lfcam's pool.
///
/// # Errors
/// - [`Error::InvalidArgument`] `"colours"` if `channels == 0` or `colours.len()` is not
///   `channels` per vertex;
/// - [`Error::InvalidItem`] `"faces"` for a triangle with a vertex index out of range;
/// - [`Error::InvalidArgument`] `"image"`, `"depth"` or `"mask"` if an output's size is
///   not `height * width` pixels (times `channels` for the image), or `"height"` /
///   `"width"` if either is 0 or too large for the bins.
pub fn rasterize(mesh: &ProjectedMesh<'_>, target: Target<'_>) -> Result<()> {
    let Target {
        image,
        depth,
        mask,
        height,
        width,
    } = target;
    let ch = mesh.channels;
    if ch == 0 {
        return Err(Error::invalid_argument(
            "colours",
            "needs at least one channel",
        ));
    }
    if mesh.vertices.len().checked_mul(ch) != Some(mesh.colours.len()) {
        return Err(Error::invalid_argument(
            "colours",
            format!(
                "has {} values, {} vertices x {ch} channels need {}",
                mesh.colours.len(),
                mesh.vertices.len(),
                mesh.vertices.len().saturating_mul(ch)
            ),
        ));
    }
    if height == 0 || width == 0 {
        return Err(Error::invalid_argument(
            if height == 0 { "height" } else { "width" },
            format!("image size must be at least 1 x 1, got {width} x {height}"),
        ));
    }
    if height > MAX_SIDE || width > MAX_SIDE {
        return Err(Error::invalid_argument(
            if height > MAX_SIDE { "height" } else { "width" },
            format!("image size {width} x {height} is too large (at most {MAX_SIDE} a side)"),
        ));
    }
    let n_px = height
        .checked_mul(width)
        .ok_or_else(|| Error::invalid_argument("height", "height x width overflows"))?;
    for (name, len, want) in [
        ("image", image.len(), n_px.checked_mul(ch)),
        ("depth", depth.len(), Some(n_px)),
        ("mask", mask.len(), Some(n_px)),
    ] {
        if Some(len) != want {
            return Err(Error::invalid_argument(
                name,
                format!("has {len} elements, a {width} x {height} image needs {want:?}"),
            ));
        }
    }
    let n_vert = mesh.vertices.len();
    if let Some((t, _)) = mesh.faces.iter().enumerate().find(|(_, f)| {
        f.iter()
            .any(|&v| usize::try_from(v).map_or(true, |v| v >= n_vert))
    }) {
        return Err(Error::invalid_item(
            "faces",
            t,
            format!("vertex index out of range for {n_vert} vertices"),
        ));
    }

    let n_tri = mesh.faces.len();
    depth.fill(f32::NAN);
    image.fill(f32::NAN);
    let threads = parallel::num_threads();
    let parts = if parallel::run_serially(n_tri.saturating_mul(64), threads) {
        1
    } else {
        threads
            .min(MAX_PARTS)
            .min(n_tri / MIN_TRIANGLES_PER_PART)
            .max(1)
    };
    if parts == 1 {
        draw_range(mesh, 0..n_tri, height, width, image, depth);
    } else {
        let per = n_tri.div_ceil(parts);
        let mut buffers: Vec<(Vec<f32>, Vec<f32>)> = (1..parts)
            .map(|_| (vec![f32::NAN; n_px * ch], vec![f32::NAN; n_px]))
            .collect();
        {
            let mut frames: Vec<(&mut [f32], &mut [f32])> = vec![(&mut *image, &mut *depth)];
            frames.extend(
                buffers
                    .iter_mut()
                    .map(|(i, d)| (i.as_mut_slice(), d.as_mut_slice())),
            );
            parallel::install(|| {
                frames
                    .into_par_iter()
                    .enumerate()
                    .for_each(|(k, (img, dep))| {
                        let range = (k * per).min(n_tri)..((k + 1) * per).min(n_tri);
                        draw_range(mesh, range, height, width, img, dep);
                    });
            })?;
        }
        // Merge in range order: a later range wins only where strictly nearer.
        parallel::for_each_row_chunk_pair(image, depth, width * ch, width, |first, img, dep| {
            let (p0, p1) = (first * width, first * width + dep.len());
            for (b_img, b_dep) in &buffers {
                let (Some(bi), Some(bd)) = (b_img.get(p0 * ch..p1 * ch), b_dep.get(p0..p1)) else {
                    return Err(Error::invalid_argument("image", "internal: buffer size"));
                };
                for (((d, px), bz), bpx) in dep
                    .iter_mut()
                    .zip(img.chunks_exact_mut(ch))
                    .zip(bd)
                    .zip(bi.chunks_exact(ch))
                {
                    if *bz < *d || (d.is_nan() && !bz.is_nan()) {
                        *d = *bz;
                        px.copy_from_slice(bpx);
                    }
                }
            }
            Ok(())
        })?;
    }
    for (m, d) in mask.iter_mut().zip(depth.iter()) {
        *m = u8::from(!d.is_nan());
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    fn render(
        verts: &[[f32; 3]],
        cols: &[f32],
        faces: &[[i32; 3]],
        h: usize,
        w: usize,
    ) -> (Vec<f32>, Vec<f32>, Vec<u8>) {
        let mesh = ProjectedMesh {
            vertices: verts,
            colours: cols,
            channels: 1,
            faces,
        };
        let mut img = vec![0.0; h * w];
        let mut dep = vec![0.0; h * w];
        let mut mask = vec![0; h * w];
        rasterize(
            &mesh,
            Target {
                image: &mut img,
                depth: &mut dep,
                mask: &mut mask,
                height: h,
                width: w,
            },
        )
        .unwrap();
        (img, dep, mask)
    }

    #[test]
    fn square_of_two_triangles_covers_each_pixel_once() {
        // A square with corners on pixel centres: the shared diagonal passes through
        // centres; each is drawn once, no cracks.
        let v = [
            [1.0, 1.0, 2.0],
            [5.0, 1.0, 2.0],
            [1.0, 5.0, 2.0],
            [5.0, 5.0, 2.0],
        ];
        let c = [1.0, 1.0, 1.0, 1.0];
        let (_, dep, mask) = render(&v, &c, &[[0, 2, 1], [1, 2, 3]], 8, 8);
        let covered: usize = mask.iter().map(|&m| usize::from(m)).sum();
        // Half-open: of the 5 x 5 centres on the closed square, 4 x 4 or a 5 x 5 with
        // two edges owned; either way, no hole inside and the diagonal is covered.
        for i in 2..5 {
            assert_eq!(mask[i * 8 + i], 1, "diagonal centre ({i}, {i})");
            assert_eq!(dep[i * 8 + i], 2.0);
        }
        assert!((16..=25).contains(&covered), "{covered}");
    }

    #[test]
    fn nearer_triangle_wins_and_errors() {
        let v = [
            [0.0, 0.0, 3.0],
            [9.0, 0.0, 3.0],
            [0.0, 9.0, 3.0],
            [0.0, 0.0, 1.0],
            [9.0, 0.0, 1.0],
            [0.0, 9.0, 1.0],
        ];
        let c = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0];
        let (img, dep, _) = render(&v, &c, &[[3, 4, 5], [0, 1, 2]], 10, 10);
        assert_eq!(dep[11], 1.0);
        assert_eq!(img[11], 1.0);
        assert!(dep[99].is_nan() && img[99].is_nan());
        let mesh = ProjectedMesh {
            vertices: &v,
            colours: &c,
            channels: 1,
            faces: &[[0, 1, 6]],
        };
        let (mut a, mut b, mut m) = (vec![0.0; 4], vec![0.0; 4], vec![0; 4]);
        let err = rasterize(
            &mesh,
            Target {
                image: &mut a,
                depth: &mut b,
                mask: &mut m,
                height: 2,
                width: 2,
            },
        )
        .unwrap_err();
        assert!(matches!(err, Error::InvalidItem { ref arg, index: 0, .. } if arg == "faces"));
    }
}
