"""Classical and trivial baselines, no model: what a learned model has to beat.

Same call signatures as the model adapters in :mod:`geonet_infer.evaluation`:

* depth ``fn(rgb) -> depth (H, W)``;
* flow ``fn(frames, K) -> flow (H, W, 2)`` from ``frames[-2]`` to ``frames[-1]``;
* pose ``fn(frames (5), K) -> (poses (5, 4, 4) in the first frame's coordinates, info)``.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from geonet_infer.metrics import rigid_inverse

DIS_PRESETS = {"medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}
ORB_FEATURES = 3000
ORB_MIN_INLIERS = 8  # the 5-point RANSAC needs more than 5; below 8 the essential matrix is unreliable


def constant_depth(rgb: np.ndarray) -> np.ndarray:
    """One depth everywhere. After per-image median scaling it becomes the frame's median GT depth."""
    return np.ones(rgb.shape[:2], np.float32)


def zero_flow(frames: list, K=None) -> np.ndarray:
    """No motion."""
    return np.zeros(frames[-1].shape[:2] + (2,), np.float32)


def identity_pose(frames: list, K=None) -> tuple[np.ndarray, dict]:
    """The camera never moves (the alignment cannot scale a zero trajectory, so ATE = |GT| / N)."""
    return np.tile(np.eye(4), (len(frames), 1, 1)), {}


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def dis_flow(preset: str):
    """OpenCV DIS optical flow (Kroeger et al. ECCV16) with one of :data:`DIS_PRESETS`, on grey frames."""
    code = DIS_PRESETS[preset]

    def predict(frames: list, K=None) -> np.ndarray:
        dis = cv2.DISOpticalFlow.create(code)  # per call: the object keeps no useful state between pairs
        return dis.calc(grey(frames[-2]), grey(frames[-1]), None)

    return predict


def orb_matcher() -> tuple[cv2.ORB, cv2.BFMatcher]:
    """The ORB detector and cross-checked Hamming matcher of :func:`orb_vo` (and of ``--pose-method orbvo``)."""
    return cv2.ORB.create(nfeatures=ORB_FEATURES), cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)


class PairPose(NamedTuple):
    """One ORB-VO step (:func:`relative_pose`)."""

    T: np.ndarray | None  # (4, 4) camera-a points -> camera-b, |t| = 1; None: the pair failed
    inliers: int
    pixels: tuple[np.ndarray, np.ndarray] | None  # the inliers' pixels in a and b, (N, 2) each, with T
    shift: float | None  # median pixel displacement of all cross-checked matches (None: no match)


def relative_pose(orb, matcher, a: np.ndarray, b: np.ndarray, K: np.ndarray) -> PairPose:
    """The ORB-VO step from grey frame ``a`` to grey frame ``b`` (see :func:`orb_vo`)."""
    kp_a, des_a = orb.detectAndCompute(a, None)
    kp_b, des_b = orb.detectAndCompute(b, None)
    if des_a is None or des_b is None:
        return PairPose(None, 0, None, None)
    matches = matcher.match(des_a, des_b)
    p_a = np.array([kp_a[m.queryIdx].pt for m in matches], dtype=np.float64).reshape(-1, 2)
    p_b = np.array([kp_b[m.trainIdx].pt for m in matches], dtype=np.float64).reshape(-1, 2)
    shift = float(np.median(np.linalg.norm(p_b - p_a, axis=1))) if len(matches) else None
    if len(matches) < ORB_MIN_INLIERS:
        return PairPose(None, len(matches), None, shift)
    try:
        E, mask = cv2.findEssentialMat(p_a, p_b, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
    except cv2.error:  # OpenCV 5 asserts (solvePoly) where 4.x returned no solution: no motion to solve
        return PairPose(None, 0, None, shift)
    if E is None or E.shape != (3, 3):  # several solutions stacked, or none: degenerate motion
        return PairPose(None, 0 if mask is None else int(mask.sum()), None, shift)
    inliers, R, t, mask = cv2.recoverPose(E, p_a, p_b, K, mask=mask)
    if inliers < ORB_MIN_INLIERS:
        return PairPose(None, int(inliers), None, shift)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel()
    keep = mask.ravel() > 0  # the RANSAC inliers that recoverPose found in front of both cameras
    return PairPose(T, int(inliers), (p_a[keep], p_b[keep]), shift)


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
        poses.append(poses[-1] @ rigid_inverse(step))
    return np.stack(poses), {"failed_pairs": failed, "inliers": inliers}
