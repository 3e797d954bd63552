"""The rigid-flow op of ``rigidflow.onnx`` in numpy + OpenCV, about twice as fast as the graph.

The op has no weights: rigid flow from depth, pose and K, the source warped onto the target,
and the photometric error that is ResFlowNet's 12th input channel. Written as small pure
functions on one snippet at a time (shapes in each docstring); :class:`RigidFlowOp` runs a batch
with the graph's inputs and outputs, so the cascade calls it exactly like the graph.
Conventions: :mod:`geonet_infer.conventions` (pose ``R = Rx @ Ry @ Rz`` target -> source, pixel
grid at pixel centres, corner-aligned bilinear sampling with zero padding). Agreement with the
graph is tested to 1e-4 px (tests/test_rigid_op.py); the graph stays the reference
(``rigid_op="graph"``, the default).
"""

from __future__ import annotations

import threading
from functools import lru_cache

import cv2
import numpy as np

__all__ = ["RigidFlowOp", "Workspace", "pose_to_matrix", "rigid_flow", "warp_bilinear", "photometric_error_map"]

SSIM_C1 = 0.01**2  # training.losses: the constants the graph bakes in
SSIM_C2 = 0.03**2
DEPTH_EPS = 1e-10  # z + 1e-10 before the perspective divide, no clamp (official code)
OUTPUTS = ("rigid_flow", "warped", "error")


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """Pose vector ``[tx, ty, tz, rx, ry, rz]`` (6,) -> (4, 4) float64 target -> source.

    Angles are clipped to [-pi, pi] as in training; ``R = Rx(rx) @ Ry(ry) @ Rz(rz)``.
    """
    t = np.asarray(pose[:3], np.float64)
    rx, ry, rz = np.clip(np.asarray(pose[3:6], np.float64), -np.pi, np.pi)
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cz, -cy * sz, sy],
        [cx * sz + sx * sy * cz, cx * cz - sx * sy * sz, -sx * cy],
        [sx * sz - cx * sy * cz, sx * cz + cx * sy * sz, cx * cy],
    ]
    T[:3, 3] = t
    return T


@lru_cache(maxsize=16)
def _pixel_grid(height: int, width: int, dtype=np.float32) -> np.ndarray:
    """(3, H*W) homogeneous pixel centres ``[u, v, 1]``, u = 0..W-1 fastest."""
    v, u = np.mgrid[0:height, 0:width].astype(dtype)
    grid = np.stack([u.ravel(), v.ravel(), np.ones(height * width, dtype)])
    grid.setflags(write=False)
    return grid


