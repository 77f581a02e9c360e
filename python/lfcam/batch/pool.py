"""A local pool of worker processes that survives the death of any one of them.

Each worker is a fresh interpreter (``spawn``: a forked child inherits OpenCV's and
BLAS's thread pools in an undefined state and can hang) that runs one task at a time,
so when a worker dies (a crash, the OOM killer) the parent knows which task it was
running, reports that task and starts a new worker for the rest. Workers die with
their parent (``PR_SET_PDEATHSIG`` on Linux, a watchdog thread elsewhere), and ignore
Ctrl-C, which the parent handles by stopping them.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any

from ..errors import LfcamError

__all__ = ["WorkerDied", "run_pool"]


# Workers in a row that may die between tasks (after their last result, before their
# next task) and be replaced.
_MAX_IDLE_DEATHS = 3


@dataclass(frozen=True)
class WorkerDied:
    """The outcome of a task whose worker process died while running it."""

    exitcode: int | None

    def __str__(self) -> str:
        code = self.exitcode
        if code is not None and code < 0:
            try:
                name = signal.Signals(-code).name
            except ValueError:
                name = f"signal {-code}"
            hint = " (the out-of-memory killer?)" if -code == signal.SIGKILL else ""
            return f"the worker process was killed by {name}{hint}"
        return f"the worker process died (exit code {code})"


def die_with_parent(parent_pid: int) -> None:
    """Make this process end when ``parent_pid`` (its parent) does."""
    if sys.platform.startswith("linux"):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0)
    else:  # pragma: no cover - polled where there is no death signal

        def watch() -> None:
            while os.getppid() == parent_pid:
                time.sleep(0.5)
            os._exit(1)

        threading.Thread(target=watch, daemon=True, name="lfcam-parent-watch").start()
    # The parent may have died before the signal was armed.
    if os.getppid() != parent_pid:
        os._exit(1)


def _worker_main(
    conn: Connection,
    parent_pid: int,
    init: Callable[..., Any],
    init_args: tuple[Any, ...],
    func: Callable[[Any, Any], Any],
) -> None:
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        state = init(*init_args)
    except BaseException as exc:
        conn.send(("init-error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", None))
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        index, task = msg
        conn.send(("result", (index, func(state, task))))


class _Worker:
    def __init__(self, ctx: Any, init: Callable[..., Any], init_args: tuple[Any, ...], func: Any):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_worker_main,
            args=(child, os.getpid(), init, init_args, func),
            daemon=True,
            name="lfcam-worker",
        )
        self.proc.start()
        child.close()
        self.ready = False
        self.current: int | None = None

    def stop(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.close()
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join()


def run_pool(
    tasks: Sequence[Any],
    jobs: int,
    init: Callable[..., Any],
    init_args: tuple[Any, ...],
    func: Callable[[Any, Any], Any],
) -> Iterator[tuple[int, Any]]:
    """Run ``func(state, task)`` for every task in ``jobs`` worker processes.

    Each worker calls ``state = init(*init_args)`` once. Yields ``(index, result)`` in
    the order tasks finish; a task whose worker died gets a :class:`WorkerDied` result
    and a new worker takes over the remaining tasks. ``init``, ``func``, the tasks and
    the results must be picklable (module-level functions, plain data).

    Raises
    ------
    LfcamError
        If a worker cannot start (``init`` raised, or it died before it was ready), or
        more than ``_MAX_IDLE_DEATHS`` workers in a row die between tasks.
    """
    ctx = mp.get_context("spawn")
    queue = deque(enumerate(tasks))
    workers: list[_Worker] = []
    # Workers that died between tasks since the last result: a few are replaced, more
    # mean no worker can live long enough to take a task.
    idle_deaths = 0

    def start() -> None:
        workers.append(_Worker(ctx, init, init_args, func))

    def feed(w: _Worker) -> None:
        if queue:
            w.current, task = queue.popleft()
            try:
                w.conn.send((w.current, task))
            except OSError:
                # The worker died after its last message: the task goes back to the
                # queue, and the worker is replaced when its pipe reports the end.
                queue.appendleft((w.current, task))
                w.current = None
        else:
            w.current = None
            with contextlib.suppress(OSError):
                w.conn.send(None)

    try:
        for _ in range(min(jobs, len(tasks))):
            start()
        while workers:
            ready = wait([w.conn for w in workers])
            for w in [w for w in workers if w.conn in ready]:
                try:
                    kind, payload = w.conn.recv()
                except (EOFError, OSError):
                    w.stop()
                    workers.remove(w)
                    if not w.ready:
                        raise LfcamError(
                            f"a worker process could not start: {WorkerDied(w.proc.exitcode)}"
                        ) from None
                    if w.current is not None:
                        yield w.current, WorkerDied(w.proc.exitcode)
                    elif queue:
                        idle_deaths += 1
                        if idle_deaths > _MAX_IDLE_DEATHS:
                            last = WorkerDied(w.proc.exitcode)
                            raise LfcamError(
                                "worker processes keep dying before they get a task"
                                f" ({idle_deaths} in a row; the last: {last})"
                            ) from None
                    if queue:
                        start()
                    continue
                if kind == "init-error":
                    raise LfcamError(f"a worker process could not start: {payload}")
                if kind == "result":
                    w.current = None
                    idle_deaths = 0
                    yield payload
                w.ready = True
                feed(w)
    finally:
        for w in workers:
            w.stop()
