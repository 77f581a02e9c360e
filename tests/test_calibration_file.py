"""The Calibration type and the .lfcal (HDF5) file: round trip, layout, atomic save, and
every way a file can be bad."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

import lfcam
from lfcam.calibration import FORMAT_VERSION, Calibration, info
from lfcam.calibration.file import _seal
from lfcam.errors import CalibrationError, InputError, LfcamWarning
from lfcam.io import file_hash

R, C = 3, 4
N = R * C
H_RAW, W_RAW = 120, 200
H_RECT, W_RECT = 40, 50
REF = 5  # row 1, col 1

ARRAYS = ("crops", "centres", "warps", "masks", "offsets", "distances", "gains")
SCALARS = (
    "grid",
    "reference",
    "raw_shape",
    "rect_shape",
    "pattern_shape",
    "scale",
    "z_b",
    "z_c",
    "metric",
    "pattern_pitch",
    "bayer",
    "report",
    "software_version",
)
DATASETS = {
    "grid",
    "reference",
    "raw_shape",
    "rect_shape",
    "pattern_shape",
    "scale",
    "crops",
    "centres",
    "warps",
    "masks",
    "offsets",
    "z_b",
    "z_c",
    "metric",
    "distances",
    "pattern_pitch",
    "gains",
    "bayer",
    "report",
    "focal_length",
}


def make_values(*, metric: bool = True, seed: int = 0) -> dict[str, Any]:
    """Constructor arguments of a small, valid, synthetic calibration."""
    rng = np.random.default_rng(seed)
    crops = np.array([[c * 50, r * 40, 50, 40] for r in range(R) for c in range(C)], np.int64)
    masks = rng.random((N, H_RECT, W_RECT)) > 0.25
    warps = (rng.random((N, H_RECT, W_RECT, 2)) * [49, 39]).astype(np.float32)
    warps[~masks] = np.nan
    warps[0, 0, 0] = [1.5, 2.5]  # a finite value outside the mask is allowed too
    masks[0, 0, 0] = False
    offsets = rng.normal(size=(N, 2)) * 30
    offsets[REF] = 0.0
    gains = (rng.random((H_RAW, W_RAW, 3 if metric else 1)) * 2).astype(np.float32)
    gains[:10, :7] = 0.0  # masked raw pixels
    return {
        "grid": (R, C),
        "reference": REF,
        "raw_shape": (H_RAW, W_RAW),
        "rect_shape": (H_RECT, W_RECT),
        "pattern_shape": (400, 500),
        "scale": 0.1,
        "crops": crops,
        "centres": crops[:, :2] + rng.normal(25.0, 1.0, size=(N, 2)),
        "warps": warps,
        "masks": masks,
        "offsets": offsets,
        "z_b": 1.0,
        "z_c": 0.18 if metric else float("nan"),
        "metric": metric,
        "distances": np.array([0.6, 1.0, 2.5]) if metric else np.array([1.0]),
        "pattern_pitch": 5e-4 if metric else float("nan"),
        "gains": gains,
        "bayer": None if metric else "RGGB",
        "report": {
            "summary": {"rms_residual_px": 0.123, "coverage": 0.81, "n_captures": 5},
            "views": [{"residual_px": 0.1 + i / 100} for i in range(N)],
            "note": None,
        },
    }


@pytest.fixture(params=[True, False], ids=["metric", "relative"])
def calib(request: pytest.FixtureRequest) -> Calibration:
    return Calibration(**make_values(metric=request.param))


@pytest.fixture
def metric_calib() -> Calibration:
    return Calibration(**make_values(metric=True))


@pytest.fixture
def good_file(tmp_path: Path, metric_calib: Calibration) -> Path:
    return metric_calib.save(tmp_path / "camera.lfcal")


def edit(path: Path, fn: Callable[[h5py.File], Any], *, seal: bool = True) -> None:
    """Change a file with h5py, then (by default) recompute its checksums, as a writer
    that made the change on purpose would: the loader's own checks must then catch it."""
    with h5py.File(path, "r+") as f:
        fn(f)
    if seal:
        _seal(path)


def unsealed(path: Path, dest: Path) -> Path:
    """A format-1.0 copy of a file: no user block, no checksum attributes."""
    with h5py.File(path, "r") as src, h5py.File(dest, "w") as out:
        for k, v in src.attrs.items():
            if k != "sha256":
                out.attrs[k] = v
        out.attrs["format_version"] = "1.0"
        for name in src:
            src.copy(src[name], out, name=name)
            del out[name].attrs["sha256"]
    return dest


def replace(name: str, data: Any) -> Callable[[h5py.File], None]:
    def fn(f: h5py.File) -> None:
        del f[name]
        f[name] = data

    return fn


def modify(name: str, change: Callable[[np.ndarray], None]) -> Callable[[h5py.File], None]:
    """Read a dataset, change the array in place, write it back (uncompressed)."""

    def fn(f: h5py.File) -> None:
        arr = f[name][()]
        change(arr)
        del f[name]
        f[name] = arr

    return fn


def set_attr(name: str, value: Any) -> Callable[[h5py.File], None]:
    def fn(f: h5py.File) -> None:
        f.attrs[name] = value

    return fn


