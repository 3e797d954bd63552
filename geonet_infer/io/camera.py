"""The pinhole camera of the runtime (:class:`Camera`: K, OpenCV distortion, the size it was made for)
and the limits a calibration is checked against. Reading calibration files: :mod:`geonet_infer.io.calib`."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from geonet_infer.conventions import KITTI_FX, KITTI_WIDTH, scale_intrinsics
from geonet_infer.errors import InputError

OPENCV_DIST_LENGTHS = (4, 5, 8, 12, 14)  # k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]]
# Sanity limits: values outside them come from a typo or a unit mix-up, and give flow with no
# valid pixel or infinite depth rather than an error. Real calibrations sit far inside (KITTI's
# and the Udacity dashcam's |k| <= 0.37; rational models reach tens).
MAX_DISTORTION = 100.0  # |coefficient|
FOCAL_RANGE = (0.05, 100.0)  # fx / image width and fy / image height (a 170-degree to a 0.6-degree view)
PRINCIPAL_POINT_MARGIN = 0.5  # cx, cy at most this fraction of the image width / height outside it
# Where a camera's intrinsics came from (``Camera.origin``): recorded in summary.json and the API's results.
ORIGINS = ("calibration file", "flag", "estimated", "assumed", "given")
# The assumed intrinsics of footage without a calibration (docs/runtime.md "Intrinsics"): the focal of
# KITTI's colour camera relative to the image width (721.5 px of 1242: an 81-degree horizontal view),
# square pixels, the principal point at the centre. Every released GeoNet model and ours learnt depth
# and motion on footage of that view, and dashcams are built near it (60-120 degrees).
ASSUMED_FOCAL_PER_WIDTH = KITTI_FX / KITTI_WIDTH
ASSUMED_RULE = (
    f"fx = fy = {ASSUMED_FOCAL_PER_WIDTH:.4f} x width (KITTI's 81-degree horizontal view, the footage GeoNet "
    "was trained on), principal point at the image centre"
)


# --------------------------------------------------------------------------- Camera
@functools.lru_cache(maxsize=8)
def _undistort_maps(K_bytes: bytes, dist_bytes: bytes, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The fixed-point maps ``cv2.undistort`` builds internally (new camera matrix = K)."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_bytes, dtype=np.float64)
    return cv2.initUndistortRectifyMap(K, dist, None, K, (width, height), cv2.CV_16SC2)


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole intrinsics, optional lens distortion and the image size they belong to.

    Attributes:
        K: (3, 3) float64 ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels (a read-only copy).
        dist: OpenCV distortion coefficients ``k1 k2 p1 p2 [k3 ...]`` (float64, read-only),
            or None when the images are rectified / undistorted.
        size: (width, height) in pixels of the images K belongs to; None when the file does not say.
        source: where the calibration came from (file and format), for messages and logs.
        origin: what kind of source that is, one of :data:`ORIGINS`: a calibration file, a flag
            (``--intrinsics``), estimated from the footage, assumed (:func:`assumed_camera`), or
            given through the API.

    ``eq=False``: cameras compare by identity (field-wise ``==`` on arrays is ambiguous).
    """

    K: np.ndarray
    dist: np.ndarray | None = None
    size: tuple[int, int] | None = None
    source: str = ""
    origin: str = "given"

    def __post_init__(self):
        K = np.array(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got shape {K.shape}")
        K.setflags(write=False)
        object.__setattr__(self, "K", K)
        if self.dist is not None:
            dist = np.array(self.dist, dtype=np.float64).reshape(-1)
            dist.setflags(write=False)
            object.__setattr__(self, "dist", dist)
        if self.size is not None:
            vals = tuple(float(v) for v in self.size)
            if len(vals) != 2 or not all(v.is_integer() for v in vals):
                raise ValueError(f"size must be (width, height) in whole pixels, got {self.size!r}")
            object.__setattr__(self, "size", (int(vals[0]), int(vals[1])))

    @property
    def has_distortion(self) -> bool:
        """True if any distortion coefficient is non-zero."""
        return self.dist is not None and bool(np.any(self.dist != 0))

    def scaled_to(self, width: int, height: int) -> Camera:
        """The camera for images resized to ``width`` x ``height``.

        (fx, cx) scale by width / size[0] and (fy, cy) by height / size[1]
        (:func:`geonet_infer.conventions.scale_intrinsics`); distortion coefficients are
        unchanged (they act on normalised coordinates). If :attr:`size` is None the
        size K belongs to is unknown and ``self`` is returned unchanged.
        """
        if self.size is None:
            return self
        if width <= 0 or height <= 0:
            raise ValueError(f"target size must be positive, got {width}x{height}")
        K = scale_intrinsics(self.K, width / self.size[0], height / self.size[1])
        return Camera(K, self.dist, (int(width), int(height)), self.source, self.origin)

    def record(self) -> dict:
        """What summary.json and the API's results say of these intrinsics: K, the size it applies to,
        the distortion removed, the source (a file's path and format, a flag, the rule) and its origin."""
        return {
            "K": self.K.tolist(),
            "size": None if self.size is None else list(self.size),
            "dist": None if self.dist is None else self.dist.tolist(),
            "source": self.source,
            "origin": self.origin,
        }

    def describe(self) -> str:
        """One line for the closing message: ``intrinsics fx 721.5 at 1242x375 (calibration file: ...)``."""
        size = f" at {self.size[0]}x{self.size[1]}" if self.size else ""
        return f"intrinsics fx {self.K[0, 0]:.1f} fy {self.K[1, 1]:.1f}{size} ({self.origin}: {self.source})"

    def undistort(self, image: np.ndarray) -> np.ndarray:
        """``image`` without lens distortion, same K: the pixels of ``cv2.undistort(image, K, dist)``.

        The remap tables are built once per camera and image size (``cv2.undistort`` rebuilds
        them on every call, about two thirds of its time on a 1280x720 frame).
        """
        if self.dist is None or not self.has_distortion:
            return image
        h, w = image.shape[:2]
        map1, map2 = _undistort_maps(self.K.tobytes(), self.dist.tobytes(), w, h)
        return cv2.remap(image, map1, map2, cv2.INTER_LINEAR)

    def validate(self, path=None) -> Camera:
        """Check the values; returns ``self``.

        Raises:
            GeoNetError (naming ``path`` if given) if K is not finite, fx or fy is
            not > 0, cx or cy is not finite, the last row of K is not (0, 0, 1), the
            distortion has non-finite values, a coefficient over :data:`MAX_DISTORTION` or a
            length OpenCV does not accept (4, 5, 8, 12, 14), or the size is not positive; with a
            size, also :meth:`check_image_size`.
        """
        K = self.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        if not np.isfinite(K).all():
            raise InputError(
                path,
                f"intrinsics contain NaN or infinity (fx={fx}, fy={fy}, cx={cx}, cy={cy})",
                "check the calibration values",
            )
        if not (fx > 0 and fy > 0):
            raise InputError(
                path, f"focal lengths must be positive, got fx={fx:g}, fy={fy:g}", "check the calibration values"
            )
        if not (np.isfinite(cx) and np.isfinite(cy)):
            raise InputError(path, f"principal point is not finite (cx={cx}, cy={cy})", "check the calibration values")
        if not np.allclose(K[2], (0.0, 0.0, 1.0), rtol=0, atol=1e-9) or abs(K[1, 0]) > 1e-9:
            raise InputError(
                path,
                f"not a pinhole K: rows 2-3 are {K[1].tolist()} {K[2].tolist()}",
                "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]",
            )
        if self.dist is not None:
            if not np.isfinite(self.dist).all():
                raise InputError(path, "distortion coefficients are not finite", "check the calibration values")
            if np.abs(self.dist).max(initial=0.0) > MAX_DISTORTION:
                raise InputError(
                    path,
                    f"distortion coefficients {self.dist.tolist()} exceed {MAX_DISTORTION:g} in magnitude",
                    "check the calibration values (OpenCV order k1 k2 p1 p2 [k3 ...])",
                )
            if self.dist.size not in OPENCV_DIST_LENGTHS:
                raise InputError(
                    path,
                    f"{self.dist.size} distortion coefficients",
                    "OpenCV takes k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]: 4, 5, 8, 12 or 14 numbers",
                )
        if self.size is not None:
            if self.size[0] <= 0 or self.size[1] <= 0:
                raise InputError(
                    path,
                    f"image size must be positive, got {self.size[0]}x{self.size[1]}",
                    "check the calibration values",
                )
            self.check_image_size(*self.size, path)
        return self

    def check_image_size(self, width: int, height: int, path=None) -> None:
        """Check K against the image size it is used at (this camera already scaled to it).

        Raises:
            GeoNetError (naming ``path``) if fx / width or fy / height is outside
            :data:`FOCAL_RANGE`, or the principal point lies more than
            :data:`PRINCIPAL_POINT_MARGIN` of the image size outside the image.
        """
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        low, high = FOCAL_RANGE
        if not (low * width <= fx <= high * width and low * height <= fy <= high * height):
            raise InputError(
                path,
                f"focal lengths fx={fx:g}, fy={fy:g} do not fit {width}x{height} images "
                f"(expected {low:g} to {high:g} times the width / height)",
                "check the calibration values and that they belong to these frames",
            )
        margin = PRINCIPAL_POINT_MARGIN
        if not (-margin * width <= cx <= (1 + margin) * width and -margin * height <= cy <= (1 + margin) * height):
            raise InputError(
                path,
                f"principal point cx={cx:g}, cy={cy:g} lies far outside the {width}x{height} image",
                "check the calibration values and that they belong to these frames",
            )


class AssumedCamera(Camera):
    """The intrinsics of :data:`ASSUMED_RULE` at whatever size the frames are: rescaling it applies the
    rule at the new size (square pixels stay square, the principal point stays at the centre)."""

    def scaled_to(self, width: int, height: int) -> Camera:
        return assumed_camera(width, height, self.source)


def assumed_camera(width: int, height: int, source: str = ASSUMED_RULE) -> AssumedCamera:
    """:data:`ASSUMED_RULE` for ``width`` x ``height`` frames (``source``: the rule, and why it was assumed)."""
    f = ASSUMED_FOCAL_PER_WIDTH * width
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return AssumedCamera(K, None, (int(width), int(height)), source, "assumed")
