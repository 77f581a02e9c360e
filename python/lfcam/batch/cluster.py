"""Batches on a Dask cluster (the optional extra ``lfcam[dask]``; docs/design.md,
"Batches").

One task per capture. The calibration reaches each worker once: from its path (a
shared file system; each worker loads it on its first task after checking its sha256
and keeps it), or, for a calibration with no file, scattered to every worker. Each
worker's lfcam thread pool is sized to ``LFCAM_NUM_THREADS`` or else to the worker's
``nthreads``. A worker that dies is restarted by its nanny and Dask runs its task
again elsewhere; atomic writing and the capture's lock make that safe.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from ..calibration import Calibration, ZoomCalibration
from ..errors import InputError
from .task import (
    CaptureOutcome,
    CaptureTask,
    ProcessOptions,
    failure_reason,
    load_calibration,
    run_capture,
)

__all__ = [
    "EXTRA",
    "JOBQUEUE_SYSTEMS",
    "WORKER_TIMEOUT_S",
    "calibration_loads",
    "cluster_client",
    "cluster_shape",
    "import_distributed",
    "make_jobqueue_cluster",
    "run_on_cluster",
]

#: How to install what this module needs.
EXTRA = 'pip install "lfcam[dask]"'
#: Seconds a batch waits for the first worker of a cluster to join (the jobs of a
#: dask-jobqueue cluster may wait in the queue).
WORKER_TIMEOUT_S = 300.0
#: ``--cluster`` names started through dask-jobqueue, and their cluster classes.
JOBQUEUE_SYSTEMS = {
    "slurm": "SLURMCluster",
    "pbs": "PBSCluster",
    "sge": "SGECluster",
    "lsf": "LSFCluster",
    "htcondor": "HTCondorCluster",
}


def import_distributed() -> Any:
    """``dask.distributed``, or an :class:`~lfcam.InputError` naming the extra."""
    try:
        import distributed
    except ImportError as exc:
        raise InputError(
            f"--cluster: Dask is not installed ({exc}); install the extra: {EXTRA}"
        ) from None
    return distributed


@contextlib.contextmanager
def cluster_client(
    spec: str, *, config: str | os.PathLike[str] | None = None, timeout: float = 10.0
) -> Iterator[Any]:
    """A Dask client for ``--cluster SPEC``, closed (with any cluster it started) after
    the block.

    Parameters
    ----------
    spec : str
        ``tcp://HOST:PORT`` (or any scheduler address): a running scheduler;
        ``local:N``: a local cluster of N worker processes; ``slurm[:N]``, ``pbs[:N]``,
        ``sge[:N]``, ``lsf[:N]``, ``htcondor[:N]``: N batch jobs of workers (default 1)
        through dask-jobqueue, configured by ``config`` or Dask's own configuration
        (``~/.config/dask/jobqueue.yaml``).
    config : path-like, optional
        A YAML file in Dask's configuration format (``jobqueue: slurm: cores: ...``).
    timeout : float
        Seconds to wait for a scheduler to answer.

    Raises
    ------
    InputError
        If the extra is missing, ``spec`` or ``config`` is malformed, or no scheduler
        answers within ``timeout``.
    """
    distributed = import_distributed()
    kind, _, arg = spec.partition(":")
    with contextlib.ExitStack() as stack:
        cluster: Any = spec
        if kind == "local":
            n = int(arg) if arg.isdigit() else 0
            if n < 1:
                raise InputError(f"--cluster: expected local:N with N >= 1 workers, got {spec!r}")
            cluster = distributed.LocalCluster(
                n_workers=n,
                threads_per_worker=max(1, (os.cpu_count() or 1) // n),
                processes=True,
                dashboard_address=":0",
            )
            stack.enter_context(cluster)
        elif kind in JOBQUEUE_SYSTEMS:
            jobs = int(arg) if arg.isdigit() else (0 if arg else 1)
            if jobs < 1:
                raise InputError(f"--cluster: expected {kind}[:JOBS] with JOBS >= 1, got {spec!r}")
            cluster = stack.enter_context(make_jobqueue_cluster(kind, config))
            cluster.scale(jobs=jobs)
        try:
            client = distributed.Client(cluster, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(
                f"--cluster: no Dask scheduler answered at {spec} within {timeout:g} s ({exc})"
            ) from None
        with client:
            yield client


def make_jobqueue_cluster(kind: str, config: str | os.PathLike[str] | None) -> Any:
    """A dask-jobqueue cluster of ``kind`` (``slurm``, ...) with no jobs yet.

    ``config`` is a YAML file in the layout of Dask's ``jobqueue.yaml``: its section
    ``jobqueue: KIND:`` (``cores``, ``memory``, ``processes``, ``walltime``, ``queue``,
    ``account``, ``job-script-prologue``, ...) is passed to the cluster class; what it
    leaves out comes from Dask's configuration.
    """
    import_distributed()
    try:
        import dask_jobqueue
    except ImportError as exc:
        raise InputError(
            f"--cluster {kind}: dask-jobqueue is not installed ({exc}); install the extra: {EXTRA}"
        ) from None
    kwargs: dict[str, Any] = {}
    where = "Dask's jobqueue configuration"
    if config is not None:
        import yaml

        where = str(config)
        try:
            tree = yaml.safe_load(Path(config).read_text()) or {}
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise InputError(f"{config}: not a readable YAML file ({exc})") from None
        section = tree.get("jobqueue", {}).get(kind) if isinstance(tree, dict) else None
        if not isinstance(section, dict):
            raise InputError(f"{config}: expected a section 'jobqueue: {kind}:' of settings")
        kwargs = {str(k).replace("-", "_"): v for k, v in section.items()}
    cls = getattr(dask_jobqueue, JOBQUEUE_SYSTEMS[kind])
    try:
        # Settings are checked when the first job is made: make one now, to fail early.
        cls.job_cls(scheduler="tcp://localhost:8786", name="check", **kwargs).job_script()
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: cannot start a {kind} cluster: {exc}") from None
    return cls(**kwargs)


# ---------------------------------------------------------------------------
# On the workers
# ---------------------------------------------------------------------------
_lock = threading.Lock()
# Per worker process: calibrations by sha256, how often each was loaded, the threads.
_state: dict[str, Any] = {"cals": {}, "loads": {}, "pool": None}


def _setup_worker() -> tuple[int, int]:
    """Size this worker's thread pool once; returns (pool threads, threads per task)."""
    from distributed import get_worker

    nthreads = get_worker().state.nthreads
    with _lock:
        if _state["pool"] is None:
            import cv2

            from .. import set_num_threads

            env = os.environ.get("LFCAM_NUM_THREADS", "")
            pool = int(env) if env.isdigit() and int(env) > 0 else nthreads
            set_num_threads(pool)
            cv2.setNumThreads(max(1, pool // nthreads))
            _state["pool"] = pool
    pool = _state["pool"]
    return pool, max(1, pool // nthreads)


def _worker_calibration(
    cal: Calibration | ZoomCalibration | str, sha256: str | None
) -> Calibration | ZoomCalibration:
    if isinstance(cal, (Calibration, ZoomCalibration)):
        return cal
    key = sha256 or cal
    with _lock:
        if key not in _state["cals"]:
            _state["cals"][key] = load_calibration(cal, sha256)
            _state["loads"][key] = _state["loads"].get(key, 0) + 1
        return _state["cals"][key]  # type: ignore[no-any-return]


def calibration_loads() -> dict[str, int]:
    """How often this worker process loaded each calibration (by sha256)."""
    return dict(_state["loads"])


def _cluster_task(
    task: CaptureTask,
    cal: Calibration | ZoomCalibration | str,
    sha256: str | None,
    options: ProcessOptions,
    extra: dict[str, Any],
    wait: bool,
) -> CaptureOutcome:
    try:
        _, threads = _setup_worker()
        calibration = _worker_calibration(cal, sha256)
    except Exception as exc:  # this worker cannot serve the batch: the capture says why
        return CaptureOutcome(task.source, task.out, "failed", failure_reason(exc))
    return run_capture(task, calibration, options, extra, threads=threads, wait=wait)


# ---------------------------------------------------------------------------
# In the calling process
# ---------------------------------------------------------------------------
def cluster_shape(client: Any, timeout: float = WORKER_TIMEOUT_S) -> tuple[int, int]:
    """(workers, threads per worker) of the cluster (threads: the largest), once at
    least one worker has joined it.

    Raises
    ------
    InputError
        If no worker joins within ``timeout`` seconds (naming the cluster).
    """
    try:
        client.wait_for_workers(1, timeout=timeout)
    except TimeoutError:
        cluster = getattr(client, "cluster", None)
        address = client.scheduler.address
        where = address if cluster is None else f"{type(cluster).__name__} at {address}"
        raise InputError(
            f"cluster {where}: no Dask worker joined within {timeout:g} s"
            " (are its jobs still waiting in the queue?)"
        ) from None
    info = client.scheduler_info()
    threads = [w.get("nthreads", 1) for w in info.get("workers", {}).values()]
    return len(threads), max(threads, default=1)


def run_on_cluster(
    client: Any,
    jobs: Sequence[tuple[CaptureTask, bool]],
    cal: Calibration | ZoomCalibration | str,
    sha256: str | None,
    options: ProcessOptions,
    extra: dict[str, Any],
) -> Iterator[tuple[int, Any]]:
    """``(index, outcome)`` of each job, run as one Dask task each, as they finish.

    A task Dask gave up on (its workers kept dying) is a ``"failed"`` outcome.
    """
    distributed = import_distributed()
    ref: Any = cal
    if isinstance(cal, (Calibration, ZoomCalibration)):
        ref = client.scatter(cal, broadcast=True, hash=False)
    futures = {
        client.submit(_cluster_task, task, ref, sha256, options, extra, wait, pure=False): k
        for k, (task, wait) in enumerate(jobs)
    }
    for fut in distributed.as_completed(futures):
        k = futures[fut]
        task = jobs[k][0]
        try:
            outcome = fut.result()
        except Exception as exc:  # Dask's own failure (e.g. KilledWorker): this capture's
            outcome = CaptureOutcome(
                task.source, task.out, "failed", f"on the cluster: {failure_reason(exc)}"
            )
        fut.release()
        yield k, outcome
