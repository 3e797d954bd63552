"""``--intrinsics estimate``: the focal length from the footage itself, or a refusal that says why.

Method (the essential-matrix constraint of Mendonça and Cipolla, 1999): for pairs of frames that moved,
the fundamental matrix F is fitted to tracked corners (OpenCV: Shi-Tomasi corners, pyramidal
Lucas-Kanade tracked forward and back, RANSAC). With square pixels and the principal point at the
centre, ``E(f) = K(f)ᵀ F K(f)`` is an essential matrix only at the true focal length f, where its two
non-zero singular values are equal; each pair's estimate is the f in 0.3-3 x the width that makes them
closest. The constraint needs rotation: for a camera that only translates (a straight road) every f
fits equally well, and a pair whose cost has no clear minimum says nothing.

The rule for answering (docs/runtime.md "Intrinsics"), written before scoring on the real sets:
at least :data:`MIN_PAIRS` pairs with a clear minimum (the cost there at most half the cost 25 % away
from it, :data:`MIN_CONTRAST`), their estimates agreeing (interquartile range at most
:data:`MAX_SPREAD` of the median), and the median inside the searched range. Anything else is a refusal
naming the reason, and the caller falls back to the assumed intrinsics.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from geonet_infer.io.camera import Camera

SEARCH = (0.3, 3.0)  # focal lengths searched, times the image width
GRID = np.geomspace(SEARCH[0], SEARCH[1], 121)
MAX_WIDTH = 960  # frames are shrunk to at most this width first (the focal scales back)
MAX_FRAMES = 150  # frames read from the start of the footage
MIN_PARALLAX = 0.01  # a pair's median corner motion, times the width, to count as moved
MIN_INLIERS = 60
MIN_CONTRAST = 0.5  # the cost at the minimum at most half the cost at f / 1.25 and at f * 1.25
MIN_PAIRS = 5
MAX_SPREAD = 0.15  # interquartile range of the pairs' estimates over their median


@dataclass(frozen=True)
class FocalEstimate:
    """What the footage says of its focal length. ``focal`` is None for a refusal (``reason`` says why)."""

    focal: float | None  # pixels at (width, height)
    width: int
    height: int
    pairs: int  # pairs with a clear minimum
    pairs_tried: int  # pairs that moved enough to be fitted
    spread: float | None  # interquartile range / median of the pairs' estimates
    reason: str
    seconds: float

    def camera(self) -> Camera | None:
        if self.focal is None:
            return None
        K = np.array([[self.focal, 0.0, self.width / 2], [0.0, self.focal, self.height / 2], [0.0, 0.0, 1.0]])
        source = (
            f"estimated from the footage: f = {self.focal:.1f} px from {self.pairs} frame pairs "
            f"(spread {self.spread:.0%}), principal point at the centre"
        )
        return Camera(K, None, (self.width, self.height), source, "estimated")


def _grey(rgb: np.ndarray) -> tuple[np.ndarray, float]:
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    scale = min(1.0, MAX_WIDTH / grey.shape[1])
    if scale < 1.0:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return grey, scale


def _track(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners of ``a`` and where they are in ``b``: tracked (kept where tracking back lands within
    1 px), or, for views too far apart to track, SIFT matches that pass Lowe's ratio test."""
    corners = cv2.goodFeaturesToTrack(a, maxCorners=1500, qualityLevel=0.01, minDistance=8)
    if corners is not None and len(corners) >= MIN_INLIERS:
        fwd, ok1, _ = cv2.calcOpticalFlowPyrLK(a, b, corners, None, winSize=(21, 21), maxLevel=4)
        back, ok2, _ = cv2.calcOpticalFlowPyrLK(b, a, fwd, None, winSize=(21, 21), maxLevel=4)
        good = (ok1[:, 0] == 1) & (ok2[:, 0] == 1) & (np.linalg.norm((back - corners)[:, 0], axis=1) < 1.0)
        if good.sum() >= MIN_INLIERS:
            return corners[good, 0].astype(np.float64), fwd[good, 0].astype(np.float64)
    sift = cv2.SIFT_create(2000)  # type: ignore[attr-defined]
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pairs = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
    pa = np.array([ka[m.queryIdx].pt for m in pairs], np.float64).reshape(-1, 2)
    pb = np.array([kb[m.trainIdx].pt for m in pairs], np.float64).reshape(-1, 2)
    return pa, pb


def pair_cost(F: np.ndarray, width: int, height: int) -> np.ndarray:
    """(len(GRID),) the essential-matrix cost (s1 - s2) / (s1 + s2) of ``F`` at each focal of the grid."""
    cx, cy = width / 2, height / 2
    costs = np.empty(len(GRID))
    for i, g in enumerate(GRID):
        f = g * width
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
        s = np.linalg.svd(K.T @ F @ K, compute_uv=False)
        costs[i] = (s[0] - s[1]) / (s[0] + s[1])
    return costs


