"""What this installation of lfcam is: version, extension build and the SIMD paths
that run on this machine (``lfcam --version`` prints it)."""

from __future__ import annotations

import platform
import sys
from typing import Any

import lfcam._lfcam as _lfcam

__all__ = ["build_info", "describe_build"]


def build_info() -> dict[str, Any]:
    """The installation and the machine's code paths.

    One wheel serves every x86-64 machine: the AVX2 and AVX-512 kernels are compiled
    in and chosen at run time from what the CPU offers (``LFCAM_SIMD=portable``,
    ``avx2`` or ``avx512`` caps the choice); other machines run the portable code.

    Returns
    -------
    dict
        ``version``; ``python`` and ``machine`` (this interpreter and CPU
        architecture); ``simd``: ``setting`` (``LFCAM_SIMD``, ``auto`` if unset),
        ``cpu`` (the best level this CPU has), ``level`` (the one in use) and, per
        kernel family, the build that runs (``portable``, ``avx2`` or ``avx512``);
        ``threads`` (lfcam's pool, :func:`lfcam.get_num_threads`); ``test_hooks``
        (whether the extension was built with the test-only functions: never in a
        release wheel).

    Examples
    --------
    >>> import lfcam
    >>> info = lfcam.build_info()
    >>> sorted(info)
    ['machine', 'python', 'simd', 'test_hooks', 'threads', 'version']
    >>> info["simd"]["level"] in ("portable", "avx2", "avx512")
    True
    """
    return {
        "version": _lfcam.__version__,
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "machine": platform.machine(),
        "simd": dict(_lfcam.simd_info()),
        "threads": _lfcam.get_num_threads(),
        "test_hooks": hasattr(_lfcam, "_raise_core_error"),
    }


def describe_build() -> str:
    """:func:`build_info` as the lines ``lfcam --version`` prints."""
    info = build_info()
    simd = dict(info["simd"])
    head = [
        f"lfcam {info['version']}",
        f"  python     {info['python']} ({sys.platform}, {info['machine']})",
        f"  simd       {simd.pop('level')} in use (cpu offers {simd.pop('cpu')},"
        f" LFCAM_SIMD={simd.pop('setting')})",
    ]
    kernels = ", ".join(f"{k} {v}" for k, v in simd.items())
    head.append(f"  kernels    {kernels}")
    head.append(f"  threads    {info['threads']}")
    if info["test_hooks"]:
        head.append("  test hooks built in (a development build, not a release wheel)")
    return "\n".join(head)
