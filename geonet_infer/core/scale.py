"""Metric scale for monocular depth from a known camera height above a flat road.

Monocular depth is known up to one factor per image. If the camera sits ``h`` metres
above a locally flat ground, the ground plane fitted to the predicted depth lies
``h_pred`` units below the camera, and ``depth * h / h_pred`` is metric.

Conventions: camera coordinates x right, y down, z forward (OpenCV); K at the
depth map's resolution. The plane is fitted with RANSAC over the lower part of the
image (where the road is), its normal required to be within ``max_tilt_deg`` of the
camera's y axis, then refined by least squares on the inliers. A candidate that the image
sees through (many pixels well beyond it along their own rays) is not the road but a level
surface above it, such as a car transporter's deck or a truck bed: it is skipped.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from geonet_infer.conventions import next_camera_to_world
from geonet_infer.core.points import camera_points
from geonet_infer.core.results import FrameResult
from geonet_infer.errors import GeoNetError, InputError

MAX_CAMERA_HEIGHT_M = 100.0  # above a road; more is a unit mix-up (mm, cm) and gives depth in kilometres
# ... and at least 1 cm (a phone on the floor): 1e-300 passed "> 0" and turned every depth into zeros
MIN_CAMERA_HEIGHT_M = 0.01


@dataclass
class GroundFit:
    """A ground plane n . X = d (|n| = 1, n pointing down, d > 0 = camera height in depth units)."""

    normal: np.ndarray  # (3,)
    height: float  # camera height above the plane, in the depth map's units
    inlier_fraction: float
    n_points: int

    def scale_for(self, camera_height_m: float) -> float:
        """The factor that makes the depth map metric."""
        return camera_height_m / self.height


def _plane_through(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    n = np.cross(p[1] - p[0], p[2] - p[0])
    norm = np.linalg.norm(n)
    if norm < 1e-12:
        return None
    n = n / norm
    if n[1] < 0:  # point down (+y), so d = n . X > 0 for ground below the camera
        n = -n
    return n, float(n @ p[0])


def fit_ground_plane(
    depth: np.ndarray,
    K: np.ndarray,
    *,
    rows_from: float | None = None,
    max_tilt_deg: float = 20.0,
    inlier_rel: float = 0.02,
    seen_through_rel: float = 0.3,
    max_seen_through: float = 0.03,
    iterations: int = 200,
    max_points: int = 20000,
    seed: int = 0,
) -> GroundFit:
    """RANSAC ground plane of a depth map.

    Args:
        depth: (H, W) positive depth (any scale); non-finite or <= 0 pixels are ignored.
        K: (3, 3) intrinsics at (H, W).
        rows_from: first image row searched, as a fraction of H; default: 5 % of H below
            the principal point (the horizon of a level camera).
        max_tilt_deg: largest angle between the plane normal and the camera's y axis.
        inlier_rel: inlier distance as a fraction of the candidate plane's camera height.
        seen_through_rel, max_seen_through: a candidate is skipped when more than
            ``max_seen_through`` of the searched pixels lie beyond it along their rays by more
            than ``seen_through_rel`` of the plane's depth there (judged on the 5x5 median of
            the depth, so scattered outliers do not veto the road). On the ground-truth depth of
            dense synthetic traffic, a plain inlier count took the top of a car close ahead for
            the road on 10 of 71 frames, all of one scene (0.6-0.8 m instead of 1.65 m).
    Raises:
        GeoNetError if no plausible ground plane is found.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InputError(None, f"depth must be (H, W), got shape {depth.shape}")
    h, _ = depth.shape
    start = int(np.clip((K[1, 2] / h + 0.05) if rows_from is None else rows_from, 0.0, 0.95) * h)
    points = camera_points(depth, K)[start:].reshape(-1, 3)
    smooth_z = cv2.medianBlur(np.nan_to_num(depth, nan=0.0, posinf=0.0).astype(np.float32), 5)[start:].reshape(-1)
    valid = np.isfinite(points).all(axis=1) & (points[:, 2] > 0)
    points, smooth_z = points[valid], smooth_z[valid]
    if len(points) < 50:
        raise InputError(
            None,
            f"only {len(points)} valid depth pixels below row {start}",
            "the ground plane needs the road in the lower part of the image",
        )
    rng = np.random.default_rng(seed)
    if len(points) > max_points:
        keep = rng.choice(len(points), max_points, replace=False)
        points, smooth_z = points[keep], smooth_z[keep]
    cos_tilt = np.cos(np.deg2rad(max_tilt_deg))
    best, best_count = None, 0
    for _ in range(iterations):
        plane = _plane_through(points[rng.choice(len(points), 3, replace=False)])
        if plane is None or plane[0][1] < cos_tilt or plane[1] <= 0:
            continue
        n, d = plane
        along = points @ n  # > 0: the pixel's ray meets the plane, at depth z * d / along
        count = int((np.abs(along - d) < inlier_rel * d).sum())
        if count <= best_count:
            continue
        beyond = (along > 0) & (smooth_z * along > (1 + seen_through_rel) * d * points[:, 2])
        if beyond.mean() <= max_seen_through:
            best, best_count = plane, count
    if best is None or best_count < 0.1 * len(points):
        raise InputError(
            None,
            f"no ground plane found in the depth map ({best_count} of {len(points)} points on the best candidate)",
            "metric scale from camera height needs a visible, roughly flat road",
        )
    n, d = best
    inliers = points[np.abs(points @ n - d) < inlier_rel * d]
    centroid = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centroid, full_matrices=False)[2][-1]
    if normal[1] < 0:
        normal = -normal
    return GroundFit(
        normal=normal, height=float(normal @ centroid), inlier_fraction=len(inliers) / len(points), n_points=len(points)
    )


