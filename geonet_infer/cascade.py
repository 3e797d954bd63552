"""The GeoNet cascade: the one place that turns frames into graph inputs and runs the graphs.

Per frame t of a sequence:

1. ``depthnet``  frame t -> disparity and depth (relative scale);
2. ``posenet``   snippet [t, t-k .. t-1, t+1 .. t+k] -> poses t -> each source;
3. ``rigidflow`` depth of t, pose t -> t+1, K -> rigid flow t -> t+1, frame t+1
   warped onto t, photometric error;
4. ``resflownet`` [t, t+1, warped, rigid flow, error] (:data:`RESFLOW_INPUT`) -> full flow
   t -> t+1 (= rigid + residual).

The graphs run at one fixed size (the manifest's ``height`` x ``width``, 128 x 416 for the
released models) on images normalised to the network range. Here, once:

* :class:`InputSpec` reads the manifest's conventions and refuses the ones this runtime does
  not implement (a model exported under other rules fails loudly instead of producing
  plausible garbage); :meth:`InputSpec.to_network` resizes with ``cv2.INTER_AREA`` and normalises;
* :func:`check_image`, :func:`read_frame`, :func:`camera_at`: frames and cameras as the graphs need them;
* :func:`graph_intrinsics` scales K from the input size to the graph size;
* :func:`snippet_indices` forms the snippet around a frame, replicating the end frames;
  :func:`posenet_order` puts the target first for PoseNet;
* :func:`resflow_input` stacks ResFlowNet's 12 channels (training builds the same order);
* :class:`GraphSet` holds one engine per graph; :func:`run_cascade` runs steps 1-4 on a batch of
  snippets; :func:`iter_frames` runs them over a whole sequence, each frame's depth once;
* :func:`disparity_to_input`, :func:`flow_to_input` map outputs back to the input size (flow
  vectors scaled per axis).

:class:`geonet_infer.Predictor` is the public face of this module; benchmarks and export's
INT8 calibration call it directly.
"""

from __future__ import annotations

import functools
import json
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import cv2
import numpy as np

from geonet_infer import conventions
from geonet_infer.check import GREY_WEIGHTS, check_pair
from geonet_infer.conventions import rigid_inverse
from geonet_infer.engines import AUTO, ENGINES, Engine, make_engine, pick_fastest
from geonet_infer.errors import GeoNetError, InputError, ModelError
from geonet_infer.int8_safety import int8_unsafe_reason
from geonet_infer.io.calib import Camera
from geonet_infer.io.images import read_image
from geonet_infer.limits import check_batch_size
from geonet_infer.manifest import MANIFEST_NAME, Manifest, check_graph_io
from geonet_infer.results import FrameResult
from geonet_infer.rigid import RigidFlowOp

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


# ----------------------------------------------------------------------------- frames and cameras
ImageLike = np.ndarray | str | Path
Intrinsics = np.ndarray | Sequence[Sequence[float]] | Camera
# "read" .. "check" are timed here; "write" by pipeline.predict_to_dir (saving outputs).
STAGES = ("read", "preprocess", "depthnet", "posenet", "rigidflow", "resflownet", "postprocess", "check", "write")


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
        return camera.scaled_to(size[1], size[0]).validate(camera.source or None)
    K = np.asarray(camera, dtype=np.float64)
    if K.shape != (3, 3):  # Camera() itself raises a plain ValueError for this
        raise InputError(
            None,
            f"intrinsics must be a 3x3 matrix, got shape {K.shape}",
            "pass K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] at the input resolution",
        )
    return Camera(K=K, dist=None, size=(size[1], size[0])).validate()


def to_network(spec: InputSpec, rgb: np.ndarray, camera: Camera | None, timer: StageTimer) -> np.ndarray:
    """(H, W, 3) uint8 -> (3, h, w) float32 network input; undistorted first if the camera has distortion."""
    with timer.stage("preprocess"):
        if camera is not None and camera.has_distortion:
            rgb = camera.undistort(rgb)
        return spec.to_network(rgb)


def snippet_frames(frames: Sequence[ImageLike], seq_length: int) -> list[ImageLike]:
    """A full snippet (``seq_length`` frames, target in the middle), or a pair [t, t+1] padded
    as at a sequence start (:func:`snippet_indices`)."""
    L = seq_length
    if isinstance(frames, np.ndarray) and frames.ndim == 4:
        frames = list(frames)
    if not isinstance(frames, (list, tuple)):
        raise InputError(
            None,
            f"expected a list of frames, got {type(frames).__name__}",
            f"pass {L} consecutive frames (target in the middle) or a pair [t, t+1]",
        )
    if len(frames) == L:
        return list(frames)
    if len(frames) == 2:
        return [frames[i] for i in sorted(snippet_indices(0, 2, L))]
    raise InputError(
        None,
        f"got {len(frames)} frames; this model takes snippets of {L} (target in the middle) or a pair [t, t+1]",
        "pass consecutive frames of one video",
    )


