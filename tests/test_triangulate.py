"""triangulate against a naive numpy implementation of the same algorithm, on synthetic
flows with known answers (exact, occluded, perpendicular error), edge cases, every kind
of bad input, and parallel == serial."""

from __future__ import annotations

import dataclasses
import doctest
import importlib
from dataclasses import dataclass

import numpy as np
import pytest

import lfcam
from lfcam import _lfcam

triangulate_module = importlib.import_module("lfcam.processing.triangulate")


# --- a naive reference: the documented algorithm, one pixel at a time, float64 -------


def wmedian(x: np.ndarray, v: np.ndarray) -> float:
    """Mean of the first sorted x with 2 C >= T and the first with 2 C > T."""
    order = np.argsort(x, kind="stable")
    xs, cum = x[order], np.cumsum(v[order])
    total = cum[-1]
    lo = xs[np.flatnonzero(2 * cum >= total)[0]]
    hi = xs[np.flatnonzero(2 * cum > total)[0]]
    return float((lo + hi) / 2)


@dataclass
class Pixel:
    s: float
    confidence: float
    residual: float
    perpendicular: float
    n_used: int
    # The smallest |r_i / c - 1| met in any pass: float32 and float64 may keep or drop
    # a view differently when it is ~1e-6.
    margin: float


def naive_pixel(
    u: np.ndarray,  # (N, 2) float32
    w: np.ndarray | None,  # (N,) float32
    offsets: np.ndarray,
    reference: int,
    *,
    min_views: int = 1,
    sigma_floor: float = 0.25,
    cutoff: float = 3.0,
    iterations: int = 5,
) -> Pixel:
    nan = Pixel(np.nan, 0.0, np.nan, np.nan, 0, np.inf)
    norm2_all = (offsets**2).sum(1)
    total_info = norm2_all.sum() - norm2_all[reference]
    u64 = u.astype(np.float64)
    w64 = np.ones(len(u)) if w is None else w.astype(np.float64)
    with np.errstate(invalid="ignore"):
        usable = (
            (np.arange(len(u)) != reference) & (norm2_all > 0) & np.isfinite(u64).all(1) & (w64 > 0)
        )
    if not usable.any():
        return nan
    o, uu, ww = offsets[usable], u64[usable], w64[usable]
    n2 = (o**2).sum(1)
    si = (o * uu).sum(1) / n2
    margin = np.inf

    def one_pass(s: float) -> tuple[np.ndarray, float]:
        nonlocal margin
        r = np.hypot(*(uu - o * s).T)
        c = cutoff * max(sigma_floor, 1.4826 * wmedian(r, ww))
        margin = min(margin, float(np.abs(r / c - 1).min()))
        return r, c

    def tukey(r: np.ndarray, c: float) -> np.ndarray:
        return np.where(r < c, (1 - (r / c) ** 2) ** 2, 0.0)

    s = wmedian(si, ww * n2)
    for _ in range(iterations):
        r, c = one_pass(s)
        b = ww * tukey(r, c)
        den = (b * n2).sum()
        if den <= 0:
            break
        nxt = float((b * (o * uu).sum(1)).sum() / den)
        done = abs(nxt - s) < 1e-6
        s = nxt
        if done:
            break
    r, c = one_pass(s)
    kept = r < c
    n = int(kept.sum())
    if n < min_views:
        return dataclasses.replace(nan, n_used=n, margin=margin)
    b = ww[kept] * tukey(r[kept], c)
    q = (o[:, 0] * uu[:, 1] - o[:, 1] * uu[:, 0]) / np.sqrt(n2)
    residual = float(np.sqrt((b * r[kept] ** 2).sum() / b.sum()))
    info = (ww * n2)[kept].sum() / total_info
    confidence = (1 - np.exp(-info / 0.25)) * np.exp(-((residual / 0.5) ** 2))
    return Pixel(s, confidence, residual, float(np.sqrt((q[kept] ** 2).mean())), n, margin)


