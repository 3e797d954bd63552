"""What the Predictor returns: frozen records of arrays, every one at the caller's input resolution.

Conventions for all of them: depth in the model's relative units (metres when a camera
height was given, then ``metric_scale`` is the factor applied), disparity = 1 / depth,
flow (u, v) in input pixels from a frame to the next one, poses as 4x4 rigid transforms in
the pose convention of :data:`geonet_infer.conventions.POSE`, ``timings_ms`` per stage of
:data:`geonet_infer.core.cascade.STAGES` plus "total".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from geonet_infer.core.check import FrameCheck, SequenceCheck
from geonet_infer.core.points import backproject
from geonet_infer.errors import InputError


class _Points:
    """``points()`` for results with ``depth`` and ``intrinsics`` (K at the input resolution)."""

    depth: np.ndarray | None
    intrinsics: np.ndarray | None

    def points(
        self, image: np.ndarray | None = None, stride: int = 1, max_depth: float | None = None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The depth back-projected with the K the runtime used: (N, 3) float32 points in this
        camera's frame (x right, y down, z forward; depth's units), and their (N, 3) uint8 colours
        from ``image`` (the input frame, RGB) or None. ``stride`` keeps every n-th pixel in u and v."""
        if self.depth is None or self.intrinsics is None:
            raise ValueError("points need depth and the camera intrinsics (pass a camera)")
        if image is not None and np.shape(image)[:2] != self.depth.shape:
            raise InputError(
                None,
                f"points(image) got an image of shape {np.shape(image)}, the depth is {self.depth.shape}",
                "pass the frame this result was predicted from (the same height and width)",
            )
        xyz, pixels = backproject(self.depth, self.intrinsics, stride, max_depth)
        colours = None if image is None else np.asarray(image)[pixels[:, 0], pixels[:, 1]]
        return xyz, colours


@dataclass(frozen=True)
class DepthResult(_Points):
    """Depth of one image (:meth:`Predictor.depth`).

    Attributes:
        depth: (H, W) float32; relative scale, or metres with a camera height.
        disparity: (H, W) float32, 1 / depth.
        undistorted: the image was undistorted first (its camera has lens distortion).
        timings_ms: stage -> ms for this image (a batch's time divided evenly).
        metric_scale: the factor that made depth metric, or None (relative depth).
        intrinsics: (3, 3) float64 K at the image's resolution that was used (after undistortion),
            or None without a camera; :meth:`points` back-projects with it.
    """

    depth: np.ndarray
    disparity: np.ndarray
    undistorted: bool
    timings_ms: dict[str, float]
    metric_scale: float | None = None
    intrinsics: np.ndarray | None = None


@dataclass(frozen=True)
class PoseResult:
    """Poses from the target (middle frame of a snippet) to each source (:meth:`Predictor.pose`).

    Attributes:
        matrices: (L-1, 4, 4) float64 rigid transforms mapping target-camera points to
            source-camera points, sources in temporal order.
        vectors: (L-1, 6) float32 [tx, ty, tz, rx, ry, rz] (Euler radians, R = Rx Ry Rz);
            translation in the depth's relative units.
        timings_ms: stage -> ms for the snippet.
    """

    matrices: np.ndarray
    vectors: np.ndarray
    timings_ms: dict[str, float]


@dataclass(frozen=True)
class FlowResult:
    """Flow from the target to the next frame (:meth:`Predictor.flow`).

    Attributes:
        flow: (H, W, 2) float32 (u, v) in input pixels = rigid_flow + residual_flow; for a model
            without ResFlowNet (a stage 'rigid' export) it is the rigid flow.
        rigid_flow: (H, W, 2) float32, the flow of the static scene from depth and pose.
        residual_flow: (H, W, 2) float32, ResFlowNet's correction; None without ResFlowNet.
        depth: (H, W) float32, the target's depth (relative scale).
        pose: (4, 4) float64, the transform target -> next frame.
        undistorted: the frames were undistorted first.
        timings_ms: stage -> ms for the snippet.
        intrinsics: the intrinsics the rigid flow was made with (:meth:`Camera.record`: K, size,
            source and origin: given, or assumed when none were).
    """

    flow: np.ndarray
    rigid_flow: np.ndarray
    residual_flow: np.ndarray | None
    depth: np.ndarray
    pose: np.ndarray
    undistorted: bool
    timings_ms: dict[str, float]
    intrinsics: dict | None = None