def metric_depth(
    depth: np.ndarray, K: np.ndarray, camera_height_m: float, **fit_options
) -> tuple[np.ndarray, GroundFit]:
    """Depth scaled so the fitted ground plane lies ``camera_height_m`` below the camera."""
    check_camera_height(camera_height_m)
    fit = fit_ground_plane(depth, K, **fit_options)
    return (depth * fit.scale_for(camera_height_m)).astype(np.float32), fit


def check_metric_request(camera_height_m: float | None, camera, where=None) -> None:
    """Before any work: a requested camera height must be valid and come with the camera's K.

    ``camera_height_m`` None = relative depth, nothing to check; ``where`` names the input.
    """
    if camera_height_m is None:
        return
    check_camera_height(camera_height_m)
    if camera is None:
        raise InputError(
            where,
            "camera_height needs the camera intrinsics",
            "pass camera= / K= (a Camera or a 3x3 K), or --calib FILE / --intrinsics FX,FY,CX,CY",
        )


def check_camera_height(camera_height_m) -> None:
    ok = isinstance(camera_height_m, (int, float)) and np.isfinite(camera_height_m)
    if not (ok and MIN_CAMERA_HEIGHT_M <= camera_height_m <= MAX_CAMERA_HEIGHT_M):
        raise InputError(
            None,
            f"camera height (--camera-height / camera_height) must be a positive number of metres from "
            f"{MIN_CAMERA_HEIGHT_M:g} to {MAX_CAMERA_HEIGHT_M:g}, got {camera_height_m!r}",
            "e.g. 1.65 for KITTI's colour cameras",
        )


MAX_FRAMES_BEFORE_GROUND = 60  # frames held back waiting for a first ground plane (2.4 s at 25 fps)
# The per-frame fit follows the model's depth, which wobbles from frame to frame (on the KITTI test drive
# consecutive factors jump 3.8 -> 2.8 -> 6.9), so a sequence's factor is smoothed over a centred window.
SCALE_HALF_WINDOW = 7  # frames each side: a 15-frame window; a stream is held back 7 frames (0.7 s at 10 Hz)
# The cap (issue 55): every frame inside the window is held in memory until its window closes (at
# 1242x375 about 8 MB a frame); 10 each side keeps a run's memory within 10 % of the default's (7).
MAX_SCALE_HALF_WINDOW = 10
SCALE_OUTLIER_K = 2.5  # a fit further than this many robust sigmas from the window's median is dropped
SCALE_MIN_SPREAD = 0.05  # floor of that sigma in log units, so a steady run does not reject a 5 % wobble


def robust_scale(values: Sequence[float]) -> float:
    """One factor for a window of per-frame factors (> 0): the geometric mean of the inliers.

    In log units: values further than ``SCALE_OUTLIER_K`` robust sigmas (1.4826 x the median
    absolute deviation, at least ``SCALE_MIN_SPREAD``) from the median are outliers; the mean of
    the rest is smoother than their median (one frame entering the window moves it by 1/n of its
    distance), and rejecting first keeps it robust.
    """
    logs = np.log(np.asarray(values, dtype=np.float64))
    median = np.median(logs)
    sigma = max(1.4826 * float(np.median(np.abs(logs - median))), SCALE_MIN_SPREAD)
    inliers = logs[np.abs(logs - median) <= SCALE_OUTLIER_K * sigma]
    return float(np.exp(inliers.mean()))