def assert_same(a: Calibration, b: Calibration) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        assert x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=name == "warps"), name
    # Bitwise, NaN payloads included.
    assert a.warps.tobytes() == b.warps.tobytes()
    for name in SCALARS:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, float) and np.isnan(x):
            assert isinstance(y, float)
            assert np.isnan(y), name
        else:
            assert x == y, name
            assert type(x) is type(y), name


# --------------------------------------------------------------------------- the type


def test_constructor_canonicalises_and_derives(metric_calib: Calibration) -> None:
    cal = metric_calib
    assert cal.n_views == 12
    assert cal.reference_rc == (1, 1)
    assert cal.software_version == lfcam.__version__
    assert cal.crops.dtype == np.int64
    assert cal.centres.dtype == np.float64
    assert cal.warps.dtype == np.float32
    assert cal.masks.dtype == np.bool_
    assert cal.gains.dtype == np.float32
    assert cal.grid == (3, 4)
    assert isinstance(cal.grid[0], int)
    assert cal.metric is True
    # Lists, uint8 masks, int32 crops and float64 warps are converted.
    v = make_values()
    v.update(
        crops=v["crops"].astype(np.int32).tolist(),
        masks=v["masks"].astype(np.uint8),
        warps=v["warps"].astype(np.float64),
        grid=[3, 4],
        report={"summary": {"t": (1, 2)}, 7: "seven"},
    )
    other = Calibration(**v)
    assert other.crops.dtype == np.int64
    np.testing.assert_array_equal(other.crops, cal.crops)
    np.testing.assert_array_equal(other.masks, cal.masks)
    assert other.warps.tobytes() == cal.warps.tobytes()
    assert other.grid == (3, 4)
    assert other.report == {"summary": {"t": [1, 2]}, "7": "seven"}  # its JSON round trip
    r = repr(cal)
    assert r.startswith("Calibration(grid=(3, 4), reference=5,")
    assert len(r) < 200


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"reference": 12}, "reference: view index 12 is out of range for a 3 x 4 grid"),
        ({"reference": True}, "reference: expected a number, got True"),
        ({"grid": (3, 0)}, r"grid: expected two integers >= 1, got \(3, 0\)"),
        ({"scale": -1.0}, "scale: expected a finite number > 0, got -1.0"),
        ({"z_b": 0.0}, "z_b: expected a finite distance > 0 m, got 0.0"),
        ({"z_c": 1.0}, r"z_c: metric mode needs a finite 0 <= z_c < z_b = 1.0 m, got 1.0"),
        ({"bayer": "rggb"}, "bayer: expected None or one of RGGB, BGGR, GRBG, GBRG, got 'rggb'"),
        ({"report": {"x": float("nan")}}, "report: not JSON-serialisable"),
        ({"report": {"x": object()}}, "report: not JSON-serialisable"),
        ({"report": [1, 2]}, r"report: expected a dict \(a JSON object\), got list"),
        ({"software_version": ""}, "software_version: expected a non-empty string"),
        ({"distances": np.array([0.5, 2.0])}, "distances: z_b = 1.0 m is not among"),
    ],
)
def test_constructor_refuses_bad_values(change: dict[str, Any], message: str) -> None:
    v = make_values()
    v.update(change)
    with pytest.raises(CalibrationError, match="^invalid calibration: " + message):
        Calibration(**v)


def test_constructor_refuses_bad_arrays() -> None:
    v = make_values()
    v["warps"][3, 7, 9] = [np.nan, 1.0]
    v["masks"][3, 7, 9] = True
    with pytest.raises(CalibrationError, match=r"warps: view 3 has NaN or inf at rectified pixel"):
        Calibration(**v)
    v = make_values()
    v["crops"][11, 0] = 151
    with pytest.raises(CalibrationError, match=r"crops: view 11 \(x0=151, y0=80, w=50, h=40\)"):
        Calibration(**v)
    v = make_values()
    v["offsets"][REF] = [0.0, 1e-12]
    with pytest.raises(CalibrationError, match=r"offsets: the reference view's offset"):
        Calibration(**v)
    v = make_values()
    v["gains"] = v["gains"][..., :2]
    with pytest.raises(
        CalibrationError,
        match=re.escape("gains: expected shape (H_raw, W_raw, C) with C = 1 or 3 = (120, 200, C)"),
    ):
        Calibration(**v)


# --------------------------------------------------------------------------- round trip


def test_save_load_is_exact(tmp_path: Path, calib: Calibration) -> None:
    path = calib.save(tmp_path / "camera.lfcal")
    assert path == tmp_path / "camera.lfcal"
    loaded = Calibration.load(path)
    assert_same(calib, loaded)
    assert np.isnan(loaded.warps[~loaded.masks]).mean() > 0.99
    # A str path works too, and saving what was loaded changes nothing but the time.
    again = Calibration.load(str(loaded.save(tmp_path / "again.lfcal")))
    assert_same(calib, again)
    assert sorted(os.listdir(tmp_path)) == ["again.lfcal", "camera.lfcal"]


