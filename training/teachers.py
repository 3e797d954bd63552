"""Classical teachers: labels for real footage that has no ground truth (issue 46).

Each teacher is a method that measures one quantity well on real video, run once by
``training.prepare --teacher-flow dis --teacher-pose orbvo``; the labels are written in the same
files as synthetic ground truth (``<frame>_flow.png``, ``<frame>_pose.txt``), so
``training.train --flow-supervision W`` / ``--pose-supervision W`` use them unchanged.

* Flow: OpenCV DIS (the eval's ``dis_flow("medium")``, 2.98 px EPE-noc on KITTI 2015 000010
  where the networks score 17) both ways, kept where the forward-backward check holds.
* Pose: two-view ORB visual odometry (the eval's ``orb_vo``), unit steps: the pose loss is
  scale-aligned per snippet, so the monocular scale does not matter.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geonet_infer.baselines import dis_flow, orb_vo
from geonet_infer.metrics import rigid_inverse

TEACHER_FLOWS = ("dis",)
TEACHER_POSES = ("orbvo",)
# Forward-backward check: |f(x) + b(x + f(x))| < FB_ABS_PX + FB_REL * (|f(x)| + |b(x + f(x))|).
# Sundaram et al. (ECCV 2010) use 0.01 and 0.5 of the squared norms; linear tolerances of this
# size kept ~80 % of the dashcam pixels in the prototype and drop occlusions and sky.
FB_ABS_PX = 0.5
FB_REL = 0.05


@dataclass(frozen=True)
class FlowLabel:
    """A teacher flow: ``flow`` (H, W, 2) px target -> next, ``valid`` (H, W) bool."""

    flow: np.ndarray
    valid: np.ndarray

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())


def sample_along(field: np.ndarray, flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``field`` (H, W, C) read at ``x + flow(x)`` (bilinear) and whether that point is inside.

    Args:
        field: (H, W, C) float32.
        flow: (H, W, 2) float32 px (u right, v down).
    Returns:
        (H, W, C) float32 and (H, W) bool.
    """
    h, w = flow.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    map_x, map_y = xs + flow[..., 0], ys + flow[..., 1]
    inside = (map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)
    sampled = cv2.remap(field, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return sampled.reshape(h, w, -1), inside


def forward_backward_valid(fwd: np.ndarray, bwd: np.ndarray, abs_px: float = FB_ABS_PX, rel: float = FB_REL):
    """(H, W) bool: where the backward flow, read at the forward flow's end, brings the pixel back.

    Args:
        fwd: (H, W, 2) flow a -> b; bwd: (H, W, 2) flow b -> a (px).
    """
    bwd_at, inside = sample_along(bwd, fwd)
    error = np.linalg.norm(fwd + bwd_at, axis=-1)
    tolerance = abs_px + rel * (np.linalg.norm(fwd, axis=-1) + np.linalg.norm(bwd_at, axis=-1))
    return inside & (error < tolerance) & np.isfinite(error)


def teacher_flow(target: np.ndarray, following: np.ndarray, method: str = "dis") -> FlowLabel:
    """Flow target -> following frame by a classical teacher, masked by the forward-backward check.

    Args:
        target, following: (H, W, 3) uint8 RGB at the training resolution.
    """
    if method not in TEACHER_FLOWS:
        raise ValueError(f"unknown teacher flow {method!r}; choose one of {', '.join(TEACHER_FLOWS)}")
    dis = dis_flow("medium")
    fwd = dis([target, following])
    bwd = dis([following, target])
    return FlowLabel(fwd.astype(np.float32), forward_backward_valid(fwd, bwd))


def teacher_motion(frames: list[np.ndarray], K: np.ndarray, target_index: int, method: str = "orbvo"):
    """(N_src, 4, 4) motion target -> each source by a classical teacher, or None where it failed.

    The convention of ``training.prepare.snippet_motion`` (it maps a point in the target
    camera's frame into the source camera's), unit steps between consecutive frames.

    Args:
        frames: the snippet's (h, w, 3) uint8 RGB frames in temporal order.
        K: (3, 3) intrinsics of those frames.
        target_index: which frame is the target (the middle one).
    """
    if method not in TEACHER_POSES:
        raise ValueError(f"unknown teacher pose {method!r}; choose one of {', '.join(TEACHER_POSES)}")
    camera_to_first, info = orb_vo(frames, K)
    if info["failed_pairs"]:
        return None  # a repeated step is a guess, not a measurement: no label
    target = camera_to_first[target_index]
    return np.stack([rigid_inverse(c) @ target for k, c in enumerate(camera_to_first) if k != target_index])
