"""geonet_infer.output.viz: Middlebury flow colours, depth colour maps, side-by-side panels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geonet_infer.output import viz


# ---------------------------------------------------------------------------- visualisation
def _hue_deg(rgb: np.ndarray) -> float:
    hsv = cv2.cvtColor(rgb.reshape(1, 1, 3).astype(np.uint8), cv2.COLOR_RGB2HSV_FULL)
    return hsv[0, 0, 0] * 360.0 / 256.0


def test_flow_to_color_hues_follow_the_middlebury_wheel():
    def colour(u, v):
        return viz.flow_to_color(np.full((2, 2, 2), (u, v), np.float32))[0, 0]

    right, left, up = colour(1, 0), colour(-1, 0), colour(0, -1)
    assert right.tolist() == [255, 0, 0]  # +x is pure red at full magnitude
    assert _hue_deg(left) == pytest.approx(191, abs=15)  # cyan-blue, opposite side of the wheel
    assert 230 < _hue_deg(up) < 290  # blue-violet
    # Zero flow is white; half the max magnitude is a lighter (less saturated) red.
    f = np.zeros((1, 2, 2), np.float32)
    f[0, 1] = (2, 0)
    img = viz.flow_to_color(f)
    assert img[0, 0].tolist() == [255, 255, 255] and img[0, 1].tolist() == [255, 0, 0]
    half = viz.flow_to_color(f, max_flow=4.0)[0, 1]
    assert half[0] == 255 and 120 < half[1] == half[2] < 135


def test_depth_to_color_near_is_brighter_and_missing_is_black():
    depth = np.array([[2.0, 20.0, 0.0]])
    img = viz.depth_to_color(depth)
    assert img.shape == (1, 3, 3) and img.dtype == np.uint8
    assert img[0, 0].sum() > img[0, 1].sum()
    assert img[0, 2].tolist() == [0, 0, 0]


# ---------------------------------------------------------------------------- side_by_side
def test_side_by_side_resizes_to_one_height_and_keeps_the_pixels():
    red = np.zeros((40, 60, 3), np.uint8)
    red[..., 0] = 255
    blue = np.zeros((20, 20, 3), np.uint8)
    blue[..., 2] = 255
    out = viz.side_by_side([red, blue])  # height = first panel's
    assert out.dtype == np.uint8 and out.shape[0] == 40
    gap = out.shape[1] - 60 - 40
    assert gap > 0  # a small gap between the panels
    assert (out[:, :60] == [255, 0, 0]).all() and (out[:, 60 + gap :] == [0, 0, 255]).all()
    assert out[:, 60 : 60 + gap].max() < 64  # dark gap
    out = viz.side_by_side([red, blue], height=10)
    assert out.shape[0] == 10 and out.shape[1] == 15 + 10 + gap


def test_side_by_side_labels_go_on_a_dark_strip_above():
    panels = [np.full((50, 80, 3), 128, np.uint8), np.full((50, 80), 200, np.uint8)]  # grey panel -> 3 channels
    out = viz.side_by_side(panels, labels=["depth", "flow"])
    strip = out.shape[0] - 50
    assert strip > 0 and out.shape[1] > 160
    assert (out[strip:, :80] == 128).all() and (out[strip:, -80:] == 200).all()
    assert out[:strip].max() > 200  # white text drawn ...
    assert np.median(out[:strip]) < 64  # ... on a dark strip
    with pytest.raises(ValueError):
        viz.side_by_side(panels, labels=["only one"])
    with pytest.raises(ValueError):
        viz.side_by_side([])
