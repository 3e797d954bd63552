"""A sequence's flow or poses from the classical methods (:mod:`geonet_infer.classical`) in place of the
networks': ``flow_method="dis"``, ``pose_method="orbvo"`` of :meth:`Predictor.iter_sequence`, predict and
batch (the module docstring of :mod:`geonet_infer.classical` says what each does)."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import replace

import cv2
import numpy as np

from geonet_infer.classical import (
    CLASSICAL_STAGES,
    DIS_PRESET,
    STILL_SHIFT_PX,
    dis_flow,
    euler_xyz,
    grey,
    orb_matcher,
    relative_pose,
    step_length,
)
from geonet_infer.conventions import next_camera_to_world
from geonet_infer.core.cascade import Intrinsics, StageTimer, camera_at, read_frame
from geonet_infer.core.check import check_pair
from geonet_infer.core.results import FrameResult
from geonet_infer.errors import InputError


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
    (h, w): DIS flow is checked against the frames there (:mod:`geonet_infer.core.check`), as the
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
    vector = np.concatenate([step[:3, 3], euler_xyz(step[:3, :3])]).astype(np.float32)
    return step, vector, previous