def test_file_is_plain_hdf5(good_file: Path, metric_calib: Calibration) -> None:
    with h5py.File(good_file, "r") as f:
        assert set(f.keys()) == DATASETS
        assert all(isinstance(f[k], h5py.Dataset) for k in f)
        assert f.attrs["format"] == "lfcam-calibration"
        assert f.attrs["format_version"] == "1.2"
        assert FORMAT_VERSION == (1, 2)
        assert f.userblock_size == 512
        assert all(re.fullmatch("[0-9a-f]{64}", f[k].attrs["sha256"]) for k in f)
        assert f.attrs["software_version"] == lfcam.__version__
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00", f.attrs["created"])
        dtypes = {k: f[k].dtype for k in f if k not in ("bayer", "report")}
        assert dtypes["crops"] == np.int64
        assert dtypes["grid"] == np.int64
        assert dtypes["warps"] == np.float32
        assert dtypes["masks"] == np.uint8
        assert dtypes["metric"] == np.uint8
        assert dtypes["gains"] == np.float32
        assert dtypes["z_c"] == np.float64
        for name in ("warps", "masks", "gains"):
            ds = f[name]
            assert ds.compression == "gzip", name
            assert ds.compression_opts == 4, name
            assert ds.fletcher32, name
            assert ds.shuffle, name
            assert ds.chunks is not None, name
        assert f["warps"].chunks == (1, 40, 50, 2)
        assert f["masks"].chunks == (1, 40, 50)
        assert f["gains"].chunks == (120, 200, 3)
        assert f["crops"].compression is None
        assert f["reference"].shape == ()
        assert f["reference"][()] == 5
        assert tuple(f["grid"][()]) == (3, 4)
        assert f["z_b"][()] == 1.0
        assert f["metric"][()] == 1
        assert f["bayer"].asstr()[()] == ""
        np.testing.assert_array_equal(f["masks"][()], metric_calib.masks.astype(np.uint8))
        assert json.loads(f["report"].asstr()[()]) == metric_calib.report
        assert all(f[k].attrs["description"] for k in f)
        # Random 0/1 bytes: gzip stores about one bit each (plus overhead).
        assert f["masks"].id.get_storage_size() < f["masks"].nbytes / 4


def test_reads_files_from_other_writers(good_file: Path, metric_calib: Calibration) -> None:
    """Fixed-length ASCII attributes (as MATLAB/C write), bool masks, int32 crops, float64 warps."""

    def rewrite(f: h5py.File) -> None:
        f.attrs["format"] = np.bytes_(b"lfcam-calibration")
        f.attrs["format_version"] = np.bytes_(b"1.0")
        f.attrs["created"] = "2026-01-02T03:04:05Z"
        replace("masks", f["masks"][()].astype(bool))(f)
        replace("crops", f["crops"][()].astype(np.int32))(f)
        replace("warps", f["warps"][()].astype(np.float64))(f)
        replace("bayer", np.bytes_(b""))(f)

    edit(good_file, rewrite)
    loaded = Calibration.load(good_file)
    assert_same(metric_calib, loaded)


def test_newer_minor_version_loads_and_ignores_additions(
    good_file: Path, metric_calib: Calibration
) -> None:
    def newer(f: h5py.File) -> None:
        f.attrs["format_version"] = "1.7"
        f["focus_table"] = np.arange(5.0)

    edit(good_file, newer)
    assert_same(metric_calib, Calibration.load(good_file))
    assert "file format  1.7" in info(good_file)


def test_newer_major_version_asks_for_an_upgrade(good_file: Path) -> None:
    edit(good_file, set_attr("format_version", "2.0"))
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file)
    msg = str(e.value)
    assert msg.startswith(str(good_file) + ": ")
    assert (
        "written by a newer lfcam (format 2.0); this lfcam reads format 1.x: upgrade lfcam" in msg
    )


# --------------------------------------------------------------------------- atomic save