def load_snippet(
    spec: InputSpec, frames: Sequence[ImageLike], camera: Intrinsics | None, timer: StageTimer
) -> tuple[np.ndarray, Camera | None, tuple[int, int]]:
    """One snippet (or pair) -> (network inputs (L, 3, h, w), camera at the frames' size, size (H, W)).

    The frames must share one size.
    """
    frames = snippet_frames(frames, spec.seq_length)
    rgbs, names = zip(*[read_frame(f, timer, i) for i, f in enumerate(frames)])
    sizes = {r.shape[:2] for r in rgbs}
    if len(sizes) > 1:
        detail = ", ".join(f"{n}: {r.shape[1]}x{r.shape[0]}" for n, r in zip(names, rgbs))
        raise InputError(
            None, f"frames of one snippet differ in size ({detail})", "pass consecutive frames of one camera"
        )
    size = rgbs[0].shape[:2]
    cam = camera_at(camera, size)
    return np.stack([to_network(spec, r, cam, timer) for r in rgbs]), cam, size


# ----------------------------------------------------------------------------- graph inputs
# ResFlowNet's input, in channel order: (part, channels). Training (training/model.py) stacks the
# same parts in the same order, so the exported graph and this runtime cannot disagree.
RESFLOW_INPUT = (("target", 3), ("source", 3), ("warped", 3), ("rigid_flow", 2), ("error", 1))


def resflow_input(parts: dict[str, np.ndarray]) -> np.ndarray:
    """The (B, 12, h, w) ResFlowNet input from its :data:`RESFLOW_INPUT` parts, each (B, C, h, w)."""
    return np.concatenate([parts[name] for name, _ in RESFLOW_INPUT], axis=1)


def posenet_order(target: int, seq_length: int) -> list[int]:
    """Snippet positions in PoseNet's input order for a snippet in temporal order whose target
    sits at ``target``: [target] + the sources in temporal order (as :func:`snippet_indices`)."""
    return [target] + [i for i in range(seq_length) if i != target]


RIGID_OPS = ("graph", "numpy")  # how the rigid-flow op runs: geonet_infer.rigid, or rigidflow.onnx


