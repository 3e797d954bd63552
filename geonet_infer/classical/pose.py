"""Two-view ORB-VO (OpenCV: ORB, cross-checked matches, 5-point RANSAC, recoverPose) and the length of
its unit steps from a depth map: ``--pose-method orbvo`` and the eval's baseline."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

MIN_TRIANGULATED = 8  # inliers in front of both cameras needed to set a step's length
# Matches whose median displacement is under this: the camera stood still. On the KITTI test drive the
# stopped frames' ORB matches move 0.0 px (median), the moving ones 1.0-2.1 px; the eval's ORB-VO
# (no such rule) fails there and repeats the last step, a car driving on through a stop.
STILL_SHIFT_PX = 0.5
ORB_FEATURES = 3000
ORB_MIN_INLIERS = 8  # the 5-point RANSAC needs more than 5; below 8 the essential matrix is unreliable


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


def euler_xyz(R: np.ndarray) -> np.ndarray:
    """[rx, ry, rz] with R = Rx(rx) Ry(ry) Rz(rz), the pose vectors' convention (results.PoseResult)."""
    return np.array([np.arctan2(-R[1, 2], R[2, 2]), np.arcsin(np.clip(R[0, 2], -1, 1)), np.arctan2(-R[0, 1], R[0, 0])])


def step_length(T: np.ndarray, pixels: tuple[np.ndarray, np.ndarray], depth: np.ndarray, K: np.ndarray) -> float | None:
    """The length of the unit step ``T`` (camera a -> b) that makes its inliers' triangulated depth in
    camera a match ``depth`` (frame a's depth map): median(depth / triangulated) over the inliers
    in front of both cameras, or None with fewer than :data:`MIN_TRIANGULATED` of them."""
    p_a, p_b = pixels
    P_a = K @ np.eye(3, 4)
    P_b = K @ T[:3]
    X = cv2.triangulatePoints(P_a, P_b, p_a.T.astype(np.float64), p_b.T.astype(np.float64))
    X = X[:3] / X[3]
    z_a, z_b = X[2], (T[:3, :3] @ X + T[:3, 3:])[2]
    h, w = depth.shape
    u = np.clip(np.round(p_a[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(p_a[:, 1]).astype(int), 0, h - 1)
    d = depth[v, u]
    ok = (z_a > 0) & (z_b > 0) & np.isfinite(z_a) & np.isfinite(d) & (d > 0)
    if ok.sum() < MIN_TRIANGULATED:
        return None
    return float(np.median(d[ok] / z_a[ok]))
