"""Pre- and post-processing between user images and the graphs, built from a model's manifest.

The graphs run at one fixed size (the manifest's ``height`` x ``width``, 128 x 416
for the released models) and take images already normalised to the network range.
Everything that maps between a user's frames and that size lives here, once:

* :class:`InputSpec` reads the manifest's conventions and refuses the ones this
  runtime does not implement (so a model exported under other rules fails loudly
  instead of producing plausible garbage);
* :func:`check_image` validates a frame (uint8, (H, W, 3));
* :meth:`InputSpec.to_network` resizes with ``cv2.INTER_AREA`` and normalises;
* :func:`graph_intrinsics` scales K from the input size to the graph size;
* :func:`disparity_to_input`, :func:`flow_to_input` map outputs back (flow vectors
  are scaled per axis);
* :func:`snippet_indices` forms the snippet around a frame, replicating the end
  frames of a sequence (see its docstring).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer import conventions
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.manifest import MANIFEST_NAME, Manifest

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

        def refuse(problem: str) -> GeoNetError:
            return InputError(
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
        head = (conv.get("disp_heads") or {}).get(manifest.arch)
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
                raise InputError(
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
        raise InputError(
            name,
            f"image shape is {image.shape}, expected (H, W, 3) RGB",
            "convert grey images with cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)",
        )
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
    return (1.0 / disparity).astype(np.float32), disparity


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


def snippet_indices(t: int, num_frames: int, seq_length: int) -> list[int]:
    """Frame indices of the snippet for target ``t``, ordered [target] + sources in temporal order.

    The snippet is the window t - k .. t + k (k = seq_length // 2). At the ends
    of a sequence a missing neighbour is replaced by the nearest existing frame
    (indices clipped to [0, num_frames - 1]): the first frame of a 3-frame model
    is seen as [f0, f0, f1] in temporal order, i.e. a zero-motion previous frame.
    This is the only place that order is written down for the runtime.
    """
    if num_frames < 2:
        raise InputError(
            None, f"a sequence needs at least 2 frames, got {num_frames}", "pass consecutive frames of one video"
        )
    k = seq_length // 2
    window = [min(max(i, 0), num_frames - 1) for i in range(t - k, t + k + 1)]
    return [window[k]] + window[:k] + window[k + 1 :]


def next_source_position(seq_length: int) -> int:
    """Position of frame t + 1 among the sources of :func:`snippet_indices` (0-based)."""
    return seq_length // 2
