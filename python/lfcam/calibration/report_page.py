"""The calibration report as a page a person reads: ``CAMERA.report.html``.

One self-contained HTML file (pictures embedded, no scripts, no network): a verdict
(pass / warn / fail) against the thresholds it states, the summary, per view the
photometric residual, coverage, flow convergence, image-circle centre and ``o_i`` as
numbers, the ``o_i`` vectors drawn on the sensor layout, the parallax fit (measured
against fitted parallax, with its residual), and the report picture.
"""

from __future__ import annotations

import base64
import html
import math
from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from .file import Calibration

__all__ = ["FAIL", "PASS", "WARN", "ReportThresholds", "report_html", "report_verdicts"]

PASS, WARN, FAIL = "pass", "warn", "fail"
_ORDER = {PASS: 0, WARN: 1, FAIL: 2}


@dataclass(frozen=True)
class ReportThresholds:
    """Limits of the report's verdicts: ``(pass up to, warn up to)``; beyond: fail.

    The defaults leave a wide margin over good calibrations of the simulated reference
    camera (residual RMS 0.17-0.18, parallax fit 0.007 px, perpendicular parallax
    0.005-0.010 px, last flow update <= 0.013 px, view coverages within 5% of each
    other) and flag what breaks depth: a view registered on a fraction of its area, a
    flow that did not converge, a board that moved sideways or tilted between
    distances (large perpendicular parallax) or a parallax model that does not fit.

    Attributes
    ----------
    residual_rms : (float, float)
        A view's photometric residual RMS after rectification (contrast units).
    coverage_ratio : (float, float)
        A view's coverage over the median view's, as lower limits (smaller is worse).
    flow_update_px : (float, float)
        The last update of a view's iterated registration flow, px.
    parallax_fit_rms_px : (float, float)
        RMS of the measured parallax minus ``o_i s(Z)``, px.
    perpendicular_rms_px : (float, float)
        RMS of the parallax component perpendicular to ``o_i``, px (pure error).
    """

    residual_rms: tuple[float, float] = (0.25, 0.40)
    coverage_ratio: tuple[float, float] = (0.80, 0.60)
    flow_update_px: tuple[float, float] = (0.05, 0.20)
    parallax_fit_rms_px: tuple[float, float] = (0.05, 0.20)
    perpendicular_rms_px: tuple[float, float] = (0.05, 0.20)


def _upper(value: float | None, limits: tuple[float, float]) -> str:
    if value is None or not math.isfinite(value):
        return WARN
    return PASS if value <= limits[0] else WARN if value <= limits[1] else FAIL


def _lower(value: float, limits: tuple[float, float]) -> str:
    return PASS if value >= limits[0] else WARN if value >= limits[1] else FAIL


def _worst(verdicts: Any) -> str:
    return max(verdicts, key=lambda v: _ORDER[v], default=PASS)


def report_verdicts(
    report: dict[str, Any], thresholds: ReportThresholds | None = None
) -> dict[str, Any]:
    """Pass / warn / fail for each view and for the depth model, from a report dict.

    Returns
    -------
    dict
        ``views``: per view ``residual``, ``coverage``, ``flow`` and ``overall``;
        ``parallax_fit``, ``perpendicular``, ``depth`` (warn for relative depth);
        ``overall``: the worst of all.

    Examples
    --------
    >>> rep = {
    ...     "summary": {"depth": "metric", "parallax_fit_rms_px": 0.01,
    ...                 "perpendicular_parallax_rms_px": 0.3},
    ...     "views": [{"photometric_residual_rms": 0.2, "coverage": 0.25,
    ...                "last_flow_update_px": 0.01}] * 2,
    ... }
    >>> v = report_verdicts(rep)
    >>> v["views"][0]["overall"], v["perpendicular"], v["overall"]
    ('pass', 'fail', 'fail')
    """
    t = thresholds or ReportThresholds()
    views = report["views"]
    cov = [float(v["coverage"]) for v in views]
    med = float(np.median(cov)) if cov else 0.0
    per_view = []
    for v in views:
        d = {
            "residual": _upper(v["photometric_residual_rms"], t.residual_rms),
            "coverage": _lower(float(v["coverage"]) / med if med > 0 else 0.0, t.coverage_ratio),
            "flow": _upper(v["last_flow_update_px"], t.flow_update_px),
        }
        d["overall"] = _worst(d.values())
        per_view.append(d)
    s = report["summary"]
    metric = s.get("depth") == "metric"
    out: dict[str, Any] = {
        "views": per_view,
        "parallax_fit": _upper(s.get("parallax_fit_rms_px"), t.parallax_fit_rms_px)
        if s.get("parallax_fit_rms_px") is not None
        else PASS,
        "perpendicular": _upper(s.get("perpendicular_parallax_rms_px"), t.perpendicular_rms_px)
        if s.get("perpendicular_parallax_rms_px") is not None
        else PASS,
        "depth": PASS if metric else WARN,
    }
    out["overall"] = _worst(
        [*(d["overall"] for d in per_view), out["parallax_fit"], out["perpendicular"], out["depth"]]
    )
    return out


