"""Frames, cameras and graph inputs as the graphs need them: the manifest's conventions (:class:`InputSpec`),
frame and camera coercion, K at graph size, outputs mapped back to the input size, stage timers."""

from __future__ import annotations

import functools
import json
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import cv2
import numpy as np

from geonet_infer import conventions
from geonet_infer.core.check import GREY_WEIGHTS
from geonet_infer.errors import GeoNetError, InputError, ModelError
from geonet_infer.io.calib import Camera
from geonet_infer.io.camera import assumed_camera
from geonet_infer.io.images import read_image
from geonet_infer.models.manifest import MANIFEST_NAME, Manifest

# What each graph of a model directory must accept and return for this runtime to drive it.
GRAPH_IO = {
    "depthnet": (("image",), ("disparity", "depth")),
    "posenet": (("snippet",), ("pose", "pose_matrix")),
    "rigidflow": (("depth", "pose", "intrinsics", "target", "source"), ("rigid_flow", "warped", "error")),
    "resflownet": (("flow_input",), ("residual_flow", "flow")),
}
CHANNEL_ORDERS = ("RGB", "BGR")


@dataclass(frozen=True)
class InputSpec:
    """How frames become graph inputs for one model.

    Attributes:
        height, width: the graphs' fixed input size.
        seq_length: frames per snippet (odd; the target is the middle one).
        norm_scale, norm_offset: network input = pixel / 255 * scale + offset.
        channel_order: "RGB" or "BGR", the order the graphs expect.
    """

    height: int
    width: int
    seq_length: int
    norm_scale: float
    norm_offset: float
    channel_order: str = "RGB"

    @classmethod
    def from_manifest(cls, manifest: Manifest) -> InputSpec:
        """Read the conventions a manifest declares; raise on any this runtime does not implement."""
        where = manifest.root / MANIFEST_NAME if manifest.root else None
        conv = manifest.conventions

        def refuse(problem: str) -> GeoNetError:  # a model this runtime cannot use: ModelError (errors.py)
            return ModelError(
                where,
                f"unsupported convention: {problem}",
                "this version of geonet-infer cannot run this model; re-export it with "
                "the matching training code or upgrade geonet-infer",
            )

        implemented = json.loads(json.dumps(conventions.as_dict()))  # tuples -> lists, as in the JSON
        if list(conv.get("input_range", [])) != implemented["input_range"]:
            raise refuse(f"input_range {conv.get('input_range')!r} (implemented: {implemented['input_range']})")
        order = conv.get("channel_order")
        if order not in CHANNEL_ORDERS:
            raise refuse(f"channel_order {order!r} (implemented: {', '.join(CHANNEL_ORDERS)})")
        for key in ("pose", "intrinsics", "sampler"):
            if conv.get(key) != implemented[key]:
                raise refuse(f"{key} {conv.get(key)!r} (implemented: {implemented[key]!r})")
        # The disparity head (scale * sigmoid + offset) is inside depthnet.onnx; mapping depth back
        # as 1 / resized disparity needs a head that keeps disparity > 0 (offset > 0).
        head = (conv.get("disp_heads") or {}).get(manifest.arch) or {}
        try:
            head_ok = float(head["scale"]) > 0 and float(head["offset"]) > 0
        except (KeyError, TypeError, ValueError):
            head_ok = False
        if not head_ok:
            raise refuse(f"disparity head for arch {manifest.arch!r}: {head!r} (need scale > 0 and offset > 0)")
        norm = conv.get("image_norm") or {}
        try:
            scale, offset = float(norm["scale"]), float(norm["offset"])
        except (KeyError, TypeError, ValueError):
            raise refuse(f"image_norm {norm!r} (expected {{'scale': s, 'offset': o}})") from None
        if manifest.seq_length < 2 or manifest.seq_length % 2 == 0:
            raise refuse(f"seq_length {manifest.seq_length} (the target must be the middle frame)")
        for precision in manifest.graphs:
            names = manifest.graph_names(precision)
            # Any subset runs (a converted depth or pose release); the tasks needing a missing graph
            # are refused by the Predictor when asked for.
            if not any(g in GRAPH_IO for g in names):
                raise ModelError(
                    where,
                    f"the {precision} set holds none of the graphs {', '.join(GRAPH_IO)}",
                    "export at least one of them with `python -m export --graphs`",
                )
            for name in names:
                entry = manifest.graph(name, precision)
                expected = GRAPH_IO.get(name)
                if expected and (entry.input_names, entry.output_names) != expected:
                    raise refuse(
                        f"{precision}/{name} has inputs {entry.input_names} and outputs "
                        f"{entry.output_names}; this runtime drives {expected[0]} -> {expected[1]}"
                    )
        return cls(
            height=manifest.height,
            width=manifest.width,
            seq_length=manifest.seq_length,
            norm_scale=scale,
            norm_offset=offset,
            channel_order=order,
        )

    @classmethod
    def from_conventions(
        cls, height: int = conventions.REFERENCE_HEIGHT, width: int = conventions.REFERENCE_WIDTH, seq_length: int = 3
    ) -> InputSpec:
        """The spec ``python -m export`` writes into manifests (for code that runs before one exists)."""
        return cls(
            height=height,
            width=width,
            seq_length=seq_length,
            norm_scale=conventions.IMAGE_NORM.scale,
            norm_offset=conventions.IMAGE_NORM.offset,
            channel_order=conventions.as_dict()["channel_order"],
        )

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) of the graphs."""
        return self.height, self.width

    def to_network(self, rgb: np.ndarray) -> np.ndarray:
        """uint8 RGB (H, W, 3) at any size -> float32 (3, height, width) in the network range.

        Downscaling uses ``cv2.INTER_AREA`` (the training data were made the same
        way), upscaling ``cv2.INTER_LINEAR``.
        """
        h, w = rgb.shape[:2]
        if (h, w) != self.size:
            interp = cv2.INTER_AREA if (h >= self.height and w >= self.width) else cv2.INTER_LINEAR
            rgb = cv2.resize(rgb, (self.width, self.height), interpolation=interp)
        if self.channel_order == "BGR":
            rgb = rgb[..., ::-1]
        # CHW while still uint8 (a quarter of the bytes to move), then scale in place: same values
        x = np.ascontiguousarray(rgb.transpose(2, 0, 1)).astype(np.float32)
        x *= np.float32(self.norm_scale / 255.0)
        x += np.float32(self.norm_offset)
        return x

    def to_grey(self, x: np.ndarray) -> np.ndarray:
        """:meth:`to_network` undone as grey levels: (3, height, width) -> (height, width) float32, 0-255
        (the channels weighted as ``cv2.COLOR_RGB2GRAY`` does; the weights sum to 1)."""
        weights = np.array(GREY_WEIGHTS[::-1] if self.channel_order == "BGR" else GREY_WEIGHTS, np.float32)
        grey = np.tensordot(weights, x, 1)
        grey -= np.float32(self.norm_offset)
        grey *= np.float32(255.0 / self.norm_scale)
        return grey


def check_image(image, name: str | Path | None = None) -> np.ndarray:
    """Validate one frame: a uint8 array (H, W, 3). Returns it as a C-contiguous array."""
    if not isinstance(image, np.ndarray):
        raise InputError(
            name,
            f"expected a numpy uint8 (H, W, 3) RGB array, got {type(image).__name__}",
            "pass an image array or a path to an image file",
        )
    if image.dtype != np.uint8:
        raise InputError(
            name,
            f"image dtype is {image.dtype}, expected uint8",
            "pass 8-bit RGB; convert float images with (img * 255).round().astype(np.uint8)",
        )
    if image.ndim != 3 or image.shape[2] != 3:
        channels = image.shape[2] if image.ndim == 3 else 1
        hint = {
            1: "convert grey images with cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)",
            4: "drop the alpha channel with cv2.cvtColor(img, cv2.COLOR_RGBA2RGB)",
        }.get(channels if image.ndim in (2, 3) else 0, "pass one (H, W, 3) RGB frame")
        raise InputError(name, f"image shape is {image.shape}, expected (H, W, 3) RGB", hint)
    if min(image.shape[:2]) < 8:
        raise InputError(name, f"image is only {image.shape[1]}x{image.shape[0]} pixels", "pass a real frame")
    return np.ascontiguousarray(image)


def graph_intrinsics(K: np.ndarray, input_size: tuple[int, int], spec: InputSpec) -> np.ndarray:
    """K at the input size (H, W) -> float32 K at the graph size (conventions.scale_intrinsics)."""
    h, w = input_size
    return conventions.scale_intrinsics(K, spec.width / w, spec.height / h).astype(np.float32)


def disparity_to_input(disparity: np.ndarray, input_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Graph-size disparity (h, w) -> (depth, disparity) at the input size (H, W), float32.

    Disparity is resized bilinearly and depth = 1 / disparity, so the pair stays consistent.
    """
    h, w = input_size
    if disparity.shape != (h, w):
        disparity = cv2.resize(disparity, (w, h), interpolation=cv2.INTER_LINEAR)
    disparity = disparity.astype(np.float32, copy=False)
    return np.divide(np.float32(1), disparity), disparity


