"""Classical and trivial baselines, no model: what a learned model has to beat.

Same call signatures as the model adapters in :mod:`geonet_infer.eval.evaluation`:

* depth ``fn(rgb) -> depth (H, W)``;
* flow ``fn(frames, K) -> flow (H, W, 2)`` from ``frames[-2]`` to ``frames[-1]``;
* pose ``fn(frames (5), K) -> (poses (5, 4, 4) in the first frame's coordinates, info)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from geonet_infer.classical import (  # noqa: F401  (the OpenCV methods are part of the baselines' API)
    DIS_PRESETS,
    ORB_FEATURES,
    ORB_MIN_INLIERS,
    PairPose,
    dis_flow,
    grey,
    orb_matcher,
    relative_pose,
)
from geonet_infer.conventions import next_camera_to_world


def constant_depth(rgb: np.ndarray) -> np.ndarray:
    """One depth everywhere. After per-image median scaling it becomes the frame's median GT depth."""
    return np.ones(rgb.shape[:2], np.float32)


def zero_flow(frames: list, K=None) -> np.ndarray:
    """No motion."""
    return np.zeros(frames[-1].shape[:2] + (2,), np.float32)


def identity_pose(frames: list, K=None) -> tuple[np.ndarray, dict]:
    """The camera never moves (the alignment cannot scale a zero trajectory, so ATE = |GT| / N)."""
    return np.tile(np.eye(4), (len(frames), 1, 1)), {}


def orb_vo(frames: list, K: np.ndarray) -> tuple[np.ndarray, dict]:
    """Two-view ORB visual odometry over one snippet.

    Each consecutive pair: ORB features, brute-force Hamming matches with cross-check,
    5-point essential matrix (RANSAC, 1 px) and ``recoverPose``. Monocular steps have no
    scale, so every step gets unit length (constant speed within the snippet); the ATE
    alignment then fits one scale per snippet, as for the paper's ORB-SLAM (short) row.
    A pair that fails (too few matches or inliers) repeats the previous step (the first
    step: no motion) and is counted in ``info["failed_pairs"]``.
    """
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global RNG: fixed for reproducible tables
    orb, matcher = orb_matcher()
    greys = [grey(f) for f in frames]
    K = np.asarray(K, dtype=np.float64)
    poses, step, failed, inliers = [np.eye(4)], np.eye(4), 0, []
    for a, b in zip(greys[:-1], greys[1:]):
        T, n, _, _ = relative_pose(orb, matcher, a, b, K)
        inliers.append(n)
        if T is None:
            failed += 1
        else:
            step = T
        poses.append(next_camera_to_world(poses[-1], step))
    return np.stack(poses), {"failed_pairs": failed, "inliers": inliers}
