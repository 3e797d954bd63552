"""The GeoNet cascade on onnxruntime: :func:`load` -> :class:`Predictor`.

One cascade for the whole project (export's INT8 calibration and accuracy checks
use it too), per frame t of a sequence:

1. ``depthnet``  frame t -> disparity and depth (relative scale);
2. ``posenet``   snippet [t, t-k .. t-1, t+1 .. t+k] -> poses t -> each source;
3. ``rigidflow`` depth of t, pose t -> t+1, K -> rigid flow t -> t+1, frame t+1
   warped onto t, photometric error;
4. ``resflownet`` [t, t+1, warped, rigid flow, error] -> full flow t -> t+1
   (= rigid + residual).

Frames of any size go in; they are undistorted (if the camera has lens
distortion), resized to the graphs' size, normalised, and outputs are mapped back
to the input size, all inside. Every result carries per-stage timings in ms.
A Predictor holds no per-call state, so one instance can serve many threads.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from geonet_infer.engines import BACKENDS, Engine, make_engine, pick_fastest
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.calib import Camera
from geonet_infer.io.images import read_image
from geonet_infer.manifest import MANIFEST_NAME, PRECISIONS, Manifest, check_graph_io, load_manifest
from geonet_infer.metrics import rigid_inverse
from geonet_infer.models import resolve_model
from geonet_infer.preprocess import (
    InputSpec,
    check_image,
    disparity_to_input,
    flow_to_input,
    graph_intrinsics,
    next_source_position,
    snippet_indices,
)
from geonet_infer.scale import check_camera_height, check_metric_request, fit_ground_plane
from geonet_infer.session import usable_cpus

ImageLike = np.ndarray | str | Path
Intrinsics = np.ndarray | Sequence[Sequence[float]] | Camera
# "write" is filled in by pipeline.predict_to_dir (saving outputs), not by the Predictor.
STAGES = ("read", "preprocess", "depthnet", "posenet", "rigidflow", "resflownet", "postprocess", "write")
TASKS = ("depth", "pose", "flow")
# The graphs each task needs. A model directory may hold only some (a converted depth or pose
# release, `python -m export --graphs`). "flow" is GeoNet's full flow; the API's flow methods
# also run on RIGID_FLOW_GRAPHS alone and then return the rigid flow (residual None).
TASK_GRAPHS = {
    "depth": ("depthnet",),
    "pose": ("posenet",),
    "flow": ("depthnet", "posenet", "rigidflow", "resflownet"),
}
RIGID_FLOW_GRAPHS = ("depthnet", "posenet", "rigidflow")
METRIC_TASK = "metric scale (camera height)"  # fits the ground to depth: needs DepthNet


def missing_graphs(task: str, graphs: Iterable[str]) -> tuple[str, ...]:
    """The graphs ``task`` needs that are not among ``graphs`` (empty: the task can run)."""
    present = set(graphs)
    return tuple(g for g in TASK_GRAPHS[task] if g not in present)


def require_graphs(task: str, needed: Iterable[str], graphs: Iterable[str], model_dir) -> None:
    """GeoNetError (one line naming the missing graphs and ``model_dir``) unless every graph
    ``task`` needs is among the model's ``graphs``."""
    graphs = tuple(graphs)
    missing = [g for g in needed if g not in graphs]
    if not missing:
        return
    leave = f"leave {task} out of the tasks" if task in TASKS else "drop the camera height"
    hint = f"{leave}, or use a model directory that holds {', '.join(missing)}"
    if "resflownet" in missing:
        hint += " (exported from a stage 'flow' checkpoint or the released geonet_resflownet)"
    raise InputError(
        model_dir,
        f"{'task ' if task in TASKS else ''}{task} needs the {' and '.join(missing)} "
        f"graph{'s' if len(missing) > 1 else ''}, which this model lacks (it holds {', '.join(graphs)})",
        hint + f"; `geonet-infer info --model {model_dir}` lists what a model can do",
    )


