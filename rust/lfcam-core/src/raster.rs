//! Z-buffered triangle rasterisation with perspective-correct interpolation: the
//! renderer of depth meshes (docs/design.md, "Novel views").
//!
//! # Conventions
//! - Vertices arrive already projected: `(x, y, z)` with `x` the column and `y` the row
//!   of the target image in pixels, `z > 0` the depth along the viewing axis (any unit).
//!   Pixel `(u, v)` is centred at integer coordinates `(u, v)` (docs/design.md, "Pixel centres").
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
//! Before that, each vertex is set up once, in parallel (snapped position, validity,
//! `1/z`): a grid mesh shares a vertex among six triangles, and most triangles are
//! then rejected by their bounding box from three indexed loads and a few shifts.

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

/// A vertex after projection set-up, done once per vertex (a vertex of a grid mesh is
/// shared by six triangles): its position snapped to 1/[`SUBPIXEL`] px and its `1/z`,
/// or [`Vertex::UNUSABLE`].
#[derive(Debug, Clone, Copy)]
struct Vertex {
    x: i32,
    y: i32,
    inv_z: f64,
}

impl Vertex {
    /// A vertex that makes its triangles skipped (`x` is no snapped coordinate:
    /// `|snap(v)| <= MAX_COORD * SUBPIXEL < 2^29`).
    const UNUSABLE: Self = Self {
        x: i32::MIN,
        y: 0,
        inv_z: 0.0,
    };

    fn new(&[px, py, pz]: &[f32; 3]) -> Self {
        // `!(a <= b)` is also true for NaN.
        if !(px.abs() <= MAX_COORD && py.abs() <= MAX_COORD && pz > 0.0 && pz.is_finite()) {
            return Self::UNUSABLE;
        }
        Self {
            x: snap(px),
            y: snap(py),
            inv_z: 1.0 / f64::from(pz),
        }
    }
}

/// [`Vertex::new`] of every vertex, in lfcam's pool when there are many.
fn project_vertices(vertices: &[[f32; 3]]) -> Result<Vec<Vertex>> {
    // Faster than collecting a parallel iterator (docs/tuning.md, "Mesh and rendering").
    let mut out = vec![Vertex::UNUSABLE; vertices.len()];
    parallel::for_each_row_chunk(&mut out, 1, |first, out| {
        let src = vertices
            .get(first..first + out.len())
            .ok_or_else(|| Error::internal("rasterize", format!("vertex {first}")))?;
        for (o, v) in out.iter_mut().zip(src) {
            *o = Vertex::new(v);
        }
        Ok(())
    })?;
    Ok(out)
}

/// `v` px in sub-pixel units, rounded half away from zero. (`f64::round` is a libm
/// call on baseline x86-64, several times slower than this truncating conversion.)
/// `|v| <= MAX_COORD`, so the result fits in `i32`.
fn snap(v: f32) -> i32 {
    let s = f64::from(v) * SUBPIXEL as f64;
    (s + if s >= 0.0 { 0.5 } else { -0.5 }) as i32
}

/// The first pixel `>= v / SUBPIXEL` and the last `<= v / SUBPIXEL`, for `v` in
/// sub-pixel units (`|v| < 2^29`, so `v + SUBPIXEL - 1` does not overflow; `>>` on a
/// signed integer rounds towards minus infinity).
#[inline(always)]
fn ceil_px(v: i32) -> i32 {
    (v + (SUBPIXEL as i32 - 1)) >> SUBPIXEL_BITS
}

#[inline(always)]
fn floor_px(v: i32) -> i32 {
    v >> SUBPIXEL_BITS
}

/// `log2(SUBPIXEL)`.
const SUBPIXEL_BITS: u32 = SUBPIXEL.trailing_zeros();

/// Whether the edge from `(ax, ay)` to `(bx, by)` owns the pixel centres exactly on it.
/// For the reversed edge the answer is the opposite, so of two triangles sharing an
/// edge (traversed in opposite directions once both are counter-clockwise) exactly one
/// owns it.
#[inline(always)]
fn owns(ax: i64, ay: i64, bx: i64, by: i64) -> bool {
    let (dx, dy) = (bx - ax, by - ay);
    dy < 0 || (dy == 0 && dx > 0)
}

/// The frame a range of triangles is drawn into: full-frame colour and depth.
struct Frame<'f> {
    image: &'f mut [f32],
    depth: &'f mut [f32],
    height: usize,
    width: usize,
}