@pytest.mark.parametrize("exc", [OSError("No space left on device"), KeyboardInterrupt()])
def test_failed_save_leaves_nothing_and_keeps_the_old_file(
    tmp_path: Path,
    metric_calib: Calibration,
    monkeypatch: pytest.MonkeyPatch,
    exc: BaseException,
) -> None:
    target = tmp_path / "camera.lfcal"
    # Nothing there yet: nothing there after.
    real = h5py.Group.create_dataset
    calls: list[str] = []

    def failing(self: h5py.Group, name: str, *args: Any, **kwargs: Any) -> Any:
        calls.append(name)
        if name == "gains":  # late: most of the file has been written
            raise exc
        return real(self, name, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(h5py.Group, "create_dataset", failing)
        with pytest.raises(type(exc)):
            metric_calib.save(target)
    assert "warps" in calls
    assert os.listdir(tmp_path) == []

    # An existing good file is untouched, byte for byte.
    metric_calib.save(target)
    before = target.read_bytes()
    other = Calibration(**make_values(seed=1))
    with monkeypatch.context() as m:
        m.setattr(h5py.Group, "create_dataset", failing)
        with pytest.raises(type(exc)):
            other.save(target)
    assert os.listdir(tmp_path) == ["camera.lfcal"]
    assert target.read_bytes() == before
    assert_same(metric_calib, Calibration.load(target))


def test_save_revalidates_and_checks_the_folder(tmp_path: Path, metric_calib: Calibration) -> None:
    metric_calib.reference = 0  # offsets[0] is not zero
    with pytest.raises(
        CalibrationError, match=r"^cannot save calibration: offsets: the reference view's offset"
    ):
        metric_calib.save(tmp_path / "camera.lfcal")
    assert os.listdir(tmp_path) == []
    metric_calib.reference = REF
    with pytest.raises(InputError, match="does not exist"):
        metric_calib.save(tmp_path / "no" / "camera.lfcal")
    with pytest.raises(InputError, match="is a folder"):
        metric_calib.save(tmp_path)


# --------------------------------------------------------------------------- bad files


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.lfcal"
    with pytest.raises(InputError, match=re.escape(f"{path}: no such calibration file")):
        Calibration.load(path)
    with pytest.raises(InputError, match="is a folder"):
        Calibration.load(tmp_path)


@pytest.mark.parametrize(
    "content",
    [b"", b"not an hdf5 file at all\n" * 100, b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8],
    ids=["empty", "text", "png"],
)
def test_not_hdf5(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.lfcal"
    path.write_bytes(content)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(path)
    assert str(e.value) == f"{path}: not an HDF5 file, so not an lfcam calibration (.lfcal)"


def test_hdf5_but_not_a_calibration(tmp_path: Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(path)
    assert str(e.value) == (
        f"{path}: not an lfcam calibration file (HDF5 without a 'format' attribute)"
    )


def test_truncated(good_file: Path) -> None:
    data = good_file.read_bytes()
    good_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file)
    msg = str(e.value)
    assert msg.startswith(f"{good_file}: corrupt or truncated: ")
    assert "SHA-256 checksum does not match" in msg


@pytest.mark.parametrize("part", ["data", "checksum"])
def test_corrupt_chunk_fails_the_checksum(good_file: Path, part: str) -> None:
    """Flip 4 bytes of one compressed chunk of warps: in its deflate stream, or in the
    Fletcher-32 checksum that HDF5 appends to it (then only the checksum can fail)."""
    with h5py.File(good_file, "r") as f:
        chunk = f["warps"].id.get_chunk_info(4)
        _, stored = f["warps"].id.read_direct_chunk(chunk.chunk_offset)
    assert chunk.size > 100
    data = bytearray(good_file.read_bytes())
    assert bytes(data[chunk.byte_offset : chunk.byte_offset + chunk.size]) == stored
    at = chunk.byte_offset + (chunk.size // 2 if part == "data" else chunk.size - 4)
    data[at : at + 4] = bytes(b ^ 0xFF for b in data[at : at + 4])
    good_file.write_bytes(bytes(data))
    with h5py.File(good_file, "r") as f:  # the other views still read
        assert np.isfinite(f["warps"][3][f["masks"][3].astype(bool)]).all()
    # The whole-file checksum catches it before HDF5 reads anything...
    with pytest.raises(CalibrationError, match="SHA-256 checksum does not match"):
        Calibration.load(good_file)
    # ...and with the file's checksum recomputed over the damage, Fletcher-32 does.
    from lfcam.calibration.file import _seal_file

    _seal_file(good_file)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file)
    msg = str(e.value)
    assert msg.startswith(f"{good_file}: corrupt or truncated: cannot read dataset 'warps' (")
    assert msg.endswith("its Fletcher-32 checksum or decompression failed, the file is damaged")


def _warps_nan_inside_mask(a: np.ndarray) -> None:
    a[2, 10, 20, 1] = np.nan


def _masks_on_where_warps_nan(a: np.ndarray) -> None:
    a[...] = 1


BAD_FILES: list[tuple[str, Callable[[h5py.File], Any], str]] = [
    # header
    (
        "format",
        set_attr("format", "hdf5-image"),
        "not an lfcam calibration file: format attribute is 'hdf5-image', "
        "expected 'lfcam-calibration'",
    ),
    ("format-type", set_attr("format", 7), "root attribute 'format' is not a string: 7"),
    (
        "version-text",
        set_attr("format_version", "one"),
        "unreadable format_version 'one' (expected MAJOR.MINOR, e.g. '1.0')",
    ),
    (
        "version-old",
        set_attr("format_version", "0.9"),
        "unsupported format version 0.9; this lfcam reads format 1.x",
    ),
    (
        "no-software-version",
        lambda f: f.attrs.__delitem__("software_version"),
        "missing root attribute 'software_version'",
    ),
    (
        "created",
        set_attr("created", "yesterday"),
        "root attribute 'created' is not an ISO-8601 time: 'yesterday'",
    ),
    # membership
    ("missing", lambda f: f.__delitem__("centres"), "missing dataset 'centres' (incomplete file)"),
    (
        "missing-2",
        lambda f: (f.__delitem__("gains"), f.__delitem__("z_c")),
        "missing datasets 'z_c', 'gains' (incomplete file)",
    ),
    (
        "extra",
        lambda f: f.create_dataset("notes", data=1),
        "unexpected dataset 'notes' in a format 1.2 file",
    ),
    (
        "group",
        lambda f: (f.__delitem__("warps"), f.create_group("warps")),
        "warps: expected a dataset, found a group",
    ),
    # dtype kinds
    (
        "crops-float",
        replace("crops", np.zeros((12, 4))),
        "crops: expected integers, got dtype float64",
    ),
    (
        "centres-text",
        replace("centres", "12 centres"),
        "centres: expected numbers, got dtype object",
    ),
    ("masks-float", replace("masks", np.ones((12, 40, 50))), "masks: expected booleans or 0/1"),
    ("bayer-number", replace("bayer", 3), "bayer: expected a string, got dtype int64"),
    (
        "report-array",
        replace("report", np.zeros(3)),
        "report: expected a string, got dtype float64",
    ),
    # shapes
    (
        "warps-shape",
        replace("warps", np.zeros((12, 40, 51, 2), np.float32)),
        "warps: expected shape (N, H_rect, W_rect, 2) = (12, 40, 50, 2), got (12, 40, 51, 2)",
    ),
    (
        "masks-shape",
        replace("masks", np.ones((11, 40, 50), np.uint8)),
        "masks: expected shape (N, H_rect, W_rect) = (12, 40, 50), got (11, 40, 50)",
    ),
    (
        "gains-channels",
        replace("gains", np.ones((120, 200, 2), np.float32)),
        "gains: expected shape (H_raw, W_raw, C) with C = 1 or 3 = (120, 200, C), "
        "got (120, 200, 2)",
    ),
    (
        "gains-raw-shape",
        replace("raw_shape", np.array([120, 201])),
        "gains: expected shape (H_raw, W_raw, C) with C = 1 or 3 = (120, 201, C), "
        "got (120, 200, 3)",
    ),
    (
        "grid",
        replace("grid", np.array([4, 4])),
        "crops: expected shape (N, 4) = (16, 4), got (12, 4)",
    ),
    (
        "rect-shape",
        replace("rect_shape", np.array([40, 60])),
        "warps: expected shape (N, H_rect, W_rect, 2) = (12, 40, 60, 2), got (12, 40, 50, 2)",
    ),
    ("grid-3", replace("grid", np.array([3, 4, 1])), "grid: expected shape (2,) = (2,), got (3,)"),
    (
        "z_b-array",
        replace("z_b", np.array([1.0])),
        "z_b: expected shape () (a scalar) = (), got (1,)",
    ),
    (
        "distances-empty",
        replace("distances", np.zeros(0)),
        "distances: expected shape (K,) with 1 <= K <= 1000 = (K,), got (0,)",
    ),
    (
        "bayer-array",
        replace("bayer", ["RGGB", "RGGB"]),
        "bayer: expected a scalar string, got shape (2,)",
    ),
    # non-finite numbers
    (
        "centres-nan",
        modify("centres", lambda a: a.__setitem__((2, 1), np.nan)),
        "centres: view 2 has a non-finite value nan (NaN or inf)",
    ),
    (
        "offsets-inf",
        modify("offsets", lambda a: a.__setitem__((7, 0), np.inf)),
        "offsets: view 7 has a non-finite value inf (NaN or inf)",
    ),
    ("z_b-nan", replace("z_b", np.nan), "z_b: expected a finite distance > 0 m, got nan"),
    ("scale-inf", replace("scale", np.inf), "scale: expected a finite number > 0, got inf"),
    ("scale-zero", replace("scale", 0.0), "scale: expected a finite number > 0, got 0.0"),
    (
        "gains-nan",
        modify("gains", lambda a: a.__setitem__((3, 7, 1), np.nan)),
        "gains: non-finite value nan at raw pixel (x=7, y=3), channel 1",
    ),
    (
        "gains-negative",
        modify("gains", lambda a: a.__setitem__((100, 150, 2), -0.5)),
        "gains: negative value -0.5 at raw pixel (x=150, y=100), channel 2",
    ),
    (
        "distances-inf",
        replace("distances", np.array([1.0, np.inf])),
        "distances: expected finite distances > 0 m, got [1.0, inf]",
    ),
    (
        "distances-no-z_b",
        replace("distances", np.array([0.6, 2.5])),
        "distances: z_b = 1.0 m is not among the board distances [0.6, 2.5]",
    ),
    (
        "warps-nan-in-mask",
        modify("warps", _warps_nan_inside_mask),
        "warps: view 2 has NaN or inf at rectified pixel (u=20, v=10) where masks is True",
    ),
    (
        "masks-over-nan",
        modify("masks", _masks_on_where_warps_nan),
        "warps: view 0 has NaN or inf at rectified pixel",
    ),
    # depth model
    (
        "z_c-nan-metric",
        replace("z_c", np.nan),
        "z_c: metric mode needs a finite 0 <= z_c < z_b = 1.0 m, got nan",
    ),
    (
        "z_c-beyond-board",
        replace("z_c", 1.5),
        "z_c: metric mode needs a finite 0 <= z_c < z_b = 1.0 m, got 1.5",
    ),
    (
        "z_c-in-relative",
        replace("metric", np.uint8(0)),
        "z_c: must be NaN in relative mode (metric is False), got 0.18",
    ),
    ("metric-2", replace("metric", np.uint8(2)), "metric: expected True/False (1/0), got 2"),
    (
        "pitch-negative",
        replace("pattern_pitch", -1e-3),
        "pattern_pitch: expected a finite number > 0 m, or NaN if unknown, got -0.001",
    ),
    (
        "pitch-inf",
        replace("pattern_pitch", np.inf),
        "pattern_pitch: expected a finite number > 0 m, or NaN if unknown, got inf",
    ),
    # geometry
    (
        "crop-outside",
        modify("crops", lambda a: a.__setitem__((11, 0), 151)),
        "crops: view 11 (x0=151, y0=80, w=50, h=40) lies outside the 200 x 120 (W x H) raw frame",
    ),
    (
        "crop-negative",
        modify("crops", lambda a: a.__setitem__((0, 1), -1)),
        "crops: view 0 (x0=0, y0=-1, w=50, h=40) lies outside the 200 x 120 (W x H) raw frame",
    ),
    (
        "crop-sizes",
        modify("crops", lambda a: a.__setitem__((3, 2), 49)),
        "crops: every view must have the same w, h; got [(49, 40), (50, 40)]",
    ),
    (
        "reference-range",
        replace("reference", 12),
        "reference: view index 12 is out of range for a 3 x 4 grid",
    ),
    (
        "reference-negative",
        replace("reference", -1),
        "reference: view index -1 is out of range for a 3 x 4 grid",
    ),
    (
        "reference-float",
        replace("reference", 5.0),
        "reference: expected integers, got dtype float64",
    ),
    (
        "reference-offset",
        modify("offsets", lambda a: a.__setitem__((REF, 1), 0.25)),
        "offsets: the reference view's offset must be (0, 0), got (0.0, 0.25) for view 5",
    ),
    (
        "reference-moved",
        replace("reference", 0),
        "offsets: the reference view's offset must be (0, 0), got (",
    ),
    (
        "masks-values",
        modify("masks", lambda a: a.__setitem__((1, 2, 3), 2)),
        "masks: expected only 0 and 1 (or False and True)",
    ),
    # strings
    (
        "bayer",
        replace("bayer", "RGBG"),
        "bayer: expected None or one of RGGB, BGGR, GRBG, GBRG, got 'RGBG'",
    ),
    ("report-json", replace("report", '{"summary": '), "report: not valid JSON ("),
    (
        "report-nan",
        replace("report", '{"rms": NaN}'),
        "report: not valid JSON (NaN is not valid JSON",
    ),
    (
        "report-list",
        replace("report", "[1, 2]"),
        "report: expected a dict (a JSON object), got list",
    ),
    (  # nothing in a file is ever unpickled or evaluated
        "report-pickle",
        replace("report", np.void(pickle.dumps({"summary": {}}))),
        "report: expected a string, got dtype |V",
    ),
    (
        "report-code",
        replace("report", "__import__('os').system('false')"),
        "report: not valid JSON (",
    ),
]


@pytest.mark.parametrize(
    ("editor", "message"), [b[1:] for b in BAD_FILES], ids=[b[0] for b in BAD_FILES]
)
def test_bad_file_names_the_problem(
    good_file: Path, editor: Callable[[h5py.File], Any], message: str
) -> None:
    copy = good_file.with_name("edited.lfcal")
    shutil.copyfile(good_file, copy)
    edit(copy, editor)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(copy)
    msg = str(e.value)
    assert msg.startswith(f"{copy}: "), msg
    assert message in msg, msg
    Calibration.load(good_file)  # the original still loads


# --------------------------------------------------------------------------- summary, info, hash


def test_summary_metric(good_file: Path, metric_calib: Calibration) -> None:
    s = metric_calib.summary()
    lines = s.splitlines()
    assert lines[0] == "lfcam calibration"
    for needle in [
        "format            lfcam-calibration 1.2",
        f"software version  {lfcam.__version__}",
        "grid              3 x 4 lenslets (12 views)",
        "reference view    5 (row 1, col 1)",
        "raw frame         120 x 200 px (H x W)",
        "rectified frame   40 x 50 px (H x W)",
        "pattern           400 x 500 px (H x W)",
        "scale             0.1 rectified px per pattern px",
        "depth mode        metric (depth Z in metres)",
        "Z_b               1 m (reference board distance)",
        "Z_c               0.18 m (object-space lenslet-centre depth)",
        "board distances   0.6, 1, 2.5 m",
        "pattern pitch     0.5 mm per pattern px",
        "Bayer             none",
        "gains             3 channels, 0.3% of raw px masked",  # 70 of 24000 px
        "report            summary, views, note",
        "rms_residual_px  0.123",
        "coverage         0.81",
        "n_captures       5",
    ]:
        assert needle in s, needle
    # The per-view table: a header and one aligned row per view, reference starred.
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("view  row"))
    header, rows = lines[start], lines[start + 1 : start + 1 + N]
    assert header.split()[-5:] == ["o_x", "o_y", "|o|", "coverage", "%"]
    assert {len(r) for r in rows} == {len(header)}
    ref_row = rows[REF].split()
    assert ref_row[:7] == ["5*", "1", "1", "50", "40", "50", "40"]
    assert ref_row[9:12] == ["0.000", "0.000", "0.000"]
    for i, row in enumerate(rows):
        cells = row.split()
        assert cells[-1] == f"{metric_calib.masks[i].mean() * 100:.1f}"
        assert float(cells[7]) == pytest.approx(metric_calib.centres[i, 0], abs=0.005)
        assert float(cells[9]) == pytest.approx(metric_calib.offsets[i, 0], abs=0.0005)
    assert s == Calibration.load(good_file).summary()


def test_summary_relative() -> None:
    cal = Calibration(**make_values(metric=False))
    s = cal.summary()
    assert "depth mode        relative (t = s * Z_c / Z_b; Z_c unknown)" in s
    assert "Z_c               unknown (relative mode)" in s
    assert "pattern pitch     unknown (X, Y not metric)" in s
    assert "Bayer             RGGB" in s
    assert "gains             1 channel, 0.3% of raw px masked" in s
    assert "d_i = o_i Z_b / Z_c in rectified px" in s
    assert "d_x" in s
    assert "o_x" not in s
    cal.report = {}
    assert "report summary" not in cal.summary()
    assert "report            empty" in cal.summary()


def test_info(good_file: Path, metric_calib: Calibration) -> None:
    text = info(good_file)
    lines = text.splitlines()
    assert lines[0] == f"file         {good_file}"
    assert lines[1] == "file format  1.2"
    assert lines[2].startswith("created      20")
    assert lines[3] == f"sha256       {file_hash(good_file)}"
    assert lines[4] == "checksums    verified (the file, every dataset)"
    assert text.endswith(metric_calib.summary())
    good_file.write_bytes(b"junk")
    with pytest.raises(CalibrationError, match="not an HDF5 file"):
        info(good_file)


def test_file_hash(good_file: Path, tmp_path: Path) -> None:
    digest = file_hash(good_file)
    assert re.fullmatch(r"[0-9a-f]{64}", digest)
    assert digest == hashlib.sha256(good_file.read_bytes()).hexdigest()
    assert file_hash(str(good_file)) == digest  # stable, str or Path
    copy = tmp_path / "copy.lfcal"
    shutil.copyfile(good_file, copy)
    assert file_hash(copy) == digest  # content, not name
    edit(copy, set_attr("created", "2030-01-01T00:00:00+00:00"))
    assert file_hash(copy) != digest
    assert file_hash(good_file) == digest
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'none'}: no such file")):
        file_hash(tmp_path / "none")


