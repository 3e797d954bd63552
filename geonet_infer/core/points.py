"""Point clouds from depth: back-projection and binary PLY files (numpy only).

Camera frame of the pinhole model (:mod:`geonet_infer.conventions`): x right, y down, z forward,
pixel centres at integer (u, v). A point is ``d * K^-1 [u, v, 1]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.io.atomic import atomic_write

__all__ = ["backproject", "camera_points", "pixels_to_camera", "write_ply", "PLY_DTYPE"]

PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def pixels_to_camera(u: np.ndarray, v: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The one back-projection: pixels (u, v) at ``depth`` -> camera points ``d * K^-1 [u, v, 1]``,
    float64, shape (..., 3) of the inputs' shape (K without skew, as every calibration here)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = np.asarray(depth, np.float64)
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def camera_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W) depth -> (H, W, 3) camera points of every pixel (:func:`pixels_to_camera`)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return pixels_to_camera(u, v, depth, K)


def backproject(
    depth: np.ndarray, K: np.ndarray, stride: int = 1, max_depth: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels with depth -> 3-D points in the camera frame.

    Args:
        depth: (H, W) depth; 0 or non-finite = none.
        K: (3, 3) intrinsics at H x W.
        stride: keep every ``stride``-th pixel in u and v.
        max_depth: drop points farther than this (same units as ``depth``).
    Returns:
        points (N, 3) float32 ``d * K^-1 [u, v, 1]``, and their pixels (N, 2) int (v, u) to look
        colours up with ``image[pixels[:, 0], pixels[:, 1]]``.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    K = np.asarray(K, np.float64)
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    d = depth[v, u].astype(np.float64)
    keep = np.isfinite(d) & (d > 0)
    if max_depth is not None:
        keep &= d <= max_depth
    v, u, d = v[keep], u[keep], d[keep]
    return pixels_to_camera(u.astype(np.float64), v.astype(np.float64), d, K).astype(np.float32), np.stack(
        [v, u], axis=1
    )


def write_ply(
    path: str | Path, points: np.ndarray, colours: np.ndarray | None = None, comments: tuple[str, ...] = ()
) -> None:
    """Binary little-endian PLY (x, y, z float32; red, green, blue uint8), written atomically.

    Args:
        points: (N, 3) float.
        colours: (N, 3) uint8 RGB; None = white.
        comments: header comment lines (e.g. the scale's unit).
    """
    vertices = np.empty(len(points), PLY_DTYPE)
    for i, axis in enumerate("xyz"):
        vertices[axis] = points[:, i]
    rgb = np.full((len(points), 3), 255, np.uint8) if colours is None else np.asarray(colours, np.uint8)
    for i, channel in enumerate(("red", "green", "blue")):
        vertices[channel] = rgb[:, i]
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
    header += [f"element vertex {len(vertices)}"]
    header += [f"property float {a}" for a in "xyz"] + [f"property uchar {c}" for c in ("red", "green", "blue")]
    header += ["end_header"]
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(vertices.tobytes())
