"""Depth accuracy against the simulator's ground truth, shared by the processing tests."""

from __future__ import annotations

import cv2
import numpy as np
import tifffile


def truth(sim, name):
    """The ground-truth depth (m) and object labels of a simulated scene."""
    depth = tifffile.imread(sim.truth_dir / name / "depth.tiff")
    labels = cv2.imread(str(sim.truth_dir / name / "labels.png"), cv2.IMREAD_UNCHANGED)
    return depth, labels


def accuracy(z, truth, labels, seen, band_px=3):
    """Median relative error and coverage away from occlusion edges (a thin band),
    and the share of pixels off by more than 5% over ALL seen pixels."""
    edges = cv2.morphologyEx(labels, cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    near = cv2.dilate(edges.astype(np.uint8), np.ones((2 * band_px + 1,) * 2, np.uint8)) > 0
    away = seen & ~near
    rel = np.abs(z - truth) / truth
    med = float(np.nanmedian(rel[away]))
    cover = float(np.isfinite(z[away]).mean())
    bad = float(np.mean(~(rel[seen] <= 0.05)))  # unknown counts as bad
    return med, cover, bad
