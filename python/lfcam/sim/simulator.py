"""``lfcam simulate``: a simulated camera's calibration folder, scene captures and
ground truth, written as a lab would hand them to lfcam.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io import CaptureMetadata, atomic_folder, write_dng, write_image
from .camera import SimConfig, SimulatedCamera
from .scenes import (
    Scene,
    _board_plane,
    _Renderer,
    add_noise,
    make_scene,
    render_truth,
)

__all__ = ["SimulationResult", "load_truth", "simulate"]


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
    zoom : dict
        Per zoom setting (focal length in mm), that setting's result.
    """

    root: Path
    calibration_dir: Path
    captures: dict[str, Path]
    truth_dir: Path
    camera: SimulatedCamera
    timings: dict[str, float]
    #: With ``zoom``: each setting's own result by focal length (mm): its calibration
    #: folder ``calibration/zoom_<f>mm``, captures ``<scene>_<f>mm``, truth
    #: ``truth/zoom_<f>mm``. Empty for a camera without zoom settings.
    zoom: dict[float, SimulationResult] = field(default_factory=dict)


#: Black level of the simulator's 8-bit DNGs (stored values are the sensor's plus this;
#: a 16-bit sensor's DNG has none, as its values fill the 16 bits).
DNG_BLACK_8BIT = 64


def _write_raw(path: Path, img: np.ndarray, cam: SimulatedCamera) -> None:
    cfg = cam.cfg
    if cfg.raw_format != "dng":
        write_image(path, img, compression=1)
        return
    assert cfg.bayer is not None
    black = DNG_BLACK_8BIT if img.dtype == np.uint8 else 0
    write_dng(
        path,
        img.astype(np.uint16) + np.uint16(black),
        cfg.bayer,
        black_level=black,
        white_level=black + int(np.iinfo(img.dtype).max),
        metadata=capture_metadata(cam),
    )


def capture_metadata(cam: SimulatedCamera) -> CaptureMetadata:
    """The EXIF metadata of the simulator's camera raw captures."""
    f = cam.cfg.focal_length
    return CaptureMetadata(
        focal_length_mm=round(f * 1e3, 3),
        exposure_s=0.01,
        iso=100.0,
        f_number=round(f / (2 * cam.aperture_radius), 2),
        make="lfcam",
        model=f"simulated {cam.R}x{cam.C} light-field camera",
    )


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
        captures/<scene>.png                  raw scene captures (.tiff, .dng: raw_format)
        truth/camera.npz                      crops, centres, warps, masks, offsets,
                                              z_b, z_c, b, l, f, D, g, board_poses
                                              (per distance: tilts about x, y in
                                              degrees, drift x, y in metres), ...
        truth/<scene>/depth.tiff              depth (metres) in the reference
                                              view's rectified frame
        truth/<scene>/labels.png              surface labels (0 none, 1 background)
        truth/<scene>/reference_2x.tiff       reference view at 2x rectified
                                              resolution, albedo, linear float32
        simulation.json                       the configuration and timings

    With ``zoom`` (focal lengths, mm), one setting per focal length:
    ``calibration/zoom_<f>mm/`` holds its pattern, camera.toml and boards (the white
    captures, the same for every setting of a parfocal zoom, stay in
    ``calibration/white/``), ``captures/<scene>_<f>mm.<ext>`` its captures and
    ``truth/zoom_<f>mm/`` its truth.

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
    with atomic_folder(out) as tmp:
        if not cfg.zoom:
            res = _simulate_setting(tmp, out, cfg, truth, say, timings)
        else:
            settings = {}
            for k, f in enumerate(cfg.zoom):
                say(f"zoom {f:g} mm")
                sub = f"zoom_{f:g}mm"
                settings[f] = _simulate_setting(
                    tmp,
                    out,
                    cfg.zoom_setting(f),
                    truth,
                    say,
                    timings,
                    cal_sub=sub,
                    truth_sub=sub,
                    capture_suffix=f"_{f:g}mm",
                    shared_white=k > 0,
                )
            first = settings[cfg.zoom[0]]
            res = SimulationResult(
                out,
                out / "calibration",
                {f"{n}_{f:g}mm": p for f, r in settings.items() for n, p in r.captures.items()},
                out / "truth",
                first.camera,
                timings,
                zoom=settings,
            )
        timings["total"] = time.perf_counter() - t_all
        cams = {f: r.camera for f, r in res.zoom.items()} or {None: res.camera}
        (tmp / "simulation.json").write_text(
            json.dumps(
                {
                    "config": cfg.to_dict(),
                    "settings": [
                        {
                            "focal_length_mm": None if f is None else f,
                            "z_b": c.z_b,
                            "z_c": c.z_c,
                            "pattern_pitch": c.pattern_pitch,
                            "rect_shape": [c.H_rect, c.W_rect],
                        }
                        for f, c in cams.items()
                    ],
                    "timings_s": timings,
                },
                indent=2,
            )
        )
    return res