class GraphSet:
    """One engine per graph of a model directory at one precision (sessions made once).

    ``backend``: a name of :data:`geonet_infer.engines.ENGINES`, or "auto" (the faster engine per
    graph, timed here). Every graph's inputs and outputs are checked against the manifest.
    ``rigid_op``: "graph" runs ``rigidflow.onnx`` on ``backend`` like the other graphs; "numpy" runs
    the weightless op with :class:`geonet_infer.rigid.RigidFlowOp` (about 1.5x as fast, within
    2e-4 px of the graph) where the manifest's sampler is the one it implements.
    """

    def __init__(self, manifest: Manifest, precision: str, backend: str, threads: int, rigid_op: str = "graph"):
        if rigid_op not in RIGID_OPS:
            raise InputError(None, f"unknown rigid_op {rigid_op!r}", f"choose one of {', '.join(RIGID_OPS)}")
        self.manifest = manifest
        self.precision = precision
        self.backend_choice: dict[str, dict] = {}  # backend="auto": per graph, the timings behind the choice
        self.runs: dict[str, dict] = {}  # per graph: engine, precision and why (summary.json, bench)
        self._engines: dict[str, Engine | RigidFlowOp] = {}
        for name in manifest.graph_names(precision):
            path = manifest.path(name, precision)
            unsafe = self._int8_unsafe(name, backend)
            if name == "rigidflow" and rigid_op == "numpy" and RigidFlowOp.supports(manifest.conventions):
                graph = make_engine(path, "onnxruntime", 1)  # read once: its declared io is the op's
                check_graph_io(manifest.graph(name, precision), path, *graph.io())
                alpha = manifest.photometric_alpha
                self._engines[name] = RigidFlowOp(
                    conventions.UNRECORDED_PHOTOMETRIC_ALPHA if alpha is None else alpha, graph.io()
                )
                self.runs[name] = {"engine": "numpy", "precision": "fp32", "why": "rigid_op numpy (geometry)"}
                continue
            if backend == AUTO:
                self._engines[name], self.backend_choice[name] = pick_fastest(path, threads, unsafe)
                why = "auto: fastest installed engine at load"
            else:
                self._engines[name] = make_engine(path, backend, threads)
                why = f"backend {backend}"
            check_graph_io(manifest.graph(name, precision), path, *self._engines[name].io())
            chosen = self._engines[name].name
            why += "".join(f"; {'' if e == chosen else 'skipped '}{r}" for e, r in unsafe.items())
            fp32 = precision == "fp32" or (manifest.quantization and name in manifest.quantization.fp32_graphs)
            self.runs[name] = {"engine": chosen, "precision": "fp32" if fp32 else precision, "why": why}

    def _int8_unsafe(self, name: str, backend: str) -> dict[str, str]:
        """{engine: why its INT8 of graph ``name`` is not exact on this CPU} (geonet_infer.int8_safety).
        Auto skips those engines (onnxruntime is always exact: its sessions set the remedy); an engine
        named by ``backend`` runs the graph anyway, after one line on stderr."""
        q = self.manifest.quantization
        if self.precision != "int8" or q is None or name in q.fp32_graphs:
            return {}
        names = [e.name for e in ENGINES.values() if e.available()] if backend == AUTO else [backend]
        unsafe = {e: r for e in names if (r := int8_unsafe_reason(e, q.int8_kernels.get(name)))}
        if backend in unsafe:
            print(f"geonet-infer: warning: {name} INT8 may be inexact: {unsafe[backend]}", file=sys.stderr)
        return unsafe

    @property
    def names(self) -> tuple[str, ...]:
        """The graphs present, in manifest order."""
        return tuple(self._engines)

    @property
    def backends(self) -> dict[str, str]:
        """Graph name -> the engine running it ("onnxruntime", "openvino")."""
        return {name: engine.name for name, engine in self._engines.items()}

    def __contains__(self, name: object) -> bool:
        return name in self._engines

    def engine(self, name: str) -> Engine | RigidFlowOp:
        """The engine of graph ``name`` (``run(feeds) -> {output: array}``); ModelError when absent."""
        if name not in self._engines:
            raise ModelError(
                Path(self.manifest.root or ".") / MANIFEST_NAME,
                f"no '{name}' graph in the {self.precision} set",
                f"graphs present: {', '.join(self._engines)}",
            )
        return self._engines[name]

    def run(self, name: str, **feeds: np.ndarray) -> dict[str, np.ndarray]:
        """Run graph ``name`` on float32 feeds keyed by its input names."""
        return self._engines[name].run({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})


def run_cascade(
    graphs: GraphSet,
    spec: InputSpec,
    snippets: np.ndarray,
    targets: list[int],
    K: np.ndarray | None,
    size: tuple[int, int],
    *,
    timer: StageTimer | None = None,
    disparity: np.ndarray | None = None,
    source_position: int | None = None,
    run_resflow: bool = True,
    with_flow: bool = True,
    feeds: dict[str, dict[str, np.ndarray]] | None = None,
) -> dict[str, Any]:
    """Steps 1-4 on a batch of normalised snippets (B, L, 3, h, w) in temporal order.

    Args:
        targets: ``targets[b]`` is the target's index in snippet b.
        K: (3, 3) intrinsics at the input size ``size`` (H, W) (None only with ``with_flow=False``).
        disparity: (B, h, w) disparity of the targets, to reuse depth computed elsewhere.
        source_position: the source (index among the sources) flow goes to; None = the frame
            after the target (:func:`next_source_position`).
        run_resflow: False stops before ResFlowNet (its input is still built: INT8 calibration).
        with_flow: False stops after PoseNet (and then needs no DepthNet).
        feeds: a dict that gets each graph's inputs as it was called with them (graph name ->
            {input name: float32 array}): realistic inputs for timing one graph alone.
    Returns:
        "disparity" (B, h, w), "pose" (B, 6) and "pose_matrix" (B, 4, 4) target -> source; with flow
        also "rigid_flow" (B, 2, h, w) and "flow_input" (B, 12, h, w), and after ResFlowNet
        "residual_flow" and "flow" (B, 2, h, w), all at the graph size.
    """
    timer = timer or StageTimer()

    def call(name: str, **inputs: np.ndarray) -> dict[str, np.ndarray]:
        if feeds is not None:
            feeds[name] = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in inputs.items()}
        return graphs.run(name, **inputs)

    B, L = snippets.shape[:2]
    rows = np.arange(B)
    target = snippets[rows, targets]
    orders = [posenet_order(t, L) for t in targets]
    src_pos = next_source_position(L) if source_position is None else source_position
    source = snippets[rows, [order[1 + src_pos] for order in orders]]
    if disparity is None and with_flow:
        with timer.stage("depthnet"):
            disparity = call("depthnet", image=target)["disparity"][:, 0]
    with timer.stage("posenet"):
        stacked = np.stack([np.concatenate(list(snippets[b, order])) for b, order in enumerate(orders)])
        pose = call("posenet", snippet=stacked)
    out: dict[str, Any] = {
        "disparity": disparity,
        "pose": pose["pose"][:, src_pos],
        "pose_matrix": pose["pose_matrix"][:, src_pos],
    }
    if not with_flow:
        return out
    if K is None or disparity is None:  # DepthNet ran above unless disparity was given
        raise InputError(None, "flow needs the camera intrinsics K", "pass K (3x3) or a Camera")
    K_graph = np.repeat(graph_intrinsics(K, size, spec)[None], B, axis=0)
    with timer.stage("rigidflow"):
        rigid = call(
            "rigidflow",
            depth=1.0 / disparity[:, None],
            pose=pose["pose"][:, src_pos],
            intrinsics=K_graph,
            target=target,
            source=source,
        )
    with timer.stage("resflownet"):  # its input: part of its cost (the latency table adds up)
        flow_input = resflow_input({"target": target, "source": source, **rigid})
    out.update(rigid_flow=rigid["rigid_flow"], flow_input=flow_input)
    if run_resflow and "resflownet" in graphs:
        with timer.stage("resflownet"):
            out.update(call("resflownet", flow_input=flow_input))
    return out


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


