"""The calibration report page: numbers per view, verdicts against stated thresholds,
the pictures embedded, titles that never cover a picture."""

from __future__ import annotations

import base64
import copy
import dataclasses
import re

import cv2
import numpy as np

from lfcam.calibration.report import TITLE_BAND, _label, calibration_figure
from lfcam.calibration.report_page import ReportThresholds, report_html, report_verdicts


def test_good_calibration_passes_and_shows_every_number(reference_camera) -> None:
    run = reference_camera.run
    cal = run.calibration
    fig = calibration_figure(cal, run.white, run.residuals)
    page = report_html(cal, fig)
    v = report_verdicts(cal.report)
    # The simulated reference camera is a good calibration: everything passes.
    assert v["overall"] == "pass", v
    assert 'Verdict: <span class="v pass">pass</span>' in page
    for view in cal.report["views"]:
        cx, cy = view["centre_px"]
        ox, oy = view["offset_px"]
        assert f"<td>{cx:.2f}, {cy:.2f}</td>" in page
        assert f"<td>{ox:.3f}, {oy:.3f}</td>" in page
        assert f"{100 * view['coverage']:.1f} %" in page
        assert f"{view['photometric_residual_rms']:.3f}" in page
    # o_i drawn on the sensor layout: one arrow per view but the reference (o = 0).
    layout = page.split('aria-label="sensor layout"')[1].split("</svg>")[0]
    assert layout.count('marker-end="url(#head)"') == cal.n_views - 1
    assert layout.count("<rect ") == cal.n_views + 1  # the frame and one crop per view
    # The parallax fit: every view's x and y at each non-reference distance.
    fit = page.split('aria-label="parallax fit"')[1].split("</svg>")[0]
    n_dist = len(cal.report["depth_model"]["parallax"])
    assert fit.count('r="2.5"') == 2 * cal.n_views * n_dist
    assert f"{cal.report['depth_model']['residual_rms_px']:.4f} px" in page
    # The embedded picture is the report picture, pixel for pixel.
    b64 = re.search(r'src="data:image/png;base64,([^"]+)"', page).group(1)
    png = cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(png[..., ::-1], fig)
    # Thresholds are stated.
    t = ReportThresholds()
    assert f"<= {t.residual_rms[0]:g}" in page
    assert f">= {t.coverage_ratio[0]:g}" in page


def test_bad_calibrations_warn_and_fail(reference_camera) -> None:
    cal = reference_camera.cal
    rep = copy.deepcopy(cal.report)
    rep["views"][3]["photometric_residual_rms"] = 0.5  # > 0.40: fail
    rep["views"][5]["coverage"] = 0.7 * float(np.median([v["coverage"] for v in rep["views"]]))
    rep["views"][7]["last_flow_update_px"] = 0.1  # between 0.05 and 0.20: warn
    rep["summary"]["perpendicular_parallax_rms_px"] = 0.3  # the board moved sideways
    v = report_verdicts(rep)
    assert v["views"][3] == {
        "residual": "fail",
        "coverage": "pass",
        "flow": "pass",
        "overall": "fail",
    }
    assert v["views"][5]["coverage"] == "warn"
    assert v["views"][7]["flow"] == "warn"
    assert v["views"][0]["overall"] == "pass"
    assert v["perpendicular"] == "fail"
    assert v["overall"] == "fail"
    page = report_html(dataclasses.replace(cal, report=rep))
    assert 'Verdict: <span class="v fail">fail</span>' in page
    # Relative depth (no Z_c) is a warning, and stricter thresholds bite.
    rep2 = copy.deepcopy(cal.report)
    rep2["summary"]["depth"] = "relative"
    assert report_verdicts(rep2)["overall"] == "warn"
    strict = ReportThresholds(residual_rms=(0.01, 0.02))
    assert report_verdicts(cal.report, strict)["views"][0]["residual"] == "fail"


def test_titles_sit_above_the_pictures() -> None:
    img = np.zeros((50, 300, 3), np.uint8)
    img[:, :, 1] = 200
    out = _label(img, "a title")
    assert out.shape == (50 + TITLE_BAND, 300, 3)
    np.testing.assert_array_equal(out[TITLE_BAND:], img)  # the picture untouched
    band = out[:TITLE_BAND].astype(int)
    assert (band[..., 0] == band[..., 1]).all()  # black text on white, drawn once
    assert (band < 128).any()
