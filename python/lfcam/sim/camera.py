"""The simulated camera: an explicit forward model of the optics (docs/design.md,
"Camera model"), its configuration and its ground-truth geometry.

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
plane + parallax equation (docs/design.md, "Plane and parallax"); the tests check that the
traced geometry obeys it, with ``Z_c = f D / (D - f)`` and
``b_i = -l_i Z_c / D``.

Coordinates: X right, Y down, Z (depth) forward, metres. Raw pixel ``(x, y)``
is centred at integer coordinates; its box spans ``x +- 0.5``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..calibration.pattern import make_pattern
from ..errors import InputError
from ..io import BAYER_PATTERNS

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["SCENES", "SimConfig", "SimulatedCamera"]

SCENES = ("planes", "spheres", "layered", "board")


# --------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------
def _is_real(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _has_type(value: Any, annotation: str) -> bool:
    """Whether a config value matches its field's annotation (the few forms SimConfig uses)."""
    if annotation.endswith(" | None"):
        return value is None or _has_type(value, annotation[: -len(" | None")])
    if annotation == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation == "float":
        return _is_real(value)
    if annotation == "str":
        return isinstance(value, str)
    if annotation.startswith("tuple[") and isinstance(value, tuple):
        inner = [t.strip() for t in annotation[6:-1].split(",")]
        if inner[-1] == "...":
            return all(_has_type(v, inner[0]) for v in value)
        return len(value) == len(inner) and all(_has_type(v, t) for v, t in zip(value, inner))
    return False


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
    board_tilt : float
        Largest tilt of a calibration board, degrees: each distance's board is
        turned by a random angle between half this and this, about a random axis in
        its plane (seeded), as boards in a real lab are.
    board_drift : float
        Largest lateral drift of a calibration board, millimetres: each distance's
        board is moved sideways by a random amount between half this and this, in a
        random direction (seeded), as a rail does.
    zoom : tuple of float
        Focal lengths (mm) of a parfocal zoom's settings to simulate, each with its own
        calibration boards, captures and truth (:meth:`zoom_setting`); empty: the one
        setting ``focal_length``.
    raw_format : str
        ``png``, ``tiff`` or ``dng`` (camera raw: a Bayer mosaic with a black level
        and the EXIF focal length, exposure, ISO and aperture; needs ``bayer``).
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
    board_tilt: float = 0.0
    board_drift: float = 0.0
    zoom: tuple[float, ...] = ()
    raw_format: str = "png"
    seed: int = 0

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> InputError:
            return InputError(f"simulator config {name!r}: {why}")

        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not _has_type(value, str(f.type)):
                raise bad(f.name, f"expected {f.type}, got {value!r}")

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
        if self.raw_format not in ("png", "tiff", "dng"):
            raise bad("raw_format", f"must be 'png', 'tiff' or 'dng', got {self.raw_format!r}")
        if self.raw_format == "dng" and self.bayer is None:
            raise bad("raw_format", "a DNG holds a Bayer mosaic: give bayer (e.g. RGGB)")
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
        if not (0 <= self.board_tilt <= 20):
            raise bad("board_tilt", f"must be 0 to 20 degrees, got {self.board_tilt!r}")
        if not (0 <= self.board_drift <= 100):
            raise bad("board_drift", f"must be 0 to 100 mm, got {self.board_drift!r}")
        if self.zoom:
            if len(set(self.zoom)) != len(self.zoom) or not all(
                _is_real(f) and 5 <= f <= 1000 for f in self.zoom
            ):
                raise bad("zoom", f"need distinct focal lengths of 5 to 1000 mm, got {self.zoom!r}")
            for f in self.zoom:
                self.zoom_setting(f)
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

    def zoom_setting(self, focal_length_mm: float) -> SimConfig:
        """This camera at another setting of a parfocal zoom: the thin-lens equivalent of
        focal length ``focal_length_mm`` whose principal plane moves with it so that the
        reference distance's image stays where it was (the lenslets stay in focus):
        ``D' = f' Z_b / (Z_b - f') + (D - f Z_b / (Z_b - f))``."""
        f, d, z = self.focal_length, self.lens_to_lenslet, self.z_b
        f2 = focal_length_mm * 1e-3
        if not f2 < z:
            raise InputError(
                f"simulator config 'zoom': {focal_length_mm:g} mm is not shorter than Z_b = {z:g} m"
            )
        d2 = f2 * z / (z - f2) + (d - f * z / (z - f))
        return dataclasses.replace(self, focal_length=f2, lens_to_lenslet=d2, zoom=())

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
        except (TypeError, InputError) as exc:
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
        # Object-space optical centres (docs/design.md, "Camera model") -- truth only,
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
        """Rectified pixel -> lateral board position (metres) at ``Z_b`` (docs/design.md,
        "Pixel centres")."""
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

    def board_poses(self) -> np.ndarray:
        """Each calibration distance's board pose, ``(K, 4)`` in ``cfg.distances``' order:
        tilt about the x and y axes (degrees) and lateral drift x, y (metres); zero
        unless ``board_tilt`` / ``board_drift`` are set."""
        cfg = self.cfg
        rng = np.random.default_rng(np.random.SeedSequence([0xB0A4D, cfg.seed & 0xFFFFFFFF]))
        out = np.zeros((len(cfg.distances), 4))
        for k in range(len(cfg.distances)):
            phi, psi = rng.uniform(0, 2 * np.pi, 2)  # tilt axis, drift direction
            tilt = rng.uniform(0.5, 1) * cfg.board_tilt
            d = rng.uniform(0.5, 1) * cfg.board_drift * 1e-3
            out[k] = [tilt * np.cos(phi), tilt * np.sin(phi), d * np.cos(psi), d * np.sin(psi)]
        return out

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
