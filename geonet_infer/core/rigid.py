"""The rigid-flow op of ``rigidflow.onnx`` in numpy + OpenCV, about 1.5x as fast as the graph on onnxruntime.

The op has no weights: rigid flow from depth, pose and K, the source warped onto the target,
and the photometric error that is ResFlowNet's 12th input channel. Written as small pure
functions on one snippet at a time (shapes in each docstring); :class:`RigidFlowOp` runs a batch
with the graph's inputs and outputs, so the cascade calls it exactly like the graph.
Conventions: :mod:`geonet_infer.conventions` (pose ``R = Rx @ Ry @ Rz`` target -> source, pixel
grid at pixel centres, corner-aligned bilinear sampling with zero padding). Agreement with the
graph is tested to 1e-4 px (tests/runtime/core/test_rigid_op.py); the graph stays the reference
(``rigid_op="graph"``, the default).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
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


def rigid_flow(depth: np.ndarray, T: np.ndarray, K: np.ndarray, ws: Workspace | None = None) -> np.ndarray:
    """Flow of a static scene seen from a moving camera.

    Args:
        depth: (H, W) depth of the target frame.
        T: (4, 4) target -> source camera.
        K: (3, 3) intrinsics at H x W.
        ws: buffers to reuse; the result is one of them (copy it to keep it past the next call).
    Returns:
        (2, H, W) float32 pixels: ``project(K, T, depth * K^-1 [u, v, 1]) - [u, v]``.
    """
    ws = ws or Workspace()
    H, W = depth.shape
    n = H * W
    grid = _pixel_grid(H, W, np.float64)
    P = K.astype(np.float64) @ T[:3, :]
    # K (R X + t) with X = d K^-1 [u, v, 1] is (K R K^-1) [u, v, 1] d + K t: one 3x3 product per pixel.
    # float64: the projected x is ~W, where float32 steps are ~3e-5 px.
    projected = np.matmul(
        P[:, :3] @ np.linalg.inv(K.astype(np.float64)), grid, out=ws.get("projected", (3, n), np.float64)
    )
    projected *= depth.reshape(1, -1)
    projected += P[:, 3:]
    projected[2] += DEPTH_EPS
    flow64 = np.divide(projected[:2], projected[2], out=ws.get("flow64", (2, n), np.float64))
    flow64 -= grid[:2]
    flow = ws.get("flow", (2, n))
    np.copyto(flow, flow64, casting="same_kind")
    return flow.reshape(2, H, W)


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
    padding_mode='zeros')``).

    The four neighbours are gathered by ``cv2.remap`` at whole-pixel positions (nearest at an
    integer position is exact, and its constant border is the zero padding); the weights are applied
    here in float32. ``cv2.remap``'s own bilinear mode would round the positions to 1/32 px.
    Non-finite flow gives NaN, as the graph does.

    Args:
        image: (C, H, W) float32, C <= 4, H and W < 32767 (OpenCV's remap limits).
        flow: (2, H, W) pixels.
        ws: buffers to reuse; the result is one of them (copy it to keep it past the next call).
    Returns:
        (C, H, W) float32.
    """
    ws = ws or Workspace()
    C, H, W = image.shape
    pixels = ws.get("pixels", (H, W, C))  # OpenCV gathers all channels of a pixel at once
    np.copyto(pixels, image.transpose(1, 2, 0))
    grid = _pixel_grid(H, W)
    x = np.add(grid[0].reshape(H, W), flow[0], out=ws.get("x", (H, W)))
    y = np.add(grid[1].reshape(H, W), flow[1], out=ws.get("y", (H, W)))
    x0, y0 = np.floor(x, out=ws.get("x0", (H, W))), np.floor(y, out=ws.get("y0", (H, W)))
    x1, y1 = np.add(x0, 1, out=ws.get("x1", (H, W))), np.add(y0, 1, out=ws.get("y1", (H, W)))
    with np.errstate(invalid="ignore"):  # inf - inf: a non-finite position's weights are NaN
        wx, wy = np.subtract(x, x0, out=x), np.subtract(y, y0, out=y)
    wx3 = cv2.merge([wx] * C, ws.get("wx3", (H, W, C)))
    wy3 = cv2.merge([wy] * C, ws.get("wy3", (H, W, C)))
    top, top_right, bottom, bottom_right = (
        cv2.remap(pixels, mx, my, cv2.INTER_NEAREST, ws.get(f"corner{k}", (H, W, C)), cv2.BORDER_CONSTANT, 0)
        for k, (mx, my) in enumerate(((x0, y0), (x1, y0), (x0, y1), (x1, y1)))
    )
    for left, right in ((top, top_right), (bottom, bottom_right)):  # lerp along x: left += wx (right - left)
        cv2.subtract(right, left, right)
        cv2.multiply(right, wx3, right)
        cv2.add(left, right, left)
    cv2.subtract(bottom, top, bottom)  # then along y
    cv2.multiply(bottom, wy3, bottom)
    cv2.add(top, bottom, top)
    out = ws.get("warped", (C, H, W))
    np.copyto(out, top.transpose(2, 0, 1))
    return out


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
        stacked.reshape(-1, W), -1, (3, 3), dst=sums.reshape(-1, W), normalize=True, borderType=cv2.BORDER_CONSTANT
    )
    # sum / 9, where a window reaching past an edge holds fewer pixels: 2 of its 3 rows (columns) at
    # an edge, 1 in a one-row (one-column) image
    means = sums[:, :, :H]
    means[:, :, [0, H - 1] if H > 1 else [0]] *= np.float32(1.5 if H > 1 else 3.0)
    means[:, :, :, [0, W - 1] if W > 1 else [0]] *= np.float32(1.5 if W > 1 else 3.0)
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
    ``alpha``: the DSSIM weight baked into the model's graph (``Manifest.photometric_alpha``);
    ``outputs``: those it computes (:meth:`only`).
    """

    name = "numpy"
    input_names = ["depth", "pose", "intrinsics", "target", "source"]

    def __init__(self, alpha: float, graph_io: tuple[list, list] | None = None, outputs: Sequence[str] = OUTPUTS):
        self.alpha = float(alpha)
        self._io = graph_io
        self.output_names = [name for name in OUTPUTS if name in outputs]
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
        photometric = "warped" in self.output_names or "error" in self.output_names
        warped = np.empty((B, 3, H, W), np.float32) if photometric else None
        errors = np.empty((B, 1, H, W), np.float32) if photometric else None
        ws = getattr(self._workspace, "buffers", None)
        if ws is None:
            ws = self._workspace.buffers = Workspace()
        for b in range(B):
            flows[b] = rigid_flow(depth[b, 0], pose_to_matrix(pose[b]), K[b], ws)
            if warped is not None and errors is not None:
                warped[b] = warp_bilinear(source[b], flows[b], ws)
                errors[b, 0] = photometric_error_map(warped[b], target[b], self.alpha, ws)
        made = {"rigid_flow": flows, "warped": warped, "error": errors}
        return {name: array for name in self.output_names if (array := made[name]) is not None}

    def only(self, outputs: Sequence[str]) -> RigidFlowOp:
        """The op computing only ``outputs`` (the warp and the error are most of its time)."""
        return RigidFlowOp(self.alpha, self._io, outputs)

    def io(self) -> tuple[list, list]:
        if self._io is None:
            raise NotImplementedError("RigidFlowOp.io needs the graph's io (given by GraphSet)")
        inputs, outputs = self._io
        return inputs, [spec for spec in outputs if spec[0] in self.output_names]

    def input_shapes(self) -> dict[str, list]:
        return {name: list(shape) for name, shape, _ in self.io()[0]}

    def describe(self) -> dict:
        return {
            "engine": self.name,
            "op": "rigidflow in numpy + OpenCV",
            "photometric_alpha": self.alpha,
            "outputs": self.output_names,
        }
