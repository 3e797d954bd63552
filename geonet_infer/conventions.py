"""The one home of GeoNet's conventions.

Training, export and the runtime all read these objects; nothing else re-types
the numbers. ``export`` writes :func:`as_dict` into every model manifest, and
the runtime rebuilds its pre/post-processing from the manifest.

Facts (from the official TF implementation, see ``docs/conventions.md``):

* Images: uint8 RGB -> float in [0, 1] -> ``x * 2 - 1`` (range [-1, 1]).
  No ImageNet mean/std.
* Reference size 128 x 416 (H x W), 4 pyramid scales (s = 0..3, H / 2**s).
* Pose vectors ``[tx, ty, tz, rx, ry, rz]``: translation in the depth's units,
  Euler angles in radians, ``R = Rx(rx) @ Ry(ry) @ Rz(rz)``. ``T = [R | t]``
  maps points from the *target* camera frame to the *source* frame.
* Intrinsics at scale s: fx, fy, cx, cy divided by 2**s, no half-pixel shift.
  Resizing an image by (sx, sy) multiplies (fx, cx) by sx and (fy, cy) by sy.
* Pixel grid: u = 0..W-1, v = 0..H-1 at pixel centres; sampling is
  corner-aligned (``grid_sample(align_corners=True)``).
* Disparity heads: ``scale * sigmoid(x) + 0.01``; depth = 1 / disparity.
* Photometric error (rigidflow.onnx's ``error`` output, ResFlowNet's 12th input channel):
  ``|| alpha * DSSIM + (1 - alpha) * |warped - target| + 1e-10 ||_2`` over the colour channels,
  with training's ``alpha_recon`` (0.85, as in GeoNet) baked into the graph. Not a runtime
  setting: manifests record it as ``conventions.photometric_alpha`` (:data:`PHOTOMETRIC_ALPHA`),
  and those written before it was recorded lack the key (their graphs bake in 0.85).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

SCHEMA_VERSION = 1


@dataclass(frozen=True)
class ImageNorm:
    """Network input = pixel / 255 * scale + offset."""

    scale: float = 2.0
    offset: float = -1.0

    def apply(self, image01):
        """[0, 1] floats (numpy array or torch tensor) -> network range."""
        return image01 * self.scale + self.offset


@dataclass(frozen=True)
class PoseConvention:
    vector: tuple[str, ...] = ("tx", "ty", "tz", "rx", "ry", "rz")
    rotation: str = "R = Rx(rx) @ Ry(ry) @ Rz(rz), radians"
    direction: str = "target_to_source"
    output_scale: float = 0.01  # PoseNet multiplies its raw output by this


@dataclass(frozen=True)
class IntrinsicsScaling:
    per_scale_divisor: float = 2.0  # K_s = K_0 / 2**s for fx, fy, cx, cy
    half_pixel_correction: bool = False


@dataclass(frozen=True)
class Sampler:
    align_corners: bool = True
    padding: str = "zeros"


@dataclass(frozen=True)
class DispHead:
    """disparity = scale * sigmoid(x) + offset; depth = 1 / disparity."""

    scale: float
    offset: float = 0.01


IMAGE_NORM = ImageNorm()
POSE = PoseConvention()
INTRINSICS = IntrinsicsScaling()
SAMPLER = Sampler()
MANIFEST_NAME = "manifest.json"  # every model directory's description (core.manifest_schema reads it)
REFERENCE_HEIGHT = 128
REFERENCE_WIDTH = 416
NUM_SCALES = 4
DISP_HEADS = {"resnet50": DispHead(5.0), "vgg": DispHead(10.0), "small": DispHead(5.0)}
FLOW_SCALING = 0.1  # ResFlowNet heads output 0.1 * conv, in units of image size
# Manifest key of the photometric error's alpha (see the module docstring). Optional, so it stays out of
# as_dict(), whose keys every manifest must have: export adds it beside them.
PHOTOMETRIC_ALPHA = "photometric_alpha"
UNRECORDED_PHOTOMETRIC_ALPHA = 0.85  # what graphs exported before the key existed bake in
# The camera assumed where none is given (synthetic scenes, INT8 calibration frames without
# calibration, export trace inputs): KITTI raw 2011_09_26 P_rect_02 at its 1242 x 375 images.
KITTI_FX, KITTI_FY, KITTI_CX, KITTI_CY, KITTI_WIDTH, KITTI_HEIGHT = 721.5377, 721.5377, 609.5593, 172.854, 1242, 375


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after resizing an image by (sx, sy) = (W'/W, H'/H).

    Args:
        K: (..., 3, 3) pinhole matrix.
    Returns:
        (..., 3, 3) copy with row 0 (fx, skew, cx) times sx and row 1 (fy, cy) times sy.
    """
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    return K


def next_camera_to_world(camera_to_world: np.ndarray, pose_to_next: np.ndarray) -> np.ndarray:
    """The trajectory's one chaining rule: frame t+1's camera-to-world from frame t's and the pose
    t -> t+1 (``POSE``: it maps frame t's points into frame t+1): ``c2w[t] @ inv(T_t->t+1)``. The
    first frame of a sequence is the identity."""
    return camera_to_world @ rigid_inverse(pose_to_next)


def rigid_inverse(T):
    """Closed-form inverse of rigid 4x4 transforms (``POSE``'s matrices): [R | t]^-1 = [R^T | -R^T t].

    T: (4, 4) or (..., 4, 4). Returns the same shape. Exact for rigid
    transforms and mirrors what the ONNX graphs do (no general matrix inverse).
    """
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    R_t = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R_t
    out[..., :3, 3:] = -R_t @ t
    out[..., 3, 3] = 1.0
    return out


def kitti_like_K(height: int, width: int) -> np.ndarray:
    """KITTI's P_rect_02 intrinsics scaled to (height, width): (3, 3) float64, fx ~ 0.58 W."""
    sx, sy = width / KITTI_WIDTH, height / KITTI_HEIGHT
    return np.array([[KITTI_FX * sx, 0, KITTI_CX * sx], [0, KITTI_FY * sy, KITTI_CY * sy], [0, 0, 1]])


def as_dict() -> dict:
    """Everything a consumer of an exported model needs, JSON-ready."""
    return {
        "schema_version": SCHEMA_VERSION,
        "image_norm": asdict(IMAGE_NORM),
        "input_range": [0.0, 1.0],
        "channel_order": "RGB",
        "pose": asdict(POSE),
        "intrinsics": asdict(INTRINSICS),
        "sampler": asdict(SAMPLER),
        "reference_size": [REFERENCE_HEIGHT, REFERENCE_WIDTH],
        "disp_heads": {k: asdict(v) for k, v in DISP_HEADS.items()},
        "flow_scaling": FLOW_SCALING,
    }
