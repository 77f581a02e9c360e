//! Warp-map inversion: for each raw pixel of a view's crop, the rectified position its
//! warp map sends there (Newton's method on the bilinear cell that covers it).

use nalgebra::{Matrix2, Vector2};

use super::{check_len, mul, positive};
use crate::error::{Error, Result};
use crate::parallel;

/// The rectified position `(u + a, v + b)` of the raw point `(px, py)` inside the cell
/// whose corners map to `p00 = w(u, v)`, `p10 = w(u + 1, v)`, `p01 = w(u, v + 1)`,
/// `p11 = w(u + 1, v + 1)`: Newton's method on the bilinear patch, from its centre.
/// Returns `(a, b)` if it converged inside the cell (with a tolerance `eps`).
#[inline]
fn invert_bilinear(
    [p00, p10, p01, p11]: [Vector2<f32>; 4],
    p: Vector2<f32>,
    eps: f32,
) -> Option<(f32, f32)> {
    let (mut a, mut b) = (0.5f32, 0.5f32);
    for _ in 0..6 {
        // The patch's point at (a, b), minus p, and its derivatives along a and b.
        let f = p00 * ((1.0 - a) * (1.0 - b))
            + p10 * (a * (1.0 - b))
            + p01 * ((1.0 - a) * b)
            + p11 * (a * b)
            - p;
        let jac = Matrix2::from_columns(&[
            (p10 - p00) * (1.0 - b) + (p11 - p01) * b,
            (p01 - p00) * (1.0 - a) + (p11 - p10) * a,
        ]);
        let det = jac.determinant();
        if !positive(det.abs() - 1e-12) {
            return None;
        }
        // The Newton step `jac^-1 f` by Cramer's rule: the adjugate times `f`, over the
        // determinant.
        let adjugate = Matrix2::new(jac.m22, -jac.m12, -jac.m21, jac.m11);
        let d = adjugate * f / det;
        a -= d.x;
        b -= d.y;
        if d.x.abs() < 1e-6 && d.y.abs() < 1e-6 {
            break;
        }
    }
    (a >= -eps && a <= 1.0 + eps && b >= -eps && b <= 1.0 + eps && a.is_finite() && b.is_finite())
        .then_some((a, b))
}

/// Inverts one view's warp map: for each pixel of its crop (`crop_h x crop_w`, raw
/// pixel centres at integers relative to the crop), the rectified position `(u, v)`
/// that the map sends there, NaN where no valid rectified cell covers it.
///
/// `warp` is `(h, w, 2)`, `mask` `(h, w)` (non-zero: valid) or `None`; `out` is
/// `(crop_h, crop_w, 2)`. A cell is valid when its four corners are finite and
/// unmasked. Raw points covered by two cells (on shared edges) take the first.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `warp`, `mask` or `out` if a size disagrees.
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
pub fn invert_map(
    warp: &[f32],
    mask: Option<&[u8]>,
    h: usize,
    w: usize,
    crop_h: usize,
    crop_w: usize,
    out: &mut [f32],
) -> Result<()> {
    check_len("warp", warp.len(), mul("warp", &[h, w, 2])?, "(H, W, 2)")?;
    if let Some(m) = mask {
        check_len("mask", m.len(), mul("mask", &[h, w])?, "(H, W)")?;
    }
    check_len(
        "out",
        out.len(),
        mul("out", &[crop_h, crop_w, 2])?,
        "(crop_h, crop_w, 2)",
    )?;
    out.fill(f32::NAN);
    if h < 2 || w < 2 {
        return Ok(());
    }
    let ok = |y: usize, x: usize| mask.is_none_or(|m| m[y * w + x] != 0);
    let at = |y: usize, x: usize| Vector2::new(warp[(y * w + x) * 2], warp[(y * w + x) * 2 + 1]);
    let (cw, ch) = (crop_w as f32, crop_h as f32);
    for v in 0..h - 1 {
        for u in 0..w - 1 {
            if !(ok(v, u) && ok(v, u + 1) && ok(v + 1, u) && ok(v + 1, u + 1)) {
                continue;
            }
            let corners = [at(v, u), at(v, u + 1), at(v + 1, u), at(v + 1, u + 1)];
            let xs = corners.map(|c| c.x);
            let ys = corners.map(|c| c.y);
            if xs.iter().chain(ys.iter()).any(|c| !c.is_finite()) {
                continue;
            }
            let xmin = xs.iter().copied().fold(f32::INFINITY, f32::min).max(0.0);
            let xmax = xs
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max)
                .min(cw - 1.0);
            let ymin = ys.iter().copied().fold(f32::INFINITY, f32::min).max(0.0);
            let ymax = ys
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max)
                .min(ch - 1.0);
            if !(xmin <= xmax && ymin <= ymax) {
                continue;
            }
            for py in (ymin.ceil() as usize)..=(ymax.floor() as usize) {
                for px in (xmin.ceil() as usize)..=(xmax.floor() as usize) {
                    if px >= crop_w || py >= crop_h {
                        continue;
                    }
                    let k = (py * crop_w + px) * 2;
                    if out[k].is_finite() {
                        continue;
                    }
                    if let Some((a, b)) =
                        invert_bilinear(corners, Vector2::new(px as f32, py as f32), 1e-4)
                    {
                        out[k] = u as f32 + a;
                        out[k + 1] = v as f32 + b;
                    }
                }
            }
        }
    }
    Ok(())
}

