"""Classical teachers: labels for real footage that has no ground truth (issue 46).

Each teacher is a method that measures one quantity well on real video, run once by
``training.prepare --teacher-flow dis --teacher-pose orbvo --teacher-depth triangulate``; the
labels are written in the same files as synthetic ground truth (``<frame>_flow.png``,
``<frame>_pose.txt``, ``<frame>_depth.png``), so ``training.train --flow-supervision W`` /
``--pose-supervision W`` / ``--depth-supervision W`` use them unchanged.

* Flow: OpenCV DIS (the eval's ``dis_flow("medium")``, 2.98 px EPE-noc on KITTI 2015 000010
  where the networks score 17) both ways, kept where the forward-backward check holds.
* Pose: two-view ORB visual odometry (the eval's ``orb_vo``), unit steps: the pose loss is
  scale-aligned per snippet, so the monocular scale does not matter.
* Depth (``--teacher-depth triangulate``): the target's depth triangulated from the DIS flow to
  the next frame and the motion that flow implies (:func:`flow_motion`), at full resolution, kept
  where the parallax is large enough and the flow agrees with the motion's epipolar geometry.
  Monocular, so it has no metric scale: each label is scaled to a median of
  :data:`DEPTH_LABEL_MEDIAN` (the depth loss is scale invariant; see :func:`teacher_depth`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geonet_infer.eval.baselines import dis_flow, orb_vo
from geonet_infer.eval.metrics import rigid_inverse

TEACHER_FLOWS = ("dis",)
TEACHER_POSES = ("orbvo",)
TEACHER_DEPTHS = ("triangulate",)
# Forward-backward check: |f(x) + b(x + f(x))| < FB_ABS_PX + FB_REL * (|f(x)| + |b(x + f(x))|).
# Sundaram et al. (ECCV 2010) use 0.01 and 0.5 of the squared norms; linear tolerances of this
# size kept ~80 % of the dashcam pixels in the prototype and drop occlusions and sky.
FB_ABS_PX = 0.5
FB_REL = 0.05
# Motion from the masked flow: the 5-point RANSAC (0.5 px) on every FLOW_MOTION_STRIDE-th pixel
# of the forward-backward valid flow. On KITTI odometry 06 pairs 0-49 its translation direction
# is 0.65 deg from the official poses (median; max 1.5), two-view ORB-VO's 2.6 deg (p90 6.2, and
# one pair 102 deg off): an error of a few degrees moves the epipole by tens of px and bends
# every depth near it.
FLOW_MOTION_STRIDE = 8
FLOW_MOTION_RANSAC_PX = 0.5
MIN_MOTION_INLIERS = 500  # of ~4000 samples at full KITTI resolution; fewer: no motion, no depth
# Triangulation (full-resolution px). A flow error of e px moves the depth by about
# e / parallax of itself, so 5 px of parallax bounds a 1 px flow error to 20 %; 1 px from the
# epipolar line is twice the motion's RANSAC threshold (drops moving objects, flow errors).
MIN_PARALLAX_PX = 5.0
MAX_EPIPOLAR_PX = 1.0
# Each depth label is scaled to this median: the monocular depth is in units of the (unknown)
# ORB step, and KITTI's 16-bit PNG holds 1/256 .. 255.996, so a slow step (depths in the
# thousands) would overflow it; the depth loss is blind to one scale per image.
DEPTH_LABEL_MEDIAN = 10.0
MIN_DEPTH_FRACTION = 0.05  # fewer labelled pixels than this: no depth label for the sample


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


@dataclass(frozen=True)
class DepthLabel:
    """A teacher depth of the target frame.

    ``depth`` (H, W) float32, 0 = none; ``valid`` (H, W) bool (``depth > 0`` exactly there);
    ``parallax`` (H, W) float32 px, the confidence: the flow's distance from where a point at
    infinity would land, so a flow error of e px makes a relative depth error of about
    e / parallax (0 where there is no depth).
    """

    depth: np.ndarray
    valid: np.ndarray
    parallax: np.ndarray

    @property
    def valid_fraction(self) -> float:
        return float(self.valid.mean())


def triangulate_depth(
    flow: np.ndarray,
    valid: np.ndarray,
    motion: np.ndarray,
    K: np.ndarray,
    min_parallax_px: float = MIN_PARALLAX_PX,
    max_epipolar_px: float = MAX_EPIPOLAR_PX,
) -> DepthLabel:
    """Per-pixel depth of the target frame from its flow to the next frame and the motion between.

    Least squares along the target ray: a pixel ``x`` with ray ``r = K^-1 x`` (z = 1) at depth
    ``z`` lands in the next camera at ``z R r + t``; its observed normalised position
    ``(a, b, 1) = K^-1 (x + flow)`` gives two linear equations in ``z``
    (``z (R r)_x + t_x = a (z (R r)_z + t_z)``, the same in y), solved in closed form. Exact
    for exact flow. A pixel keeps its depth where all hold:

    * ``valid`` (e.g. the forward-backward check);
    * parallax >= ``min_parallax_px``: the flow end lies at least that far from the point at
      infinity ``K R r`` (drops distant points, the epipole's neighbourhood and pure rotation);
    * the flow end lies within ``max_epipolar_px`` of the epipolar line ``F x`` (the flow agrees
      with the motion: drops moving objects and flow errors across the line);
    * the point is in front of both cameras (drops flow or motion pointing the wrong way).

    Args:
        flow: (H, W, 2) float px target -> next (u right, v down).
        valid: (H, W) bool, where the flow is trusted.
        motion: (4, 4) rigid transform target -> next in the POSE convention of
            ``training.prepare.snippet_motion``: it maps a point in the target camera's frame
            into the next camera's frame. Its translation sets the depth's unit.
        K: (3, 3) intrinsics of both frames, at the flow's resolution.
        min_parallax_px, max_epipolar_px: the thresholds above, in px.
    Returns:
        :class:`DepthLabel`: depth (H, W) float32 along the optical axis in the units of
        ``motion``'s translation, 0 = none; valid; parallax px.
    """
    h, w = flow.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    R, t = np.asarray(motion, np.float64)[:3, :3], np.asarray(motion, np.float64)[:3, 3]
    K_inv = np.linalg.inv(K)
    us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x1 = np.stack([us, vs, np.ones_like(us)], axis=-1)  # (H, W, 3) homogeneous px
    x2 = np.stack([us + flow[..., 0], vs + flow[..., 1], np.ones_like(us)], axis=-1)
    ray = x1 @ K_inv.T  # (H, W, 3), z = 1
    n2 = x2 @ K_inv.T
    rot = ray @ R.T  # R r
    a, b = n2[..., 0], n2[..., 1]
    A = np.stack([rot[..., 0] - a * rot[..., 2], rot[..., 1] - b * rot[..., 2]], axis=-1)
    B = np.stack([a * t[2] - t[0], b * t[2] - t[1]], axis=-1)
    t_cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = K_inv.T @ t_cross @ R @ K_inv
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (A * B).sum(-1) / (A * A).sum(-1)
        z_next = z * rot[..., 2] + t[2]
        at_infinity = rot @ K.T
        at_infinity = at_infinity[..., :2] / at_infinity[..., 2:]
        parallax = np.linalg.norm(x2[..., :2] - at_infinity, axis=-1)
        line = x1 @ F.T  # epipolar line in the next frame, a u + b v + c = 0
        epipolar = np.abs((line * x2).sum(-1)) / np.hypot(line[..., 0], line[..., 1])
        keep = (
            np.asarray(valid, bool)
            & np.isfinite(z)
            & (z > 0)
            & (z_next > 0)
            & (rot[..., 2] > 0)
            & (parallax >= min_parallax_px)
            & (epipolar <= max_epipolar_px)  # NaN (no translation: no epipolar line) fails
        )
    depth = np.where(keep, z, 0.0).astype(np.float32)
    return DepthLabel(depth, keep, np.where(keep, parallax, 0.0).astype(np.float32))


def flow_motion(label: FlowLabel, K: np.ndarray) -> np.ndarray | None:
    """(4, 4) motion target -> next implied by a teacher flow, unit translation, or None.

    The essential matrix of the valid flow's correspondences (every :data:`FLOW_MOTION_STRIDE`-th
    pixel; 5-point RANSAC, :data:`FLOW_MOTION_RANSAC_PX`) and ``cv2.recoverPose``; None with
    fewer than :data:`MIN_MOTION_INLIERS` inliers (a standing camera, a scene that moves).

    Args:
        label: the flow target -> next and its mask (:func:`teacher_flow`).
        K: (3, 3) intrinsics at the flow's resolution.
    Returns:
        The POSE convention of ``training.prepare.snippet_motion`` (it maps a point in the target
        camera's frame into the next camera's frame).
    """
    s = FLOW_MOTION_STRIDE
    keep = label.valid[::s, ::s]
    vs, us = np.nonzero(keep)
    p_target = np.stack([us * s, vs * s], axis=-1).astype(np.float64)
    p_next = p_target + label.flow[::s, ::s][keep]
    if len(p_target) < MIN_MOTION_INLIERS:
        return None
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global RNG: the same label on every run
    K = np.asarray(K, dtype=np.float64)
    try:
        E, mask = cv2.findEssentialMat(
            p_target, p_next, K, method=cv2.RANSAC, prob=0.999, threshold=FLOW_MOTION_RANSAC_PX
        )
    except cv2.error:  # OpenCV 5 asserts where 4.x returned no solution (baselines._relative_pose)
        return None
    if E is None or E.shape != (3, 3):
        return None
    inliers, R, t, _ = cv2.recoverPose(E, p_target, p_next, K, mask=mask)
    if inliers < MIN_MOTION_INLIERS:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel() / np.linalg.norm(t)
    return T


def teacher_depth(target: np.ndarray, following: np.ndarray, K: np.ndarray, method: str = "triangulate"):
    """Depth of ``target`` by a classical teacher, scaled to a median of :data:`DEPTH_LABEL_MEDIAN`,
    or None where the motion failed or fewer than :data:`MIN_DEPTH_FRACTION` of the pixels have one.

    DIS flow both ways with the forward-backward mask (:func:`teacher_flow`), the motion it
    implies (:func:`flow_motion`, unit step) and :func:`triangulate_depth`. The depth has
    no metric scale (monocular): each label gets its own scale, which
    ``training.losses.scale_invariant_log_error`` (``--depth-supervision``) ignores.

    Args:
        target, following: (H, W, 3) uint8 RGB consecutive frames at full resolution (the
            thresholds are in full-resolution px).
        K: (3, 3) intrinsics of those frames.
    """
    if method not in TEACHER_DEPTHS:
        raise ValueError(f"unknown teacher depth {method!r}; choose one of {', '.join(TEACHER_DEPTHS)}")
    flow = teacher_flow(target, following)
    motion = flow_motion(flow, K)
    if motion is None:
        return None
    label = triangulate_depth(flow.flow, flow.valid, motion, K)
    if label.valid_fraction < MIN_DEPTH_FRACTION:
        return None
    scale = DEPTH_LABEL_MEDIAN / float(np.median(label.depth[label.valid]))
    return DepthLabel((label.depth * scale).astype(np.float32), label.valid, label.parallax)