# --------------------------------------------------------------------------- checksums, format 1.0


def test_every_byte_is_covered(good_file: Path) -> None:
    """Each of 400 single-byte changes, spread over the whole file, is refused before
    h5py opens it (user block) or by the file's checksum."""
    data = good_file.read_bytes()
    bad = good_file.with_name("bad.lfcal")
    rng = np.random.default_rng(3)
    for at in sorted({0, 30, 90, 511, 512, len(data) - 1, *rng.integers(0, len(data), 394)}):
        mutant = bytearray(data)
        mutant[at] ^= 1 << int(rng.integers(0, 8))
        bad.write_bytes(bytes(mutant))
        with pytest.raises(CalibrationError) as e:
            Calibration.load(bad)
        assert str(e.value).startswith(f"{bad}: "), at


@pytest.mark.parametrize("name", ["z_c", "offsets", "crops", "centres", "reference", "report"])
def test_dataset_checksums_catch_value_changes(good_file: Path, name: str) -> None:
    """A small dataset changed through HDF5, the file's checksum recomputed (as a careless
    tool would), is still refused: its own checksum no longer matches."""
    from lfcam.calibration.file import _seal_file

    def change(f: h5py.File) -> None:
        ds = f[name]
        if name == "report":
            ds[()] = '{"summary": {}}'
        else:
            arr = ds[()]
            ds[()] = arr + 1 if arr.dtype.kind in "iu" else arr * 1.25

    edit(good_file, change, seal=False)
    _seal_file(good_file)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file)
    assert str(e.value) == (
        f"{good_file}: {name}: its values do not match their checksum "
        "(the dataset was changed or damaged after it was written)"
    )