class ScaleSmoother:
    """Per-frame factors (None = no ground fit) in, smoothed factors out, in order, streaming.

    Frame t gets :func:`robust_scale` of the fits among frames t-h .. t+h (``h = half_window``;
    clipped at the sequence's ends), so it is decided once frame t+h is in: a look-ahead of h
    frames. Centred rather than causal: a causal window lags every real change of scale (the
    model's depth drifting as the scene changes) by half its length, a centred one does not.
    A frame with no fit in its window takes the previous frame's factor; frames before any
    such frame wait for the first factor decided. ``h = 0``: each frame's own fit.
    """

    def __init__(self, half_window: int = SCALE_HALF_WINDOW):
        if not (isinstance(half_window, int) and half_window >= 0):
            raise InputError(None, f"scale smoothing window must be a whole number >= 0, got {half_window!r}")
        if half_window > MAX_SCALE_HALF_WINDOW:
            raise InputError(
                None,
                f"scale smoothing window {half_window} is over the cap of {MAX_SCALE_HALF_WINDOW} frames each side",
                "frames are held in memory until their window closes: pass at most "
                f"--scale-smoothing {MAX_SCALE_HALF_WINDOW}",
            )
        self.half_window = half_window
        self._raw: deque[float | None] = deque()  # the fits of frames _base .. pushed-1
        self._base = 0
        self._pushed = 0
        self._next = 0  # the next frame to decide
        self.waiting = 0  # frames decided to have no factor yet: they take the next one
        self._last: float | None = None

    def push(self, raw: float | None) -> list[float]:
        """One more frame's fit; returns the factors of the frames decided now, in order."""
        self._raw.append(raw)
        self._pushed += 1
        return self._decide(self._pushed - 1 - self.half_window)

    def finish(self) -> list[float]:
        """The factors of the frames still undecided (``waiting`` > 0 after it: no fit at all)."""
        return self._decide(self._pushed - 1)

    def _decide(self, last: int) -> list[float]:
        out: list[float] = []
        h = self.half_window
        while self._next <= last:
            t = self._next
            fits = [v for i, v in enumerate(self._raw) if v is not None and abs(self._base + i - t) <= h]
            if fits:
                self._last = robust_scale(fits)
                out += [self._last] * (self.waiting + 1)
                self.waiting = 0
            elif self._last is not None:
                out.append(self._last)
            else:
                self.waiting += 1
            self._next += 1
            while self._base < self._next - h:  # frames no later window reaches
                self._raw.popleft()
                self._base += 1
        return out


def smooth_scales(raw: Sequence[float | None], half_window: int = SCALE_HALF_WINDOW) -> list[float | None]:
    """:class:`ScaleSmoother` over a whole series (None throughout when no frame has a fit)."""
    smoother = ScaleSmoother(half_window)
    out: list[float | None] = [s for r in raw for s in smoother.push(r)]
    out += smoother.finish()
    return out + [None] * (len(raw) - len(out))


def scale_flicker(scales: Sequence[float | None], percentile: float = 95.0) -> float | None:
    """The ``percentile`` of max(r, 1/r) over consecutive frames' factors r = s[t+1] / s[t]
    (pairs with a None left out; None without a pair): 1 = a steady scale, 2 = depth doubling or halving."""
    pairs = [(a, b) for a, b in zip(scales[:-1], scales[1:]) if a is not None and b is not None]
    if not pairs:
        return None
    ratios = np.array([b / a for a, b in pairs])
    return float(np.percentile(np.maximum(ratios, 1.0 / ratios), percentile))


