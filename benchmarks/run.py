"""Benchmarks of lfcam's functions against the numpy / OpenCV way of doing the same thing.

Each row times lfcam and its reference in the same run, alternating calls, and prints
the medians and the ratio lfcam / reference (below 1: lfcam is faster). Outputs are
compared once before timing, so a row cannot be fast by being wrong.

    python benchmarks/run.py                  # full-size frames, 15 repeats
    python benchmarks/run.py --quick          # 5 repeats
    python benchmarks/run.py --size small     # 1920x1080 frames
    python benchmarks/run.py -k crop          # rows whose name contains "crop"

To add a row (rectify, triangulate, ...), write a function that takes the size name and
returns a :class:`Case`, and decorate it with ``@row("name")``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

import lfcam

SIZES = ("small", "full")


@dataclass
class Case:
    """One benchmark: lfcam's call and the reference call, on the same inputs."""

    lfcam: Callable[[], Any]
    reference: Callable[[], Any]
    reference_name: str
    shape: str
    # Compares the two outputs; the row fails loudly if they differ.
    same: Callable[[Any, Any], bool] = field(default=lambda a, b: bool(np.array_equal(a, b)))
    threads: int | None = None  # lfcam threads for this row; None: the current setting


@dataclass
class Row:
    name: str
    make: Callable[[str], Case]


ROWS: list[Row] = []


def row(name: str) -> Callable[[Callable[[str], Case]], Callable[[str], Case]]:
    """Register ``make(size) -> Case`` as the benchmark row ``name``."""

    def register(make: Callable[[str], Case]) -> Callable[[str], Case]:
        ROWS.append(Row(name, make))
        return make

    return register


# --- rows ---------------------------------------------------------------------------


def _crop_case(size: str, threads: int | None, preallocated: bool = False) -> Case:
    # The paper's 3x4 lenslet array: ~1 Mpx views on the full-size sensor.
    frame, view = {"full": ((2700, 4800), (1200, 900)), "small": ((1080, 1920), (480, 360))}[size]
    (fh, fw), (vw, vh) = frame, view
    raw = np.random.default_rng(0).integers(0, 256, (fh, fw, 3), dtype=np.uint8)
    rects = np.array([[c * vw, r * vh, vw, vh] for r in range(3) for c in range(4)])

    def stack() -> np.ndarray:
        return np.stack([np.ascontiguousarray(raw[y : y + h, x : x + w]) for x, y, w, h in rects])

    def assign() -> np.ndarray:
        out = np.empty((len(rects), vh, vw, 3), raw.dtype)
        for view, (x, y, w, h) in zip(out, rects):
            view[...] = raw[y : y + h, x : x + w]
        return out

    return Case(
        lfcam=lambda: lfcam.crop_lenslets(raw, rects),
        reference=assign if preallocated else stack,
        reference_name="numpy empty + assign" if preallocated else "numpy stack of slices",
        shape=f"{fw}x{fh}x3 u8 -> 12x{vw}x{vh}",
        threads=threads,
    )


@row("crop_lenslets")
def crop_default_threads(size: str) -> Case:
    return _crop_case(size, threads=None)


@row("crop_lenslets, 1 thread")
def crop_one_thread(size: str) -> Case:
    return _crop_case(size, threads=1)


@row("crop_lenslets vs one copy")
def crop_vs_preallocated(size: str) -> Case:
    # The best plain-numpy way: one output allocation, one copy per view.
    return _crop_case(size, threads=None, preallocated=True)


# --- harness ------------------------------------------------------------------------


@dataclass
class Result:
    name: str
    shape: str
    threads: int
    lfcam_ms: float
    reference_name: str
    reference_ms: float

    @property
    def ratio(self) -> float:
        return self.lfcam_ms / self.reference_ms


def _time_ms(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) * 1e3


def run_row(r: Row, size: str, repeats: int) -> Result:
    case = r.make(size)
    default_threads = lfcam.get_num_threads()
    if case.threads is not None:
        lfcam.set_num_threads(case.threads)
    try:
        threads = lfcam.get_num_threads()
        if not case.same(case.lfcam(), case.reference()):  # also the warm-up call
            raise AssertionError(f"{r.name}: lfcam and {case.reference_name} disagree")
        ours, theirs = [], []
        for _ in range(repeats):
            ours.append(_time_ms(case.lfcam))
            theirs.append(_time_ms(case.reference))
    finally:
        lfcam.set_num_threads(default_threads)
    return Result(
        r.name,
        case.shape,
        threads,
        statistics.median(ours),
        case.reference_name,
        statistics.median(theirs),
    )


def format_table(results: list[Result]) -> str:
    header = ["benchmark", "input", "threads", "lfcam ms", "reference", "ref ms", "lfcam/ref"]
    body = [
        [
            res.name,
            res.shape,
            str(res.threads),
            f"{res.lfcam_ms:.2f}",
            res.reference_name,
            f"{res.reference_ms:.2f}",
            f"{res.ratio:.2f}",
        ]
        for res in results
    ]
    numeric = {2, 3, 5, 6}
    widths = [max(len(line[i]) for line in [header, *body]) for i in range(len(header))]

    def fmt(line: list[str]) -> str:
        cells = [
            cell.rjust(w) if i in numeric else cell.ljust(w)
            for i, (cell, w) in enumerate(zip(line, widths))
        ]
        return "  ".join(cells).rstrip()

    rule = "  ".join("-" * w for w in widths)
    return "\n".join([fmt(header), rule, *(fmt(line) for line in body)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 repeats instead of 15")
    parser.add_argument("--size", choices=SIZES, default="full", help="input size")
    parser.add_argument("--repeats", type=int, help="timed calls per row (overrides --quick)")
    parser.add_argument("-k", metavar="TEXT", help="only rows whose name contains TEXT")
    args = parser.parse_args(argv)
    repeats = args.repeats or (5 if args.quick else 15)

    rows = [r for r in ROWS if not args.k or args.k in r.name]
    print(
        f"lfcam {lfcam.__version__}, numpy {np.__version__}, OpenCV {cv2.__version__}, "
        f"Python {sys.version.split()[0]}; size {args.size}, median of {repeats}"
    )
    results = [run_row(r, args.size, repeats) for r in rows]
    print(format_table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
