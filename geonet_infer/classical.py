"""The classical methods as choices beside the networks: DIS flow and ORB-VO poses for a sequence.

The eval scores them as baselines (:mod:`geonet_infer.eval.baselines`, ``geonet-infer eval``);
here the same code fills a sequence's :class:`~geonet_infer.core.results.FrameResult` flow or poses,
so ``predict``, ``batch`` and :meth:`Predictor.iter_sequence` write them in the usual layout.

* ``flow_method="dis"``: OpenCV DIS optical flow, preset medium (:func:`dis_flow`, the
  eval's "DIS medium"), frame t -> t+1 at the input resolution on the frames as the networks
  see them (undistorted when the camera has distortion). No network and no intrinsics needed.
* ``pose_method="orbvo"``: the eval's two-view ORB-VO step (:func:`relative_pose`:
  ORB, cross-checked matches, 5-point RANSAC, ``recoverPose``) per consecutive pair. Monocular
  steps have no length; each step's is set from the frame's predicted depth: the step's inliers
  are triangulated with a unit step and the length is the median of (predicted depth /
  triangulated depth) over them. Translations are so in the depth's units, like the network's
  poses: metres with a camera height (the smoothed metric depth), else the model's relative
  scale. A pair whose matches moved less than :data:`STILL_SHIFT_PX` (median) is a camera
  standing still: no motion. Any other pair that fails (too few matches, inliers or triangulated
  points) repeats the previous step (the first one: no motion), as the eval's ORB-VO does.
  Needs DepthNet and K.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import replace
from typing import NamedTuple

import cv2
import numpy as np

from geonet_infer.check import check_pair
from geonet_infer.conventions import next_camera_to_world
from geonet_infer.core.cascade import Intrinsics, StageTimer, camera_at, read_frame
from geonet_infer.core.results import FrameResult
from geonet_infer.errors import InputError

FLOW_METHODS = ("network", "dis")
POSE_METHODS = ("network", "orbvo")
DIS_PRESET = "medium"  # the eval's DIS row (docs/real_eval.md)
MIN_TRIANGULATED = 8  # inliers in front of both cameras needed to set a step's length
# Matches whose median displacement is under this: the camera stood still. On the KITTI test drive the
# stopped frames' ORB matches move 0.0 px (median), the moving ones 1.0-2.1 px; the eval's ORB-VO
# (no such rule) fails there and repeats the last step, a car driving on through a stop.
STILL_SHIFT_PX = 0.5
CLASSICAL_STAGES = ("dis", "orbvo")  # timings_ms keys of the classical methods
CLASSICAL_GRAPHS = {"flow": (), "pose": ("depthnet",)}  # ORB-VO takes its steps' length from the depth

DIS_PRESETS = {"medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST}
ORB_FEATURES = 3000
ORB_MIN_INLIERS = 8  # the 5-point RANSAC needs more than 5; below 8 the essential matrix is unreliable


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def dis_flow(preset: str):
    """OpenCV DIS optical flow (Kroeger et al. ECCV16) with one of :data:`DIS_PRESETS`, on grey frames."""
    code = DIS_PRESETS[preset]

    def predict(frames: list, K=None) -> np.ndarray:
        dis = cv2.DISOpticalFlow.create(code)  # per call: the object keeps no useful state between pairs
        a, b = grey(frames[-2]), grey(frames[-1])
        try:
            return dis.calc(a, b, None)
        except cv2.error:  # its image pyramid: a frame under 16 px high at a wide aspect resizes to nothing
            raise InputError(
                None,
                f"DIS optical flow cannot run on {a.shape[1]}x{a.shape[0]} frames (too thin for its image pyramid)",
                "use --flow-method network, or frames at least 16 pixels high",
            ) from None

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


def check_methods(flow_method: str, pose_method: str) -> None:
    if flow_method not in FLOW_METHODS:
        raise InputError(None, f"unknown flow method {flow_method!r}", f"choose one of {', '.join(FLOW_METHODS)}")
    if pose_method not in POSE_METHODS:
        raise InputError(None, f"unknown pose method {pose_method!r}", f"choose one of {', '.join(POSE_METHODS)}")


def classical_tasks(tasks: Iterable[str], flow_method: str, pose_method: str) -> tuple[str, ...]:
    """The tasks of ``tasks`` that a classical method makes."""
    chosen = {"flow": flow_method == "dis", "pose": pose_method == "orbvo"}
    return tuple(t for t in tasks if chosen.get(t, False))


def describe(tasks: Iterable[str], flow_method: str, pose_method: str) -> dict:
    """What made each output, for summary.json."""
    tasks = tuple(tasks)
    out: dict[str, dict] = {}
    if "depth" in tasks:
        out["depth"] = {"method": "network"}
    if "flow" in tasks:
        out["flow"] = (
            {"method": "dis", "detail": f"OpenCV DIS optical flow, preset {DIS_PRESET}, at the input resolution"}
            if flow_method == "dis"
            else {"method": "network"}
        )
    if "pose" in tasks:
        out["pose"] = (
            {
                "method": "orbvo",
                "detail": "two-view ORB-VO per consecutive pair (ORB, 5-point RANSAC, recoverPose); matches "
                f"moving under {STILL_SHIFT_PX:g} px (median): no motion; another failed pair repeats the last step",
                "scale": "step length = median(predicted depth / triangulated depth) over the step's inliers: "
                "in the depth's units (metres with a camera height)",
            }
            if pose_method == "orbvo"
            else {"method": "network"}
        )
    return out


class KeptFrames:
    """The frames of a sequence passed through unchanged, each also kept for the classical methods
    until :meth:`take` (the networks read them a few frames ahead of the results)."""

    def __init__(self, frames: Iterable):
        self.frames = frames
        self.kept: dict[int, object] = {}

    def __iter__(self) -> Iterator:
        for index, frame in enumerate(self.frames):
            self.kept[index] = frame
            yield frame

    def take(self, index: int):
        return self.kept.pop(index)


def _euler_xyz(R: np.ndarray) -> np.ndarray:
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


def classical_frames(
    results: Iterable[FrameResult],
    kept: KeptFrames,
    camera: Intrinsics | None,
    flow_method: str,
    pose_method: str,
    check_size: tuple[int, int] | None = None,
) -> Iterator[FrameResult]:
    """``results`` with their flow (DIS) and/or poses (ORB-VO) replaced; see the module docstring.

    ``kept`` holds the input frames by index; frame t's result needs frames t and t+1 (the
    networks have read t+1 before they yield t; a last frame has no next one). ``check_size``
    (h, w): DIS flow is checked against the frames there (:mod:`geonet_infer.check`), as the
    networks' flow is at their size; None: not checked."""
    dis = dis_flow(DIS_PRESET) if flow_method == "dis" else None
    orb = orb_matcher() if pose_method == "orbvo" else None
    frames: dict[int, np.ndarray] = {}  # undistorted RGB at the input size, by index
    step = np.eye(4)
    pose_world = np.eye(4)

    def frame(index: int) -> np.ndarray | None:
        if index not in frames:
            if index not in kept.kept:
                return None
            rgb, _ = read_frame(kept.take(index), StageTimer(), index)
            cam = camera_at(camera, rgb.shape[:2])
            frames[index] = rgb if cam is None else cam.undistort(rgb)
        return frames[index]

    for result in results:
        a, b = frame(result.index), frame(result.index + 1)
        assert a is not None  # kept until its own result
        frames.pop(result.index - 1, None)
        timings = dict(result.timings_ms)
        changes: dict = {}
        if dis is not None:
            t0 = time.perf_counter()
            changes["flow"] = None if b is None else dis([a, b])
            changes["rigid_flow_at_input"] = None
            timings["dis"] = (time.perf_counter() - t0) * 1e3
            if check_size is not None and b is not None:
                t0 = time.perf_counter()
                changes["check"] = check_pair(a, b, changes["flow"], size=check_size)
                timings["check"] = (time.perf_counter() - t0) * 1e3
        if orb is not None:
            t0 = time.perf_counter()
            pose_next = vector = None
            if b is not None:
                pose_next, vector, step = _orb_step(orb, a, b, result, step)
            changes |= {"pose_to_next": pose_next, "pose_vector_to_next": vector}
            changes["camera_to_world"] = pose_world.copy()
            if pose_next is not None:
                pose_world = next_camera_to_world(pose_world, pose_next)
            timings["orbvo"] = (time.perf_counter() - t0) * 1e3
        timings["total"] = timings.get("total", 0.0) + sum(timings.get(k, 0.0) for k in CLASSICAL_STAGES)
        yield replace(result, timings_ms=timings, **changes)


def _orb_step(orb, a: np.ndarray, b: np.ndarray, result: FrameResult, previous: np.ndarray):
    """(pose to next, its vector, the step to repeat if the next pair fails) for the pair a -> b."""
    if result.depth is None or result.intrinsics is None:
        raise InputError(result.name, "ORB-VO poses need the frame's depth and the camera intrinsics")
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global RNG: a frame's pose does not depend on the ones before
    K = result.intrinsics
    detector, matcher = orb
    pair = relative_pose(detector, matcher, grey(a), grey(b), K)
    T, pixels = pair.T, pair.pixels
    length = None if T is None or pixels is None else step_length(T, pixels, result.depth, K)
    if pair.shift is not None and pair.shift < STILL_SHIFT_PX:
        previous = np.eye(4)  # the matches did not move: the camera stood still (E is degenerate here)
    elif T is not None and length is not None:
        T = T.copy()
        T[:3, 3] *= length
        previous = T
    step = previous.copy()
    vector = np.concatenate([step[:3, 3], _euler_xyz(step[:3, :3])]).astype(np.float32)
    return step, vector, previous
