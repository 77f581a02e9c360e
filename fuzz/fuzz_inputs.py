"""Fuzz target (atheris) for lfcam's readers of untrusted files: the calibration loader
(``Calibration.load``) and the image reader (``read_image``: PNG, JPEG, TIFF).

Each input is one selector byte (``C`` calibration, ``P`` PNG, ``J`` JPEG, ``T`` TIFF)
and the file's bytes. A finding is: a crash or uncaught exception other than the
documented ``InputError`` / ``CalibrationError`` (a Python exception, a signal), a hang
(libFuzzer's ``-timeout``), or a calibration that loads without a warning with values
other than the seed's (a silently changed value). docs/robustness.md, "Fuzzing".

Run (new inputs go to a temporary folder; the committed seeds in fuzz/corpus are
read only)::

    pip install atheris
    python fuzz/fuzz_inputs.py -max_total_time=60        # or -runs=100000

A calibration file without the format-1.1 seal goes through the loader's probe (the
HDF5 read in a child process first); here the child is forked from the fuzzer instead of
started afresh (``--subprocess-probe`` keeps the loader's own, about a second an input).
Remake the seed corpus: ``python fuzz/fuzz_inputs.py --make-corpus``.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import tempfile
import time
import warnings
from pathlib import Path

import atheris
import numpy as np

with atheris.instrument_imports(include=["lfcam"]):
    import lfcam
    from lfcam.errors import CalibrationError, InputError, LfcamWarning

HERE = Path(__file__).resolve().parent
CORPUS = HERE / "corpus"
SEED_CALIBRATION = CORPUS / "calibration.bin"
# Seconds the forked probe waits for its child (the loader's probe: 120 s).
PROBE_TIMEOUT_S = 10.0
EXTENSIONS = {ord("C"): ".lfcal", ord("P"): ".png", ord("J"): ".jpg", ord("T"): ".tif"}

_WORK = Path(tempfile.mkdtemp(prefix="lfcam-fuzz-"))
_REFERENCE: lfcam.Calibration | None = None


def _tiny_calibration() -> lfcam.Calibration:
    """A valid 1 x 2 calibration of 8 x 16 px raw frames, small enough to fuzz fast."""
    rng = np.random.default_rng(0)
    masks = np.ones((2, 4, 5), bool)
    masks[1, 0, 0] = False
    warps = (rng.random((2, 4, 5, 2)) * [7, 7]).astype(np.float32)
    warps[~masks] = np.nan
    return lfcam.Calibration(
        grid=(1, 2),
        reference=0,
        raw_shape=(8, 16),
        rect_shape=(4, 5),
        pattern_shape=(64, 80),
        scale=0.1,
        crops=np.array([[0, 0, 8, 8], [8, 0, 8, 8]], np.int64),
        centres=np.array([[4.0, 4.0], [12.0, 4.1]]),
        warps=warps,
        masks=masks,
        offsets=np.array([[0.0, 0.0], [3.25, -0.5]]),
        z_b=1.0,
        z_c=0.1832,
        metric=True,
        distances=np.array([0.7, 1.0, 1.5]),
        pattern_pitch=5e-4,
        gains=(rng.random((8, 16, 3)) + 0.5).astype(np.float32),
        bayer=None,
        report={"summary": {"rms": 0.1}},
    )


def make_corpus() -> None:
    """Write the seed corpus: a calibration file and a tiny PNG, JPEG and TIFF."""
    import cv2
    import tifffile

    CORPUS.mkdir(exist_ok=True)
    path = _WORK / "seed.lfcal"
    _tiny_calibration().save(path)
    SEED_CALIBRATION.write_bytes(b"C" + path.read_bytes())
    img = (np.arange(6 * 7 * 3).reshape(6, 7, 3) * 5 % 256).astype(np.uint8)
    for sel, name, ext in ((b"P", "image.png", ".png"), (b"J", "image.jpg", ".jpg")):
        ok, buf = cv2.imencode(ext, img)
        assert ok
        (CORPUS / f"{name}.bin").write_bytes(sel + buf.tobytes())
    tif = _WORK / "seed.tif"
    tifffile.imwrite(tif, (img.astype(np.uint16) * 257), photometric="rgb")
    (CORPUS / "image.tif.bin").write_bytes(b"T" + tif.read_bytes())
    grey = _WORK / "grey.png"
    lfcam.io.write_image(grey, img[..., 0])
    (CORPUS / "grey.png.bin").write_bytes(b"P" + grey.read_bytes())


def _same(a: lfcam.Calibration, b: lfcam.Calibration) -> bool:
    for name in ("crops", "centres", "warps", "masks", "offsets", "distances", "gains"):
        x, y = getattr(a, name), getattr(b, name)
        if x.shape != y.shape or x.tobytes() != y.tobytes():
            return False
    for name in ("grid", "reference", "raw_shape", "rect_shape", "pattern_shape", "scale"):
        if getattr(a, name) != getattr(b, name):
            return False
    for name in ("z_b", "z_c", "metric", "pattern_pitch", "bayer", "report"):
        x, y = getattr(a, name), getattr(b, name)
        if x != y and not (isinstance(x, float) and np.isnan(x) and np.isnan(y)):
            return False
    return True


def test_one_input(data: bytes) -> None:
    global _REFERENCE
    if not data or data[0] not in EXTENSIONS:
        return
    ext = EXTENSIONS[data[0]]
    path = _WORK / f"input{ext}"
    path.write_bytes(data[1:])
    if ext == ".lfcal":
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                cal = lfcam.Calibration.load(path)
            except (InputError, CalibrationError):
                return
        warned = any(issubclass(w.category, LfcamWarning) for w in caught)
        if _REFERENCE is None:
            _REFERENCE = lfcam.Calibration.load(_seed_path())
        if not warned and not _same(cal, _REFERENCE):
            raise RuntimeError("a changed calibration file loaded without error or warning")
        return
    try:
        img = lfcam.read_image(path)
    except InputError:
        return
    if img.ndim not in (2, 3) or img.dtype not in (np.uint8, np.uint16, np.float32):
        raise RuntimeError(f"read_image returned {img.dtype} {img.shape}")


def _seed_path() -> Path:
    p = _WORK / "reference.lfcal"
    if not p.exists():
        p.write_bytes(SEED_CALIBRATION.read_bytes()[1:])
    return p


def _forked_probe(p: Path, where: str) -> None:
    """The loader's probe of an unsealed file (``_probe``: the HDF5 read in a child
    process), by fork instead of a fresh interpreter: the same code in a child, a
    crash or a hang still a CalibrationError, in milliseconds instead of the second an
    interpreter takes to import lfcam. The timeout is shorter than the loader's (and
    than libFuzzer's -timeout), so that a hang of the HDF5 library is the loader's
    error here too, not a finding."""
    from lfcam.calibration import file as calfile

    pid = os.fork()
    if pid == 0:  # the child: read, and leave without running any cleanup
        code = 0
        try:
            calfile._read_hdf5(p, where)
        except lfcam.LfcamError:
            pass
        except BaseException:
            code = 1
        os._exit(code)
    deadline = time.monotonic() + PROBE_TIMEOUT_S
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:  # the loader's probe times out the same way
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise CalibrationError(
                f"{where}: corrupt: reading it did not finish within {PROBE_TIMEOUT_S:.0f} s"
            )
        time.sleep(0.002)
    if os.WIFSIGNALED(status):
        raise CalibrationError(
            f"{where}: corrupt: reading it crashed the HDF5 library (signal {os.WTERMSIG(status)})"
        )
    if os.WEXITSTATUS(status) != 0:
        raise CalibrationError(f"{where}: a format 1.0 file is read in a child process first")


def main() -> None:
    argv = list(sys.argv)
    if "--make-corpus" in argv:
        make_corpus()
        return
    if not any(not a.startswith("-") for a in argv[1:]):
        # New inputs go to a temporary folder; the committed seeds are read only.
        argv += [tempfile.mkdtemp(prefix="lfcam-fuzz-new-"), str(CORPUS)]
    if not any(a.startswith("-timeout=") for a in argv):
        argv.append("-timeout=30")
    os.environ.setdefault("LFCAM_NUM_THREADS", "1")
    # tifffile logs every damaged tag it meets: quiet, the fuzzer prints its own stats.
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    if "--subprocess-probe" in argv:  # the loader's own probe, a fresh interpreter each
        argv.remove("--subprocess-probe")
    else:
        from lfcam.calibration import file as calfile

        calfile._probe = _forked_probe
    atheris.Setup(argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