# --------------------------------------------------------------------------- drawing
def _fmt(x: float | None, nd: int = 3) -> str:
    return "n/a" if x is None or not math.isfinite(float(x)) else f"{float(x):.{nd}f}"


def _badge(verdict: str) -> str:
    return f'<span class="v {verdict}">{verdict}</span>'


def _layout_svg(cal: Calibration, width: int = 760) -> str:
    """The raw frame with each view's crop, circle centre and ``o_i`` arrow."""
    H, W = (int(v) for v in cal.raw_shape)
    k = width / W
    h = round(H * k)
    longest = max(float(np.hypot(*o)) for o in cal.offsets) or 1.0
    crop_w = float(np.median(cal.crops[:, 2]))
    arrow = 0.4 * crop_w / longest  # the longest arrow: 40% of a crop's width
    C = cal.grid[1]
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{h}"'
        f' viewBox="0 0 {width} {h}" role="img" aria-label="sensor layout">',
        f'<rect x="0" y="0" width="{width}" height="{h}" fill="#222"/>',
        '<defs><marker id="head" markerWidth="8" markerHeight="8" refX="6" refY="4"'
        ' orient="auto"><path d="M0,0 L8,4 L0,8 z" fill="#ffcc00"/></marker></defs>',
    ]
    for i, (x0, y0, cw, ch) in enumerate(cal.crops.tolist()):
        r, c = divmod(i, C)
        ref = i == cal.reference
        parts.append(
            f'<rect x="{x0 * k:.1f}" y="{y0 * k:.1f}" width="{cw * k:.1f}"'
            f' height="{ch * k:.1f}" fill="none" stroke="{"#4fc3f7" if ref else "#3c3"}"'
            ' stroke-width="1.5"/>'
        )
        parts.append(
            f'<text x="{x0 * k + 4:.1f}" y="{y0 * k + 14:.1f}" fill="#ddd" font-size="12"'
            f' font-family="sans-serif">({r}, {c}){" ref" if ref else ""}</text>'
        )
        cx, cy = (float(v) * k for v in cal.centres[i])
        parts.append(f'<circle cx="{cx:.1f}" cy="{cy:.1f}" r="3" fill="#f44"/>')
        ox, oy = (float(v) * arrow * k for v in cal.offsets[i])
        if math.hypot(ox, oy) > 1:
            parts.append(
                f'<line x1="{cx:.1f}" y1="{cy:.1f}" x2="{cx + ox:.1f}" y2="{cy + oy:.1f}"'
                ' stroke="#ffcc00" stroke-width="2" marker-end="url(#head)"/>'
            )
    parts.append("</svg>")
    return "".join(parts)


