"""training.stereo_val: KITTI stereo pairs -> SGBM depth for validation outside the test drive."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geonet_infer.eval.datasets import load_dataset
from geonet_infer.io import read_calib_file, read_depth_kitti
from training.stereo_val import PAIRS, focal_and_baseline, main, stereo_depth


def test_baselines_of_the_kitti_calibrations(realdata):
    # KITTI: 0.54 m between the two grey cameras (README of the extract: P1[0,3] = -386.1448, fx 718.856)
    fx, baseline = focal_and_baseline(realdata / "kitti_odometry_00/sequences/00/calib.txt", "P0", "P1")
    assert fx == pytest.approx(718.856) and baseline == pytest.approx(386.1448 / 718.856)
    # colour pair of sequence 06: P2[0,3] = 46.88783, P3[0,3] = -333.4597 (calib.txt), fx 707.0912
    fx, baseline = focal_and_baseline(realdata / "kitti_odometry_06/sequences/06/calib.txt", "P2", "P3")
    assert baseline == pytest.approx((46.88783 + 333.4597) / 707.0912, rel=1e-6)


def test_sgbm_recovers_a_plane_at_a_known_disparity():
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.uniform(0, 255, (60, 200)).astype(np.float32), (800, 240), interpolation=cv2.INTER_CUBIC)
    texture = np.clip(texture, 0, 255).astype(np.uint8)
    disparity = 24  # px: a fronto-parallel plane; a point at column x in the left view is at x - 24 in the right
    left = np.dstack([texture[:, :-disparity]] * 3)
    right = np.dstack([texture[:, disparity:]] * 3)
    fx, baseline = 700.0, 0.5
    depth = stereo_depth(left, right, fx, baseline)
    valid = depth > 0
    assert valid.mean() > 0.6  # the first 128 columns (no match possible) and the borders are dropped
    assert np.median(depth[valid]) == pytest.approx(fx * baseline / disparity, rel=0.01)
    assert np.mean(np.abs(depth[valid] / (fx * baseline / disparity) - 1) < 0.05) > 0.95


def test_real_pairs_put_the_road_at_the_camera_height(realdata, tmp_path):
    """Flat road ahead: depth * (v - cy) / fy is the camera height, 1.65 m on KITTI's car (Geiger et al.)."""
    assert main(["--realdata", str(realdata), "--out", str(tmp_path / "val")]) == 0
    dataset = load_dataset("depth", tmp_path / "val")
    assert dataset.layout == "kitti-raw" and len(dataset.items) == len(PAIRS) == 2
    for item in dataset.items:
        depth = read_depth_kitti(item.gt)
        seq = next(s for s, p in PAIRS.items() if p.name == item.name)
        assert depth.shape == cv2.imread(str(item.image)).shape[:2]
        P = read_calib_file(realdata / seq / "calib.txt")[PAIRS[seq].left_key].reshape(3, 4)
        fy, cy = P[1, 1], P[1, 2]
        rows = np.arange(300, depth.shape[0] - 5)  # road between ~6 and ~11 m, centre columns
        centre = depth[rows, depth.shape[1] // 2 - 60 : depth.shape[1] // 2 + 60]
        heights = [np.median(r[r > 0]) * (v - cy) / fy for v, r in zip(rows, centre) if (r > 0).sum() > 20]
        assert len(heights) > 40
        assert np.median(heights) == pytest.approx(1.65, rel=0.1)
        assert np.percentile(heights, 90) / np.percentile(heights, 10) < 1.1  # a plane: same height on every row