@dataclass(frozen=True)
class FrameResult(_Points):
    """One frame of :meth:`Predictor.iter_sequence`; a task left out leaves its fields None.

    Attributes:
        index: the frame's position in the sequence (0-based).
        name: the frame's file stem, the given name, or its index as 6 digits.
        depth, disparity: (H, W) float32 (None without "depth", unless flow or a camera
            height needed them).
        camera_to_world: (4, 4) float64, this frame's pose in the first frame's camera
            coordinates (first frame = identity; without "pose" always the identity).
        pose_to_next: (4, 4) float64 transform this frame -> the next (None for the last frame
            or without "pose").
        pose_vector_to_next: (6,) float32 [tx, ty, tz, rx, ry, rz] of ``pose_to_next``.
        flow: (H, W, 2) float32 flow to the next frame (None for the last frame or without "flow").
        rigid_flow, residual_flow: (H, W, 2) float32, its static-scene part and ResFlowNet's
            correction (residual None without ResFlowNet); properties, resized to the input
            size on first access (a 1242x375 frame's pair costs 7 MB and a resize that
            ``predict`` never needs).
        undistorted: the frame was undistorted first.
        timings_ms: this frame's share of each stage (batched stages divided evenly).
        metric_scale: with a camera height, the factor that made depth and translations metres
            (smoothed over the sequence, :class:`geonet_infer.core.scale.ScaleSmoother`).
        metric_scale_raw: this frame's own ground-fit factor before smoothing (None: no road found).
        intrinsics: (3, 3) float64 K at the input resolution that was used, or None without a
            camera; :meth:`points` back-projects with it.
        check: the flow checked against the frames (:class:`~geonet_infer.core.check.FrameCheck`: does
            it explain the next frame better than no motion?); None without flow or with the check off.
    """

    index: int
    name: str
    depth: np.ndarray | None
    disparity: np.ndarray | None
    camera_to_world: np.ndarray
    pose_to_next: np.ndarray | None
    pose_vector_to_next: np.ndarray | None
    flow: np.ndarray | None
    undistorted: bool
    timings_ms: dict[str, float]
    metric_scale: float | None = None
    metric_scale_raw: float | None = None
    intrinsics: np.ndarray | None = None
    check: FrameCheck | None = None
    # Makes the rigid flow at the input size; None = the flow is all rigid (no ResFlowNet).
    rigid_flow_at_input: Callable[[], np.ndarray] | None = field(default=None, repr=False, compare=False)

    @cached_property
    def rigid_flow(self) -> np.ndarray | None:
        if self.flow is None or self.rigid_flow_at_input is None:
            return self.flow
        return self.rigid_flow_at_input()

    @cached_property
    def residual_flow(self) -> np.ndarray | None:
        if self.flow is None or self.rigid_flow_at_input is None:
            return None
        rigid = self.rigid_flow
        assert rigid is not None
        return self.flow - rigid  # resizing is linear: the residual graph output resized, one resize saved


@dataclass(frozen=True)
class SequenceResult:
    """All frames of a sequence (:meth:`Predictor.predict_sequence`).

    Attributes:
        frames: one :class:`FrameResult` per frame, in order.
        timings_ms: stage -> ms summed over the sequence.
        intrinsics: the intrinsics used at the frames' size (:meth:`Camera.record`: K, size, source,
            origin: given, or assumed when none were and a task needed them); None when none were used.
    """

    frames: list[FrameResult]
    timings_ms: dict[str, float] = field(default_factory=dict)
    intrinsics: dict | None = None

    @property
    def check(self) -> SequenceCheck | None:
        """The frames' flow checks summed up (None when no frame was checked)."""
        checks = [f.check for f in self.frames if f.check is not None]
        return SequenceCheck.from_checks(checks) if checks else None

    @property
    def depth(self) -> np.ndarray:
        """(N, H, W) depth of every frame."""
        depths = [f.depth for f in self.frames if f.depth is not None]
        if len(depths) < len(self.frames):
            raise ValueError("this sequence was predicted without depth")
        return np.stack(depths)

    @property
    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses, first frame = identity."""
        return np.stack([f.camera_to_world for f in self.frames])

    @property
    def flow(self) -> np.ndarray:
        """(N-1, H, W, 2) flow t -> t+1."""
        flows = [f.flow for f in self.frames[:-1] if f.flow is not None]
        if len(flows) < len(self.frames) - 1:
            raise ValueError("this sequence was predicted without flow (with_flow=False)")
        return np.stack(flows)
