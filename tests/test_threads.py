"""lfcam's thread pool: its size, and its behaviour across fork()."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import pytest

import lfcam

FORK_TIMEOUT_S = 60.0


@pytest.fixture
def restore_threads() -> Iterator[None]:
    before = lfcam.get_num_threads()
    yield
    lfcam.set_num_threads(before)


def _threads_in_subprocess(env_value: str | None) -> int:
    env = {k: v for k, v in os.environ.items() if k != "LFCAM_NUM_THREADS"}
    if env_value is not None:
        env["LFCAM_NUM_THREADS"] = env_value
    out = subprocess.run(
        [sys.executable, "-c", "import lfcam; print(lfcam.get_num_threads())"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return int(out.stdout)


def test_env_var_sets_the_thread_count() -> None:
    assert _threads_in_subprocess("1") == 1
    assert _threads_in_subprocess("3") == 3


@pytest.mark.parametrize("value", ["0", "-2", "many", ""])
def test_bad_env_var_falls_back_to_the_default(value: str) -> None:
    # The default is the available parallelism (CPU affinity and cgroup quota aware).
    default = _threads_in_subprocess(None)
    assert 1 <= default <= (os.cpu_count() or 1)
    assert _threads_in_subprocess(value) == default


def test_set_num_threads(restore_threads: None) -> None:
    lfcam.set_num_threads(2)
    assert lfcam.get_num_threads() == 2
    lfcam.set_num_threads(np.int64(1))
    assert lfcam.get_num_threads() == 1
    raw = np.arange(600 * 800 * 3, dtype=np.uint32).astype(np.float32).reshape(600, 800, 3)
    rects = [[0, 0, 400, 300], [400, 300, 400, 300]]
    want = np.stack([raw[:300, :400], raw[300:, 400:]])
    for n in (1, 2, 3):
        lfcam.set_num_threads(n)
        assert np.array_equal(lfcam.crop_lenslets(raw, rects), want)


@pytest.mark.parametrize("bad", [0, -1, 1025, 2.0, "2", None, True])
def test_set_num_threads_rejects_bad_values(bad: object, restore_threads: None) -> None:
    before = lfcam.get_num_threads()
    with pytest.raises(lfcam.InputError, match=r"^n: "):
        lfcam.set_num_threads(bad)  # type: ignore[arg-type]
    assert lfcam.get_num_threads() == before


def _crop_in_child(conn, raw: np.ndarray, rects: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    try:
        conn.send(("ok", lfcam.crop_lenslets(raw, rects)))
    except BaseException as e:  # report anything, the parent asserts
        conn.send(("error", repr(e)))
    finally:
        conn.close()


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="needs fork()")
@pytest.mark.filterwarnings("ignore:This process .* is multi-threaded:DeprecationWarning")
def test_forked_child_after_a_parallel_crop(restore_threads: None) -> None:
    # The parent must have started its worker threads before the fork: a child that
    # inherited the pool without its threads would hang on its first parallel job.
    lfcam.set_num_threads(2)
    raw = np.random.default_rng(1).integers(0, 255, (1080, 1920, 3), dtype=np.uint8)
    rects = np.array([[c * 480, r * 360, 480, 360] for r in range(3) for c in range(4)])
    want = np.stack([raw[y : y + h, x : x + w] for x, y, w, h in rects])
    assert np.array_equal(lfcam.crop_lenslets(raw, rects), want)  # parallel path, > 256 KiB

    ctx = multiprocessing.get_context("fork")
    parent_conn, child_conn = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_crop_in_child, args=(child_conn, raw, rects))
    child.start()
    child_conn.close()
    try:
        assert parent_conn.poll(FORK_TIMEOUT_S), "forked child hung: rayon pool not rebuilt"
        status, result = parent_conn.recv()
        assert status == "ok", result
        assert np.array_equal(result, want)
    finally:
        child.join(5)
        if child.is_alive():
            child.kill()
            child.join()
    assert child.exitcode == 0
    # The parent's pool still works.
    assert np.array_equal(lfcam.crop_lenslets(raw, rects), want)


_MAIN_THREAD_JOINS = """
import os, threading
import numpy as np
import lfcam

def lfcam_threads():
    names = []
    for t in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{t}/comm") as f:
            names.append(f.read().strip())
    return sorted(n for n in names if n.startswith("lfcam-"))

raw = np.random.default_rng(1).integers(0, 255, (1080, 1920, 3), dtype=np.uint8)
rects = np.array([[c * 480, r * 360, 480, 360] for r in range(3) for c in range(4)])
want = np.stack([raw[y : y + h, x : x + w] for x, y, w, h in rects])
assert np.array_equal(lfcam.crop_lenslets(raw, rects), want)
print("main", lfcam_threads())
# Other threads use the ordinary pool, also while the main thread works.
ok = []
def other():
    for _ in range(5):
        ok.append(np.array_equal(lfcam.crop_lenslets(raw, rects), want))
threads = [threading.Thread(target=other) for _ in range(2)]
for t in threads:
    t.start()
for _ in range(5):
    ok.append(np.array_equal(lfcam.crop_lenslets(raw, rects), want))
for t in threads:
    t.join()
print("all", len(ok), all(ok), lfcam_threads())
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="Linux only")
def test_main_thread_takes_part_and_other_threads_use_the_pool() -> None:
    # 2 threads: the main thread is worker 0 of its pool, which starts one more
    # ("lfcam-1"); calls from other threads go to the ordinary pool ("lfcam-0",
    # "lfcam-1"), and everyone gets the same result, concurrently too.
    env = {**os.environ, "LFCAM_NUM_THREADS": "2"}
    out = subprocess.run(
        [sys.executable, "-c", _MAIN_THREAD_JOINS],
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout.splitlines()
    assert out == [
        "main ['lfcam-1']",
        "all 15 True ['lfcam-0', 'lfcam-1', 'lfcam-1']",
    ]