def test_root_attribute_checksum(good_file: Path) -> None:
    from lfcam.calibration.file import _seal_file

    edit(good_file, set_attr("software_version", "9.9.9"), seal=False)
    _seal_file(good_file)
    with pytest.raises(CalibrationError, match="root attributes do not match their checksum"):
        Calibration.load(good_file)


def test_damaged_user_block(good_file: Path) -> None:
    data = bytearray(good_file.read_bytes())
    data[200] = 7  # the zero padding after the seal
    good_file.write_bytes(bytes(data))
    with pytest.raises(CalibrationError, match=r"its checksum block .* is damaged"):
        Calibration.load(good_file)
    data[200] = 0
    data[0:5] = b"LFCAM"  # no seal: then it claims 1.2 without checksums
    good_file.write_bytes(bytes(data))
    with pytest.raises(CalibrationError, match=r"a format 1\.2 file carries a checksum"):
        Calibration.load(good_file)


def test_format_1_0_loads_with_a_warning(
    good_file: Path, metric_calib: Calibration, tmp_path: Path
) -> None:
    old = unsealed(good_file, tmp_path / "old.lfcal")
    with pytest.warns(LfcamWarning, match="format 1.0 calibration file, without checksums"):
        loaded = Calibration.load(old)
    assert_same(metric_calib, loaded)
    with pytest.warns(LfcamWarning):
        assert "checksums    none (format 1.0 file)" in info(old)
    # Saving it again upgrades it.
    loaded.save(old)
    assert_same(metric_calib, Calibration.load(old))
    # A damaged 1.0 file still gets the loader's checks.
    old2 = unsealed(good_file, tmp_path / "old2.lfcal")
    edit(old2, replace("z_c", 1.5), seal=False)
    with (
        pytest.raises(CalibrationError, match="z_c: metric mode needs"),
        pytest.warns(LfcamWarning),
    ):
        Calibration.load(old2)


