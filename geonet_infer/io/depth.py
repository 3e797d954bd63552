"""KITTI depth PNG: 16-bit grey, round(depth_m * 256); 0 = no measurement."""

from __future__ import annotations

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.images import _imread, _imwrite

__all__ = ["DEPTH_SCALE", "write_depth_kitti", "read_depth_kitti"]

DEPTH_SCALE = 256.0  # KITTI depth: 1/256 m steps


def write_depth_kitti(path, depth: np.ndarray, too_far: str = "zero") -> None:
    """Write (H, W) depth in metres (0 = none) as 16-bit PNG of round(depth * 256).

    Non-finite or non-positive values are written as 0 (none). Depths beyond
    the format's range (65535 / 256 = 255.996 m) become 0 with ``too_far="zero"``
    (default: a clipped value would be a wrong measurement) or 65535 with
    ``too_far="clip"`` (e.g. for predictions).
    """
    if too_far not in ("zero", "clip"):
        raise ValueError(f"too_far must be 'zero' or 'clip', got {too_far!r}")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    enc = np.round(depth * DEPTH_SCALE)
    enc = np.where(enc > 65535, 0 if too_far == "zero" else 65535, enc).astype(np.uint16)
    with atomic_write(path) as tmp:
        _imwrite(tmp, enc)


def read_depth_kitti(path) -> np.ndarray:
    """Read KITTI depth PNG -> (H, W) float32 metres, 0 = no measurement."""
    img = _imread(path)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise InputError(
            path,
            f"not a KITTI depth PNG (need 16-bit 1-channel, got {img.dtype} shape {img.shape})",
            "KITTI depth is stored as 16-bit grey PNG of depth*256",
        )
    return img.astype(np.float32) / DEPTH_SCALE