/// [`invert_map`] for all `N` views at once, in parallel over views, written into one
/// raw-frame-sized map: `inv` `(raw_h, raw_w, 2)` gets the rectified position of each
/// raw pixel in its view's frame (NaN if none) and `view` `(raw_h, raw_w)` the view's
/// index (-1 if none). `warps` is `(N, h, w, 2)` relative to each crop, `masks`
/// `(N, h, w)` or `None`, `crops` `(x0, y0, cw, ch)` per view. A raw pixel inside two
/// crops takes the first view that covers it.
///
/// # Errors
/// [`Error::InvalidArgument`] or [`Error::InvalidItem`] (a crop outside the frame).
#[allow(clippy::too_many_arguments)]
#[allow(clippy::indexing_slicing, reason = "sizes checked on entry")]
pub fn invert_maps(
    warps: &[f32],
    masks: Option<&[u8]>,
    crops: &[[i64; 4]],
    h: usize,
    w: usize,
    raw_h: usize,
    raw_w: usize,
    inv: &mut [f32],
    view: &mut [i32],
) -> Result<()> {
    let n = crops.len();
    let per = mul("warps", &[h, w, 2])?;
    check_len(
        "warps",
        warps.len(),
        mul("warps", &[n, h, w, 2])?,
        "(N, H, W, 2)",
    )?;
    if let Some(m) = masks {
        check_len("masks", m.len(), mul("masks", &[n, h, w])?, "(N, H, W)")?;
    }
    check_len(
        "inv",
        inv.len(),
        mul("inv", &[raw_h, raw_w, 2])?,
        "(H_raw, W_raw, 2)",
    )?;
    check_len(
        "view",
        view.len(),
        mul("view", &[raw_h, raw_w])?,
        "(H_raw, W_raw)",
    )?;
    let mut rects = Vec::with_capacity(n);
    for (i, c) in crops.iter().enumerate() {
        let [x0, y0, cw, ch] = *c;
        let inside = x0 >= 0
            && y0 >= 0
            && cw > 0
            && ch > 0
            && x0.checked_add(cw).is_some_and(|x1| x1 <= raw_w as i64)
            && y0.checked_add(ch).is_some_and(|y1| y1 <= raw_h as i64);
        if !inside {
            return Err(Error::invalid_item(
                "crops",
                i,
                format!("rectangle {c:?} is empty or outside the {raw_w}x{raw_h} frame"),
            ));
        }
        rects.push([x0 as usize, y0 as usize, cw as usize, ch as usize]);
    }
    // One task per view (the inverted crops' bytes measure the work).
    let work = rects.iter().map(|&[_, _, cw, ch]| cw * ch * 8).sum();
    let per_view = parallel::map_tasks(n, work, |i| {
        let [_, _, cw, ch] = rects[i];
        let mut buf = vec![0f32; ch * cw * 2];
        let m = masks.map(|m| &m[i * h * w..(i + 1) * h * w]);
        invert_map(&warps[i * per..(i + 1) * per], m, h, w, ch, cw, &mut buf)?;
        Ok(buf)
    })?;
    inv.fill(f32::NAN);
    view.fill(-1);
    for (i, (buf, rect)) in per_view.iter().zip(&rects).enumerate() {
        let [x0, y0, cw, ch] = *rect;
        for yc in 0..ch {
            for xc in 0..cw {
                let s = (yc * cw + xc) * 2;
                let d = (y0 + yc) * raw_w + x0 + xc;
                if buf[s].is_finite() && view[d] < 0 {
                    inv[2 * d] = buf[s];
                    inv[2 * d + 1] = buf[s + 1];
                    view[d] = i as i32;
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// [`invert_bilinear`] written out component by component.
    fn invert_bilinear_scalar(c: [[f32; 2]; 4], px: f32, py: f32, eps: f32) -> Option<(f32, f32)> {
        let [p00, p10, p01, p11] = c;
        let (mut a, mut b) = (0.5f32, 0.5f32);
        for _ in 0..6 {
            let fx = (1.0 - a) * (1.0 - b) * p00[0]
                + a * (1.0 - b) * p10[0]
                + (1.0 - a) * b * p01[0]
                + a * b * p11[0]
                - px;
            let fy = (1.0 - a) * (1.0 - b) * p00[1]
                + a * (1.0 - b) * p10[1]
                + (1.0 - a) * b * p01[1]
                + a * b * p11[1]
                - py;
            let dxa = (1.0 - b) * (p10[0] - p00[0]) + b * (p11[0] - p01[0]);
            let dya = (1.0 - b) * (p10[1] - p00[1]) + b * (p11[1] - p01[1]);
            let dxb = (1.0 - a) * (p01[0] - p00[0]) + a * (p11[0] - p10[0]);
            let dyb = (1.0 - a) * (p01[1] - p00[1]) + a * (p11[1] - p10[1]);
            let det = dxa * dyb - dxb * dya;
            if !positive(det.abs() - 1e-12) {
                return None;
            }
            let da = (fx * dyb - fy * dxb) / det;
            let db = (dxa * fy - dya * fx) / det;
            a -= da;
            b -= db;
            if da.abs() < 1e-6 && db.abs() < 1e-6 {
                break;
            }
        }
        let inside = a >= -eps && a <= 1.0 + eps && b >= -eps && b <= 1.0 + eps;
        (inside && a.is_finite() && b.is_finite()).then_some((a, b))
    }

    #[test]
    fn newton_steps_equal_the_scalar_formula_bit_for_bit() {
        let mut seed = 3u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32) / (1u64 << 24) as f32
        };
        let mut inside = 0;
        for k in 0..20_000 {
            // Cells of about a pixel, skewed and scaled, some degenerate; points in and
            // around them.
            let s = if k % 500 == 0 { 0.0 } else { 0.3 + 2.0 * rnd() };
            let c = [[0.0, 0.0], [s, 0.2 * rnd()], [0.3 * rnd(), s], [s, s]]
                .map(|[x, y]| [x + 0.3 * rnd() + 40.0, y + 0.3 * rnd() + 7.0]);
            let (px, py) = (40.0 + 2.5 * rnd() - 0.5, 7.0 + 2.5 * rnd() - 0.5);
            let want = invert_bilinear_scalar(c, px, py, 1e-4);
            let got = invert_bilinear(c.map(Vector2::from), Vector2::new(px, py), 1e-4);
            let bits = |v: Option<(f32, f32)>| v.map(|(a, b)| (a.to_bits(), b.to_bits()));
            assert_eq!(bits(got), bits(want), "cell {c:?}, point ({px}, {py})");
            inside += usize::from(got.is_some());
        }
        assert!(inside > 2000, "{inside}");
    }

    #[test]
    fn invert_affine_map() {
        // w(u, v) = (2 + 1.1 u + 0.1 v, 1 + 0.05 u + 0.9 v) on a 12 x 10 grid.
        let (h, w) = (10, 12);
        let mut warp = vec![0f32; h * w * 2];
        for v in 0..h {
            for u in 0..w {
                warp[(v * w + u) * 2] = 2.0 + 1.1 * u as f32 + 0.1 * v as f32;
                warp[(v * w + u) * 2 + 1] = 1.0 + 0.05 * u as f32 + 0.9 * v as f32;
            }
        }
        let (ch, cw) = (12, 16);
        let mut out = vec![0f32; ch * cw * 2];
        invert_map(&warp, None, h, w, ch, cw, &mut out).unwrap();
        let mut n = 0;
        for y in 0..ch {
            for x in 0..cw {
                let (u, v) = (out[(y * cw + x) * 2], out[(y * cw + x) * 2 + 1]);
                if u.is_finite() {
                    n += 1;
                    let fx = 2.0 + 1.1 * u + 0.1 * v;
                    let fy = 1.0 + 0.05 * u + 0.9 * v;
                    assert!((fx - x as f32).abs() < 1e-4 && (fy - y as f32).abs() < 1e-4);
                }
            }
        }
        assert!(n > 80, "{n}");
    }
}