def _simulate_setting(
    tmp: Path,
    out: Path,
    cfg: SimConfig,
    truth: bool,
    say: Callable[[str], None],
    timings: dict[str, float],
    *,
    cal_sub: str = "",
    truth_sub: str = "",
    capture_suffix: str = "",
    shared_white: bool = False,
) -> SimulationResult:
    """One optical setting: its calibration folder (``calibration/<cal_sub>``), captures
    and truth; the white captures go to ``calibration/white`` unless ``shared_white``
    (a parfocal zoom's settings see the same image circles)."""
    t0 = time.perf_counter()
    say("camera model")
    cam = SimulatedCamera(cfg)
    renderer = _Renderer(cam)
    # A zoom setting's noise has a stream of its own; one setting keeps the seed's.
    key = [0x401E, cfg.seed & 0xFFFFFFFF] + ([round(cfg.focal_length * 1e6)] if cal_sub else [])
    rng = np.random.default_rng(np.random.SeedSequence(key))
    ext = cfg.raw_format
    root = tmp / "calibration"
    cal = root / cal_sub if cal_sub else root
    cal.mkdir(parents=True, exist_ok=True)
    write_image(cal / "pattern.png", cam.pattern)
    rr, rc = cfg.reference_view
    (cal / "camera.toml").write_text(
        "# Written by lfcam simulate: what a lab would know about its camera.\n"
        f"grid = [{cfg.grid[0]}, {cfg.grid[1]}]\n"
        f"reference = [{rr}, {rc}]\n"
        f"pattern_pitch = {cam.pattern_pitch!r}  # metres per pattern pixel on the board\n"
        + (f'bayer = "{cfg.bayer}"\n' if cfg.bayer else "")
    )
    timings["camera"] = timings.get("camera", 0.0) + time.perf_counter() - t0

    if not shared_white:
        t0 = time.perf_counter()
        say("white captures")
        (root / "white").mkdir(exist_ok=True)
        clean = renderer.render(Scene("white", white=True))
        for k in range(cfg.white_captures):
            _write_raw(root / "white" / f"white_{k:02d}.{ext}", add_noise(clean, cfg, rng), cam)
        timings["white"] = timings.get("white", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    poses = cam.board_poses()
    for z, pose in zip(cfg.distances, poses):
        say(f"board at {z:g} m")
        folder = cal / f"board_{z:.2f}m"
        folder.mkdir()
        clean = renderer.render(Scene("board", [_board_plane(cam, z, pose)]))
        for k in range(cfg.captures_per_distance):
            _write_raw(folder / f"board_{k:02d}.{ext}", add_noise(clean, cfg, rng), cam)
    timings["boards"] = timings.get("boards", 0.0) + time.perf_counter() - t0

    t0 = time.perf_counter()
    (tmp / "captures").mkdir(exist_ok=True)
    captures: dict[str, Path] = {}
    scenes = {name: make_scene(name, cam, seed=cfg.seed) for name in cfg.scenes}
    for name, scene in scenes.items():
        say(f"scene {name}")
        clean = renderer.render(scene)
        p = tmp / "captures" / f"{name}{capture_suffix}.{ext}"
        _write_raw(p, add_noise(clean, cfg, rng), cam)
        captures[name] = out / "captures" / p.name
    timings["scenes"] = timings.get("scenes", 0.0) + time.perf_counter() - t0

    troot = tmp / "truth"
    tdir = troot / truth_sub if truth_sub else troot
    if truth:
        t0 = time.perf_counter()
        say("ground truth")
        tdir.mkdir(parents=True)
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
            board_poses=poses,
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
        timings["truth"] = timings.get("truth", 0.0) + time.perf_counter() - t0
    rel_cal = out / "calibration" / cal_sub if cal_sub else out / "calibration"
    rel_truth = out / "truth" / truth_sub if truth_sub else out / "truth"
    return SimulationResult(out, rel_cal, captures, rel_truth, cam, timings)


def load_truth(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Load ``truth/camera.npz`` written by :func:`simulate` (no pickles)."""
    with np.load(Path(path), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