def flow_to_input(flow_chw: np.ndarray, input_size: tuple[int, int]) -> np.ndarray:
    """Graph-size flow (2, h, w) in graph pixels -> (H, W, 2) float32 in input pixels.

    Bilinear resize of both channels; u scales by W / w and v by H / h.
    """
    h_in, w_in = input_size
    _, h, w = flow_chw.shape
    flow = np.ascontiguousarray(flow_chw.transpose(1, 2, 0), dtype=np.float32)
    if (h, w) == (h_in, w_in):
        return flow
    flow = cv2.resize(flow, (w_in, h_in), interpolation=cv2.INTER_LINEAR)
    flow[..., 0] *= w_in / w
    flow[..., 1] *= h_in / h
    return flow


# ----------------------------------------------------------------------------- frames and cameras
ImageLike = np.ndarray | str | Path
Intrinsics = np.ndarray | Sequence[Sequence[float]] | Camera
# "read" .. "check" are timed here; "write" by pipeline.predict_to_dir (saving outputs).
STAGES = ("read", "preprocess", "depthnet", "posenet", "rigidflow", "resflownet", "postprocess", "check", "write")
# throughput mode: a stage that ran on the cascade threads, beside the caller's, is named with this prefix
CASCADE_THREADS = "workers_"


class StageTimer:
    """Accumulates wall time per stage in ms: ``with timer.stage("depthnet"): ...``."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = defaultdict(float)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.ms[name] += (time.perf_counter() - t0) * 1e3

    def result(self, share: float = 1.0) -> dict[str, float]:
        """Stage -> ms times ``share`` (a frame's part of a batch), plus "total"."""
        out = {k: v * share for k, v in self.ms.items()}
        out["total"] = sum(out.values())
        return out


def read_frame(image: ImageLike, timer: StageTimer, index: int = 0) -> tuple[np.ndarray, str]:
    """A checked uint8 RGB (H, W, 3) frame and its label (the path, or "image <index>" for arrays)."""
    if isinstance(image, (str, Path)):
        with timer.stage("read"):
            return check_image(read_image(image), image), str(image)
    label = f"image {index}"
    return check_image(image, label), label


@overload
def camera_at(camera: None, size: tuple[int, int]) -> None: ...


@overload
def camera_at(camera: Intrinsics, size: tuple[int, int]) -> Camera: ...


def camera_at(camera: Intrinsics | None, size: tuple[int, int]) -> Camera | None:
    """K or a Camera as a validated Camera at the input size (H, W); a Camera calibrated at
    another size is rescaled to it (:meth:`Camera.scaled_to`). None stays None."""
    if camera is None:
        return None
    if isinstance(camera, Camera):
        if camera.size is None:  # a calibration that does not say its size is at the input resolution
            camera = Camera(camera.K, camera.dist, (size[1], size[0]), camera.source, camera.origin)
        return camera.scaled_to(size[1], size[0]).validate(camera.source or None)
    K = np.asarray(camera, dtype=np.float64)
    if K.shape != (3, 3):  # Camera() itself raises a plain ValueError for this
        raise InputError(
            None,
            f"intrinsics must be a 3x3 matrix, got shape {K.shape}",
            "pass K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] at the input resolution",
        )
    return Camera(K=K, dist=None, size=(size[1], size[0])).validate()


def with_assumed(camera: Intrinsics | None) -> Intrinsics:
    """``camera``, or the assumed intrinsics (:data:`geonet_infer.io.camera.ASSUMED_RULE`) where none were
    given: they follow the frames' size (:class:`~geonet_infer.io.camera.AssumedCamera`)."""
    return camera if camera is not None else assumed_camera(conventions.KITTI_WIDTH, conventions.KITTI_HEIGHT)


def to_network(spec: InputSpec, rgb: np.ndarray, camera: Camera | None, timer: StageTimer) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, h, w) float32 network input; undistorted first if the camera has distortion."""
    with timer.stage("preprocess"):
        if camera is not None and camera.has_distortion:
            rgb = camera.undistort(rgb)
        return spec.to_network(rgb)


def flows_to_input(
    parts: dict[str, np.ndarray], b: int, size: tuple[int, int]
) -> tuple[np.ndarray, Callable[[], np.ndarray] | None]:
    """Snippet ``b``'s flow of :func:`run_cascade` at the input size, (H, W, 2), and what makes its
    rigid part at that size when asked (:attr:`FrameResult.rigid_flow`); None without ResFlowNet
    (then the flow is the rigid flow)."""
    if "flow" not in parts:
        return flow_to_input(parts["rigid_flow"][b], size), None
    rigid_graph = parts["rigid_flow"][b].copy()  # not a view: the batch's array can go
    return flow_to_input(parts["flow"][b], size), functools.partial(flow_to_input, rigid_graph, size)
