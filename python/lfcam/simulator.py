"""The lfcam camera simulator: an explicit forward model of DESIGN.md section 1.

Optics, front to back (light travels from the scene at depth ``Z`` > 0 towards
the sensor; ``w`` is the distance behind the front lens):

* a thin front lens of focal length ``f`` at ``w = 0`` with a circular aperture;
* ``R x C`` pinhole lenslets on the plane ``w = D`` (behind the intermediate
  image), lenslet ``i`` at lateral position ``l_i``;
* the sensor at ``w = D + g``. A baffle limits each lenslet's image to its own
  rectangle; the front aperture seen through the pinhole gives each view an
  image circle centred on ``l_i (1 + g/D)``, with vignetting.

Each lenslet also has a smooth, non-axial distortion of its own (radial about an
off-centre point, decentering, a random low-frequency displacement field, a
small rotation and scale): the mapping from the *actual* sensor position of a
ray to its *ideal* pinhole position is explicit; the forward direction is solved
by fixed-point iteration.

Rays are traced explicitly: sensor -> pinhole -> front lens (thin-lens
refraction, slope change ``x0 / f``) -> scene. Nothing here uses the
plane + parallax equation of DESIGN.md section 3; the tests check that the
traced geometry obeys it, with ``Z_c = f D / (D - f)`` and
``b_i = -l_i Z_c / D``.

Coordinates: X right, Y down, Z (depth) forward, metres. Raw pixel ``(x, y)``
is centred at integer coordinates; its box spans ``x +- 0.5``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import InputError
from .io import write_image
from .pattern import make_pattern, procedural_texture

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "BAYER_PATTERNS",
    "SCENES",
    "Scene",
    "SimConfig",
    "SimulatedCamera",
    "SimulationResult",
    "depth_accuracy",
    "make_scene",
    "simulate",
]

SCENES = ("planes", "spheres", "layered", "board")
BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


# --------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class SimConfig:
    """Parameters of a simulated camera and of what it captures.

    Every field has a realistic default (the reference camera: 3 x 4 lenslets,
    480 x 360 px views, f = 100 mm, D = 220 mm, so ``Z_c`` = 0.183 m).

    Attributes
    ----------
    grid : (int, int)
        Lenslet rows and columns.
    view_size : (int, int)
        Width and height of one lenslet's cell on the sensor, raw pixels.
        ``(1200, 900)`` is the full-size camera (about 1 Mpx views).
    focal_length, lens_to_lenslet, lenslet_to_sensor : float
        ``f``, ``D`` and ``g`` in metres (``D > f``).
    cell_width : float
        Width of one lenslet's cell on the sensor, metres (sets pixel pitch).
    reference : (int, int) or None
        Reference view (row, col); default the view nearest the array centre,
        ``((R - 1) // 2, (C - 1) // 2)``: (1, 1) for 3 x 4, as in the paper.
    image_circle : float
        Image-circle radius as a fraction of the cell's half diagonal (0.7: the
        circle is clipped by the baffle at the top and bottom of each cell).
    baffle_gap : float
        Dark gap between neighbouring cells, fraction of the cell size per side.
    lenslet_jitter : float
        Random lenslet position error, fraction of the lenslet pitch.
    rotation_jitter_deg, scale_jitter : float
        Per-lenslet image rotation (degrees) and scale (fraction), uniform +-.
    distortion : float
        Multiplier of the default per-lenslet distortion (0 = none).
    vignetting : float
        Relative fall-off of brightness at the image-circle edge.
    transmission_jitter : float
        Per-lenslet relative transmission error.
    colour_cast : (float, float, float)
        Relative RGB response to white light (illuminant times sensor).
    exposure : float
        Brightest white-target value, fraction of full scale.
    blur_sigma : float
        Gaussian optical blur, raw pixels.
    full_well, read_noise : float
        Electrons at full scale and read noise in electrons (Poisson-Gaussian).
    bit_depth : int
        8 or 16.
    bayer : str or None
        Bayer mosaic of the raw frames (RGGB, BGGR, GRBG, GBRG) or None for RGB.
    supersample : int
        Samples per raw pixel side (box-integrated pixels; >= 2 for real aliasing).
    distances : tuple of float
        Calibration board distances, metres. ``Z_b`` is the one nearest 1 m.
    captures_per_distance, white_captures : int
        Board captures per distance and white-target captures.
    scenes : tuple of str
        Scenes to capture: ``planes``, ``spheres``, ``layered``, ``board``.
    board_distance : float
        Distance of the test board scene (``board``), metres; default 1.12 m,
        not a calibration distance.
    raw_format : str
        ``png`` or ``tiff``.
    seed : int
        Everything random derives from this seed.
    """

    grid: tuple[int, int] = (3, 4)
    view_size: tuple[int, int] = (480, 360)
    focal_length: float = 0.100
    lens_to_lenslet: float = 0.220
    lenslet_to_sensor: float = 0.055
    cell_width: float = 6.0e-3
    reference: tuple[int, int] | None = None
    image_circle: float = 0.70
    baffle_gap: float = 0.03
    lenslet_jitter: float = 0.01
    rotation_jitter_deg: float = 0.8
    scale_jitter: float = 0.01
    distortion: float = 1.0
    vignetting: float = 0.35
    transmission_jitter: float = 0.04
    colour_cast: tuple[float, float, float] = (0.92, 1.0, 0.62)
    exposure: float = 0.85
    blur_sigma: float = 0.5
    full_well: float = 8000.0
    read_noise: float = 6.0
    bit_depth: int = 8
    bayer: str | None = None
    supersample: int = 2
    distances: tuple[float, ...] = (0.7, 1.0, 1.5)
    captures_per_distance: int = 5
    white_captures: int = 3
    scenes: tuple[str, ...] = ("planes", "spheres", "layered")
    board_distance: float = 1.12
    raw_format: str = "png"
    seed: int = 0

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> InputError:
            return InputError(f"simulator config {name!r}: {why}")

        r, c = self.grid
        if not (isinstance(r, int) and isinstance(c, int) and 1 <= r <= 16 and 1 <= c <= 16):
            raise bad("grid", f"expected two integers in 1..16, got {self.grid!r}")
        if r * c < 2:
            raise bad("grid", "a light-field camera needs at least 2 lenslets")
        w, h = self.view_size
        if not (isinstance(w, int) and isinstance(h, int) and 32 <= w <= 8192 and 32 <= h <= 8192):
            raise bad("view_size", f"expected two integers in 32..8192, got {self.view_size!r}")
        f, d, g = self.focal_length, self.lens_to_lenslet, self.lenslet_to_sensor
        if not (f > 0 and d > f and g > 0):
            raise bad("focal_length", f"need 0 < f < D and g > 0, got f={f}, D={d}, g={g}")
        if self.reference is not None:
            rr, rc = self.reference
            if not (0 <= rr < r and 0 <= rc < c):
                raise bad("reference", f"{self.reference!r} is outside the {r}x{c} grid")
        if self.bit_depth not in (8, 16):
            raise bad("bit_depth", f"must be 8 or 16, got {self.bit_depth!r}")
        if self.bayer is not None and self.bayer not in BAYER_PATTERNS:
            raise bad("bayer", f"must be one of {BAYER_PATTERNS} or None, got {self.bayer!r}")
        if self.raw_format not in ("png", "tiff"):
            raise bad("raw_format", f"must be 'png' or 'tiff', got {self.raw_format!r}")
        if not (1 <= self.supersample <= 8):
            raise bad("supersample", f"must be in 1..8, got {self.supersample!r}")
        if len(self.distances) < 1 or any(not (z > 2 * self.z_c) for z in self.distances):
            raise bad(
                "distances",
                f"need at least one distance, each beyond 2 * Z_c = {2 * self.z_c:.3f} m,"
                f" got {self.distances!r}",
            )
        if len(set(self.distances)) != len(self.distances):
            raise bad("distances", f"distances must differ, got {self.distances!r}")
        for s in self.scenes:
            if s not in SCENES:
                raise bad("scenes", f"unknown scene {s!r}; known: {', '.join(SCENES)}")
        if self.captures_per_distance < 1 or self.white_captures < 1:
            raise bad("captures_per_distance", "need at least one capture of each kind")
        if len(self.colour_cast) != 3 or min(self.colour_cast) <= 0:
            raise bad("colour_cast", f"need three positive numbers, got {self.colour_cast!r}")
        if not (0 < self.exposure <= 1):
            raise bad("exposure", f"must be in (0, 1], got {self.exposure!r}")

    # Derived optics -------------------------------------------------------
    @property
    def z_c(self) -> float:
        """Depth of the lenslets' object-space centres, ``f D / (D - f)``."""
        f, d = self.focal_length, self.lens_to_lenslet
        return f * d / (d - f)

    @property
    def z_b(self) -> float:
        """The reference board distance: the calibration distance nearest 1 m."""
        return min(self.distances, key=lambda z: (abs(z - 1.0), z))

    @property
    def reference_view(self) -> tuple[int, int]:
        r, c = self.grid
        return self.reference if self.reference is not None else ((r - 1) // 2, (c - 1) // 2)

    @property
    def reference_index(self) -> int:
        rr, rc = self.reference_view
        return rr * self.grid[1] + rc

    @property
    def raw_shape(self) -> tuple[int, int]:
        return (self.grid[0] * self.view_size[1], self.grid[1] * self.view_size[0])

    def replace(self, **changes: Any) -> SimConfig:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def full_size(cls, **changes: Any) -> SimConfig:
        """The full-size camera: 12 views of about 1 Mpx (1200 x 900)."""
        return cls(**{"view_size": (1200, 900), **changes})

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str], **changes: Any) -> SimConfig:
        """Read a configuration from a TOML file; ``changes`` override it.

        Keys are the field names; a ``[camera]`` table, if present, is merged
        into the top level. Unknown keys are an error.
        """
        p = Path(path)
        try:
            with p.open("rb") as fh:
                data = tomllib.load(fh)
        except FileNotFoundError:
            raise InputError(f"{p}: no such simulator config file") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"{p}: not valid TOML: {exc}") from None
        flat: dict[str, Any] = {k: v for k, v in data.items() if not isinstance(v, dict)}
        for v in data.values():
            if isinstance(v, dict):
                flat.update(v)
        return cls.from_dict(flat, source=str(p), **changes)

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], *, source: str = "config", **changes: Any
    ) -> SimConfig:
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise InputError(f"{source}: unknown simulator setting(s) {', '.join(unknown)}")
        kw: dict[str, Any] = {}
        for k, v in {**data, **changes}.items():
            if isinstance(v, list):
                v = tuple(v)
            kw[k] = v
        try:
            return cls(**kw)
        except TypeError as exc:
            raise InputError(f"{source}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


# --------------------------------------------------------------------------
# The camera
# --------------------------------------------------------------------------
class SimulatedCamera:
    """The explicit optical model of one simulated camera.

    All geometry is vectorised float64 numpy over trailing ``(..., 2)`` arrays
    of lateral positions in metres.

    Parameters
    ----------
    config : SimConfig
        Camera parameters; the random per-lenslet properties derive from
        ``config.seed``.
    """

    #: Default distortion strengths, in units of half a cell width.
    K1_RANGE = (0.015, 0.035)
    K2_MAX = 0.002
    DECENTER_MAX = 0.003
    FIELD_AMP = (0.002, 0.006)
    FIELD_TERMS = 4

    def __init__(self, config: SimConfig) -> None:
        self.cfg = cfg = config
        rng = np.random.default_rng(np.random.SeedSequence([0x51A, cfg.seed & 0xFFFFFFFF]))
        self.R, self.C = R, C = cfg.grid
        self.N = R * C
        self.f = cfg.focal_length
        self.D = cfg.lens_to_lenslet
        self.g = cfg.lenslet_to_sensor
        self.z_c = cfg.z_c
        self.z_b = cfg.z_b
        vw, vh = cfg.view_size
        self.pixel_pitch = cfg.cell_width / vw
        self.cell = np.array([cfg.cell_width, vh * self.pixel_pitch])
        self.H_raw, self.W_raw = cfg.raw_shape
        self.unit = cfg.cell_width / 2.0  # distortion normalisation
        mag = 1.0 + self.g / self.D
        # Lenslet positions (pinholes) on the lenslet plane.
        rows, cols = np.meshgrid(np.arange(R), np.arange(C), indexing="ij")
        nominal = np.stack(
            [
                (cols.ravel() - (C - 1) / 2.0) * self.cell[0],
                (rows.ravel() - (R - 1) / 2.0) * self.cell[1],
            ],
            axis=1,
        )
        jitter = rng.uniform(-1, 1, (self.N, 2)) * cfg.lenslet_jitter * self.cell / mag
        self.l = nominal / mag + jitter  # (N, 2)
        self.pp = self.l * mag  # ideal image of the front lens centre on the sensor
        # Baffles (physical rectangles on the sensor, actual coordinates).
        half = self.cell * (0.5 - cfg.baffle_gap)
        self.baffle = np.concatenate([self.pp - half, self.pp + half], axis=1)  # (N, 4)
        # Front aperture radius from the image-circle radius on the sensor.
        r_img = cfg.image_circle * 0.5 * float(np.hypot(*self.cell))
        self.aperture_radius = r_img * self.D / self.g
        # Per-lenslet distortion (normalised units).
        s = cfg.distortion
        self.k1 = rng.uniform(*self.K1_RANGE, self.N) * rng.choice([-1.0, 1.0], self.N) * s
        self.k2 = rng.uniform(-1, 1, self.N) * self.K2_MAX * s
        self.dc = rng.uniform(-1, 1, (self.N, 2)) * self.DECENTER_MAX * s
        self.rc = rng.uniform(-0.4, 0.4, (self.N, 2))  # off-centre radial centre
        K = self.FIELD_TERMS
        ang = rng.uniform(0, 2 * np.pi, (self.N, K))
        freq = rng.uniform(0.12, 0.45, (self.N, K))
        self.fw = np.stack([freq * np.cos(ang), freq * np.sin(ang)], axis=2)  # cycles per unit
        amp_ang = rng.uniform(0, 2 * np.pi, (self.N, K))
        amp = rng.uniform(*self.FIELD_AMP, (self.N, K)) * s
        self.fa = np.stack([amp * np.cos(amp_ang), amp * np.sin(amp_ang)], axis=2)
        self.fp = rng.uniform(0, 2 * np.pi, (self.N, K))
        th = np.deg2rad(rng.uniform(-1, 1, self.N) * cfg.rotation_jitter_deg)
        sc = 1.0 + rng.uniform(-1, 1, self.N) * cfg.scale_jitter
        self.M = np.stack(
            [
                np.stack([sc * np.cos(th), -sc * np.sin(th)], 1),
                np.stack([sc * np.sin(th), sc * np.cos(th)], 1),
            ],
            axis=1,
        )  # (N, 2, 2)
        self.Minv = np.linalg.inv(self.M)
        self.transmission = 1.0 + rng.uniform(-1, 1, self.N) * cfg.transmission_jitter
        # Object-space optical centres (DESIGN.md section 1) -- truth only,
        # never used for tracing.
        self.b = -self.l * self.z_c / self.D
        self.ref = cfg.reference_index
        self._pattern_geometry()

    # -- sensor <-> raw pixels ---------------------------------------------
    def sensor_from_raw(self, xy: np.ndarray) -> np.ndarray:
        """Raw pixel coordinates -> sensor position (metres)."""
        xy = np.asarray(xy, np.float64)
        off = np.array([(self.W_raw - 1) / 2.0, (self.H_raw - 1) / 2.0])
        return (xy - off) * self.pixel_pitch

    def raw_from_sensor(self, a: np.ndarray) -> np.ndarray:
        off = np.array([(self.W_raw - 1) / 2.0, (self.H_raw - 1) / 2.0])
        return np.asarray(a, np.float64) / self.pixel_pitch + off

    # -- distortion ---------------------------------------------------------
    def _delta(self, i: np.ndarray | int, an: np.ndarray, jacobian: bool = False) -> Any:
        """Distortion displacement at normalised actual position ``an``.

        With ``jacobian``, also returns its ``(..., 2, 2)`` derivative. Written
        component by component: numpy reductions over tiny trailing axes are slow.
        """
        x, y = an[..., 0], an[..., 1]
        dx, dy = x - self.rc[i, 0], y - self.rc[i, 1]
        r2 = dx * dx + dy * dy
        k1, k2 = self.k1[i], self.k2[i]
        rad_f = k1 * r2 + k2 * r2 * r2
        p1, p2 = self.dc[i, 0], self.dc[i, 1]
        rr = x * x + y * y
        ox = rad_f * dx + 2 * p1 * x * y + p2 * (rr + 2 * x * x)
        oy = rad_f * dy + p1 * (rr + 2 * y * y) + 2 * p2 * x * y
        if jacobian:
            g = 2 * k1 + 4 * k2 * r2
            jxx = rad_f + g * dx * dx + 2 * p1 * y + 6 * p2 * x
            jxy = g * dx * dy + 2 * p1 * x + 2 * p2 * y
            jyx = g * dx * dy + 2 * p1 * x + 2 * p2 * y
            jyy = rad_f + g * dy * dy + 6 * p1 * y + 2 * p2 * x
        for k in range(self.FIELD_TERMS):
            wx, wy = self.fw[i, k, 0], self.fw[i, k, 1]
            ax, ay = self.fa[i, k, 0], self.fa[i, k, 1]
            ph = 2 * np.pi * (x * wx + y * wy) + self.fp[i, k]
            sn = np.sin(ph)
            ox = ox + ax * sn
            oy = oy + ay * sn
            if jacobian:
                cs = 2 * np.pi * np.cos(ph)
                jxx = jxx + ax * cs * wx
                jxy = jxy + ax * cs * wy
                jyx = jyx + ay * cs * wx
                jyy = jyy + ay * cs * wy
        delta = np.stack([ox, oy], -1)
        if not jacobian:
            return delta
        return delta, (jxx, jxy, jyx, jyy)

    def ideal_from_actual(self, i: np.ndarray | int, a: np.ndarray) -> np.ndarray:
        """Actual sensor position of a ray -> its ideal pinhole position (explicit)."""
        an = (a - self.pp[i]) / self.unit
        v = an + self._delta(i, an)
        q = np.einsum("...ij,...j->...i", self.M[i], v)
        return self.pp[i] + q * self.unit

    #: Beyond this normalised radius a position is far outside its view (whose
    #: corners are at 1.25): there the inverse is not computed and is NaN.
    DOMAIN = 2.0

    def actual_from_ideal(
        self, i: np.ndarray | int, q: np.ndarray, tol: float = 1e-12
    ) -> np.ndarray:
        """Inverse of :meth:`ideal_from_actual` by Newton's method.

        Positions far outside the view (where the inverse is not needed) are NaN.
        """
        q = np.asarray(q, np.float64)
        i_arr = np.broadcast_to(np.asarray(i), q.shape[:-1])
        v = np.einsum("...ij,...j->...i", self.Minv[i_arr], (q - self.pp[i_arr]) / self.unit)
        near = v[..., 0] ** 2 + v[..., 1] ** 2 <= self.DOMAIN**2  # False for NaN too
        out = np.full(q.shape, np.nan)
        vv = v[near]
        ii = i if np.ndim(i) == 0 else i_arr[near]
        an = vv.copy()
        act = np.arange(len(vv))  # elements still moving
        with np.errstate(all="ignore"):
            for _ in range(40):
                ia = ii if np.ndim(ii) == 0 else ii[act]
                a_act = an[act]
                delta, (jxx, jxy, jyx, jyy) = self._delta(ia, a_act, jacobian=True)
                rx = a_act[:, 0] + delta[:, 0] - vv[act, 0]
                ry = a_act[:, 1] + delta[:, 1] - vv[act, 1]
                jxx += 1.0
                jyy += 1.0
                det = jxx * jyy - jxy * jyx
                sx = (jyy * rx - jxy * ry) / det
                sy = (jxx * ry - jyx * rx) / det
                an[act, 0] -= sx
                an[act, 1] -= sy
                act = act[np.maximum(np.abs(sx), np.abs(sy)) >= tol]
                if not act.size:
                    break
            res = np.abs(an + self._delta(ii, an) - vv).max(-1)
        an[~(res < 1e-9)] = np.nan
        pp = self.pp[i] if np.ndim(i) == 0 else self.pp[ii]
        out[near] = pp + an * self.unit
        return out

    # -- rays -----------------------------------------------------------------
    def ray_from_sensor(self, i: np.ndarray | int, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Trace the ray that reaches actual sensor position ``a`` back into the scene.

        Returns ``(x0, m)``: the ray crosses the front lens plane at ``x0`` and
        the scene point at depth ``Z`` is ``x0 - m Z``.
        """
        q = self.ideal_from_actual(i, a)
        li = self.l[i]
        x0 = li + (li - q) * (self.D / self.g)  # pinhole ray continued to the lens
        m_img = (li - x0) / self.D  # image-side slope dx/dw
        m = m_img + x0 / self.f  # thin-lens refraction
        return x0, m

    def project(self, i: np.ndarray | int, P: np.ndarray) -> np.ndarray:
        """Actual sensor position (metres) of scene point ``P = (X, Y, Z)`` in view ``i``.

        Thin-lens imaging (1/Z + 1/z' = 1/f, x' = -X z'/Z), then the pinhole.
        """
        P = np.asarray(P, np.float64)
        Z = P[..., 2:3]
        zi = self.f * Z / (Z - self.f)
        xi = -P[..., :2] * zi / Z
        li = self.l[i]
        q = li + (li - xi) * (self.g / (self.D - zi))
        return self.actual_from_ideal(i, q)

    def lens_point(self, i: np.ndarray | int, a: np.ndarray) -> np.ndarray:
        """Where the ray to actual sensor position ``a`` crosses the front lens."""
        q = self.ideal_from_actual(i, a)
        li = self.l[i]
        return li + (li - q) * (self.D / self.g)

    # -- the board and the rectified frame -------------------------------------
    def _pattern_geometry(self) -> None:
        """Size the calibration pattern to cover every view at ``Z_b``, with margin."""
        # Pitch: one pattern pixel ~ one raw pixel at the reference view's centre.
        i = self.ref
        c = self.optical_centre_sensor(i)
        eps = self.pixel_pitch
        pts = np.array([c, c + np.array([eps, 0.0])])
        x0, m = self.ray_from_sensor(i, pts)
        B = x0 - m * self.z_b
        self.pattern_pitch = float(np.hypot(*(B[1] - B[0])))
        # Extent: the union of every view's baffle at Z_b.
        ext = np.zeros(2)
        for j in range(self.N):
            bx0, by0, bx1, by1 = self.baffle[j]
            t = np.linspace(0, 1, 33)
            edge = np.concatenate(
                [
                    np.stack([bx0 + (bx1 - bx0) * t, np.full_like(t, by0)], 1),
                    np.stack([bx0 + (bx1 - bx0) * t, np.full_like(t, by1)], 1),
                    np.stack([np.full_like(t, bx0), by0 + (by1 - by0) * t], 1),
                    np.stack([np.full_like(t, bx1), by0 + (by1 - by0) * t], 1),
                ]
            )
            x0, m = self.ray_from_sensor(j, edge)
            B = x0 - m * self.z_b
            ext = np.maximum(ext, np.abs(B).max(0))
        margin = 1.06
        self.W_pat = int(2 * math.ceil(ext[0] * margin / self.pattern_pitch))
        self.H_pat = int(2 * math.ceil(ext[1] * margin / self.pattern_pitch))
        self.W_rect, self.H_rect = self.W_pat, self.H_pat  # scale 1
        self.rect_pitch = self.pattern_pitch * self.W_pat / self.W_rect
        self.offsets = (self.b - self.b[self.ref]) / self.rect_pitch

    @functools.cached_property
    def pattern(self) -> np.ndarray:
        """The digital calibration pattern shown on the board, ``(H_pat, W_pat)`` uint8."""
        return make_pattern(self.W_pat, self.H_pat, seed=self.cfg.seed)

    def board_from_rect(self, uv: np.ndarray) -> np.ndarray:
        """Rectified pixel -> lateral board position (metres) at ``Z_b`` (DESIGN.md section 2)."""
        uv = np.asarray(uv, np.float64)
        sx, sy = self.W_pat / self.W_rect, self.H_pat / self.H_rect
        xp = (uv[..., 0] + 0.5) * sx - 0.5
        yp = (uv[..., 1] + 0.5) * sy - 0.5
        return np.stack(
            [
                (xp - (self.W_pat - 1) / 2.0) * self.pattern_pitch,
                (yp - (self.H_pat - 1) / 2.0) * self.pattern_pitch,
            ],
            -1,
        )

    def rect_from_board(self, B: np.ndarray) -> np.ndarray:
        B = np.asarray(B, np.float64)
        xp = B[..., 0] / self.pattern_pitch + (self.W_pat - 1) / 2.0
        yp = B[..., 1] / self.pattern_pitch + (self.H_pat - 1) / 2.0
        return np.stack(
            [
                (xp + 0.5) * self.W_rect / self.W_pat - 0.5,
                (yp + 0.5) * self.H_rect / self.H_pat - 0.5,
            ],
            -1,
        )

    def rect_from_sensor(self, i: np.ndarray | int, a: np.ndarray) -> np.ndarray:
        """Actual sensor position in view ``i`` -> rectified coordinates (via the board)."""
        x0, m = self.ray_from_sensor(i, a)
        return self.rect_from_board(x0 - m * self.z_b)

    def optical_centre_sensor(self, i: int) -> np.ndarray:
        """Actual sensor position of the ray through the front lens centre (image-circle centre)."""
        return self.actual_from_ideal(i, self.pp[i])

    # -- truth for calibration ----------------------------------------------------
    def lit_boxes(self) -> np.ndarray:
        """Bounding boxes ``(left, top, right, bottom)`` of each view's lit region.

        In continuous raw-pixel coordinates (pixel ``x`` spans ``x +- 0.5``): the
        part of the (distorted) image circle inside the baffle.
        """
        t = np.linspace(0.0, 2 * np.pi, 4096, endpoint=False)
        ring = self.circle_radius * np.stack([np.cos(t), np.sin(t)], 1)
        s = np.linspace(0.0, 1.0, 2049)
        out = np.empty((self.N, 4))
        for i in range(self.N):
            bx0, by0, bx1, by1 = self.baffle[i]
            a = self.actual_from_ideal(i, self.pp[i] + ring)
            with np.errstate(invalid="ignore"):
                a = a[(a[:, 0] >= bx0) & (a[:, 0] <= bx1) & (a[:, 1] >= by0) & (a[:, 1] <= by1)]
            edges = np.concatenate(
                [
                    np.stack([bx0 + (bx1 - bx0) * s, np.full_like(s, by0)], 1),
                    np.stack([bx0 + (bx1 - bx0) * s, np.full_like(s, by1)], 1),
                    np.stack([np.full_like(s, bx0), by0 + (by1 - by0) * s], 1),
                    np.stack([np.full_like(s, bx1), by0 + (by1 - by0) * s], 1),
                ]
            )
            q = self.ideal_from_actual(i, edges)
            inside = ((q - self.pp[i]) ** 2).sum(1) <= self.circle_radius**2
            pts = self.raw_from_sensor(np.concatenate([a, edges[inside]]))
            out[i] = [pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max()]
        return out

    def crops(self) -> np.ndarray:
        """True crop rectangles ``(x0, y0, w, h)``, all of one size.

        The rule a measurement can follow: each crop is centred on its view's lit
        bounding box (:meth:`lit_boxes`); the common size is the smallest box's,
        less one pixel, so every crop's pixels lie whole inside their lit box.
        """
        box = self.lit_boxes()
        w = int(np.floor((box[:, 2] - box[:, 0]).min())) - 1
        h = int(np.floor((box[:, 3] - box[:, 1]).min())) - 1
        x0 = np.round((box[:, 0] + box[:, 2]) / 2 - (w - 1) / 2).astype(np.int64)
        y0 = np.round((box[:, 1] + box[:, 3]) / 2 - (h - 1) / 2).astype(np.int64)
        return np.stack([x0, y0, np.full_like(x0, w), np.full_like(y0, h)], 1)

    @property
    def circle_radius(self) -> float:
        """Image-circle radius on the sensor (ideal coordinates), metres."""
        return self.aperture_radius * self.g / self.D

    def centres(self) -> np.ndarray:
        """True image-circle centres in raw pixels, as a measurement can define them.

        The circle (the front aperture seen through the pinhole) is distorted and
        partly hidden by the baffle: its centre is the least-squares circle
        through the visible part of its edge. With non-axial distortion this is
        a few pixels from the optical centre (:meth:`optical_centres`).
        """
        t = np.linspace(0.0, 2 * np.pi, 1440, endpoint=False)
        ring = self.circle_radius * np.stack([np.cos(t), np.sin(t)], 1)
        out = np.empty((self.N, 2))
        for i in range(self.N):
            a = self.actual_from_ideal(i, self.pp[i] + ring)
            bx0, by0, bx1, by1 = self.baffle[i]
            with np.errstate(invalid="ignore"):
                vis = (a[:, 0] > bx0) & (a[:, 0] < bx1) & (a[:, 1] > by0) & (a[:, 1] < by1)
            xy = self.raw_from_sensor(a[vis])
            A = np.column_stack([2 * xy, np.ones(len(xy))])
            sol = np.linalg.lstsq(A, (xy**2).sum(1), rcond=None)[0]
            out[i] = sol[:2]
        return out

    def optical_centres(self) -> np.ndarray:
        """Raw-pixel position of the ray through the front lens centre, per view."""
        return np.stack(
            [self.raw_from_sensor(self.optical_centre_sensor(i)) for i in range(self.N)]
        )

    def vignetting(self, x0: np.ndarray) -> np.ndarray:
        """Transmission of a ray crossing the front lens at ``x0`` (0 outside the aperture)."""
        rho2 = (x0**2).sum(-1) / self.aperture_radius**2
        return np.where(rho2 <= 1.0, 1.0 - self.cfg.vignetting * rho2, 0.0)

    def warps(self, margin: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
        """True warp maps and masks.

        Returns
        -------
        warps : (N, H_rect, W_rect, 2) float32
            For each rectified pixel, the x, y position in view i's crop (NaN far
            outside the view).
        masks : (N, H_rect, W_rect) bool
            Where view i sees the rectified pixel: at least ``margin`` raw pixels
            inside its crop and inside its image circle (so a bilinear sample
            reads only fully lit pixels).
        """
        crops = self.crops()
        vv, uu = np.mgrid[0 : self.H_rect, 0 : self.W_rect].astype(np.float64)
        B = self.board_from_rect(np.stack([uu, vv], -1))
        P = np.concatenate([B, np.full((*B.shape[:-1], 1), self.z_b)], -1)
        warps = np.empty((self.N, self.H_rect, self.W_rect, 2), np.float32)
        masks = np.empty((self.N, self.H_rect, self.W_rect), bool)
        r_in = 1.0 - margin * self.pixel_pitch / self.circle_radius
        for i in range(self.N):
            a = self.project(i, P)
            xy = self.raw_from_sensor(a) - crops[i, :2]
            warps[i] = xy
            w, h = crops[i, 2], crops[i, 3]
            lo, hx, hy = margin - 1.0, w - margin, h - margin
            with np.errstate(invalid="ignore"):
                inside = (
                    (xy[..., 0] >= lo)
                    & (xy[..., 0] <= hx)
                    & (xy[..., 1] >= lo)
                    & (xy[..., 1] <= hy)
                )
                x0 = self.lens_point(i, a)
                rho2 = (x0**2).sum(-1) / self.aperture_radius**2
                masks[i] = inside & (rho2 <= r_in**2)
        return warps, masks


# --------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------
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


def _board_plane(cam: SimulatedCamera, z: float) -> _Plane:
    """The calibration pattern shown on a flat, fronto-parallel board at depth ``z``."""
    pattern = cam.pattern
    img = (0.03 + 0.94 * (pattern.astype(np.float32) / 255.0))[..., None].repeat(3, axis=2)
    origin = (
        -(cam.W_pat - 1) / 2.0 * cam.pattern_pitch,
        -(cam.H_pat - 1) / 2.0 * cam.pattern_pitch,
    )
    tex = _Texture(np.ascontiguousarray(img), cam.pattern_pitch, origin)
    return _Plane(
        np.array([0.0, 0.0, z]),
        np.array([0.0, 0.0, 1.0]),
        np.array([1.0, 0.0, 0.0]),
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
@dataclass
class SimulationResult:
    """What :func:`simulate` wrote, and the camera's ground truth.

    Attributes
    ----------
    root : pathlib.Path
        The output folder.
    calibration_dir : pathlib.Path
        ``root / "calibration"``: the folder ``lfcam calibrate`` reads.
    captures : dict
        Scene name -> raw capture path.
    truth_dir : pathlib.Path
        ``root / "truth"``: ``camera.npz`` and one folder of ground truth per scene.
    camera : SimulatedCamera
        The simulated camera (for its explicit geometry).
    timings : dict
        Seconds per stage.
    """

    root: Path
    calibration_dir: Path
    captures: dict[str, Path]
    truth_dir: Path
    camera: SimulatedCamera
    timings: dict[str, float]


def _write_raw(path: Path, img: np.ndarray) -> None:
    write_image(path, img, compression=1)


def simulate(
    out_dir: str | os.PathLike[str],
    config: SimConfig | None = None,
    *,
    overwrite: bool = False,
    truth: bool = True,
    progress: Callable[[str], None] | None = None,
    **changes: Any,
) -> SimulationResult:
    """Simulate a camera: write a calibration folder and captures with ground truth.

    Layout written under ``out_dir``::

        calibration/pattern.png               the digital pattern
        calibration/camera.toml               grid, reference view, pattern pitch
        calibration/white/white_NN.png        white-target captures
        calibration/board_<d>m/board_NN.png   pattern captures per distance
        captures/<scene>.png                  raw scene captures
        truth/camera.npz                      crops, centres, warps, masks, offsets,
                                              z_b, z_c, b, l, f, D, g, ...
        truth/<scene>/depth.tiff              depth (metres) in the reference
                                              view's rectified frame
        truth/<scene>/labels.png              surface labels (0 none, 1 background)
        truth/<scene>/reference_2x.tiff       reference view at 2x rectified
                                              resolution, albedo, linear float32
        simulation.json                       the configuration and timings

    The folder is assembled under a temporary name and renamed at the end, so a
    failed run leaves nothing half-written.

    Parameters
    ----------
    out_dir : path
        Output folder; must not exist or be empty unless ``overwrite``.
    config : SimConfig, optional
        Camera and capture parameters (default: the reference camera).
    overwrite : bool
        Replace an existing non-empty ``out_dir``.
    truth : bool
        Also compute the ground truth (warps, depth, 2x reference).
    progress : callable, optional
        Called with a short description before each step.
    **changes
        Overrides of ``config`` fields, e.g. ``seed=3, grid=(3, 3)``.

    Returns
    -------
    SimulationResult

    Examples
    --------
    >>> import lfcam
    >>> res = lfcam.simulate("sim", seed=1)          # doctest: +SKIP
    >>> sorted(res.captures)                          # doctest: +SKIP
    ['layered', 'planes', 'spheres']
    """
    cfg = config if config is not None else SimConfig()
    if changes:
        cfg = cfg.replace(**changes)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise InputError(f"{out}: folder is not empty (use overwrite=True / --overwrite)")
    say = progress or (lambda _msg: None)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        t0 = time.perf_counter()
        say("camera model")
        cam = SimulatedCamera(cfg)
        renderer = _Renderer(cam)
        rng = np.random.default_rng(np.random.SeedSequence([0x401E, cfg.seed & 0xFFFFFFFF]))
        ext = "png" if cfg.raw_format == "png" else "tiff"
        cal = tmp / "calibration"
        (cal / "white").mkdir(parents=True)
        write_image(cal / "pattern.png", cam.pattern)
        rr, rc = cfg.reference_view
        (cal / "camera.toml").write_text(
            "# Written by lfcam simulate: what a lab would know about its camera.\n"
            f"grid = [{cfg.grid[0]}, {cfg.grid[1]}]\n"
            f"reference = [{rr}, {rc}]\n"
            f"pattern_pitch = {cam.pattern_pitch!r}  # metres per pattern pixel on the board\n"
            + (f'bayer = "{cfg.bayer}"\n' if cfg.bayer else "")
        )
        timings["camera"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        say("white captures")
        clean = renderer.render(Scene("white", white=True))
        for k in range(cfg.white_captures):
            _write_raw(cal / "white" / f"white_{k:02d}.{ext}", add_noise(clean, cfg, rng))
        timings["white"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        for z in cfg.distances:
            say(f"board at {z:g} m")
            folder = cal / f"board_{z:.2f}m"
            folder.mkdir()
            clean = renderer.render(Scene("board", [_board_plane(cam, z)]))
            for k in range(cfg.captures_per_distance):
                _write_raw(folder / f"board_{k:02d}.{ext}", add_noise(clean, cfg, rng))
        timings["boards"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        (tmp / "captures").mkdir()
        captures: dict[str, Path] = {}
        scenes = {name: make_scene(name, cam, seed=cfg.seed) for name in cfg.scenes}
        for name, scene in scenes.items():
            say(f"scene {name}")
            clean = renderer.render(scene)
            p = tmp / "captures" / f"{name}.{ext}"
            _write_raw(p, add_noise(clean, cfg, rng))
            captures[name] = out / "captures" / p.name
        timings["scenes"] = time.perf_counter() - t0

        if truth:
            t0 = time.perf_counter()
            say("ground truth")
            tdir = tmp / "truth"
            tdir.mkdir()
            # The warps and each scene's truth are independent: numpy and OpenCV
            # release the GIL in their large operations, so threads overlap.
            with ThreadPoolExecutor(max_workers=2) as ex:
                fut_warps = ex.submit(cam.warps)
                fut_truth = {
                    name: ex.submit(render_truth, cam, scene) for name, scene in scenes.items()
                }
                warps, masks = fut_warps.result()
                truths = {name: f.result() for name, f in fut_truth.items()}
            np.savez_compressed(
                tdir / "camera.npz",
                grid=np.array(cfg.grid),
                reference=np.array(cam.ref),
                raw_shape=np.array([cam.H_raw, cam.W_raw]),
                rect_shape=np.array([cam.H_rect, cam.W_rect]),
                pattern_shape=np.array([cam.H_pat, cam.W_pat]),
                pattern_pitch=np.array(cam.pattern_pitch),
                rect_pitch=np.array(cam.rect_pitch),
                crops=cam.crops(),
                centres=cam.centres(),
                optical_centres=cam.optical_centres(),
                warps=warps,
                masks=masks,
                offsets=cam.offsets,
                z_b=np.array(cam.z_b),
                z_c=np.array(cam.z_c),
                distances=np.array(cfg.distances),
                b=cam.b,
                l=cam.l,
                f=np.array(cam.f),
                D=np.array(cam.D),
                g=np.array(cam.g),
                colour_cast=np.array(cfg.colour_cast),
            )
            for name, t in truths.items():
                sd = tdir / name
                sd.mkdir()
                write_image(sd / "depth.tiff", t["depth"])
                write_image(sd / "labels.png", t["labels"])
                write_image(sd / "reference_2x.tiff", t["reference_2x"])
            timings["truth"] = time.perf_counter() - t0

        timings["total"] = time.perf_counter() - t_all
        (tmp / "simulation.json").write_text(
            json.dumps(
                {
                    "config": cfg.to_dict(),
                    "z_b": cam.z_b,
                    "z_c": cam.z_c,
                    "pattern_pitch": cam.pattern_pitch,
                    "rect_shape": [cam.H_rect, cam.W_rect],
                    "timings_s": timings,
                },
                indent=2,
            )
        )
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SimulationResult(out, out / "calibration", captures, out / "truth", cam, timings)


def load_truth(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Load ``truth/camera.npz`` written by :func:`simulate` (no pickles)."""
    with np.load(Path(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def depth_accuracy(
    depth: np.ndarray, truth: np.ndarray, seen: np.ndarray
) -> tuple[float, float, float]:
    """Depth against the simulator's truth, as ``lfcam demo`` reports it.

    Over the pixels the reference view ``seen`` (all of them, occlusion bands
    included): the median of ``|Z - Z_true| / Z_true``, the share of pixels off by
    more than 5%, and the coverage (share with a finite error).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.abs(depth - truth) / truth
    ok = seen & np.isfinite(rel)
    return float(np.median(rel[ok])), float((rel[ok] > 0.05).mean()), float(ok.sum() / seen.sum())