def rigid_flow(depth: np.ndarray, T: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Flow of a static scene seen from a moving camera.

    Args:
        depth: (H, W) depth of the target frame.
        T: (4, 4) target -> source camera.
        K: (3, 3) intrinsics at H x W.
    Returns:
        (2, H, W) float32 pixels: ``project(K, T, depth * K^-1 [u, v, 1]) - [u, v]``.
    """
    H, W = depth.shape
    grid = _pixel_grid(H, W, np.float64)
    P = K.astype(np.float64) @ T[:3, :]
    # K (R X + t) with X = d K^-1 [u, v, 1] is (K R K^-1) [u, v, 1] d + K t: one 3x3 product per pixel.
    # float64: the projected x is ~W, where float32 steps are ~3e-5 px.
    projected = (P[:, :3] @ np.linalg.inv(K.astype(np.float64))) @ grid
    projected *= depth.reshape(1, -1)
    projected += P[:, 3:]
    projected[2] += DEPTH_EPS
    flow = projected[:2] / projected[2]
    flow -= grid[:2]
    return flow.astype(np.float32).reshape(2, H, W)


class Workspace:
    """Arrays reused from call to call, by name: a fresh large array costs page faults that, in a
    VM, took longer than the arithmetic (the op ran 3-5x slower allocating per call)."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float32, zero: bool = False) -> np.ndarray:
        array = self._arrays.get(name)
        if array is None or array.shape != shape or array.dtype != dtype:
            array = self._arrays[name] = np.zeros(shape, dtype)
        elif zero:
            array.fill(0)
        return array


def warp_bilinear(image: np.ndarray, flow: np.ndarray, ws: Workspace | None = None) -> np.ndarray:
    """``image`` sampled at ``[u, v] + flow``, bilinear, zero outside (``grid_sample(align_corners=True,
    padding_mode='zeros')``; cv2.remap would round the positions to 1/32 px).

    Args:
        image: (C, H, W) float32.
        flow: (2, H, W) pixels.
        ws: buffers to reuse; the result is one of them (copy it to keep it past the next call).
    Returns:
        (C, H, W) float32.
    """
    ws = ws or Workspace()
    C, H, W = image.shape
    n = H * W
    padded = ws.get("padded", (C, H + 2, W + 2))  # the border is never written: corners outside read 0
    padded[:, 1:-1, 1:-1] = image
    planes = padded.reshape(C, -1)
    grid = _pixel_grid(H, W)
    x = np.add(grid[0], flow[0].reshape(-1), out=ws.get("x", (n,)))
    y = np.add(grid[1], flow[1].reshape(-1), out=ws.get("y", (n,)))
    x0f, y0f = np.floor(x, out=ws.get("x0f", (n,))), np.floor(y, out=ws.get("y0f", (n,)))
    wx1, wy1 = np.subtract(x, x0f, out=x), np.subtract(y, y0f, out=y)
    wx0, wy0 = np.subtract(1, wx1, out=ws.get("wx0", (n,))), np.subtract(1, wy1, out=ws.get("wy0", (n,)))

    def border_index(start: np.ndarray, step: int, size: int, name: str) -> np.ndarray:
        # -1 and size are the zero border; anything further out (and NaN: no depth) reads it too
        i = np.add(start, step + 1, out=ws.get("index_f", (n,)))
        np.clip(i, 0, size + 1, out=i)
        np.nan_to_num(i, copy=False, nan=0)
        index = ws.get(name, (n,), np.intp)
        np.copyto(index, i, casting="unsafe")
        return index

    x0, x1 = border_index(x0f, 0, W, "x0"), border_index(x0f, 1, W, "x1")
    row0, row1 = border_index(y0f, 0, H, "y0"), border_index(y0f, 1, H, "y1")
    row0 *= W + 2
    row1 *= W + 2
    out, gathered = ws.get("warped", (C, n)), ws.get("gathered", (C, n))
    index, weight = ws.get("index", (n,), np.intp), ws.get("weight", (n,))
    corners = ((row0, x0, wx0, wy0), (row0, x1, wx1, wy0), (row1, x0, wx0, wy1), (row1, x1, wx1, wy1))
    for k, (row, col, wx, wy) in enumerate(corners):
        np.add(row, col, out=index)
        np.take(planes, index, axis=1, out=gathered)
        np.multiply(wx, wy, out=weight)
        if k == 0:
            np.multiply(gathered, weight, out=out)
        else:
            gathered *= weight
            out += gathered
    return out.reshape(C, H, W)


@lru_cache(maxsize=8)
def _window_counts(height: int, width: int) -> np.ndarray:
    """(H, W) pixels of each 3x3 window inside the image (9, 6 at edges, 4 at corners)."""
    ones = np.ones((height, width), np.float32)
    counts = cv2.boxFilter(ones, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    counts.setflags(write=False)
    return counts


def photometric_error_map(
    warped: np.ndarray, target: np.ndarray, alpha: float, ws: Workspace | None = None
) -> np.ndarray:
    """``|| alpha * DSSIM + (1 - alpha) * |warped - target| + 1e-10 ||_2`` over channels.

    Args:
        warped, target: (C, H, W) float32 network-range images.
        ws: buffers to reuse; the result is one of them.
    Returns:
        (H, W) float32, SSIM over 3x3 windows (training.losses.photometric_error, then l2_norm).
    """
    ws = ws or Workspace()
    C, H, W = warped.shape
    # The five maps SSIM averages, stacked with a zero row after each plane: one box filter does all
    # 5C planes, and the zero rows are the constant border each plane would have alone.
    stacked = ws.get("stacked", (5, C, H + 1, W))
    maps = stacked[:, :, :H]
    maps[0] = warped
    maps[1] = target
    np.multiply(warped, warped, out=maps[2])
    np.multiply(target, target, out=maps[3])
    np.multiply(warped, target, out=maps[4])
    sums = ws.get("sums", stacked.shape)
    cv2.boxFilter(
        stacked.reshape(-1, W), -1, (3, 3), dst=sums.reshape(-1, W), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    means = sums[:, :, :H]
    means /= _window_counts(H, W)
    mu_x, mu_y, mean_xx, mean_yy, mean_xy = means
    a, b, c = (ws.get(name, (C, H, W)) for name in ("a", "b", "c"))
    np.multiply(mu_x, mu_y, out=a)  # mu_xy
    np.subtract(mean_xy, a, out=b)  # sigma_xy
    a *= 2
    a += np.float32(SSIM_C1)
    b *= 2
    b += np.float32(SSIM_C2)
    a *= b  # numerator
    np.multiply(mu_x, mu_x, out=b)  # mu_xx
    np.multiply(mu_y, mu_y, out=c)  # mu_yy
    mean_xx -= b  # sigma_x
    mean_yy -= c  # sigma_y
    b += c
    b += np.float32(SSIM_C1)
    np.add(mean_xx, mean_yy, out=c)
    c += np.float32(SSIM_C2)
    b *= c  # denominator
    np.divide(a, b, out=a)  # SSIM
    np.subtract(1, a, out=a)
    a /= 2
    np.clip(a, 0, 1, out=a)  # DSSIM
    a *= np.float32(alpha)
    np.subtract(warped, target, out=b)
    np.abs(b, out=b)
    b *= np.float32(1 - alpha)
    a += b
    np.abs(a, out=a)
    a += np.float32(1e-10)
    error = np.einsum("chw,chw->hw", a, a, out=ws.get("error", (H, W)))
    return np.sqrt(error, out=error)


class RigidFlowOp:
    """``rigidflow.onnx``'s inputs and outputs, computed in numpy (an :class:`~geonet_infer.engines.Engine`).

    ``run({"depth": (B,1,H,W), "pose": (B,6), "intrinsics": (B,3,3), "target": (B,3,H,W),
    "source": (B,3,H,W)})`` -> ``{"rigid_flow": (B,2,H,W), "warped": (B,3,H,W), "error": (B,1,H,W)}``.
    ``alpha``: the DSSIM weight baked into the model's graph (``Manifest.photometric_alpha``).
    """

    name = "numpy"
    input_names = ["depth", "pose", "intrinsics", "target", "source"]
    output_names = list(OUTPUTS)

    def __init__(self, alpha: float, graph_io: tuple[list, list] | None = None):
        self.alpha = float(alpha)
        self._io = graph_io
        self._workspace = threading.local()  # one set of buffers per thread: a Predictor may be shared

    @staticmethod
    def supports(model_conventions: dict) -> bool:
        """Whether a model's graph (its manifest's conventions) samples as this op does:
        corner-aligned, zero padding."""
        sampler = model_conventions.get("sampler", {})
        return bool(sampler.get("align_corners")) and sampler.get("padding") == "zeros"

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        depth, pose, K = feeds["depth"], feeds["pose"], feeds["intrinsics"]
        target, source = feeds["target"], feeds["source"]
        B, _, H, W = target.shape
        flows = np.empty((B, 2, H, W), np.float32)
        warped = np.empty((B, 3, H, W), np.float32)
        errors = np.empty((B, 1, H, W), np.float32)
        ws = getattr(self._workspace, "buffers", None)
        if ws is None:
            ws = self._workspace.buffers = Workspace()
        for b in range(B):
            flows[b] = rigid_flow(depth[b, 0], pose_to_matrix(pose[b]), K[b])
            warped[b] = warp_bilinear(source[b], flows[b], ws)
            errors[b, 0] = photometric_error_map(warped[b], target[b], self.alpha, ws)
        return {"rigid_flow": flows, "warped": warped, "error": errors}

    def io(self) -> tuple[list, list]:
        if self._io is None:
            raise NotImplementedError("RigidFlowOp.io needs the graph's io (given by GraphSet)")
        return self._io

    def input_shapes(self) -> dict[str, list]:
        return {name: list(shape) for name, shape, _ in self.io()[0]}

    def describe(self) -> dict:
        return {"engine": self.name, "op": "rigidflow in numpy + OpenCV", "photometric_alpha": self.alpha}