def test_format_1_0_crash_in_hdf5_is_an_error(
    good_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An unsealed file is read in a child process first: its crash or hang is reported."""
    import subprocess

    from lfcam.calibration import file as calfile

    old = unsealed(good_file, tmp_path / "old.lfcal")
    real = subprocess.run

    def crash(args: list[Any], **kw: Any) -> Any:
        return real(
            [args[0], "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"], **kw
        )

    monkeypatch.setattr(calfile.subprocess, "run", crash)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(old)
    assert str(e.value) == f"{old}: corrupt: reading it crashed the HDF5 library (signal 11)"

    def hang(args: list[Any], **kw: Any) -> Any:
        return real([args[0], "-c", "import time; time.sleep(60)"], **{**kw, "timeout": 0.5})

    monkeypatch.setattr(calfile.subprocess, "run", hang)
    with pytest.raises(
        CalibrationError, match=f"{re.escape(str(old))}: corrupt: reading it did not"
    ):
        Calibration.load(old)


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("raw_shape", [200_000, 200_000], "raw_shape: a 200000 x 200000 (H x W) frame is larger"),
        ("rect_shape", [200_000, 200_000], "rect_shape: a 200000 x 200000 (H x W) frame is larger"),
        ("rect_shape", [16_000, 16_000], "rect_shape: 12 views of 16000 x 16000 px are more"),
        ("grid", [100, 100], "grid: 100 x 100 = 10000 views, more than lfcam reads (4096)"),
    ],
)
def test_declared_sizes_are_bounded(
    good_file: Path, name: str, value: list[int], message: str
) -> None:
    """Huge declared sizes are refused before any array is read or allocated."""
    edit(good_file, replace(name, np.array(value)))
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file)
    assert str(e.value).startswith(f"{good_file}: {message}")


def test_load_refuses_non_paths() -> None:
    for bad in (None, 3, b"\xff.lfcal"):
        with pytest.raises(InputError, match=r"^path: expected a calibration file.s path"):
            Calibration.load(bad)  # type: ignore[arg-type]


def test_non_utf8_file_name(good_file: Path, tmp_path: Path) -> None:
    """A name that is not valid UTF-8 (byte 0xff) loads, and errors name it."""
    name = os.fsdecode(b"cam\xff.lfcal")
    shutil.copyfile(good_file, tmp_path / name)
    Calibration.load(tmp_path / name)
    (tmp_path / name).write_bytes(b"junk")
    with pytest.raises(CalibrationError, match="not an HDF5 file"):
        Calibration.load(tmp_path / name)


def test_format_1_0_probe_succeeds_unpatched(
    good_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The child process really reads a good 1.0 file and says so (the lfcam it imports
    is this one, whatever PYTHONPATH says)."""
    from lfcam.calibration import file as calfile

    old = unsealed(good_file, tmp_path / "old.lfcal")
    calfile._probe(old, str(old))
    monkeypatch.delenv("PYTHONPATH", raising=False)
    calfile._probe(old, str(old))


@pytest.mark.parametrize(
    ("child", "why"),
    [
        (
            "import lfcam_missing",
            "exit code 1: ModuleNotFoundError: No module named 'lfcam_missing'",
        ),
        ("pass", "exit code 0"),  # ended without its success marker
    ],
)
def test_format_1_0_failed_probe_is_an_error(
    good_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, child: str, why: str
) -> None:
    import subprocess

    from lfcam.calibration import file as calfile

    old = unsealed(good_file, tmp_path / "old.lfcal")
    real = subprocess.run

    def failing(args: list[Any], **kw: Any) -> Any:
        return real([args[0], "-c", child], **kw)

    monkeypatch.setattr(calfile.subprocess, "run", failing)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(old)
    assert str(e.value) == (
        f"{old}: a format 1.0 file is read in a child process first, and that failed ({why})"
    )


def test_the_file_hashed_is_the_file_parsed(
    good_file: Path, metric_calib: Calibration, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another file renamed over the path between the checksum and the parse is not read."""
    from lfcam.calibration import file as calfile

    other = Calibration(**make_values(seed=1)).save(tmp_path / "other.lfcal")
    real = calfile._check_seal

    def then_swap(fh: Any, where: str) -> bool:
        sealed = real(fh, where)
        os.replace(other, good_file)
        return sealed

    monkeypatch.setattr(calfile, "_check_seal", then_swap)
    digest = file_hash(good_file)
    assert_same(metric_calib, Calibration.load(good_file, sha256=digest))
    monkeypatch.undo()
    assert not np.array_equal(Calibration.load(good_file).offsets, metric_calib.offsets)
    with pytest.raises(CalibrationError) as e:
        Calibration.load(good_file, sha256=digest)
    assert str(e.value) == (
        f"{good_file}: sha256 {file_hash(good_file)} differs from the expected {digest}"
    )


def test_file_hash_offset_and_open_files(good_file: Path) -> None:
    data = good_file.read_bytes()
    assert file_hash(good_file, offset=512) == hashlib.sha256(data[512:]).hexdigest()
    with open(good_file, "rb") as fh:
        assert file_hash(fh) == hashlib.sha256(data).hexdigest()
        assert file_hash(fh, offset=512) == hashlib.sha256(data[512:]).hexdigest()
    # The seal in the user block is the hash of what follows it.
    assert data.startswith(b"lfcam-calibration sha256 " + file_hash(good_file, offset=512).encode())


def test_format_1_0_file_that_hangs_hdf5(monkeypatch: pytest.MonkeyPatch) -> None:
    """A damaged unsealed file on which the HDF5 library itself hangs (found by fuzzing:
    fuzz/fuzz_inputs.py) ends in a CalibrationError once the probe's time is up."""
    from lfcam.calibration import file as calfile

    monkeypatch.setattr(calfile, "_PROBE_TIMEOUT_S", 5.0)
    path = Path(__file__).parent / "data" / "hdf5_hang_1_0.lfcal"
    with pytest.raises(CalibrationError) as e:
        Calibration.load(path)
    assert str(e.value) == f"{path}: corrupt: reading it did not finish within 5 s"