# --- synthetic captures ----------------------------------------------------------------


def grid_offsets(rows: int, cols: int, reference: int, spacing: float) -> np.ndarray:
    r, c = np.divmod(np.arange(rows * cols), cols)
    rr, rc = divmod(reference, cols)
    return spacing * np.stack([c - rc, r - rr], axis=1).astype(np.float64)


def exact_flows(offsets: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(N, H, W, 2) float32 flows o_i s(p), no noise."""
    return (offsets[:, None, None, :] * s[None, :, :, None]).astype(np.float32)


def random_capture(
    rng: np.random.Generator, n: int, h: int, w: int, weighted: bool
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray | None, np.ndarray]:
    reference = int(rng.integers(n))
    length, angle = rng.uniform(3, 40, n), rng.uniform(0, 2 * np.pi, n)
    offsets = np.stack([length * np.cos(angle), length * np.sin(angle)], axis=1)
    offsets[reference] = 0
    s = rng.uniform(-1.5, 0.9, (h, w))
    flows = offsets[:, None, None, :] * s[None, :, :, None]
    flows += rng.normal(0, rng.uniform(0.02, 0.4), flows.shape)
    flows = flows.astype(np.float32)
    flows[rng.random((n, h, w)) < 0.08, 0] = np.nan
    weights = None
    if weighted:
        weights = rng.uniform(0.05, 2.0, (n, h, w)).astype(np.float32)
        roll = rng.random((n, h, w))
        weights[roll < 0.1] = 0
        weights[(roll >= 0.1) & (roll < 0.15)] = np.nan
    return flows, offsets, reference, weights, s


def compare_to_naive(flows, offsets, reference, weights, **params) -> int:  # type: ignore[no-untyped-def]
    """Every pixel against naive_pixel to 1e-4; returns how many were skipped because a
    view came within 1e-4 of the cutoff."""
    res = lfcam.triangulate(flows, offsets, reference, weights, **params)
    h, w = flows.shape[1:3]
    skipped = 0
    for y in range(h):
        for x in range(w):
            want = naive_pixel(
                flows[:, y, x],
                None if weights is None else weights[:, y, x],
                offsets,
                reference,
                **params,
            )
            if want.margin < 1e-4:
                skipped += 1
                continue
            where = f"pixel ({y}, {x}): want {want}"
            assert res.n_used[y, x] == want.n_used, where
            for name, tol in [
                ("s", 1e-4),
                ("residual", 1e-4),
                ("perpendicular", 1e-4),
                ("confidence", 1e-4),
            ]:
                got = float(getattr(res, "parallax" if name == "s" else name)[y, x])
                expected = getattr(want, name)
                if np.isnan(expected):
                    assert np.isnan(got), f"{where}: {name} {got}"
                else:
                    assert abs(got - expected) <= tol * max(1.0, abs(expected)), (
                        f"{where}: {name} {got}"
                    )
    return skipped


# --- tests -----------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_matches_naive_numpy_implementation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 17))
    h, w = 4, int(rng.integers(60, 90))  # a few hundred pixels, more than one block
    flows, offsets, reference, weights, _ = random_capture(rng, n, h, w, weighted=seed % 2 == 1)
    params = {
        "min_views": int(rng.integers(1, min(3, n - 1) + 1)),
        "sigma_floor": float(rng.uniform(0.05, 0.6)),
        "cutoff": float(rng.uniform(1.5, 4.5)),
        "iterations": int(rng.integers(0, 8)),
    }
    skipped = compare_to_naive(flows, offsets, reference, weights, **params)
    assert skipped <= 2


def test_default_parameters_match_naive_with_occlusions() -> None:
    rng = np.random.default_rng(42)
    flows, offsets, reference, weights, _ = random_capture(rng, 12, 3, 100, weighted=True)
    occluded = rng.random(flows.shape[:3]) < 0.15
    flows[occluded] += rng.uniform(2, 10, (int(occluded.sum()), 2)).astype(np.float32)
    assert compare_to_naive(flows, offsets, reference, weights) <= 2


def test_exact_flows_are_recovered() -> None:
    offsets = grid_offsets(3, 4, 5, 25.0)
    s = np.linspace(-1.0, 0.95, 7 * 90, dtype=np.float32).reshape(7, 90)
    res = lfcam.triangulate(exact_flows(offsets, s), offsets, 5)
    np.testing.assert_allclose(res.parallax, s, atol=1e-5, rtol=0)
    assert np.abs(res.residual).max() < 1e-3
    assert np.abs(res.perpendicular).max() < 1e-3
    assert (res.n_used == 11).all()
    assert (res.confidence > 0.98).all()
    for a in dataclasses.astuple(res):
        assert a.shape == (7, 90)
        assert a.flags.c_contiguous
    assert res.parallax.dtype == np.float32
    assert res.confidence.dtype == res.residual.dtype == res.perpendicular.dtype
    assert res.n_used.dtype == np.uint8


def test_occluded_third_of_views_is_dropped() -> None:
    # Small offsets (1 px per unit s), so that 5 px errors move plain least squares a lot.
    offsets = grid_offsets(3, 4, 5, 1.0)
    norms = np.hypot(*offsets.T)
    # A third of the views (4 of 12), the nearest to the reference, so that they hold
    # less than half of the information sum |o_i|^2 and the median start holds.
    bad = np.array([1, 4, 6, 9])
    assert (norms[bad] == 1).all()  # 4 of sum |o_i|^2 = 26
    rng = np.random.default_rng(1)
    s = rng.uniform(-0.8, 0.8, (5, 70)).astype(np.float32)
    flows = exact_flows(offsets, s) + rng.normal(0, 0.03, (12, 5, 70, 2)).astype(np.float32)
    flows[bad] += (5 * offsets[bad] / norms[bad, None])[:, None, None, :].astype(np.float32)
    res = lfcam.triangulate(flows, offsets, 5)
    assert np.abs(res.parallax - s).max() < 0.05
    assert (res.n_used == 7).all()  # the 4 bad views are not counted
    # Plain least squares is off by more than 0.5 everywhere: the test can fail.
    others = np.arange(12) != 5
    dot = (offsets[others, None, None, :] * flows[others]).sum(-1).sum(0)
    plain = dot / (norms[others] ** 2).sum()
    assert np.abs(plain - s).min() > 0.5
    # The naive reference agrees.
    assert compare_to_naive(flows[:, :2, :30], offsets, 5, None) == 0


def test_perpendicular_error_is_reported() -> None:
    offsets = grid_offsets(3, 4, 5, 20.0)
    s = np.full((2, 50), 0.3, np.float32)
    flows = exact_flows(offsets, s)
    # 0.4 px perpendicular to o_i, alternating in sign: pure error.
    norms = np.hypot(*offsets.T)
    others = norms > 0
    perp = np.zeros_like(offsets)
    perp[others] = np.stack([-offsets[others, 1], offsets[others, 0]], 1) / norms[others, None]
    sign = np.where(np.arange(12) % 2 == 0, 1.0, -1.0)[:, None]
    flows += (0.4 * sign * perp)[:, None, None, :].astype(np.float32)
    res = lfcam.triangulate(flows, offsets, 5)
    np.testing.assert_allclose(res.parallax, 0.3, atol=1e-5)
    np.testing.assert_allclose(res.perpendicular, 0.4, atol=1e-5)
    np.testing.assert_allclose(res.residual, 0.4, atol=1e-5)
    assert (res.n_used == 11).all()
    # exp(-(0.4 / 0.5)^2) = 0.527, times 0.98 for all the information.
    np.testing.assert_allclose(res.confidence, (1 - np.exp(-4)) * np.exp(-0.64), rtol=1e-5)


def test_all_nan_gives_nan_and_zero_confidence() -> None:
    offsets = grid_offsets(2, 2, 0, 10.0)
    flows = np.full((4, 3, 5, 2), np.nan, np.float32)
    res = lfcam.triangulate(flows, offsets, 0)
    for name in ("parallax", "residual", "perpendicular"):
        assert np.isnan(getattr(res, name)).all(), name
    assert (res.confidence == 0).all()
    assert (res.n_used == 0).all()


def test_single_view() -> None:
    offsets = np.array([[0.0, 0.0], [12.0, -5.0]])  # |o| = 13
    s = np.array([[0.5, -0.25, 0.0]], np.float32)
    flows = exact_flows(offsets, s)
    flows[1, 0, 2] += np.array([5.0, 12.0], np.float32) / 13 * 0.2  # 0.2 px perpendicular
    res = lfcam.triangulate(flows, offsets, 0)
    np.testing.assert_allclose(res.parallax, s, atol=1e-6)
    np.testing.assert_allclose(res.perpendicular, [[0, 0, 0.2]], atol=1e-6)
    np.testing.assert_allclose(res.residual, res.perpendicular, atol=1e-6)
    assert (res.n_used == 1).all()
    with pytest.raises(lfcam.InputError, match=r"^min_views: expected an integer between 1"):
        lfcam.triangulate(flows, offsets, 0, min_views=2)


def test_reference_entry_is_ignored() -> None:
    rng = np.random.default_rng(3)
    flows, offsets, reference, weights, _ = random_capture(rng, 6, 3, 40, weighted=True)
    assert weights is not None
    flows[reference] = np.nan
    want = lfcam.triangulate(flows, offsets, reference, weights)
    flows[reference] = rng.normal(0, 50, flows[reference].shape)
    weights[reference] = -5.0  # not read either: no error
    got = lfcam.triangulate(flows, offsets, reference, weights)
    for a, b in zip(dataclasses.astuple(want), dataclasses.astuple(got)):
        np.testing.assert_array_equal(a, b)


def test_zero_or_nan_weight_is_a_missing_flow() -> None:
    rng = np.random.default_rng(4)
    flows, offsets, reference, _, _ = random_capture(rng, 8, 3, 40, weighted=False)
    weights = np.ones(flows.shape[:3], np.float32)
    drop = rng.random(weights.shape) < 0.3
    weights[drop] = np.where(rng.random(int(drop.sum())) < 0.5, 0.0, np.nan)
    got = lfcam.triangulate(flows, offsets, reference, weights)
    holes = flows.copy()
    holes[drop] = np.nan
    want = lfcam.triangulate(holes, offsets, reference)
    for a, b in zip(dataclasses.astuple(want), dataclasses.astuple(got)):
        np.testing.assert_array_equal(a, b)
    # Weight 1 everywhere is the same as no weights.
    ones = lfcam.triangulate(flows, offsets, reference, np.ones_like(weights))
    none = lfcam.triangulate(flows, offsets, reference)
    for a, b in zip(dataclasses.astuple(ones), dataclasses.astuple(none)):
        np.testing.assert_array_equal(a, b)


def test_zero_offset_view_is_not_used() -> None:
    offsets = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 0.0], [0.0, 10.0]])
    s = np.full((1, 4), 0.5, np.float32)
    flows = exact_flows(offsets, s)
    flows[2] = 7.0  # a view without parallax: its flow says nothing about s
    res = lfcam.triangulate(flows, offsets, 0)
    np.testing.assert_allclose(res.parallax, 0.5, atol=1e-6)
    assert (res.n_used == 2).all()


def test_min_views_and_iterations() -> None:
    rng = np.random.default_rng(5)
    flows, offsets, reference, _, _ = random_capture(rng, 5, 4, 30, weighted=False)
    res = lfcam.triangulate(flows, offsets, reference, min_views=4)
    few = res.n_used < 4
    assert few.any()
    assert np.isnan(res.parallax[few]).all()
    assert (res.confidence[few] == 0).all()
    assert not np.isnan(res.parallax[~few]).any()
    zero = lfcam.triangulate(flows, offsets, reference, iterations=0)
    assert compare_to_naive(flows, offsets, reference, None, iterations=0) == 0
    assert not np.array_equal(zero.parallax, res.parallax, equal_nan=True)


def test_parallel_equals_serial() -> None:
    rng = np.random.default_rng(6)
    flows, offsets, reference, weights, _ = random_capture(rng, 12, 150, 220, weighted=True)
    before = lfcam.get_num_threads()
    try:
        lfcam.set_num_threads(1)
        serial = lfcam.triangulate(flows, offsets, reference, weights)
        lfcam.set_num_threads(2)
        parallel = lfcam.triangulate(flows, offsets, reference, weights)
    finally:
        lfcam.set_num_threads(before)
    for a, b in zip(dataclasses.astuple(serial), dataclasses.astuple(parallel)):
        np.testing.assert_array_equal(a, b)


def test_non_contiguous_inputs_are_copied() -> None:
    rng = np.random.default_rng(7)
    flows, offsets, reference, weights, _ = random_capture(rng, 4, 10, 12, weighted=True)
    want = lfcam.triangulate(flows, offsets, reference, weights)
    f_t = np.ascontiguousarray(flows.transpose(0, 2, 1, 3)).transpose(0, 2, 1, 3)
    w_t = np.ascontiguousarray(weights.transpose(0, 2, 1)).transpose(0, 2, 1)  # type: ignore[union-attr]
    assert not f_t.flags.c_contiguous
    got = lfcam.triangulate(f_t, offsets.tolist(), reference, w_t)
    for a, b in zip(dataclasses.astuple(want), dataclasses.astuple(got)):
        np.testing.assert_array_equal(a, b)


def test_result_is_frozen() -> None:
    offsets = grid_offsets(1, 2, 0, 5.0)
    res = lfcam.triangulate(np.zeros((2, 1, 1, 2), np.float32), offsets, 0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.parallax = res.residual  # type: ignore[misc]


def good_args() -> dict[str, object]:
    return {
        "flows": np.zeros((3, 2, 4, 2), np.float32),
        "offsets": np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]),
        "reference": 0,
        "weights": np.ones((3, 2, 4), np.float32),
    }


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        ({"flows": np.zeros((3, 2, 4, 2))}, r"^flows: dtype float64 is not supported"),
        ({"flows": np.zeros((3, 2, 4), np.float32)}, r"^flows: expected a non-empty \(N, H, W"),
        ({"flows": np.zeros((3, 2, 4, 3), np.float32)}, r"^flows: expected shape \(N, H, W, 2\)"),
        ({"flows": np.zeros((3, 0, 4, 2), np.float32)}, r"^flows: expected a non-empty"),
        ({"flows": "abc"}, r"^flows: dtype <U3 is not supported"),
        ({"flows": np.zeros((129, 1, 1, 2), np.float32)}, r"^flows: expected between 2 and 128"),
        ({"offsets": np.zeros((2, 2))}, r"^offsets: expected shape \(N, 2\) = \(3, 2\)"),
        ({"offsets": [[0, 0], [1, 1], [1j, 0]]}, r"^offsets: expected real numbers"),
        ({"offsets": [[0, 0], [np.nan, 1], [1, 0]]}, r"^offsets\[1\]: .* is not finite"),
        ({"offsets": [[0.5, 0], [1, 1], [1, 0]]}, r"^offsets\[0\]: the reference view's offset"),
        ({"offsets": np.zeros((3, 2))}, r"^offsets: every view's offset is zero"),
        ({"reference": 3}, r"^reference: expected a view index between 0 and 2, got 3"),
        ({"reference": -1}, r"^reference: expected an integer >= 0"),
        ({"reference": 1.0}, r"^reference: expected an integer"),
        ({"weights": np.ones((3, 2, 4))}, r"^weights: dtype float64 is not supported"),
        ({"weights": np.ones((3, 2, 5), np.float32)}, r"^weights: expected shape \(N, H, W\)"),
        ({"weights": np.ones((3, 8), np.float32)}, r"^weights: expected a non-empty \(N, H, W\)"),
        ({"min_views": 0}, r"^min_views: expected an integer >= 1"),
        ({"min_views": 3}, r"^min_views: expected an integer between 1 and N - 1 = 2"),
        ({"sigma_floor": 0.0}, r"^sigma_floor: expected a finite number > 0"),
        ({"sigma_floor": "1"}, r"^sigma_floor: expected a finite number > 0"),
        ({"cutoff": np.inf}, r"^cutoff: expected a finite number > 0"),
        ({"cutoff": -1}, r"^cutoff: expected a finite number > 0"),
        ({"iterations": -1}, r"^iterations: expected an integer >= 0"),
        ({"iterations": True}, r"^iterations: expected an integer >= 0"),
    ],
)
def test_bad_input_names_the_argument(change: dict[str, object], pattern: str) -> None:
    args = {**good_args(), **change}
    with pytest.raises(lfcam.InputError, match=pattern):
        lfcam.triangulate(**args)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [-0.5, np.inf])
def test_negative_or_infinite_weight_names_view_and_pixel(bad: float) -> None:
    args = good_args()
    weights = args["weights"]
    assert isinstance(weights, np.ndarray)
    weights[2, 1, 3] = bad
    with pytest.raises(lfcam.InputError, match=r"^weights\[2\]: weight .* at row 1, column 3"):
        lfcam.triangulate(**args)  # type: ignore[arg-type]


def test_bindings_check_their_own_arguments() -> None:
    a = good_args()
    flows, offsets, weights = a["flows"], a["offsets"], a["weights"]
    assert isinstance(flows, np.ndarray)
    assert isinstance(weights, np.ndarray)

    def call(**change: object) -> None:
        args = {
            "flows": flows,
            "offsets": offsets,
            "reference": 0,
            "weights": weights,
            "min_views": 1,
            "sigma_floor": 0.25,
            "cutoff": 3.0,
            "iterations": 5,
            **change,
        }
        _lfcam.triangulate(*args.values())  # type: ignore[arg-type]

    call()
    cases = [
        ({"flows": flows.astype(np.float64)}, r"^flows: expected dtype float32, got float64"),
        ({"flows": flows[..., 0]}, r"^flows: expected a 4-D \(N, H, W, 2\) array"),
        ({"flows": flows[:, :, ::2]}, r"^flows: must be C-contiguous"),
        ({"flows": flows[:1]}, r"^flows: expected between 2 and 128 views"),
        ({"flows": [[1.0]]}, r"^flows: expected a numpy.ndarray, got list"),
        ({"offsets": np.zeros((3, 2), np.float32)}, r"^offsets: expected dtype float64"),
        ({"offsets": np.zeros((3, 3))}, r"^offsets: expected shape \(N, 2\)"),
        ({"weights": weights[:2]}, r"^weights: expected shape \(N, H, W\) = \(3, 2, 4\)"),
        ({"weights": weights[..., 0]}, r"^weights: expected a 3-D \(N, H, W\) array"),
        ({"reference": -1}, r"^reference: expected an integer >= 0, got -1"),
        ({"reference": 7}, r"^reference: expected a view index between 0 and 2"),
        ({"min_views": 0}, r"^min_views: expected an integer between 1 and 127"),
        ({"sigma_floor": 1e-60}, r"^sigma_floor: expected a finite number > 0"),
        ({"cutoff": float("nan")}, r"^cutoff: expected a finite number > 0"),
        ({"iterations": -2}, r"^iterations: expected an integer >= 0"),
    ]
    for change, pattern in cases:
        with pytest.raises(lfcam.InputError, match=pattern):
            call(**change)


def test_docstring_examples() -> None:
    result = doctest.testmod(triangulate_module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0