def resolve_tasks(
    graphs: Iterable[str], tasks: Iterable[str] | None, model_dir, *, metric: bool = False
) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]]]:
    """(tasks to run in canonical order, {task skipped: the graphs it lacks}) for a model holding ``graphs``.

    ``tasks=None``: every task the model can do, the others skipped; given tasks are all
    required (GeoNetError naming a missing graph) and none is skipped. ``metric``: a camera
    height will be given (it needs DepthNet whatever the tasks).
    """
    graphs = tuple(graphs)
    if metric:
        require_graphs(METRIC_TASK, TASK_GRAPHS["depth"], graphs, model_dir)
    if tasks is not None:
        tasks = list(tasks)
        unknown = [t for t in tasks if t not in TASKS]
        if unknown:
            raise InputError(None, f"unknown task(s) {unknown}", f"choose from {','.join(TASKS)}")
        for task in tasks:
            require_graphs(task, TASK_GRAPHS[task], graphs, model_dir)
        return tuple(t for t in TASKS if t in tasks), {}
    skipped = {t: missing_graphs(t, graphs) for t in TASKS if missing_graphs(t, graphs)}
    if len(skipped) == len(TASKS):
        raise InputError(
            model_dir,
            f"this model can do none of {', '.join(TASKS)} (it holds {', '.join(graphs)})",
            "export depthnet or posenet into it with `python -m export --graphs`",
        )
    return tuple(t for t in TASKS if t not in skipped), skipped


def describe_skipped(skipped: dict[str, tuple[str, ...]]) -> str:
    """'pose (no posenet graph), flow (no posenet, resflownet graphs)' for the notes of predict and batch."""
    return ", ".join(
        f"{task} (no {', '.join(graphs)} graph{'s' if len(graphs) > 1 else ''})" for task, graphs in skipped.items()
    )


# ----------------------------------------------------------------------------- results
@dataclass
class DepthResult:
    """depth and disparity (H, W) float32 at the input resolution; depth = 1 / disparity.

    Relative scale, unless a camera height was given: then ``metric_scale`` is the factor
    applied (see :mod:`geonet_infer.scale`) and depth is in metres.
    """

    depth: np.ndarray
    disparity: np.ndarray
    undistorted: bool
    timings_ms: dict[str, float]
    metric_scale: float | None = None


@dataclass
class PoseResult:
    """Poses from the target (middle frame) to each source, sources in temporal order.

    matrices: (L-1, 4, 4) rigid transforms mapping target-camera points to source-camera points.
    vectors: (L-1, 6) [tx, ty, tz, rx, ry, rz] (Euler radians, R = Rx Ry Rz); translation in
    the depth's relative units.
    """

    matrices: np.ndarray
    vectors: np.ndarray
    timings_ms: dict[str, float]


@dataclass
class FlowResult:
    """Flow target -> next frame, (H, W, 2) float32 (u, v) in input pixels.

    ``flow`` = ``rigid_flow`` + ``residual_flow``; for a model without ResFlowNet
    (a stage 'rigid' export) ``flow`` is the rigid flow and ``residual_flow`` is None.
    ``depth`` is the target's depth, ``pose`` its (4, 4) transform target -> next frame.
    """

    flow: np.ndarray
    rigid_flow: np.ndarray
    residual_flow: np.ndarray | None
    depth: np.ndarray
    pose: np.ndarray
    undistorted: bool
    timings_ms: dict[str, float]


@dataclass
class FrameResult:
    """One frame of :meth:`Predictor.iter_sequence`.

    depth, disparity: (H, W) float32 at the input resolution (None when "depth" was not asked for
    and nothing else needed it).
    camera_to_world: (4, 4) this frame's pose in the first frame's camera coordinates
    (first frame = identity; translation up to the model's unknown scale, or metres with
    ``camera_height``: each pair's translation takes its target frame's ``metric_scale``).
    pose_to_next: (4, 4) target -> next-frame transform (None for the last frame, or without "pose").
    flow, rigid_flow, residual_flow: (H, W, 2) flow to the next frame (None for the last
    frame; residual None for a model without ResFlowNet).
    timings_ms: this frame's share of each stage (batched stages divided evenly).
    """

    index: int
    name: str
    depth: np.ndarray | None
    disparity: np.ndarray | None
    camera_to_world: np.ndarray
    pose_to_next: np.ndarray | None
    pose_vector_to_next: np.ndarray | None
    flow: np.ndarray | None
    rigid_flow: np.ndarray | None
    residual_flow: np.ndarray | None
    undistorted: bool
    timings_ms: dict[str, float]
    metric_scale: float | None = None  # with camera_height: depth and translations are in metres