def metric_scale_summary(camera_height: float, half_window: int, per_frame: dict[str, list]) -> dict:
    """summary.json's ``metric_scale``: the settings, each frame's raw and smoothed factor
    (``per_frame``: lists "frames", "raw" (None: no road found), "smoothed", in frame order), and
    the flicker (:func:`scale_flicker`) of both."""
    raw, smoothed = per_frame["raw"], per_frame["smoothed"]
    return {
        "camera_height_m": camera_height,
        "smoothing": {
            "method": "centred window: median-MAD outlier rejection in log scale, then the inliers' geometric mean",
            "half_window_frames": half_window,
            "outlier_sigmas": SCALE_OUTLIER_K,
            "min_spread_log": SCALE_MIN_SPREAD,
        },
        "frames_without_fit": sum(r is None for r in raw),
        "flicker_p95": {"raw": scale_flicker(raw), "smoothed": scale_flicker(smoothed)},
        "per_frame_median": float(np.median(smoothed)) if smoothed else None,
        "per_frame_min": min(smoothed, default=None),
        "per_frame_max": max(smoothed, default=None),
        "per_frame": per_frame,
    }


def metric_frames(
    results: Iterable[FrameResult],
    camera_height: float,
    K_at: Callable[[tuple[int, int]], np.ndarray],
    half_window: int = SCALE_HALF_WINDOW,
) -> Iterator[FrameResult]:
    """The frames of a sequence in metres, in order.

    Each frame's factor is fitted to its depth (:func:`geonet_infer.core.scale.fit_ground_plane`:
    the factor that puts the ground plane ``camera_height`` metres below the camera; None where
    the road is hidden) and smoothed over the sequence (:class:`ScaleSmoother` with
    ``half_window``: frames are yielded ``half_window`` frames late); depth and pose translation
    are multiplied by the smoothed factor (``metric_scale``; the frame's own fit is
    ``metric_scale_raw``). With no fit in the first ``MAX_FRAMES_BEFORE_GROUND`` frames the
    sequence stops. ``camera_to_world`` is chained again from the scaled poses.
    ``K_at((H, W))``: the intrinsics at a depth map's size.
    """
    check_camera_height(camera_height)
    smoother = ScaleSmoother(half_window)
    held: deque[tuple[FrameResult, float | None, float]] = deque()  # frame, its fit, the fit's ms
    pose_world = np.eye(4)
    fitted = False

    def scaled(scales: list[float]) -> Iterator[FrameResult]:
        nonlocal pose_world
        for scale in scales:
            t0 = time.perf_counter()
            frame, raw, fit_ms = held.popleft()
            pose_next, vector = frame.pose_to_next, frame.pose_vector_to_next
            if pose_next is not None and vector is not None:
                pose_next, vector = pose_next.copy(), vector.copy()
                pose_next[:3, 3] *= scale
                vector[:3] *= scale
            depth, disparity = _depth_of(frame) * scale, _depth_of(frame, "disparity") / scale
            ms = fit_ms + (time.perf_counter() - t0) * 1e3  # the fit and the scaling: the "ground_fit" stage
            timings = frame.timings_ms | {"ground_fit": ms, "total": frame.timings_ms.get("total", 0.0) + ms}
            yield replace(
                frame,
                depth=depth,
                disparity=disparity,
                timings_ms=timings,
                camera_to_world=pose_world.copy(),
                pose_to_next=pose_next,
                pose_vector_to_next=vector,
                metric_scale=scale,
                metric_scale_raw=raw,
            )
            if pose_next is not None:
                pose_world = next_camera_to_world(pose_world, pose_next)

    for result in results:
        t0 = time.perf_counter()
        depth = _depth_of(result)
        raw: float | None = None
        try:
            raw = fit_ground_plane(depth, K_at(depth.shape)).scale_for(camera_height)
            fitted = True
        except GeoNetError as err:
            if not fitted and len(held) + 1 > MAX_FRAMES_BEFORE_GROUND:
                first = held[0][0].name if held else result.name
                raise InputError(
                    first,
                    f"no ground plane in the first {len(held) + 1} frames ({err.problem})",
                    "metric scale needs the road in view early in the video: start it where the road "
                    "shows, or drop --camera-height for relative depth",
                ) from None
        held.append((result, raw, (time.perf_counter() - t0) * 1e3))
        yield from scaled(smoother.push(raw))
    yield from scaled(smoother.finish())
    if held:
        raise InputError(
            held[0][0].name,
            f"no ground plane in any of the {len(held)} frames",
            "metric scale from camera height needs a visible, roughly flat road; drop --camera-height "
            "for relative depth",
        )


def _depth_of(frame: FrameResult, field: str = "depth") -> np.ndarray:
    """``frame``'s depth (or disparity): a sequence made metric must have been predicted with depth."""
    value = getattr(frame, field)
    if value is None:
        raise InputError(frame.name, f"metric scale needs the frame's {field}", "predict with the depth task")
    return value
