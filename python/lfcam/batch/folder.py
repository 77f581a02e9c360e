"""A batch: every capture of a folder processed into an output folder that survives
crashes and concurrent runs (docs/design.md, "Batches").

The captures run in the calling process (``jobs=1``), in a pool of local worker
processes (``jobs > 1``, :mod:`lfcam.batch.pool`) or on a Dask cluster (``client``,
:mod:`lfcam.batch.cluster`).
Before it starts, a batch removes what killed runs left beside its outputs
(:func:`lfcam.io.lock.remove_stale`); each capture is processed while holding its
output folder's lock, and a capture whose lock another run holds is left for the end
of the batch, when this run waits for it (and then usually finds it complete).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ..calibration import Calibration, ZoomCalibration
from ..errors import InputError
from ..io import file_hash, is_image_file
from ..io.lock import remove_stale
from .pool import WorkerDied, run_pool
from .task import (
    CaptureOutcome,
    CaptureTask,
    ProcessOptions,
    as_tuple,
    is_complete,
    load_calibration,
    result_extra,
    run_capture,
)

__all__ = ["BatchSummary", "find_captures", "process_folder"]


@dataclass(frozen=True)
class BatchSummary:
    """What a batch did (:func:`process_folder`).

    Attributes
    ----------
    done, skipped : tuple of str
        Captures processed, and captures skipped because their folder was complete.
    failed : tuple of (str, str)
        Captures that failed, with the reason.
    outcomes : tuple of CaptureOutcome
        Every capture's outcome, in input order.
    seconds : float
        The batch's wall-clock time.
    workers : int
        Worker processes (or Dask workers) used; 1 in the calling process.
    threads : int
        Threads per worker.
    """

    done: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: tuple[tuple[str, str], ...]
    outcomes: tuple[CaptureOutcome, ...] = field(repr=False)
    seconds: float
    workers: int
    threads: int

    @property
    def ok(self) -> bool:
        """Whether no capture failed."""
        return not self.failed


def find_captures(
    inputs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
) -> list[CaptureTask]:
    """The captures of ``inputs`` with their output folders, sorted.

    A file ``x.png`` goes to ``OUT/x``; a folder is searched recursively and
    ``IN/a/b.png`` goes to ``OUT/a/b``, leaving out anything inside ``OUT`` itself.
    Two captures whose output folders are the same, or one inside the other (``IN/a.png``
    and ``IN/a/b.png``), are an :class:`~lfcam.InputError` naming both.
    """
    out = Path(out_dir)
    items = [inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs)
    if not items:
        raise InputError("inputs: no captures given")
    tasks: list[CaptureTask] = []
    out_res = out.resolve()
    for item in items:
        path = Path(item)
        if path.is_file():
            tasks.append(CaptureTask(str(path), str(out / path.stem)))
            continue
        if not path.is_dir():
            raise InputError(f"{path}: no such file or folder")
        found = [
            p
            for p in sorted(path.rglob("*"))
            if is_image_file(p) and out_res not in p.resolve().parents
        ]
        if not found:
            raise InputError(f"{path}: no raw captures (PNG, TIFF, JPEG or camera raw) found")
        tasks += [
            CaptureTask(str(p), str(out / p.relative_to(path).with_suffix(""))) for p in found
        ]
    # One output folder inside another would be deleted when the outer one is written.
    seen: dict[tuple[str, ...], CaptureTask] = {}
    for t in tasks:
        parts = Path(t.out).parts
        if parts in seen:
            raise InputError(
                f"{t.source}: has the same output folder as {seen[parts].source} ({t.out})"
            )
        seen[parts] = t
    for parts, t in seen.items():
        for n in range(1, len(parts)):
            outer = seen.get(parts[:n])
            if outer is not None:
                raise InputError(
                    f"{t.source}: its output folder {t.out} is inside that of"
                    f" {outer.source} ({outer.out}), which writing it would replace"
                )
    return tasks


# The calling process's or a pool worker's state: the calibration (every zoom
# setting), loaded once.
@dataclass(frozen=True)
class _WorkerState:
    cal: Calibration | ZoomCalibration
    options: ProcessOptions
    extra: dict[str, Any]
    threads: int


def _init_worker(
    cal: Calibration | ZoomCalibration | str,
    sha256: str | None,
    options: ProcessOptions,
    extra: dict[str, Any],
    threads: int,
) -> _WorkerState:
    import cv2

    from .. import set_num_threads

    set_num_threads(threads)
    cv2.setNumThreads(threads)
    if not isinstance(cal, (Calibration, ZoomCalibration)):
        cal = load_calibration(cal, sha256)
    return _WorkerState(cal, options, extra, threads)


def _run(state: _WorkerState, job: tuple[CaptureTask, bool]) -> CaptureOutcome:
    task, wait = job
    return run_capture(
        task, state.cal, state.options, state.extra, threads=state.threads, wait=wait
    )


def process_folder(
    inputs: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    cal: Calibration | ZoomCalibration | str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    client: Any = None,
    worker_timeout: float | None = None,
    jobs: int = 1,
    threads: int | None = None,
    progress: Callable[[CaptureOutcome, int, int], None] | None = None,
    options: ProcessOptions | None = None,
    **option_values: Any,
) -> BatchSummary:
    """Process every capture of ``inputs`` into ``out_dir``, surviving bad captures.

    Each capture gets ``OUT/<relative path without suffix>/`` with the files of
    :func:`lfcam.outputs.write_capture`, written atomically. Complete folders are
    skipped (unless ``overwrite``); a capture that fails (any exception, or the death
    of the worker process running it) is reported in the summary and the batch goes
    on. Results do not depend on ``client``, ``jobs`` or ``threads``.

    Parameters
    ----------
    inputs : path-like or sequence of path-like
        Raw captures, or folders searched recursively for them.
    cal : Calibration, ZoomCalibration or path-like
        The camera; a path (``.lfcal``) is what worker processes load, once each, after
        checking its sha256, and what ``result.json`` records. Of several zoom
        settings, each capture gets the one its focal length picks (the option
        ``focal_length``, else its metadata, within 2%); a capture that matches none,
        or has no focal length, fails with a reason naming it and the settings.
    out_dir : path-like
        The output folder (made if missing).
    client : dask.distributed.Client, optional
        Run the captures on this Dask cluster, one task each (needs ``lfcam[dask]``
        and a file system the workers share with the caller).
    worker_timeout : float, optional
        Seconds to wait for the cluster's first worker to join (default
        :data:`lfcam.batch.cluster.WORKER_TIMEOUT_S`); then an :class:`~lfcam.InputError`.
    jobs : int
        Local worker processes; 1 processes the captures in the calling process.
    threads : int, optional
        Threads per worker (default: the cores divided among the workers).
    progress : callable, optional
        Called in the calling process as ``progress(outcome, finished, total)`` after
        each capture.
    options : ProcessOptions, optional
        What to make of each capture; keyword arguments (``save_views=True``, ...)
        replace its fields.

    Returns
    -------
    BatchSummary

    Raises
    ------
    InputError
        If an input is missing or has no captures, an option is malformed or does not
        fit ``cal``, or no worker of ``client``'s cluster joins within ``worker_timeout``.
    CalibrationError
        If ``cal`` cannot be loaded.
    """
    t0 = time.perf_counter()
    try:
        opts = replace(options or ProcessOptions(), **option_values)
    except TypeError:
        fields = set(ProcessOptions.__dataclass_fields__)
        raise InputError(
            f"{', '.join(sorted(set(option_values) - fields))}: not an option"
            f" (options: {', '.join(sorted(fields))})"
        ) from None
    opts = replace(opts, refocus=as_tuple(opts.refocus))  # a list is fine: stored as a tuple
    opts.check_values()
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise InputError(f"jobs: must be an integer >= 1, got {jobs!r}")
    if threads is not None and (not isinstance(threads, int) or threads < 1):
        raise InputError(f"threads: must be an integer >= 1, got {threads!r}")
    cal_path: str | None = None
    sha256: str | None = None
    calibration: Calibration | ZoomCalibration
    if isinstance(cal, (Calibration, ZoomCalibration)):
        calibration = cal
    else:
        cal_path = str(cal)
        sha256 = file_hash(cal_path)
        calibration = load_calibration(cal_path, sha256)
    opts.check(calibration)
    tasks = find_captures(inputs, out_dir)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    parents = sorted({str(Path(t.out).parent) for t in tasks})
    for folder in parents:
        remove_stale(folder)

    outcomes: dict[int, CaptureOutcome] = {}
    total = len(tasks)

    def report(i: int, outcome: CaptureOutcome) -> None:
        outcomes[i] = outcome
        if progress is not None:
            progress(outcome, len(outcomes), total)

    todo: list[int] = []
    for i, t in enumerate(tasks):
        if not opts.overwrite and is_complete(t.out):
            report(i, CaptureOutcome(t.source, t.out, "skipped"))
        else:
            todo.append(i)

    cal_arg = calibration if cal_path is None else cal_path
    runner: Callable[[list[tuple[CaptureTask, bool]]], Iterator[tuple[int, Any]]]
    if client is not None:
        from .cluster import cluster_shape, run_on_cluster

        if jobs != 1:
            raise InputError("jobs: not with a client (the cluster's workers run the captures)")
        if worker_timeout is None:
            workers, nthreads = cluster_shape(client)
        else:
            workers, nthreads = cluster_shape(client, worker_timeout)
        extra = result_extra(cal_path, sha256, opts, {"jobs": workers, "threads": nthreads})

        def runner(batch: list[tuple[CaptureTask, bool]]) -> Iterator[tuple[int, Any]]:
            return run_on_cluster(client, batch, cal_arg, sha256, opts, extra)

    else:
        workers = min(jobs, max(1, len(todo)))
        nthreads = threads or max(1, (os.cpu_count() or 1) // workers)
        extra = result_extra(cal_path, sha256, opts, {"jobs": workers, "threads": nthreads})
        args = (cal_arg, sha256, opts, extra, nthreads)
        # In this process, with the calibration already loaded.
        here = (calibration, *args[1:]) if workers == 1 else None

        def runner(batch: list[tuple[CaptureTask, bool]]) -> Iterator[tuple[int, Any]]:
            if here is None:
                return run_pool(batch, workers, _init_worker, args, _run)
            return _run_here(batch, here)

    # Workers given the path load their own copy: this process keeps the calibration
    # only to run captures itself (a full-size one holds about half a gigabyte).
    del calibration
    # Captures whose lock another run holds are tried again at the end, waiting for it.
    busy: list[int] = []
    for wait, batch in ((False, todo), (True, busy)):
        if not batch:
            continue
        for k, outcome in runner([(tasks[i], wait) for i in batch]):
            i = batch[k]
            if isinstance(outcome, WorkerDied):
                # Its lock died with it: what it left half-written can go now.
                out = Path(tasks[i].out)
                remove_stale(out.parent, out.name)
                outcome = CaptureOutcome(tasks[i].source, tasks[i].out, "failed", str(outcome))
            if outcome.status == "busy" and not wait:
                busy.append(i)
            else:
                report(i, outcome)
    # What workers that died left (a cluster runs their tasks again elsewhere).
    for folder in parents:
        remove_stale(folder)

    ordered = tuple(outcomes[i] for i in range(total))
    return BatchSummary(
        done=tuple(o.source for o in ordered if o.status == "done"),
        skipped=tuple(o.source for o in ordered if o.status == "skipped"),
        failed=tuple((o.source, o.reason or o.status) for o in ordered if o.status == "failed"),
        outcomes=ordered,
        seconds=time.perf_counter() - t0,
        workers=workers,
        threads=nthreads,
    )


def _run_here(
    jobs: list[tuple[CaptureTask, bool]], init_args: tuple[Any, ...]
) -> Iterator[tuple[int, Any]]:
    """``(index, outcome)`` of each job, run in this process."""
    import cv2

    from .. import get_num_threads, set_num_threads

    before = get_num_threads(), cv2.getNumThreads()
    state = _init_worker(*init_args)
    try:
        for k, job in enumerate(jobs):
            yield k, _run(state, job)
    finally:
        set_num_threads(before[0])
        cv2.setNumThreads(before[1])