@dataclass
class SequenceResult:
    """All frames of a sequence (:meth:`Predictor.predict_sequence`)."""

    frames: list[FrameResult]
    timings_ms: dict[str, float] = field(default_factory=dict)  # stage totals over the sequence

    @property
    def depth(self) -> np.ndarray:
        """(N, H, W) depth of every frame."""
        return np.stack([f.depth for f in self.frames])

    @property
    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world poses, first frame = identity."""
        return np.stack([f.camera_to_world for f in self.frames])

    @property
    def flow(self) -> np.ndarray:
        """(N-1, H, W, 2) flow t -> t+1."""
        if any(f.flow is None for f in self.frames[:-1]):
            raise ValueError("this sequence was predicted without flow (with_flow=False)")
        return np.stack([f.flow for f in self.frames[:-1]])


MAX_FRAMES_BEFORE_GROUND = 60  # frames held back waiting for a first ground plane (2.4 s at 25 fps)


def metric_frames(
    results: Iterable[FrameResult], camera_height: float, K_at: Callable[[tuple[int, int]], np.ndarray]
) -> Iterator[FrameResult]:
    """The frames of a sequence in metres, in order.

    Each frame's depth and pose translation are multiplied by the factor that puts the ground
    plane fitted to its depth (:func:`geonet_infer.scale.fit_ground_plane`) ``camera_height``
    metres below the camera. A frame whose road is hidden (a truck ahead) takes the previous
    frame's factor; frames before the first fit are held back (at most
    ``MAX_FRAMES_BEFORE_GROUND``) and take the first fit's. ``camera_to_world`` is chained
    again from the scaled poses. ``K_at((H, W))``: the intrinsics at a depth map's size.
    """
    check_camera_height(camera_height)
    pending: list[FrameResult] = []
    scale: float | None = None
    pose_world = np.eye(4)
    for result in results:
        try:
            scale = fit_ground_plane(result.depth, K_at(result.depth.shape)).scale_for(camera_height)
        except GeoNetError as err:
            if scale is None:
                pending.append(result)
                if len(pending) > MAX_FRAMES_BEFORE_GROUND:
                    raise InputError(
                        pending[0].name,
                        f"no ground plane in the first {len(pending)} frames ({err.problem})",
                        "metric scale needs the road in view early in the video: start it where the road "
                        "shows, or drop --camera-height for relative depth",
                    ) from None
                continue
        for frame in [*pending, result]:
            pose_next, vector = frame.pose_to_next, frame.pose_vector_to_next
            if pose_next is not None:
                pose_next, vector = pose_next.copy(), vector.copy()
                pose_next[:3, 3] *= scale
                vector[:3] *= scale
            yield replace(
                frame,
                depth=frame.depth * scale,
                disparity=frame.disparity / scale,
                camera_to_world=pose_world.copy(),
                pose_to_next=pose_next,
                pose_vector_to_next=vector,
                metric_scale=scale,
            )
            if pose_next is not None:
                pose_world = pose_world @ rigid_inverse(pose_next)
        pending = []
    if pending:
        raise InputError(
            pending[0].name,
            f"no ground plane in any of the {len(pending)} frames",
            "metric scale from camera height needs a visible, roughly flat road; drop --camera-height "
            "for relative depth",
        )


class _Timer:
    """Accumulates wall time per stage in ms."""

    def __init__(self):
        self.ms: dict[str, float] = defaultdict(float)

    def stage(self, name: str):
        timer = self

        class _Stage:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                timer.ms[name] += (time.perf_counter() - self.t0) * 1e3

        return _Stage()

    def result(self, share: float = 1.0) -> dict[str, float]:
        out = {k: v * share for k, v in self.ms.items()}
        out["total"] = sum(out.values())
        return out


# ----------------------------------------------------------------------------- predictor
def load(
    model: str | Path | None = None,
    *,
    precision: str = "fp32",
    threads: int | None = None,
    backend: str = "onnxruntime",
) -> Predictor:
    """Load a model: None = the bundled default, a bundled name, or a model directory.

    Args:
        model: see above (``geonet_infer.models.bundled_models()`` lists the names).
        precision: "fp32" or "int8" (quantised ConvNets; the rigid-flow op stays fp32).
        threads: intra-op threads per graph; None = the CPUs this process may use.
        backend: "onnxruntime", "openvino" (extra ``geonet-infer[openvino]``) or "auto"
            (times both on each graph at load, keeps the faster; see :mod:`geonet_infer.engines`).
    """
    return Predictor(resolve_model(model), precision=precision, threads=threads, backend=backend)


class Predictor:
    """GeoNet depth, pose and flow on onnxruntime for one model directory.

    Sessions are created once here (file hashes checked against the manifest).
    Methods take uint8 RGB (H, W, 3) arrays of any size or image paths.
    """

    def __init__(
        self,
        model_dir: str | Path,
        precision: str = "fp32",
        threads: int | None = None,
        manifest: Manifest | None = None,
        backend: str = "onnxruntime",
    ):
        if precision not in PRECISIONS:
            raise InputError(None, f"unknown precision {precision!r}", f"choose one of {', '.join(PRECISIONS)}")
        if backend not in BACKENDS:
            raise InputError(None, f"unknown backend {backend!r}", f"choose one of {', '.join(BACKENDS)}")
        self.manifest = manifest or load_manifest(model_dir)
        self.model_dir = Path(self.manifest.root or model_dir)
        self.precision = precision
        self.spec = InputSpec.from_manifest(self.manifest)
        self.threads = usable_cpus() if threads is None else threads
        self.graphs = self.manifest.graph_names(precision)
        self.backend = backend
        self.backend_choice: dict[str, dict] = {}  # backend="auto": per graph, the timings behind the choice
        self._engines: dict[str, Engine] = {}
        for name in self.graphs:
            path = self.manifest.path(name, precision)
            if backend == "auto":
                self._engines[name], self.backend_choice[name] = pick_fastest(path, self.threads)
            else:
                self._engines[name] = make_engine(path, backend, self.threads)
            check_graph_io(self.manifest.graph(name, precision), path, *self._engines[name].io())

    @property
    def engines(self) -> dict[str, str]:
        """Graph name -> the engine running it ("onnxruntime" or "openvino")."""
        return {name: engine.backend for name, engine in self._engines.items()}

    def __repr__(self) -> str:
        return (
            f"Predictor({str(self.model_dir)!r}, precision={self.precision!r}, threads={self.threads}, "
            f"backend={self.backend!r}, arch={self.manifest.arch!r}, size={self.spec.height}x{self.spec.width})"
        )

    @property
    def has_flow(self) -> bool:
        """Whether the model has ResFlowNet (else flow = rigid flow)."""
        return "resflownet" in self._engines

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks this model's graphs can do, of "depth", "pose", "flow" (see ``TASK_GRAPHS``)."""
        return tuple(t for t in TASKS if not self.missing_graphs(t))

    def missing_graphs(self, task: str) -> tuple[str, ...]:
        """The graphs ``task`` needs that this model (at its precision) lacks."""
        return missing_graphs(task, self._engines)

    def require_tasks(self, tasks: Iterable[str]) -> None:
        """Raise GeoNetError (one line naming the graph and this directory) unless every task can run."""
        resolve_tasks(self._engines, tasks, self.model_dir)

    def resolve_tasks(
        self, tasks: Iterable[str] | None = None, *, metric: bool = False
    ) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]]]:
        """(tasks to run in canonical order, {task skipped: the graphs it lacks}); see :func:`resolve_tasks`."""
        return resolve_tasks(self._engines, tasks, self.model_dir, metric=metric)

    def _require_graphs(self, task: str, graphs: Iterable[str]) -> None:
        require_graphs(task, graphs, self._engines, self.model_dir)

    @property
    def seq_length(self) -> int:
        return self.spec.seq_length

    def engine(self, name: str) -> Engine:
        """The engine of graph ``name``: ``run(feeds) -> {output: array}`` (benchmarks, profiling)."""
        if name not in self._engines:
            raise InputError(
                self.model_dir / MANIFEST_NAME,
                f"no '{name}' graph in the {self.precision} set",
                f"graphs present: {', '.join(self._engines)}",
            )
        return self._engines[name]

    # ------------------------------------------------------------------ graph calls
    def _run(self, name: str, **feeds: np.ndarray) -> dict[str, np.ndarray]:
        return self._engines[name].run({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()})

    # ------------------------------------------------------------------ inputs
    def _read(self, image: ImageLike, timer: _Timer, index: int = 0) -> tuple[np.ndarray, str]:
        """A checked frame and its label (the path, or "image <index>" for arrays)."""
        if isinstance(image, (str, Path)):
            with timer.stage("read"):
                return check_image(read_image(image), image), str(image)
        label = f"image {index}"
        return check_image(image, label), label

    def _camera(self, K: Intrinsics | None, size: tuple[int, int]) -> Camera | None:
        """K or a Camera at the input size (H, W); a Camera with another size is rescaled to it."""
        if K is None:
            return None
        if isinstance(K, Camera):
            return K.scaled_to(size[1], size[0]).validate(K.source or None)
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):  # Camera() itself raises a plain ValueError for this
            raise InputError(
                None,
                f"intrinsics must be a 3x3 matrix, got shape {K.shape}",
                "pass K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] at the input resolution",
            )
        return Camera(K=K, dist=None, size=(size[1], size[0])).validate()

    def _to_network(self, rgb: np.ndarray, camera: Camera | None, timer: _Timer) -> np.ndarray:
        with timer.stage("preprocess"):
            if camera is not None and camera.has_distortion:
                rgb = camera.undistort(rgb)
            return self.spec.to_network(rgb)

    def _load_frames(self, frames: Sequence[ImageLike], camera_or_K, timer: _Timer, what: str):
        """Read and check frames of one snippet (same size) -> (rgbs, camera, size)."""
        rgbs, names = zip(*[self._read(f, timer, i) for i, f in enumerate(frames)])
        sizes = {r.shape[:2] for r in rgbs}
        if len(sizes) > 1:
            detail = ", ".join(f"{n}: {r.shape[1]}x{r.shape[0]}" for n, r in zip(names, rgbs))
            raise InputError(
                None, f"frames of one {what} differ in size ({detail})", "pass consecutive frames of one camera"
            )
        size = rgbs[0].shape[:2]
        return list(rgbs), self._camera(camera_or_K, size), size

    def _snippet_frames(self, frames: Sequence[ImageLike]) -> list[ImageLike]:
        """A full snippet (L frames, target in the middle) or a pair [t, t+1] padded per snippet_indices."""
        L = self.seq_length
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

    # ------------------------------------------------------------------ depth
    def depth(
        self,
        image: ImageLike | Sequence[ImageLike],
        camera: Intrinsics | None = None,
        *,
        camera_height: float | None = None,
    ) -> DepthResult | list[DepthResult]:
        """Depth of one image, or of a list of images run as one batch.

        Args:
            image: uint8 RGB (H, W, 3) array or path; or a list of them (sizes may differ).
            camera: optional Camera (or K); a camera with lens distortion undistorts first.
            camera_height: metres between the camera and a flat road: depth is scaled so the
                ground plane fitted to it lies that far below (needs ``camera``).
        Returns:
            DepthResult (a list for a list input) at each image's own resolution.
        """
        self._require_graphs("depth", TASK_GRAPHS["depth"])
        single = not isinstance(image, (list, tuple))
        images = [image] if single else list(image)
        if not images:
            return []
        check_metric_request(camera_height, camera)
        timer = _Timer()
        rgbs = [self._read(img, timer, i)[0] for i, img in enumerate(images)]
        cameras = [self._camera(camera, r.shape[:2]) for r in rgbs]
        x = np.stack([self._to_network(r, c, timer) for r, c in zip(rgbs, cameras)])
        with timer.stage("depthnet"):
            disparity = self._run("depthnet", image=x)["disparity"][:, 0]
        results = []
        with timer.stage("postprocess"):
            for i, (d, r, c) in enumerate(zip(disparity, rgbs, cameras)):
                depth, disp = disparity_to_input(d, r.shape[:2])
                scale = None
                if camera_height is not None:
                    try:
                        scale = fit_ground_plane(depth, c.K).scale_for(camera_height)
                    except GeoNetError as err:
                        raise InputError(f"image {i}", err.problem, err.hint) from None
                    depth, disp = depth * scale, disp / scale
                results.append((depth, disp, bool(c and c.has_distortion), scale))
        timings = timer.result(1.0 / len(images))
        out = [
            DepthResult(depth=d, disparity=p, undistorted=u, timings_ms=dict(timings), metric_scale=m)
            for d, p, u, m in results
        ]
        return out[0] if single else out

    # ------------------------------------------------------------------ pose
    def pose(self, frames: Sequence[ImageLike], camera: Intrinsics | None = None) -> PoseResult:
        """Poses of one snippet: ``seq_length`` consecutive frames in temporal order, target in the middle.

        A pair [t, t+1] is padded to a snippet as at a sequence start (see
        ``preprocess.snippet_indices``). ``camera`` only matters for undistortion.
        """
        self._require_graphs("pose", TASK_GRAPHS["pose"])
        timer = _Timer()
        frames = self._snippet_frames(frames)
        rgbs, cam, _ = self._load_frames(frames, camera, timer, "snippet")
        x = [self._to_network(r, cam, timer) for r in rgbs]
        order = snippet_indices(len(x) // 2, len(x), len(x))
        with timer.stage("posenet"):
            out = self._run("posenet", snippet=np.concatenate([x[i] for i in order])[None])
        return PoseResult(
            matrices=out["pose_matrix"][0].astype(np.float64), vectors=out["pose"][0], timings_ms=timer.result()
        )

    # ------------------------------------------------------------------ flow
    def flow(self, frames: Sequence[ImageLike], K: Intrinsics) -> FlowResult:
        """Flow from the target (middle frame of the snippet) to the frame after it.

        Args:
            frames: ``seq_length`` consecutive frames (target in the middle), or a
                pair [t, t+1] (padded as at a sequence start).
            K: (3, 3) intrinsics at the frames' resolution, or a Camera.
        Needs the depthnet, posenet and rigidflow graphs; without resflownet, flow = rigid flow.
        """
        self._require_graphs("flow", RIGID_FLOW_GRAPHS)
        timer = _Timer()
        frames = self._snippet_frames(frames)
        rgbs, cam, size = self._load_frames(frames, K, timer, "snippet")
        if cam is None:
            raise InputError(None, "flow needs the camera intrinsics K", "pass K (3x3) or a Camera")
        x = np.stack([self._to_network(r, cam, timer) for r in rgbs])
        mid = len(rgbs) // 2
        parts = self._cascade(x[None], [mid], cam.K, size, timer)
        with timer.stage("postprocess"):
            depth, _ = disparity_to_input(parts["disparity"][0], size)
            flows = self._flows_to_input(parts, 0, size)
        return FlowResult(
            depth=depth,
            pose=parts["pose_matrix"][0].astype(np.float64),
            undistorted=cam.has_distortion,
            timings_ms=timer.result(),
            **flows,
        )

    def resflow_input(self, frames: Sequence[np.ndarray], K: np.ndarray, source_index: int | None = None) -> np.ndarray:
        """The (1, 12, h, w) ResFlowNet input for target -> source ``source_index`` (INT8 calibration).

        ``frames``: a snippet (any size; resized like every other call); ``source_index`` counts
        sources in temporal order without the target (None = the frame after the target).
        """
        self._require_graphs("flow", RIGID_FLOW_GRAPHS)  # builds ResFlowNet's input, does not run it
        frames = self._snippet_frames(frames)
        timer = _Timer()
        rgbs, cam, size = self._load_frames(frames, K, timer, "snippet")
        x = np.stack([self._to_network(r, cam, timer) for r in rgbs])
        mid = len(rgbs) // 2
        source = next_source_position(self.seq_length) if source_index is None else source_index
        parts = self._cascade(x[None], [mid], cam.K, size, timer, source_position=source, run_resflow=False)
        return parts["flow_input"]

    def _cascade(
        self,
        snippets: np.ndarray,
        targets: list[int],
        K: np.ndarray | None,
        size: tuple[int, int],
        timer: _Timer,
        disparity: np.ndarray | None = None,
        source_position: int | None = None,
        run_resflow: bool = True,
        with_flow: bool = True,
    ) -> dict[str, np.ndarray]:
        """Batched cascade on normalised snippets (B, L, 3, h, w) in temporal order.

        ``targets[b]`` is the target's index in snippet b; the source is the frame after it
        unless ``source_position`` (index among the sources) is given. ``disparity``
        (B, h, w) of the targets can be passed to reuse depth computed elsewhere.
        ``with_flow=False`` stops after PoseNet (and then needs no DepthNet).
        """
        B, L = snippets.shape[:2]
        rows = np.arange(B)
        target = snippets[rows, targets]
        order = [[t] + [i for i in range(L) if i != t] for t in targets]
        src_pos = next_source_position(L) if source_position is None else source_position
        source = snippets[rows, [o[1 + src_pos] for o in order]]
        if disparity is None and with_flow:
            with timer.stage("depthnet"):
                disparity = self._run("depthnet", image=target)["disparity"][:, 0]
        with timer.stage("posenet"):
            stacked = np.stack([np.concatenate(list(snippets[b, o])) for b, o in enumerate(order)])
            pose = self._run("posenet", snippet=stacked)
        out = {"disparity": disparity, "pose": pose["pose"][:, src_pos], "pose_matrix": pose["pose_matrix"][:, src_pos]}
        if not with_flow:
            return out
        K_graph = np.repeat(graph_intrinsics(K, size, self.spec)[None], B, axis=0)
        with timer.stage("rigidflow"):
            rigid = self._run(
                "rigidflow",
                depth=1.0 / disparity[:, None],
                pose=pose["pose"][:, src_pos],
                intrinsics=K_graph,
                target=target,
                source=source,
            )
        flow_input = np.concatenate([target, source, rigid["warped"], rigid["rigid_flow"], rigid["error"]], axis=1)
        out.update(rigid_flow=rigid["rigid_flow"], flow_input=flow_input)
        if run_resflow and self.has_flow:
            with timer.stage("resflownet"):
                out.update(self._run("resflownet", flow_input=flow_input))
        return out

    def _flows_to_input(self, parts: dict, b: int, size: tuple[int, int]) -> dict[str, np.ndarray | None]:
        rigid = flow_to_input(parts["rigid_flow"][b], size)
        if "flow" not in parts:
            return {"flow": rigid, "rigid_flow": rigid, "residual_flow": None}
        flow = flow_to_input(parts["flow"][b], size)
        # flow = rigid + residual in the graph, and resizing is linear: one resize saved per frame
        return {"flow": flow, "rigid_flow": rigid, "residual_flow": flow - rigid}

    # ------------------------------------------------------------------ sequences
    def iter_sequence(
        self,
        frames: Iterable[ImageLike],
        K: Intrinsics | None,
        *,
        batch_size: int = 4,
        names: Sequence[str] | None = None,
        with_flow: bool = True,
        camera_height: float | None = None,
        tasks: Iterable[str] = TASKS,
    ) -> Iterator[FrameResult]:
        """Stream a whole sequence: yields one :class:`FrameResult` per frame, in order.

        Each frame's depth is computed once (one DepthNet batch per ``batch_size``
        frames) and reused by the rigid-flow op of the pair it is the target of.
        Pose and flow of frame t come from the snippet centred on t (ends
        replicated, see ``preprocess.snippet_indices``) towards t + 1; the last
        frame has depth and a pose but no flow. Poses are chained into one
        trajectory: camera_to_world[t + 1] = camera_to_world[t] @ inv(T_t->t+1).
        Frames are read lazily (an iterator of frames or paths is fine).
        ``tasks``: any of "depth", "pose", "flow"; a task left out is not computed (its
        fields are None; without "pose" every camera_to_world is the identity), so a model
        lacking a graph runs the tasks it has. "flow" needs depthnet, posenet and rigidflow
        (without resflownet, flow = rigid flow). ``with_flow=False`` drops "flow" (depth and
        poses only; K may then be None, or a Camera used only to undistort).
        ``camera_height`` (metres, needs K and depthnet) makes each frame's depth and its pose
        translation metric (:func:`metric_frames`: a frame whose road is hidden takes the
        previous frame's scale, frames before the first fit the first fit's).
        A missing graph or a bad request raises here, before any frame is read.
        """
        tasks = tuple(tasks)
        self.require_tasks(t for t in tasks if t != "flow")
        tasks = tuple(t for t in TASKS if t in tasks and (with_flow or t != "flow"))
        if "flow" in tasks:
            self._require_graphs("flow", RIGID_FLOW_GRAPHS)
        if camera_height is not None:
            self._require_graphs(METRIC_TASK, TASK_GRAPHS["depth"])
        check_metric_request(camera_height, K)
        results = self._iter_relative(frames, K, batch_size, names, tasks, camera_height is not None)
        if camera_height is not None:
            results = metric_frames(results, camera_height, lambda size: self._camera(K, size).K)
        return results

    def _iter_relative(
        self,
        frames: Iterable[ImageLike],
        K: Intrinsics | None,
        batch_size: int,
        names: Sequence[str] | None,
        tasks: tuple[str, ...],
        need_depth: bool = False,
    ) -> Iterator[FrameResult]:
        """:meth:`iter_sequence` in the model's own (relative) scale, for checked ``tasks``."""
        if batch_size < 1:
            raise InputError(None, f"batch_size must be >= 1, got {batch_size}")
        with_flow = "flow" in tasks
        run_depth = need_depth or "depth" in tasks or with_flow
        run_pose = "pose" in tasks or with_flow
        L = self.seq_length
        k = L // 2
        source = iter(frames)
        prepared: dict[int, np.ndarray] = {}
        frame_names: dict[int, str] = {}
        camera: Camera | None = None
        size: tuple[int, int] | None = None
        n_read, exhausted = 0, False
        pose_world = np.eye(4)
        t0 = 0
        while True:
            timer = _Timer()
            while not exhausted and n_read < t0 + batch_size + k:
                try:
                    item = next(source)
                except StopIteration:
                    exhausted = True
                    break
                rgb, label = self._read(item, timer, n_read)
                if size is None:
                    size = rgb.shape[:2]
                    camera = self._camera(K, size)
                    if camera is None and with_flow:
                        raise InputError(None, "a sequence needs the camera intrinsics K", "pass K (3x3) or a Camera")
                elif rgb.shape[:2] != size:
                    raise InputError(
                        label,
                        f"frame {n_read} is {rgb.shape[1]}x{rgb.shape[0]}, the sequence started at {size[1]}x{size[0]}",
                        "all frames of a sequence must have one size",
                    )
                prepared[n_read] = self._to_network(rgb, camera, timer)
                frame_names[n_read] = (
                    names[n_read]
                    if names is not None
                    else Path(label).stem
                    if isinstance(item, (str, Path))
                    else f"{n_read:06d}"
                )
                n_read += 1
            if t0 == 0 and exhausted and n_read < 2:
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
                    disparity = self._run("depthnet", image=images)["disparity"][:, 0]
            parts = {}
            if paired:
                windows = [[min(max(i, 0), n_read - 1) for i in range(t - k, t + k + 1)] for t in paired]
                snippets = np.stack([np.stack([prepared[i] for i in w]) for w in windows])
                parts = self._cascade(
                    snippets,
                    [k] * len(paired),
                    camera.K if camera else None,
                    size,
                    timer,
                    disparity=None if disparity is None else disparity[: len(paired)],
                    with_flow=with_flow,
                )
            results = []
            with timer.stage("postprocess"):
                for j, t in enumerate(batch):
                    depth, disp = (None, None) if disparity is None else disparity_to_input(disparity[j], size)
                    flows = (
                        self._flows_to_input(parts, j, size)
                        if t in paired and with_flow
                        else {"flow": None, "rigid_flow": None, "residual_flow": None}
                    )
                    pose_next = parts["pose_matrix"][j].astype(np.float64) if t in paired else None
                    vector = parts["pose"][j] if t in paired else None
                    results.append((t, depth, disp, pose_next, vector, flows))
            share = timer.result(1.0 / len(batch))
            for t, depth, disp, pose_next, vector, flows in results:
                yield FrameResult(
                    index=t,
                    name=frame_names.pop(t),
                    depth=depth,
                    disparity=disp,
                    camera_to_world=pose_world.copy(),
                    pose_to_next=pose_next,
                    pose_vector_to_next=vector,
                    undistorted=bool(camera and camera.has_distortion),
                    timings_ms=dict(share),
                    **flows,
                )
                if pose_next is not None:
                    pose_world = pose_world @ rigid_inverse(pose_next)
            t0 = batch[-1] + 1
            for i in [i for i in prepared if i < t0 - k]:
                del prepared[i]

    def predict_sequence(
        self, frames: Iterable[ImageLike], K: Intrinsics, *, batch_size: int = 4, camera_height: float | None = None
    ) -> SequenceResult:
        """All of :meth:`iter_sequence` in memory (mind the size of flow for long videos)."""
        results = list(self.iter_sequence(frames, K, batch_size=batch_size, camera_height=camera_height))
        totals: dict[str, float] = defaultdict(float)
        for r in results:
            for stage, ms in r.timings_ms.items():
                totals[stage] += ms
        return SequenceResult(frames=results, timings_ms=dict(totals))
