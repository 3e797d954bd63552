"""Ground truth of a rendered frame: depth, surface ids, motion mask and exact flow t -> t+1.

Flow: each hit point is moved by the camera motion (and, on a moving car, by that car's
own rigid motion) and projected into frame t+1. ``occ`` validity = it lands inside
[0, W-1] x [0, H-1] in front of the camera; ``noc`` additionally requires it to be
visible in frame t+1: its depth there is not behind all four rendered depths around its
landing point (on a plane inverse depth is linear in the image, so a visible point is
never behind all four).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training.synth.render import Renderer
from training.synth.scene import BOX0, NEAR, Scene

VIS_REL_TOL = 1e-3  # noc test: point may be this much (relative) behind the visible surface


@dataclass
class FrameGeom:
    depth: np.ndarray  # (H, W) float64 z-depth
    ids: np.ndarray  # (H, W) int32
    points: np.ndarray  # (H, W, 3) float64 road-world hit points
    moving: np.ndarray  # (H, W) bool


def box_groups(scene: Scene, ids: np.ndarray) -> np.ndarray:
    """(H, W) int: the moving group of the box each pixel sees, -1 for static surfaces."""
    grp = np.full(ids.shape, -1)
    box = ids >= BOX0
    grp[box] = scene.box_group[ids[box] - BOX0]
    return grp


def frame_geometry(r: Renderer, t: int) -> FrameGeom:
    depth, ids, D = r.cast(t, 1)
    C = r.scene.T_wc[t, :3, 3]
    points = np.stack([C[i] + depth * D[i] for i in range(3)], -1)
    return FrameGeom(depth, ids, points, box_groups(r.scene, ids) >= 0)


def flow_gt(scene: Scene, t: int, g0: FrameGeom, g1: FrameGeom):
    """Exact flow t -> t+1 at pixel centres.

    Returns:
        flow (H, W, 2) float32 px, noc (H, W) bool, occ (H, W) bool.
    """
    H, W = g0.depth.shape
    P = g0.points.copy()
    grp = box_groups(scene, g0.ids)
    for gi in np.unique(grp[grp >= 0]):
        A = scene.group_T[gi, t + 1] @ np.linalg.inv(scene.group_T[gi, t])  # group motion in the world
        m = grp == gi
        P[m] = P[m] @ A[:3, :3].T + A[:3, 3]
    T1 = scene.T_wc[t + 1]
    X = (P - T1[:3, 3]) @ T1[:3, :3]  # into camera t+1
    K = scene.K
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = K[0, 0] * X[..., 0] / z + K[0, 2]
        y = K[1, 1] * X[..., 1] / z + K[1, 2]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    flow = np.stack([x - u, y - v], -1)
    occ = (z > NEAR) & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    # Visible in t+1 unless behind all 4 rendered depths around the landing point.
    xc, yc = np.where(occ, x, 0), np.where(occ, y, 0)
    x0 = np.clip(np.floor(xc).astype(int), 0, W - 1)
    y0 = np.clip(np.floor(yc).astype(int), 0, H - 1)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    d1 = g1.depth
    dmax = np.maximum(np.maximum(d1[y0, x0], d1[y0, x1]), np.maximum(d1[y1, x0], d1[y1, x1]))
    noc = occ & (z <= dmax * (1 + VIS_REL_TOL))
    flow = np.where(occ[..., None], flow, 0.0).astype(np.float32)
    return flow, noc, occ