def _fit_svg(cal: Calibration, report: dict[str, Any], size: int = 360) -> str | None:
    """Measured board parallax (x and y components of every view) against the fit
    ``o_i s(Z)``, one colour per distance; points on the diagonal fit exactly."""
    dm = report.get("depth_model", {})
    s_of = dm.get("s") or {}
    par = dm.get("parallax") or {}
    pts = []
    for key, p in par.items():
        if key not in s_of:
            continue
        meas = np.asarray(p["parallax_px"], np.float64)
        pred = cal.offsets * float(s_of[key])
        pts.append((key, pred.ravel(), meas.ravel()))
    if not pts:
        return None
    lim = max(float(np.nanmax(np.abs(np.concatenate([a, b])))) for _, a, b in pts) * 1.1 or 1.0
    m = 44  # margin for the axis labels

    def xy(u: float, v: float) -> tuple[float, float]:
        return m + (u + lim) / (2 * lim) * (size - m - 8), 8 + (lim - v) / (2 * lim) * (
            size - m - 8
        )

    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"]
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{size + 150}" height="{size}"'
        ' role="img" aria-label="parallax fit" font-family="sans-serif" font-size="12">',
        f'<rect x="{m}" y="8" width="{size - m - 8}" height="{size - m - 8}" fill="#fafafa"'
        ' stroke="#999"/>',
    ]
    (x0, y0), (x1, y1) = xy(-lim, -lim), xy(lim, lim)
    out.append(
        f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" stroke="#999"'
        ' stroke-dasharray="4 3"/>'
    )
    for j, (key, pred, meas) in enumerate(pts):
        col = colours[j % len(colours)]
        for u, v in zip(pred, meas):
            if math.isfinite(u) and math.isfinite(v):
                px, py = xy(u, v)
                out.append(f'<circle cx="{px:.1f}" cy="{py:.1f}" r="2.5" fill="{col}"/>')
        ly = 20 + 18 * j
        out.append(f'<circle cx="{size + 12}" cy="{ly - 4}" r="4" fill="{col}"/>')
        out.append(f'<text x="{size + 22}" y="{ly}">board at {html.escape(key)} m</text>')
    out.append(
        f'<text x="{(m + size) / 2:.0f}" y="{size - 12}" text-anchor="middle">'
        "fitted o_i s(Z), px</text>"
    )
    out.append(
        f'<text x="12" y="{(size - m) / 2:.0f}" text-anchor="middle"'
        f' transform="rotate(-90 12 {(size - m) / 2:.0f})">measured, px</text>'
    )
    out.append(f'<text x="{m}" y="{size - 28}">-{lim:.3g}</text>')
    out.append(f'<text x="{size - 8}" y="{size - 28}" text-anchor="end">{lim:.3g}</text>')
    out.append("</svg>")
    return "".join(out)


_CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { margin-bottom: 0.2em; }
h2 { margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; }
td, th { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th { background: #f0f0f0; }
td.l, th.l { text-align: left; }
.v { padding: 1px 8px; border-radius: 3px; color: #fff; font-weight: bold; }
.v.pass { background: #2e7d32; } .v.warn { background: #ef6c00; } .v.fail { background: #c62828; }
figure { margin: 0.8em 0; } figcaption { color: #555; font-size: 0.9em; max-width: 900px; }
img { max-width: 100%; }
"""


def report_html(
    cal: Calibration,
    figure: np.ndarray | None = None,
    thresholds: ReportThresholds | None = None,
    *,
    title: str = "lfcam calibration report",
) -> str:
    """The report page of a calibration (self-contained HTML, UTF-8).

    Parameters
    ----------
    cal : Calibration
        Its ``report`` dict holds the numbers.
    figure : (H, W, 3) uint8 array, optional
        The report picture (:func:`lfcam.calibration.report.calibration_figure`),
        embedded as PNG.
    thresholds : ReportThresholds, optional
        The verdicts' limits (stated on the page).
    title : str
        The page's title.
    """
    t = thresholds or ReportThresholds()
    rep = cal.report
    verdict = report_verdicts(rep, t)
    s = rep["summary"]
    esc = html.escape
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{esc(title)}</h1>",
        f"<p>Verdict: {_badge(verdict['overall'])} &nbsp; {cal.grid[0]} x {cal.grid[1]}"
        f" lenslets, reference view {tuple(cal.reference_rc)}, depth {esc(str(s.get('depth')))}"
        f" ({esc(str(s.get('depth_model_route')))}).</p>",
        "<h2>Summary</h2><table>",
    ]
    rows = [
        ("raw frame", f"{cal.raw_shape[1]} x {cal.raw_shape[0]} px"),
        ("rectified frame", f"{cal.rect_shape[1]} x {cal.rect_shape[0]} px, scale {cal.scale:g}"),
        ("Z_b (reference board)", f"{cal.z_b:g} m"),
        ("Z_c", f"{cal.z_c:.4f} m" if cal.metric else "unknown: depth is relative"),
        ("board distances", ", ".join(f"{d:g}" for d in cal.distances.tolist()) + " m"),
        (
            "parallax fit RMS",
            f"{_fmt(s.get('parallax_fit_rms_px'), 4)} px {_badge(verdict['parallax_fit'])}",
        ),
        (
            "perpendicular parallax RMS",
            f"{_fmt(s.get('perpendicular_parallax_rms_px'), 4)} px"
            f" {_badge(verdict['perpendicular'])}",
        ),
        ("depth", f"{esc(str(s.get('depth')))} {_badge(verdict['depth'])}"),
        ("calibration time", f"{_fmt(s.get('seconds'), 1)} s"),
    ]
    out += [f'<tr><th class="l">{esc(k)}</th><td class="l">{v}</td></tr>' for k, v in rows]
    out.append("</table>")
    out.append("<h2>Thresholds</h2><table><tr><th class='l'>quantity</th><th>pass</th>")
    out.append("<th>warn</th><th>fail</th></tr>")
    for name, (a, b) in asdict(t).items():
        lower = name == "coverage_ratio"
        op, opw = (">=", ">=") if lower else ("<=", "<=")
        out.append(
            f'<tr><td class="l">{esc(name.replace("_", " "))}</td><td>{op} {a:g}</td>'
            f"<td>{opw} {b:g}</td><td>{'<' if lower else '>'} {b:g}</td></tr>"
        )
    out.append(
        "</table><p>Coverage ratio: a view's coverage over the median view's. Relative "
        "depth (no Z_c) is a warning: depth maps are then not in metres.</p>"
    )
    out.append("<h2>Views</h2><table><tr>")
    heads = [
        "view",
        "crop x0, y0, w, h",
        "circle centre x, y (px)",
        "radius (px)",
        "o_i x, y (px)",
        "coverage",
        "residual RMS",
        "flow iterations, last update (px)",
        "verdict",
    ]
    out += [f"<th>{esc(h)}</th>" for h in heads]
    out.append("</tr>")
    for v, d in zip(rep["views"], verdict["views"]):
        r, c = v["row_col"]
        cx, cy = v["centre_px"]
        ox, oy = v["offset_px"]
        out.append(
            f'<tr><td class="l">({r}, {c}){" ref" if v["index"] == cal.reference else ""}</td>'
            f"<td>{', '.join(str(x) for x in v['crop'])}</td>"
            f"<td>{cx:.2f}, {cy:.2f}</td><td>{_fmt(v['circle_radius_px'], 1)}</td>"
            f"<td>{ox:.3f}, {oy:.3f}</td>"
            f"<td>{100 * v['coverage']:.1f} % {_badge(d['coverage'])}</td>"
            f"<td>{_fmt(v['photometric_residual_rms'])} {_badge(d['residual'])}</td>"
            f"<td>{v['flow_iterations']}, {_fmt(v['last_flow_update_px'], 4)}"
            f" {_badge(d['flow'])}</td><td>{_badge(d['overall'])}</td></tr>"
        )
    out.append("</table>")
    out.append(
        "<h2>Sensor layout</h2><figure>"
        + _layout_svg(cal)
        + "<figcaption>The raw frame: each view's crop (green; the reference in blue), its "
        "image-circle centre (red) and its parallax vector o_i (yellow arrow, scaled so the "
        "longest is 40% of a crop's width; a view's image of a point moves by o_i s as "
        "the point's parallax s changes).</figcaption></figure>"
    )
    fit = _fit_svg(cal, rep)
    if fit is not None:
        dm = rep["depth_model"]
        out.append(
            "<h2>Parallax fit</h2><figure>"
            + fit
            + "<figcaption>Board parallax of every view (x and y components) measured at each "
            "calibration distance, against the fitted model o_i s(Z): on the dashed "
            f"diagonal when the model fits. Residual RMS {_fmt(dm.get('residual_rms_px'), 4)}"
            f" px, largest {_fmt(dm.get('residual_max_px'), 4)} px.</figcaption></figure>"
        )
    if figure is not None:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(figure[..., ::-1]))
        if ok:
            b64 = base64.b64encode(buf.tobytes()).decode("ascii")
            out.append(
                "<h2>Pictures</h2><figure>"
                f'<img alt="calibration report picture" src="data:image/png;base64,{b64}">'
                "<figcaption>Top: the white frame with the crops and circle centres. Middle: "
                "each view's warp map beyond its best affine fit (hue: direction, "
                "brightness: magnitude). Bottom: each view's photometric residual after "
                "rectification (white: large; purple: outside the mask).</figcaption></figure>"
            )
    out.append("</body></html>")
    return "\n".join(out)