def calibration_input(
    graphs: GraphSet,
    spec: InputSpec,
    frames: Sequence[ImageLike],
    camera: Intrinsics,
    source_index: int | None = None,
) -> np.ndarray:
    """The (1, 12, h, w) ResFlowNet input for target -> source ``source_index`` (INT8 calibration).

    ``frames``: a snippet (any size; resized like every other call); ``source_index`` counts
    sources in temporal order without the target (None = the frame after the target).
    """
    missing = [g for g in ("depthnet", "posenet", "rigidflow") if g not in graphs]
    if missing:  # builds ResFlowNet's input, does not run it
        raise ModelError(graphs.manifest.root, f"calibrating ResFlowNet needs the {', '.join(missing)} graph(s)")
    timer = StageTimer()
    x, cam, size = load_snippet(spec, frames, camera, timer)
    mid = len(x) // 2
    source = next_source_position(spec.seq_length) if source_index is None else source_index
    parts = run_cascade(
        graphs,
        spec,
        x[None],
        [mid],
        cam.K if cam else None,
        size,
        timer=timer,
        source_position=source,
        run_resflow=False,
    )
    return parts["flow_input"]


# ----------------------------------------------------------------------------- sequences
def iter_frames(
    graphs: GraphSet,
    spec: InputSpec,
    frames: Iterable[ImageLike],
    camera: Intrinsics | None,
    *,
    batch_size: int,
    names: Sequence[str] | None,
    tasks: tuple[str, ...],
    need_depth: bool = False,
    check: bool = False,
) -> Iterator[FrameResult]:
    """A sequence in the model's own (relative) scale, one :class:`FrameResult` per frame, in order.

    ``tasks`` (checked by the caller): of "depth", "pose", "flow". Each frame's depth is computed
    once (one DepthNet batch per ``batch_size`` frames) and reused by the rigid-flow op of the pair
    it is the target of; pose and flow of frame t come from the snippet centred on t (ends
    replicated, :func:`snippet_indices`) towards t + 1. Frames are read lazily, at most
    ``batch_size + seq_length // 2`` ahead. With pose or flow a sequence needs 2 frames of one size;
    depth alone runs on any number, each frame at its own size. ``need_depth``: depth is needed
    though not asked for (metric scale).
    ``check``: each flow is checked against the frames (:mod:`geonet_infer.check`, at the graph size).
    """
    check_batch_size(batch_size)
    with_flow = "flow" in tasks
    run_depth = need_depth or "depth" in tasks or with_flow
    run_pose = "pose" in tasks or with_flow
    L = spec.seq_length
    k = L // 2
    source = iter(frames)
    prepared: dict[int, np.ndarray] = {}
    frame_names: dict[int, str] = {}
    cam: Camera | None = None
    size: tuple[int, int] = (0, 0)
    sizes: dict[int, tuple[tuple[int, int], Camera | None]] = {}  # depth alone: each frame its own size
    n_read, exhausted = 0, False
    pose_world = np.eye(4)
    t0 = 0
    while True:
        timer = StageTimer()
        while not exhausted and n_read < t0 + batch_size + k:
            try:
                item = next(source)
            except StopIteration:
                exhausted = True
                break
            rgb, label = read_frame(item, timer, n_read)
            if n_read == 0 or (not run_pose and rgb.shape[:2] != size):
                size = rgb.shape[:2]
                cam = camera_at(camera, size)
                if cam is None and with_flow:
                    raise InputError(None, "a sequence needs the camera intrinsics K", "pass K (3x3) or a Camera")
            elif rgb.shape[:2] != size:
                raise InputError(
                    label,
                    f"frame {n_read} is {rgb.shape[1]}x{rgb.shape[0]}, the sequence started at {size[1]}x{size[0]}",
                    "all frames of a sequence must have one size",
                )
            prepared[n_read] = to_network(spec, rgb, cam, timer)
            sizes[n_read] = (size, cam)
            frame_names[n_read] = (
                names[n_read]
                if names is not None
                else Path(label).stem
                if isinstance(item, (str, Path))
                else f"{n_read:06d}"
            )
            n_read += 1
        if run_pose and t0 == 0 and exhausted and n_read < 2:
            raise InputError(
                None, f"a sequence needs at least 2 frames, got {n_read}", "pass consecutive frames of one video"
            )
        if t0 >= n_read:
            return
        last = n_read - 1 if exhausted else n_read - 1 - k
        batch = list(range(t0, min(t0 + batch_size, last + 1)))
        # Frames with a next frame get pose + flow; every frame gets depth.
        paired = [t for t in batch if t + 1 < n_read] if run_pose else []
        disparity = None
        if run_depth:
            with timer.stage("depthnet"):
                images = np.stack([prepared[t] for t in batch])
                disparity = graphs.run("depthnet", image=images)["disparity"][:, 0]
        parts: dict[str, np.ndarray] = {}
        if paired:
            windows = [[min(max(i, 0), n_read - 1) for i in range(t - k, t + k + 1)] for t in paired]
            with timer.stage("preprocess"):  # the snippets: timed, so the latency table adds up
                snippets = np.stack([np.stack([prepared[i] for i in w]) for w in windows])
            parts = run_cascade(
                graphs,
                spec,
                snippets,
                [k] * len(paired),
                cam.K if cam else None,
                size,
                timer=timer,
                disparity=None if disparity is None else disparity[: len(paired)],
                with_flow=with_flow,
            )
        results = []
        no_flow: tuple[np.ndarray | None, Callable[[], np.ndarray] | None] = (None, None)
        with timer.stage("postprocess"):
            for j, t in enumerate(batch):
                at = sizes[t][0]  # the frame's own size (one size for a sequence with pose or flow)
                depth, disp = (None, None) if disparity is None else disparity_to_input(disparity[j], at)
                flows = flows_to_input(parts, j, size) if t in paired and with_flow else no_flow
                pose_next = parts["pose_matrix"][j].astype(np.float64) if t in paired else None
                vector = parts["pose"][j] if t in paired else None
                results.append((t, depth, disp, pose_next, vector, flows))
        checks = {}
        if check and with_flow and paired:
            with timer.stage("check"):
                units = (size[1] / spec.width, size[0] / spec.height)  # input pixels per graph pixel
                rigid = parts["rigid_flow"].transpose(0, 2, 3, 1)
                full = parts["flow"].transpose(0, 2, 3, 1) if "flow" in parts else None
                for j, t in enumerate(paired):
                    frame, after = spec.to_grey(prepared[t]), spec.to_grey(prepared[t + 1])
                    checks[t] = (
                        check_pair(frame, after, rigid[j], units=units)  # no ResFlowNet: the flow is rigid
                        if full is None
                        else check_pair(frame, after, full[j], rigid[j], units=units)
                    )
        share = timer.result(1.0 / len(batch))
        for t, depth, disp, pose_next, vector, flows in results:
            at_cam = sizes[t][1]
            yield FrameResult(
                index=t,
                name=frame_names.pop(t),
                depth=depth,
                disparity=disp,
                camera_to_world=pose_world.copy(),
                pose_to_next=pose_next,
                pose_vector_to_next=vector,
                undistorted=bool(at_cam and at_cam.has_distortion),
                timings_ms=dict(share),
                flow=flows[0],
                rigid_flow_at_input=flows[1],
                intrinsics=None if at_cam is None else at_cam.K,
                check=checks.get(t),
            )
            if pose_next is not None:
                pose_world = pose_world @ rigid_inverse(pose_next)
        t0 = batch[-1] + 1
        for i in [i for i in prepared if i < t0 - k]:
            del prepared[i], sizes[i]