/// Where a range of triangles is drawn: the target's colour and depth (the first
/// range), or a frame buffer of its own, allocated by its task.
enum Part<'a> {
    Target(&'a mut [f32], &'a mut [f32]),
    Buffer(&'a mut (Vec<f32>, Vec<f32>)),
}

/// Draws the triangles `range` of `mesh` (vertices set up as `verts`) into `frame`, in
/// order: a triangle is skipped if a vertex is unusable, its snapped area is zero or its
/// bounding box holds no pixel centre (most triangles of a dense mesh: half a pixel
/// each); pixels are drawn where the edge functions say inside and the z-buffer says
/// strictly nearer (or nothing yet).
fn draw_range(
    mesh: &ProjectedMesh<'_>,
    verts: &[Vertex],
    range: std::ops::Range<usize>,
    frame: Frame<'_>,
) {
    let Frame {
        image,
        depth,
        height,
        width,
    } = frame;
    let ch = mesh.channels;
    // Sides fit in i32 (MAX_SIDE = 2^20).
    let (w_last, h_last) = (width as i32 - 1, height as i32 - 1);
    let faces = mesh.faces.get(range).unwrap_or_default();
    for face in faces {
        let vertex = |vi: i32| {
            usize::try_from(vi)
                .ok()
                .and_then(|i| verts.get(i).map(|v| (i, *v)))
        };
        let [f0, f1, f2] = *face;
        let (Some((i0, v0)), Some((i1, v1)), Some((i2, v2))) = (vertex(f0), vertex(f1), vertex(f2))
        else {
            continue;
        };
        if v0.x == i32::MIN || v1.x == i32::MIN || v2.x == i32::MIN {
            continue;
        }
        // Bounding box in pixels, clipped to the image.
        let c0 = ceil_px(v0.x.min(v1.x).min(v2.x)).max(0);
        let c1 = floor_px(v0.x.max(v1.x).max(v2.x)).min(w_last);
        let r0 = ceil_px(v0.y.min(v1.y).min(v2.y)).max(0);
        let r1 = floor_px(v0.y.max(v1.y).max(v2.y)).min(h_last);
        if c0 > c1 || r0 > r1 {
            continue;
        }
        let (mut x, mut y) = (
            [v0.x, v1.x, v2.x].map(i64::from),
            [v0.y, v1.y, v2.y].map(i64::from),
        );
        let mut area = (x[1] - x[0]) * (y[2] - y[0]) - (y[1] - y[0]) * (x[2] - x[0]);
        if area == 0 {
            continue;
        }
        let mut inv_z = [v0.inv_z, v1.inv_z, v2.inv_z];
        let mut idx = [i0, i1, i2];
        if area < 0 {
            x.swap(1, 2);
            y.swap(1, 2);
            inv_z.swap(1, 2);
            idx.swap(1, 2);
            area = -area;
        }
        let ([x0, x1, x2], [y0, y1, y2]) = (x, y);
        // Edge k is opposite vertex k: from vertex k+1 to vertex k+2.
        // E(p) = (bx - ax)(py - ay) - (by - ay)(px - ax), p in sub-pixel units; per pixel
        // step it changes by `step_x` along a row and `step_y` down a column. A pixel
        // centre is inside when E + bias > 0 for all three edges.
        let edges = [(x1, y1, x2, y2), (x2, y2, x0, y0), (x0, y0, x1, y1)];
        let step_x = edges.map(|(_, ay, _, by)| -(by - ay) * SUBPIXEL);
        let step_y = edges.map(|(ax, _, bx, _)| (bx - ax) * SUBPIXEL);
        let base = edges.map(|(ax, ay, bx, by)| {
            -(bx - ax) * ay + (by - ay) * ax + i64::from(owns(ax, ay, bx, by))
        });
        let bias = edges.map(|(ax, ay, bx, by)| i64::from(owns(ax, ay, bx, by)));
        let inv_area = 1.0 / area as f64;
        let [iz0, iz1, iz2] = inv_z;
        let (ci, ri) = (i64::from(c0), i64::from(r0));
        let mut start = base;
        for ((e, sx), sy) in start.iter_mut().zip(&step_x).zip(&step_y) {
            *e += sx * ci + sy * ri;
        }
        for r in r0..=r1 {
            let row = r as usize * width;
            let mut e = start;
            for c in c0..=c1 {
                if e[0] > 0 && e[1] > 0 && e[2] > 0 {
                    // Without the ownership bias again: the exact edge values.
                    let w0 = (e[0] - bias[0]) as f64 * inv_area * iz0;
                    let w1 = (e[1] - bias[1]) as f64 * inv_area * iz1;
                    let w2 = (e[2] - bias[2]) as f64 * inv_area * iz2;
                    let sum = w0 + w1 + w2;
                    let p = row + c as usize;
                    if sum > 0.0
                        && let Some(zb) = depth.get_mut(p)
                    {
                        let inv = 1.0 / sum;
                        let z = inv as f32;
                        if z < *zb || zb.is_nan() {
                            *zb = z;
                            let colour = |i: usize| mesh.colours.get(i * ch..(i + 1) * ch);
                            if let (Some(px), Some(a), Some(b), Some(d)) = (
                                image.get_mut(p * ch..(p + 1) * ch),
                                colour(idx[0]),
                                colour(idx[1]),
                                colour(idx[2]),
                            ) {
                                for (((out, &a), &b), &d) in px.iter_mut().zip(a).zip(b).zip(d) {
                                    let v =
                                        (w0 * f64::from(a) + w1 * f64::from(b) + w2 * f64::from(d))
                                            * inv;
                                    *out = v as f32;
                                }
                            }
                        }
                    }
                }
                for (e, s) in e.iter_mut().zip(&step_x) {
                    *e += s;
                }
            }
            for (e, s) in start.iter_mut().zip(&step_y) {
                *e += s;
            }
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
    // `v as u32` maps a negative index above 2^31 - 1, which no vertex count below 2^31
    // reaches; beyond, every non-negative `i32` is a valid index.
    let limit = n_vert.min(1 << 31);
    let out_of_range = |f: &[i32; 3]| f.iter().any(|&v| v as u32 as usize >= limit);
    if mesh.faces.iter().any(out_of_range)
        && let Some(t) = mesh.faces.iter().position(out_of_range)
    {
        return Err(Error::invalid_item(
            "faces",
            t,
            format!("vertex index out of range for {n_vert} vertices"),
        ));
    }

    let n_tri = mesh.faces.len();
    let threads = parallel::num_threads();
    let verts = project_vertices(mesh.vertices)?;
    let parts = if parallel::run_serially(n_tri.saturating_mul(64), threads) {
        1
    } else {
        threads
            .min(MAX_PARTS)
            .min(n_tri / MIN_TRIANGLES_PER_PART)
            .max(1)
    };
    let per = n_tri.div_ceil(parts);
    let range = |k: usize| (k * per).min(n_tri)..((k + 1) * per).min(n_tri);
    // Range 0 into the target, range k >= 1 into a frame buffer of its own (allocated
    // by its task, so that the buffers' first touch runs in parallel too).
    let mut buffers: Vec<(Vec<f32>, Vec<f32>)> =
        (1..parts).map(|_| (Vec::new(), Vec::new())).collect();
    let frames = std::iter::once(Part::Target(&mut *image, &mut *depth))
        .chain(buffers.iter_mut().map(Part::Buffer))
        .collect();
    parallel::for_each_task_init(
        frames,
        n_tri.saturating_mul(64),
        || (),
        |(), k, part| {
            let (image, depth) = match part {
                Part::Target(image, depth) => {
                    image.fill(f32::NAN);
                    depth.fill(f32::NAN);
                    (image, depth)
                }
                Part::Buffer((img, dep)) => {
                    *img = vec![f32::NAN; n_px * ch];
                    *dep = vec![f32::NAN; n_px];
                    (img.as_mut_slice(), dep.as_mut_slice())
                }
            };
            let frame = Frame {
                image,
                depth,
                height,
                width,
            };
            draw_range(mesh, &verts, range(k), frame);
            Ok(())
        },
    )?;
    if parts > 1 {
        // Merge in range order: a later range wins only where strictly nearer.
        parallel::for_each_row_chunk_pair(image, depth, width * ch, width, |first, img, dep| {
            let (p0, p1) = (first * width, first * width + dep.len());
            for (b_img, b_dep) in &buffers {
                let (Some(bi), Some(bd)) = (b_img.get(p0 * ch..p1 * ch), b_dep.get(p0..p1)) else {
                    return Err(Error::internal("rasterize", "buffer size"));
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
    fn pixel_rounding_matches_euclidean_division() {
        let s = SUBPIXEL as i32;
        let edge = [(1 << 28) - 1, 1 << 28, -(1 << 28), -(1 << 28) + 1];
        for v in (-5000..5000).chain(edge) {
            assert_eq!(floor_px(v), v.div_euclid(s), "{v}");
            assert_eq!(
                ceil_px(v),
                v.div_euclid(s) + i32::from(v.rem_euclid(s) != 0),
                "{v}"
            );
        }
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
