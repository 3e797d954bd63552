"""``--intrinsics estimate`` on point matches of a known camera (closed-form projection): the focal
is found where the camera rotates, and refused where it only translates."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geonet_infer.core.self_calibration import MIN_PAIRS, focal_from_matches

W, H, F = 1242, 375, 720.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])


def _pairs(rotation_deg: float, n: int = 12, noise_px: float = 0.5, seed: int = 0):
    """n pairs of views of 800 random points 5-40 m away: the second view turned by ``rotation_deg``
    about a random axis and moved 1 m forward (and a little sideways), with pixel noise."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        X = np.c_[rng.uniform(-20, 20, 800), rng.uniform(-3, 3, 800), rng.uniform(5, 40, 800)]
        axis = rng.normal(size=3)
        R, _ = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(rotation_deg))
        X2 = X @ R.T + np.array([0.2, 0.05, 1.0])
        x1, x2 = (X @ K.T), (X2 @ K.T)
        x1, x2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
        inside = np.all((x1 > 0) & (x1 < (W, H)) & (x2 > 0) & (x2 < (W, H)), axis=1) & (X2[:, 2] > 0)
        noise = rng.normal(0, noise_px, (2, int(inside.sum()), 2))
        out.append((x1[inside] + noise[0], x2[inside] + noise[1]))
    return out


def test_a_rotating_camera_gives_its_focal_length():
    estimate = focal_from_matches(_pairs(20), W, H)
    assert estimate.focal == pytest.approx(F, rel=0.05), estimate
    assert estimate.pairs >= MIN_PAIRS and estimate.camera().origin == "estimated"


def test_a_camera_that_only_translates_is_refused():
    estimate = focal_from_matches(_pairs(0), W, H)
    assert estimate.focal is None and estimate.camera() is None
    assert "the camera hardly rotates" in estimate.reason


def test_no_moving_pair_is_refused():
    estimate = focal_from_matches([], W, H)
    assert estimate.focal is None and "does not move" in estimate.reason
