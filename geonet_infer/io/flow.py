"""Optical flow files: KITTI flow PNG (16-bit) and Middlebury ``.flo``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.images import _imread
from geonet_infer.io.png import encode_png

__all__ = [
    "FLOW_SCALE",
    "FLOW_OFFSET",
    "FLO_MAGIC",
    "encode_flow_kitti",
    "decode_flow_kitti",
    "write_flow_kitti",
    "read_flow_kitti",
    "write_flo",
    "read_flo",
]

FLOW_SCALE = 64.0  # KITTI flow: 1/64 px steps
FLOW_OFFSET = 2**15
FLO_MAGIC = 202021.25


# --------------------------------------------------------------------------- KITTI flow PNG
def encode_flow_kitti(flow: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 2) float flow in px + (H, W) bool valid -> (H, W, 3) uint16 in **RGB** order.

    Values are rounded to the 1/64 px grid and clipped to the uint16 range;
    invalid (or non-finite) pixels become (0, 0, 0).
    """
    return cv2.merge(_flow_planes(flow, valid))


def _flow_planes(flow: np.ndarray, valid: np.ndarray | None) -> list[np.ndarray]:
    """The KITTI flow PNG's R, G, B planes: (H, W) uint16 each (u code, v code, valid)."""
    flow = np.asarray(flow)
    if flow.dtype not in (np.float32, np.float64):
        flow = flow.astype(np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    finite = np.isfinite(flow[..., 0]) & np.isfinite(flow[..., 1])
    if valid is not None:
        finite &= np.asarray(valid, dtype=bool)
    everywhere = bool(finite.all())
    planes = []
    for c in range(2):
        # Scaling by 64 is exact, and rint(x + 2**15) == rint(x) + 2**15 (an even integer keeps
        # round-half-even's choice): the codes of rounding in float64, computed in the flow's dtype.
        steps = flow[..., c] * flow.dtype.type(FLOW_SCALE)
        np.rint(steps, out=steps)
        np.clip(steps, -FLOW_OFFSET, FLOW_OFFSET - 1, out=steps)
        steps += FLOW_OFFSET
        if not everywhere:
            steps[~finite] = 0  # before the cast: NaN has no integer value
        planes.append(steps.astype(np.uint16))
    planes.append(finite.astype(np.uint16))
    return planes


def decode_flow_kitti(rgb16: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint16 RGB-ordered KITTI flow -> (flow (H, W, 2) float32 px, valid (H, W) bool).

    Invalid pixels get flow 0.
    """
    valid = rgb16[..., 2] != 0
    flow = (rgb16[..., :2].astype(np.float32) - FLOW_OFFSET) / FLOW_SCALE
    flow[~valid] = 0.0
    return flow, valid


def write_flow_kitti(path, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write KITTI flow PNG (16-bit, R=u*64+2^15, G=v*64+2^15, B=valid).

    Args:
        flow: (H, W, 2) float, pixels (u right, v down).
        valid: (H, W) bool; None = every finite pixel.
    """
    rgb = cv2.merge(_flow_planes(flow, valid))
    with atomic_write(path) as tmp:
        # Up filter: a network's flow resized to the input is smooth down the columns (a 720p frame:
        # 1.07 MB against 1.34 MB with Sub, and faster to deflate); the pixels are the same either way.
        tmp.write_bytes(encode_png(rgb, up=True))


def read_flow_kitti(path) -> tuple[np.ndarray, np.ndarray]:
    """Read KITTI flow PNG -> (flow (H, W, 2) float32 px, valid (H, W) bool)."""
    img = _imread(path)
    if img.dtype != np.uint16 or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(
            path,
            f"not a KITTI flow PNG (need 16-bit 3-channel, got {img.dtype} shape {img.shape})",
            "KITTI flow is stored as 16-bit RGB PNG (flow_occ / flow_noc)",
        )
    return decode_flow_kitti(img[..., ::-1])  # BGR -> RGB


# --------------------------------------------------------------------------- Middlebury .flo
def write_flo(path, flow: np.ndarray) -> None:
    """Write (H, W, 2) float flow as Middlebury .flo (little-endian float32)."""
    flow = np.asarray(flow, dtype="<f4")
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    h, w = flow.shape[:2]
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        np.array([FLO_MAGIC], dtype="<f4").tofile(f)
        np.array([w, h], dtype="<i4").tofile(f)
        np.ascontiguousarray(flow).tofile(f)


def read_flo(path) -> np.ndarray:
    """Read Middlebury .flo -> (H, W, 2) float32 (u, v) px.

    Values above 1e9 mark unknown flow in Middlebury files; they are returned as is.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "flow file not found", "check the path")
    raw = path.read_bytes()
    if len(raw) < 12:
        raise InputError(path, "file too short for a .flo header", "is it a Middlebury .flo file?")
    magic = np.frombuffer(raw, dtype="<f4", count=1)[0]
    if magic != np.float32(FLO_MAGIC):
        raise InputError(path, f"bad .flo magic {magic!r} (expected {FLO_MAGIC})", "is it a Middlebury .flo file?")
    w, h = (int(x) for x in np.frombuffer(raw, dtype="<i4", count=2, offset=4))
    if w <= 0 or h <= 0 or len(raw) != 12 + 8 * w * h:
        raise InputError(
            path, f".flo header says {w}x{h} but file has {len(raw)} bytes", "the file is truncated or corrupt"
        )
    return np.frombuffer(raw, dtype="<f4", offset=12).reshape(h, w, 2).astype(np.float32)
