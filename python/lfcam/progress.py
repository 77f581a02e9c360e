"""Progress of long commands: a bar on a terminal, log lines elsewhere.

On a terminal a :mod:`tqdm` bar shows progress and is erased when done. When the
stream is not a terminal (``nohup``, CI, a cluster job's log file), each step is one
line through :mod:`logging` (logger ``lfcam.progress``) with the elapsed time and the
rate, so logs show how far a run got and how fast. ``quiet`` shows nothing.
"""

from __future__ import annotations

import logging
import sys
import time
from types import TracebackType
from typing import Any, TextIO

__all__ = ["LOG_FORMAT", "Progress", "configure_logging"]

#: The format of progress lines (and of any other ``lfcam`` log record).
LOG_FORMAT = "%(asctime)s %(name)s %(levelname)s %(message)s"

_LOG = logging.getLogger("lfcam.progress")


def configure_logging(stream: TextIO | None = None, *, quiet: bool = False) -> None:
    """Send ``lfcam``'s log records (INFO and above) to ``stream`` (default stderr).

    Called once by the command line; a program that sets up logging itself skips it.
    ``quiet`` raises the threshold to WARNING: progress lines are INFO.
    """
    root = logging.getLogger("lfcam")
    for h in list(root.handlers):
        if getattr(h, "_lfcam_cli", False):
            root.removeHandler(h)
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(logging.Formatter(LOG_FORMAT, datefmt="%Y-%m-%dT%H:%M:%S"))
    handler._lfcam_cli = True  # type: ignore[attr-defined]
    root.addHandler(handler)
    root.setLevel(logging.WARNING if quiet else logging.INFO)


class Progress:
    """Progress over ``total`` steps of one command.

    Parameters
    ----------
    total : int
        Number of steps (captures, views, stages).
    desc : str
        What is running (``"calibrate"``, ``"process"``), the start of every line.
    unit : str
        What a step is, for the rate (``"capture"`` gives ``capture/s``).
    quiet : bool
        Show nothing.
    stream : file, optional
        Where a bar goes (default stderr); whether it is a terminal chooses between
        the bar and log lines.

    Examples
    --------
    >>> import io
    >>> with Progress(2, "demo", stream=io.StringIO()) as p:
    ...     p.step("simulating")
    ...     p.step("calibrating")
    >>> p.done
    2
    """

    def __init__(
        self,
        total: int,
        desc: str,
        *,
        unit: str = "step",
        quiet: bool = False,
        stream: TextIO | None = None,
    ) -> None:
        self.total = int(total)
        self.desc = desc
        self.unit = unit
        self.done = 0
        self._t0 = time.perf_counter()
        out = stream if stream is not None else sys.stderr
        isatty = getattr(out, "isatty", None)
        self._bar: Any = None
        self._log = not quiet
        if not quiet and isatty is not None and isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, file=out, leave=False)
            self._log = False

    def step(self, msg: str = "", n: int = 1) -> None:
        """Count ``n`` finished steps; ``msg`` says which (or what comes next)."""
        self.done += n
        if self._bar is not None:
            if msg:
                self._bar.set_postfix_str(msg, refresh=False)
            self._bar.update(n)
        elif self._log:
            dt = time.perf_counter() - self._t0
            rate = self.done / dt if dt > 0 else float("inf")
            _LOG.info(
                "%s %d/%d%s (%.1f s elapsed, %.3g %s/s)",
                self.desc,
                self.done,
                self.total,
                f" {msg}" if msg else "",
                dt,
                rate,
                self.unit,
            )

    def skip(self, n: int = 1) -> None:
        """``n`` steps turned out to need no work (complete already): the total, and so
        the rate and the time left, count only the others."""
        self.total = max(self.done, self.total - n)
        if self._bar is not None:
            self._bar.total = self.total
            self._bar.refresh()

    def __call__(self, msg: str = "") -> None:
        """One step: a :class:`Progress` is the ``progress=`` callback of long functions."""
        self.step(msg)

    def close(self) -> None:
        """Erase the bar (log lines stay)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