def _clear_minimum(costs: np.ndarray) -> int | None:
    """The grid index of the cost's minimum if it is clear (see the module docstring), else None."""
    i = int(np.argmin(costs))
    step = np.log(GRID[1] / GRID[0])
    k = int(round(np.log(1.25) / step))  # grid steps in a factor 1.25
    if i - k < 0 or i + k >= len(GRID):
        return None
    return i if costs[i] <= (1 - MIN_CONTRAST) * min(costs[i - k], costs[i + k]) else None


def focal_from_matches(
    matches: Iterable[tuple[np.ndarray, np.ndarray]], width: int, height: int, started: float | None = None
) -> FocalEstimate:
    """The focal length (pixels) of a ``width`` x ``height`` camera from point matches of frame pairs
    ((N, 2) and (N, 2) pixel coordinates each), or a refusal (the rule of the module docstring)."""
    started = time.perf_counter() if started is None else started
    estimates, tried = [], 0
    for a, b in matches:
        F, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, 1.0, 0.999)
        if F is None or F.shape != (3, 3) or int(mask.sum()) < MIN_INLIERS:
            continue
        tried += 1
        k = _clear_minimum(pair_cost(F, width, height))
        if k is not None:
            estimates.append(GRID[k] * width)

    def refuse(reason: str, spread: float | None = None) -> FocalEstimate:
        return FocalEstimate(None, width, height, len(estimates), tried, spread, reason, time.perf_counter() - started)

    if tried == 0:
        return refuse("the camera does not move enough (no pair of frames with parallax)")
    if tried < MIN_PAIRS:
        return refuse(f"only {tried} pairs of frames moved (at least {MIN_PAIRS} needed)")
    if len(estimates) < MIN_PAIRS:
        return refuse(
            f"{len(estimates)} of {tried} moving pairs determine it (at least {MIN_PAIRS} needed): "
            "the camera hardly rotates"
        )
    f = float(np.median(estimates))
    q1, q3 = np.percentile(estimates, [25, 75])
    spread = float((q3 - q1) / f)
    if spread > MAX_SPREAD:
        return refuse(f"the {len(estimates)} pairs disagree (spread {spread:.0%})", spread)
    if not (SEARCH[0] * 1.25 * width <= f <= SEARCH[1] / 1.25 * width):
        return refuse(f"the estimate {f:.0f} px is at the edge of the searched range", spread)
    return FocalEstimate(f, width, height, len(estimates), tried, spread, "", time.perf_counter() - started)


def estimate_focal(frames: Iterable[np.ndarray]) -> FocalEstimate:
    """The focal length of (H, W, 3) RGB ``frames`` in pixels at their size, or a refusal.

    Each frame is paired with the nearest later one that moved at least :data:`MIN_PARALLAX` of the
    width (the next pair starts there), over the first :data:`MAX_FRAMES` frames.
    """
    started = time.perf_counter()
    greys: list[np.ndarray] = []
    size, scale = (0, 0), 1.0
    for n, rgb in enumerate(frames):
        if n >= MAX_FRAMES:
            break
        if not greys:
            size = (rgb.shape[1], rgb.shape[0])
        grey, scale = _grey(rgb)
        greys.append(grey)
    if len(greys) < 2:
        return FocalEstimate(None, *size, 0, 0, None, "fewer than 2 frames", time.perf_counter() - started)

    def moved_pairs():
        i = 0
        while i < len(greys) - 1:
            for j in range(i + 1, len(greys)):
                a, b = _track(greys[i], greys[j])
                if (
                    len(a) >= MIN_INLIERS
                    and np.median(np.linalg.norm(b - a, axis=1)) >= MIN_PARALLAX * MAX_WIDTH * scale
                ):
                    yield a / scale, b / scale  # pixels of the frames as given
                    break
            else:
                return
            i = j

    return focal_from_matches(moved_pairs(), size[0], size[1], started)


def camera_from_footage(frames: Iterable[np.ndarray]) -> tuple[Camera, str | None]:
    """``--intrinsics estimate``: the estimated camera, or the assumed one and the one-line refusal."""
    from geonet_infer.conventions import KITTI_HEIGHT, KITTI_WIDTH
    from geonet_infer.io.camera import ASSUMED_RULE, assumed_camera

    estimate = estimate_focal(frames)
    camera = estimate.camera()
    if camera is not None:
        return camera, None
    refusal = f"this footage cannot determine the focal length: {estimate.reason}"
    source = f"{ASSUMED_RULE} (--intrinsics estimate: {refusal})"
    return assumed_camera(KITTI_WIDTH, KITTI_HEIGHT, source), f"{refusal}; assumed {ASSUMED_RULE} instead"
