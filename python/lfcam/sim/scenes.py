"""Scenes for the simulated camera, and rendering them: textured planes and spheres
traced ray by ray through the camera of :mod:`lfcam.sim.camera`, sensor noise, Bayer
mosaics, and the ground truth (depth, labels, a 2x reference view).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..calibration.pattern import procedural_texture
from ..errors import InputError
from .camera import SCENES, SimConfig, SimulatedCamera

__all__ = ["Scene", "add_noise", "make_scene", "reference_rays", "render_truth", "trace"]


@dataclass
class _Texture:
    image: np.ndarray  # (h, w, 3) float32
    texel: float  # metres per texel
    origin: tuple[float, float]  # surface coordinate of texel (0, 0)


@dataclass
class _Plane:
    point: np.ndarray
    normal: np.ndarray
    u_axis: np.ndarray
    extent: tuple[float, float, float, float] | None  # (u0, u1, v0, v1) or infinite
    texture: _Texture | None
    emission: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    label: int = 0


@dataclass
class _Sphere:
    centre: np.ndarray
    radius: float
    texture: _Texture
    label: int = 0


@dataclass
class Scene:
    """A scene: a list of surfaces (planes and spheres) lit by white light."""

    name: str
    surfaces: list[Any] = field(default_factory=list)
    #: A uniform white target (for the white captures): radiance 1 everywhere.
    white: bool = False


def _texture_for(
    rng: np.random.Generator, extent_u: float, extent_v: float, texel: float
) -> _Texture:
    w = math.ceil(extent_u / texel) + 4
    h = math.ceil(extent_v / texel) + 4
    img = procedural_texture(h, w, rng, finest=2.0)
    return _Texture(img, texel, (-2 * texel, -2 * texel))


def make_scene(name: str, cam: SimulatedCamera, seed: int = 0) -> Scene:
    """Build one of the named test scenes for a camera.

    Lateral sizes are fractions of the field of view, depths multiples of
    ``Z_b``, so the scenes suit any camera.

    * ``planes``: a fronto-parallel card, a slanted plane and a far background;
    * ``spheres``: three spheres in front of a background;
    * ``layered``: four overlapping fronto-parallel cards and a background
      (occlusion edges everywhere);
    * ``board``: the calibration pattern on a flat board at
      ``config.board_distance`` (not a calibration distance).
    """
    if name not in SCENES:
        raise InputError(f"scene: unknown scene {name!r}; known: {', '.join(SCENES)}")
    rng = np.random.default_rng(
        np.random.SeedSequence([0x5CE, seed & 0xFFFFFFFF, SCENES.index(name)])
    )
    zb = cam.z_b
    half = np.array([cam.W_pat, cam.H_pat]) * cam.pattern_pitch / 2.0 / zb  # half field per metre
    texel_per_m = cam.rect_pitch / zb / 2.0  # two texels per rectified pixel
    fwd = np.array([0.0, 0.0, 1.0])
    ex = np.array([1.0, 0.0, 0.0])

    def card(z: float, fx0: float, fx1: float, fy0: float, fy1: float, label: int) -> _Plane:
        z = z * zb
        u0, u1 = fx0 * half[0] * z, fx1 * half[0] * z
        v0, v1 = fy0 * half[1] * z, fy1 * half[1] * z
        tex = _texture_for(rng, u1 - u0, v1 - v0, texel_per_m * z)
        tex.origin = (u0 - 2 * tex.texel, v0 - 2 * tex.texel)
        return _Plane(np.array([0.0, 0.0, z]), fwd, ex, (u0, u1, v0, v1), tex, label=label)

    def background(z: float) -> _Plane:
        p = card(z, -1.5, 1.5, -1.5, 1.5, 1)
        p.extent = None
        return p

    surfaces: list[Any] = []
    if name == "planes":
        surfaces.append(background(2.2))
        surfaces.append(card(1.1, -1.5, -0.08, -1.5, 1.5, 2))
        # A plane through (0.5 w, 0, Z_b) turned 35 degrees about the vertical axis.
        th = np.deg2rad(35.0)
        z0 = 1.0 * zb
        point = np.array([0.5 * half[0] * z0, 0.0, z0])
        u_axis = np.array([np.cos(th), 0.0, np.sin(th)])
        normal = np.array([-np.sin(th), 0.0, np.cos(th)])
        ext_u = 0.55 * half[0] * z0 / np.cos(th)
        ext_v = 1.5 * half[1] * z0
        tex = _texture_for(rng, 2 * ext_u, 2 * ext_v, texel_per_m * z0 * 0.8)
        tex.origin = (-ext_u - 2 * tex.texel, -ext_v - 2 * tex.texel)
        surfaces.append(_Plane(point, normal, u_axis, (-ext_u, ext_u, -ext_v, ext_v), tex, label=3))
    elif name == "spheres":
        surfaces.append(background(1.8))
        for k, (fx, fy, z, fr) in enumerate(
            [(-0.45, -0.3, 0.8, 0.42), (0.35, 0.2, 1.05, 0.5), (-0.05, 0.55, 1.35, 0.35)]
        ):
            zz = z * zb
            r = fr * half[1] * zz
            c = np.array([fx * half[0] * zz, fy * half[1] * zz, zz + r])
            tex = _texture_for(rng, 2 * r, 2 * r, texel_per_m * zz)
            tex.origin = (c[0] - r - 2 * tex.texel, c[1] - r - 2 * tex.texel)
            surfaces.append(_Sphere(c, r, tex, label=2 + k))
    elif name == "layered":
        surfaces.append(background(2.0))
        surfaces.append(card(1.45, -1.6, 1.6, -0.15, 0.25, 2))
        surfaces.append(card(1.15, 0.05, 1.6, -1.6, 0.6, 3))
        surfaces.append(card(0.9, -0.55, -0.3, -1.6, 1.6, 4))
        surfaces.append(card(0.75, -1.6, -0.7, -0.5, 0.2, 5))
        surfaces.append(card(0.82, 0.3, 0.75, 0.35, 0.9, 6))
    elif name == "board":
        surfaces.append(_board_plane(cam, cam.cfg.board_distance))
    return Scene(name, surfaces)


def _board_plane(cam: SimulatedCamera, z: float, pose: np.ndarray | None = None) -> _Plane:
    """The calibration pattern shown on a flat board at depth ``z``: fronto-parallel and
    centred on the axis, or with ``pose`` (:meth:`SimulatedCamera.board_poses`: tilts
    about x and y in degrees, drift in metres) turned about and moved from there."""
    tx, ty, dx, dy = (0.0, 0.0, 0.0, 0.0) if pose is None else (float(v) for v in pose)
    ax, ay = np.radians(tx), np.radians(ty)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rot = ry @ rx
    pattern = cam.pattern
    img = (0.03 + 0.94 * (pattern.astype(np.float32) / 255.0))[..., None].repeat(3, axis=2)
    origin = (
        -(cam.W_pat - 1) / 2.0 * cam.pattern_pitch,
        -(cam.H_pat - 1) / 2.0 * cam.pattern_pitch,
    )
    tex = _Texture(np.ascontiguousarray(img), cam.pattern_pitch, origin)
    return _Plane(
        np.array([dx, dy, z]),
        rot @ np.array([0.0, 0.0, 1.0]),
        rot @ np.array([1.0, 0.0, 0.0]),
        None,
        tex,
        label=1,
    )


def _sample(tex: _Texture, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup at surface coordinates ``u, v`` (1-D) -> ``(n, 3)``.

    cv2.remap takes maps below 32767 on each side: the points are laid out in
    rows of 2048.
    """
    n = u.size
    width = 2048
    rows = max(1, -(-n // width))
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n] = (u - tex.origin[0]) / tex.texel
    my[:n] = (v - tex.origin[1]) / tex.texel
    out = cv2.remap(
        tex.image,
        mx.reshape(rows, width),
        my.reshape(rows, width),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT_101,
    )
    return out.reshape(rows * width, 3)[:n]


def trace(scene: Scene, x0: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersect rays ``P(Z) = (x0 - m Z, Z)`` with a scene.

    Returns the radiance ``(..., 3)`` float32, the depth ``Z`` and the label of
    the surface hit (0: nothing).
    """
    shape = x0.shape[:-1]
    if scene.white:
        return np.ones((*shape, 3), np.float32), np.full(shape, np.inf), np.zeros(shape, np.uint8)
    best = np.full(shape, np.inf)
    label = np.zeros(shape, np.uint8)
    hits: list[tuple[Any, np.ndarray]] = []
    for k, s in enumerate(scene.surfaces):
        if isinstance(s, _Plane):
            n = s.normal
            d = float(n @ s.point)
            den = n[2] - n[0] * m[..., 0] - n[1] * m[..., 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                Z = (d - n[0] * x0[..., 0] - n[1] * x0[..., 1]) / den
            ok = np.isfinite(Z) & (Z > 0)
            if s.extent is not None:
                u, v = _plane_uv(s, x0, m, Z)
                ok &= (
                    (u >= s.extent[0])
                    & (u <= s.extent[1])
                    & (v >= s.extent[2])
                    & (v <= s.extent[3])
                )
        else:
            c, r = s.centre, s.radius
            A0 = x0[..., 0] - c[0]
            A1 = x0[..., 1] - c[1]
            A2 = -c[2]
            Bx, By = -m[..., 0], -m[..., 1]
            a = Bx * Bx + By * By + 1.0
            b = Bx * A0 + By * A1 + A2
            cc = A0 * A0 + A1 * A1 + A2 * A2 - r * r
            disc = b * b - a * cc
            ok = disc >= 0
            with np.errstate(invalid="ignore"):
                Z = (-b - np.sqrt(np.where(ok, disc, 0.0))) / a
            ok &= Z > 0
        Z = np.where(ok, Z, np.inf)
        closer = best > Z
        best = np.where(closer, Z, best)
        label = np.where(closer, k + 1, label).astype(np.uint8)
        hits.append((s, Z))
    rad = np.zeros((*shape, 3), np.float32)
    for k, (s, Z) in enumerate(hits):
        sel = label == k + 1
        if not sel.any():
            continue
        xs, ms, zs = x0[sel], m[sel], Z[sel]
        if isinstance(s, _Plane):
            u, v = _plane_uv(s, xs, ms, zs)
            col = _sample(s.texture, u, v)
        else:
            X = xs[..., 0] - ms[..., 0] * zs
            Y = xs[..., 1] - ms[..., 1] * zs
            col = _sample(s.texture, X, Y)
            nrm = np.stack([X - s.centre[0], Y - s.centre[1], zs - s.centre[2]], -1) / s.radius
            light = np.array([-0.4, -0.5, -0.77])
            light /= np.linalg.norm(light)
            col = col * (0.55 + 0.45 * np.clip(nrm @ light, 0, 1))[:, None].astype(np.float32)
        rad[sel] = col
    out_label = np.zeros(shape, np.uint8)
    for k, s in enumerate(scene.surfaces):
        out_label[label == k + 1] = s.label
    return rad, best, out_label


def _plane_uv(
    s: _Plane, x0: np.ndarray, m: np.ndarray, Z: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    X = x0[..., 0] - m[..., 0] * Z - s.point[0]
    Y = x0[..., 1] - m[..., 1] * Z - s.point[1]
    Zr = Z - s.point[2]
    v_axis = np.cross(s.normal, s.u_axis)
    u = X * s.u_axis[0] + Y * s.u_axis[1] + Zr * s.u_axis[2]
    v = X * v_axis[0] + Y * v_axis[1] + Zr * v_axis[2]
    return u, v


# --------------------------------------------------------------------------
# Rendering raw frames
# --------------------------------------------------------------------------
class _Renderer:
    """Renders clean (noise-free) raw frames, one lenslet cell at a time.

    The cells tile the sensor and each baffle lies inside its cell with a dark
    gap around it, so rendering, blurring and integrating a cell on its own is
    exact.
    """

    def __init__(self, cam: SimulatedCamera) -> None:
        self.cam = cam
        self.ss = cam.cfg.supersample

    def cell_rays(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays of the supersamples of lenslet ``i``'s cell: ``x0, m`` and transmission."""
        cam, ss = self.cam, self.ss
        vw, vh = cam.cfg.view_size
        r, c = divmod(i, cam.C)
        ys = r * vh + (np.arange(vh * ss) + 0.5) / ss - 0.5
        xs = c * vw + (np.arange(vw * ss) + 0.5) / ss - 0.5
        gx, gy = np.meshgrid(xs, ys)
        a = cam.sensor_from_raw(np.stack([gx, gy], -1))
        bx0, by0, bx1, by1 = cam.baffle[i]
        inside = (a[..., 0] >= bx0) & (a[..., 0] <= bx1) & (a[..., 1] >= by0) & (a[..., 1] <= by1)
        x0, m = cam.ray_from_sensor(i, a)
        vig = cam.vignetting(x0) * inside * cam.transmission[i]
        return x0, m, vig

    def render(self, scene: Scene, threads: int = 2) -> np.ndarray:
        """Clean raw frame (H_raw, W_raw, 3) float32 in [0, 1] (before noise)."""
        cam, ss = self.cam, self.ss
        vw, vh = cam.cfg.view_size
        cast = np.asarray(cam.cfg.colour_cast, np.float32)
        gain = cam.cfg.exposure / float(cast.max())
        out = np.empty((cam.H_raw, cam.W_raw, 3), np.float32)
        sigma = cam.cfg.blur_sigma * ss

        def job(i: int) -> None:
            x0, m, vig = self.cell_rays(i)
            rad, _, _ = trace(scene, x0, m)
            img = rad * ((vig * gain)[..., None] * cast).astype(np.float32)
            if sigma > 0:
                img = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
            r, c = divmod(i, cam.C)
            out[r * vh : (r + 1) * vh, c * vw : (c + 1) * vw] = cv2.resize(
                img, (vw, vh), interpolation=cv2.INTER_AREA
            )

        with ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
            list(ex.map(job, range(cam.N)))
        return out


def add_noise(clean: np.ndarray, cfg: SimConfig, rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian sensor noise, quantisation and (optionally) a Bayer mosaic.

    Returns uint8 or uint16, ``(H, W, 3)`` or ``(H, W)`` for Bayer.
    """
    x = clean
    if cfg.bayer is not None:
        x = _mosaic(x, cfg.bayer)
    electrons = np.clip(x, 0, None) * cfg.full_well
    sd = np.sqrt(electrons + cfg.read_noise**2).astype(np.float32)
    noisy = (electrons + sd * rng.standard_normal(x.shape, dtype=np.float32)) / cfg.full_well
    top = 255 if cfg.bit_depth == 8 else 65535
    q = np.clip(np.round(noisy * top), 0, top)
    return q.astype(np.uint8 if cfg.bit_depth == 8 else np.uint16)


def _mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    chan = {"R": 0, "G": 1, "B": 2}
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        out[dy::2, dx::2] = rgb[dy::2, dx::2, chan[pattern[k]]]
    return out


# --------------------------------------------------------------------------
# Ground truth in the reference view's rectified frame
# --------------------------------------------------------------------------
def reference_rays(cam: SimulatedCamera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object-space rays of the reference view through rectified points ``uv``.

    Explicit: the board point's thin-lens image, the ray from it through the
    reference pinhole, where that ray crosses the lens, and its refraction.
    """
    B = cam.board_from_rect(uv)
    P = np.concatenate([B, np.full((*B.shape[:-1], 1), cam.z_b)], -1)
    Z = P[..., 2:3]
    zi = cam.f * Z / (Z - cam.f)
    xi = -P[..., :2] * zi / Z
    li = cam.l[cam.ref]
    x0 = li + (xi - li) * (cam.D / (cam.D - zi))  # the line through xi and li at w = 0
    m = (li - x0) / cam.D + x0 / cam.f
    return x0, m


def render_truth(
    cam: SimulatedCamera, scene: Scene, factor: int = 2, ss: int = 2
) -> dict[str, np.ndarray]:
    """Depth and labels at rectified resolution, and the ``factor``-times finer
    reference image (albedo under white light, box-integrated, no blur/noise/cast)."""
    vv, uu = np.mgrid[0 : cam.H_rect, 0 : cam.W_rect].astype(np.float64)
    x0, m = reference_rays(cam, np.stack([uu, vv], -1))
    _, depth, labels = trace(scene, x0, m)
    H2, W2 = cam.H_rect * factor, cam.W_rect * factor
    img = np.zeros((H2, W2, 3), np.float32)
    # Fine pixel U sits at rectified (U + 0.5) / factor - 0.5; its box is 1/factor wide.
    for k in range(ss):
        for j in range(ss):
            oy = (k + 0.5) / ss - 0.5
            ox = (j + 0.5) / ss - 0.5
            V, U = np.mgrid[0:H2, 0:W2].astype(np.float64)
            u = (U + 0.5 + ox) / factor - 0.5
            v = (V + 0.5 + oy) / factor - 0.5
            x0, m = reference_rays(cam, np.stack([u, v], -1))
            rad, _, _ = trace(scene, x0, m)
            img += rad
    img /= ss * ss
    return {"depth": depth.astype(np.float32), "labels": labels, "reference_2x": img}


# --------------------------------------------------------------------------
# The whole simulation
# --------------------------------------------------------------------------
