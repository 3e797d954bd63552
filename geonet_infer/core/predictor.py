"""The public API: :func:`load` -> :class:`Predictor` -> depth, pose, flow, whole sequences.

The Predictor is a thin face over :mod:`geonet_infer.core.cascade` (graph inputs and the cascade)
and :mod:`geonet_infer.core.scale` (metric depth). Frames of any size go in; they are undistorted
(if the camera has lens distortion), resized to the graphs' size, normalised, and outputs are
mapped back to the input size, all inside. Every result (:mod:`geonet_infer.core.results`) carries
per-stage timings in ms. A Predictor holds no per-call state, so one instance can serve many
threads.
"""

from __future__ import annotations

import warnings
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, overload

import numpy as np

from geonet_infer.classical import CLASSICAL_GRAPHS, check_methods, classical_tasks
from geonet_infer.core.cascade import run_cascade
from geonet_infer.core.classical_frames import KeptFrames, classical_frames
from geonet_infer.core.graphs import GraphSet
from geonet_infer.core.results import DepthResult, FlowResult, FrameResult, PoseResult, SequenceResult
from geonet_infer.core.scale import (
    SCALE_HALF_WINDOW,
    ScaleSmoother,
    check_metric_request,
    fit_ground_plane,
    metric_frames,
)
from geonet_infer.core.sequence import iter_frames
from geonet_infer.core.snippets import load_snippet, posenet_order
from geonet_infer.core.spec import (
    STAGES,
    ImageLike,
    InputSpec,
    Intrinsics,
    StageTimer,
    camera_at,
    disparity_to_input,
    flows_to_input,
    read_frame,
    to_network,
    with_assumed,
)
from geonet_infer.core.task_graphs import (
    METRIC_TASK,
    RIGID_FLOW_GRAPHS,
    TASK_GRAPHS,
    describe_skipped,
    missing_graphs,
    require_graphs,
    resolve_tasks,
)
from geonet_infer.core.tasks import TASKS, needs_intrinsics
from geonet_infer.engines import BACKENDS, check_threads, usable_cpus
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.limits import DEFAULT_BATCH_SIZE, MAX_BATCH_SIZE, check_batch_size
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import PRECISION_CHOICES, Manifest, load_manifest

__all__ = [
    "STAGES",
    "TASKS",
    "DepthResult",
    "FlowResult",
    "FrameResult",
    "PoseResult",
    "Predictor",
    "SequenceResult",
    "describe_skipped",
    "load",
    "missing_graphs",
    "require_graphs",
    "resolve_tasks",
]


def _camera_keyword(camera: Intrinsics | None, kwargs: dict[str, Any], method: str) -> Intrinsics | None:
    """``camera`` or the deprecated keyword ``K=`` of 0.x (one release of grace)."""
    if "K" in kwargs:
        if camera is not None:
            raise InputError(None, f"{method}() got both camera= and K=", "pass camera= only")
        warnings.warn(
            f"Predictor.{method}(K=...) is deprecated; pass camera= (a 3x3 K or a Camera)",
            DeprecationWarning,
            stacklevel=3,
        )
        camera = kwargs.pop("K")
    if kwargs:
        raise TypeError(f"{method}() got unexpected keyword argument(s) {', '.join(kwargs)}")
    return camera


def load(
    model: str | Path | None = None,
    *,
    precision: str = "fp32",
    threads: int | None = None,
    backend: str = "onnxruntime",
    rigid_op: str = "graph",
    mode: str = "latency",
) -> Predictor:
    """Load a model: None = the bundled default, a bundled name, or a model directory.

    Args:
        model: see above (``geonet_infer.models.bundled_models()`` lists the names).
        precision: "fp32", "int8" (quantised ConvNets; the rigid-flow op stays fp32), or "auto": per
            graph, the fastest of the model's precisions that is exact on this CPU, timed at load with
            the engines ``backend`` allows (``Predictor.graph_set.runs`` says what each graph runs).
        threads: the CPUs to use; None = the CPUs this process may use. In latency mode each graph call
            runs on all of them; in throughput mode as many batches of a sequence are computed at once, one
            thread each.
        backend: "onnxruntime", "openvino" (extra ``geonet-infer[openvino]``) or "auto"
            (times both on each graph at load, keeps the faster; see :mod:`geonet_infer.engines`).
        rigid_op: "graph" (default: ``rigidflow.onnx`` on ``backend``, the reference) or "numpy"
            (the weightless rigid-flow op in numpy + OpenCV, :mod:`geonet_infer.core.rigid`: about 1.5x
            as fast; flows agree with the graph's to 2e-4 px, so a KITTI flow PNG may differ by
            one 1/64 px step in a few values).
        mode: "latency" (one graph call at a time on every thread) or "throughput" (a sequence's batches
            computed at once, one thread each: more frames per second on a multi-core CPU). The same graph
            calls either way: the same outputs to float rounding. See :data:`MODES`.
    """
    return Predictor(
        resolve_model(model), precision=precision, threads=threads, backend=backend, rigid_op=rigid_op, mode=mode
    )


# How a Predictor spends its CPUs (issue 54). Recorded in summary.json and bench's JSON.
MODES = {
    "latency": "one call at a time, every graph on all threads (single calls, bench's latency figures)",
    "throughput": "a sequence's batches computed at once, one graph call per thread (video jobs)",
}


OUTPUT_SIZES = ("input", "network")


def check_output_size(output_size: str, flow_method: str = "network", pose_method: str = "network") -> None:
    if output_size not in OUTPUT_SIZES:
        raise InputError(None, f"unknown output size {output_size!r}", f"choose one of {', '.join(OUTPUT_SIZES)}")
    if output_size == "network" and (flow_method, pose_method) != ("network", "network"):
        raise InputError(
            None,
            "--output-size network keeps the networks' outputs at their size; DIS and ORB-VO work at the input's",
            "use --output-size input with --flow-method dis or --pose-method orbvo",
        )


class Predictor:
    """GeoNet depth, pose and flow for one model directory.

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
        rigid_op: str = "graph",
        mode: str = "latency",
    ):
        if precision not in PRECISION_CHOICES:
            raise InputError(None, f"unknown precision {precision!r}", f"choose one of {', '.join(PRECISION_CHOICES)}")
        if backend not in BACKENDS:
            raise InputError(None, f"unknown backend {backend!r}", f"choose one of {', '.join(BACKENDS)}")
        self.manifest = manifest or load_manifest(model_dir)
        self.model_dir = Path(self.manifest.root or model_dir)
        self.precision = precision
        self.spec = InputSpec.from_manifest(self.manifest)
        if mode not in MODES:
            raise InputError(None, f"unknown mode {mode!r}", f"choose one of {', '.join(MODES)}")
        self.threads = usable_cpus() if threads is None else check_threads(threads)
        self.backend = backend
        self.mode = mode
        # throughput: one thread per graph call, as many sequence batches in flight as threads
        self.workers = self.threads if mode == "throughput" else 1
        # One engine per graph; for benchmarks and export's INT8 calibration (geonet_infer.core.cascade).
        self.graph_set = GraphSet(
            self.manifest, precision, backend, self.threads // self.workers, rigid_op, streams=self.workers
        )

    @property
    def graphs(self) -> tuple[str, ...]:
        """The graphs of this model at its precision."""
        return self.graph_set.names

    @property
    def backend_choice(self) -> dict[str, dict]:
        """backend="auto": per graph, the timings behind the engine chosen."""
        return self.graph_set.backend_choice

    @property
    def engines(self) -> dict[str, str]:
        """Graph name -> the engine running it ("onnxruntime" or "openvino")."""
        return self.graph_set.engines

    def __repr__(self) -> str:
        return (
            f"Predictor({str(self.model_dir)!r}, precision={self.precision!r}, threads={self.threads}, "
            f"mode={self.mode!r}, "
            f"backend={self.backend!r}, arch={self.manifest.arch!r}, size={self.spec.height}x{self.spec.width})"
        )

    @property
    def has_flow(self) -> bool:
        """Whether the model has ResFlowNet (else flow = rigid flow)."""
        return "resflownet" in self.graph_set

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks this model's graphs can do, of "depth", "pose", "flow" (see ``TASK_GRAPHS``)."""
        return tuple(t for t in TASKS if not self.missing_graphs(t))

    def missing_graphs(self, task: str) -> tuple[str, ...]:
        """The graphs ``task`` needs that this model (at its precision) lacks."""
        return missing_graphs(task, self.graphs)

    def require_tasks(self, tasks: Iterable[str]) -> None:
        """Raise ModelError (one line naming the graph and this directory) unless every task can run."""
        resolve_tasks(self.graphs, tasks, self.model_dir)

    def resolve_tasks(
        self, tasks: Iterable[str] | None = None, *, metric: bool = False, classical: Iterable[str] = ()
    ) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]]]:
        """(tasks to run in canonical order, {task skipped: the graphs it lacks}); see :func:`resolve_tasks`."""
        return resolve_tasks(self.graphs, tasks, self.model_dir, metric=metric, classical=classical)

    @property
    def seq_length(self) -> int:
        return self.spec.seq_length

    # ------------------------------------------------------------------ depth
    @overload
    def depth(
        self, image: ImageLike, camera: Intrinsics | None = None, *, camera_height: float | None = None
    ) -> DepthResult: ...

    @overload
    def depth(
        self,
        image: list[ImageLike] | tuple[ImageLike, ...],
        camera: Intrinsics | None = None,
        *,
        camera_height: float | None = None,
    ) -> list[DepthResult]: ...

    def depth(
        self,
        image: ImageLike | list[ImageLike] | tuple[ImageLike, ...],
        camera: Intrinsics | None = None,
        *,
        camera_height: float | None = None,
    ) -> DepthResult | list[DepthResult]:
        """Depth of one image, or of a list of images run as one batch.

        Args:
            image: uint8 RGB (H, W, 3) array or path; or a list of at most ``MAX_BATCH_SIZE``
                (:mod:`geonet_infer.limits`) of them (sizes may differ).
            camera: optional Camera (or K); a camera with lens distortion undistorts first.
            camera_height: metres between the camera and a flat road: depth is scaled so the
                ground plane fitted to it lies that far below (needs ``camera``).
        Returns:
            DepthResult (a list for a list input) at each image's own resolution.
        """
        require_graphs("depth", TASK_GRAPHS["depth"], self.graphs, self.model_dir)
        single = not isinstance(image, (list, tuple))
        images: list[ImageLike] = list(image) if isinstance(image, (list, tuple)) else [image]
        if not images:
            return []
        if len(images) > MAX_BATCH_SIZE:  # they run as one batch: memory grows with it (1000 frames took 13.7 GB)
            raise InputError(
                None,
                f"depth() got {len(images)} images, over the limit of {MAX_BATCH_SIZE} per call",
                f"pass at most {MAX_BATCH_SIZE} at a time, or stream them with iter_sequence(..., tasks=['depth'])",
            )
        if camera_height is not None:
            camera = with_assumed(camera)  # the ground fit needs K: the assumed one where none was given
            check_metric_request(camera_height, camera)
        timer = StageTimer()
        rgbs = [read_frame(img, timer, i)[0] for i, img in enumerate(images)]
        cameras = [camera_at(camera, r.shape[:2]) for r in rgbs]
        x = np.stack([to_network(self.spec, r, c, timer) for r, c in zip(rgbs, cameras)])
        with timer.stage("depthnet"):
            disparity = self.graph_set.run("depthnet", image=x)["disparity"][:, 0]
        results = []
        with timer.stage("postprocess"):
            for i, (d, r, c) in enumerate(zip(disparity, rgbs, cameras)):
                depth, disp = disparity_to_input(d, r.shape[:2])
                scale = None
                if camera_height is not None:
                    assert c is not None  # check_metric_request refused a missing camera
                    try:
                        scale = fit_ground_plane(depth, c.K).scale_for(camera_height)
                    except GeoNetError as err:
                        raise InputError(f"image {i}", err.problem, err.hint) from None
                    depth, disp = depth * scale, disp / scale
                results.append((depth, disp, bool(c and c.has_distortion), scale, None if c is None else c.K))
        timings = timer.result(1.0 / len(images))
        out = [
            DepthResult(depth=d, disparity=p, undistorted=u, timings_ms=dict(timings), metric_scale=m, intrinsics=k)
            for d, p, u, m, k in results
        ]
        return out[0] if single else out

    # ------------------------------------------------------------------ pose
    def pose(self, frames: Sequence[ImageLike], camera: Intrinsics | None = None) -> PoseResult:
        """Poses of one snippet: ``seq_length`` consecutive frames in temporal order, target in the middle.

        A pair [t, t+1] is padded to a snippet as at a sequence start (see
        ``cascade.snippet_indices``). ``camera`` only matters for undistortion.
        """
        require_graphs("pose", TASK_GRAPHS["pose"], self.graphs, self.model_dir)
        timer = StageTimer()
        x, _, _ = load_snippet(self.spec, frames, camera, timer)
        with timer.stage("posenet"):
            order = posenet_order(len(x) // 2, len(x))
            out = self.graph_set.run("posenet", snippet=np.concatenate([x[i] for i in order])[None])
        return PoseResult(
            matrices=out["pose_matrix"][0].astype(np.float64), vectors=out["pose"][0], timings_ms=timer.result()
        )

    # ------------------------------------------------------------------ flow
    def flow(self, frames: Sequence[ImageLike], camera: Intrinsics | None = None, **deprecated: Any) -> FlowResult:
        """Flow from the target (middle frame of the snippet) to the frame after it.

        Args:
            frames: ``seq_length`` consecutive frames (target in the middle), or a
                pair [t, t+1] (padded as at a sequence start).
            camera: (3, 3) intrinsics at the frames' resolution, or a Camera (``K=`` is a
                deprecated alias).
        Needs the depthnet, posenet and rigidflow graphs; without resflownet, flow = rigid flow.
        """
        camera = _camera_keyword(camera, deprecated, "flow")
        require_graphs("flow", RIGID_FLOW_GRAPHS, self.graphs, self.model_dir)
        timer = StageTimer()
        x, cam, size = load_snippet(self.spec, frames, with_assumed(camera), timer)
        assert cam is not None  # with_assumed gave one
        parts = run_cascade(self.graph_set, self.spec, x[None], [len(x) // 2], cam.K, size, timer=timer)
        with timer.stage("postprocess"):
            depth, _ = disparity_to_input(parts["disparity"][0], size)
            flow, rigid_at_input = flows_to_input(parts, 0, size)
            rigid_flow = flow if rigid_at_input is None else rigid_at_input()
            residual_flow = None if rigid_at_input is None else flow - rigid_flow
        return FlowResult(
            depth=depth,
            pose=parts["pose_matrix"][0].astype(np.float64),
            undistorted=cam.has_distortion,
            timings_ms=timer.result(),
            flow=flow,
            rigid_flow=rigid_flow,
            residual_flow=residual_flow,
            intrinsics=cam.record(),
        )

    # ------------------------------------------------------------------ sequences
    def iter_sequence(
        self,
        frames: Iterable[ImageLike],
        camera: Intrinsics | None = None,
        *,
        batch_size: int = DEFAULT_BATCH_SIZE,
        names: Sequence[str] | None = None,
        with_flow: bool = True,
        camera_height: float | None = None,
        tasks: Iterable[str] = TASKS,
        check: bool = True,
        flow_method: str = "network",
        pose_method: str = "network",
        scale_smoothing: int = SCALE_HALF_WINDOW,
        output_size: str = "input",
        **deprecated: Any,
    ) -> Iterator[FrameResult]:
        """Stream a whole sequence: yields one :class:`FrameResult` per frame, in order.

        Each frame's depth is computed once (one DepthNet batch per ``batch_size``
        frames) and reused by the rigid-flow op of the pair it is the target of.
        Pose and flow of frame t come from the snippet centred on t (ends
        replicated, see ``cascade.snippet_indices``) towards t + 1; the last
        frame has depth and a pose but no flow. Poses are chained into one
        trajectory: camera_to_world[t + 1] = camera_to_world[t] @ inv(T_t->t+1).
        Frames are read lazily (an iterator of frames or paths is fine).
        ``camera``: (3, 3) K at the frames' resolution or a Camera (``K=`` is a deprecated alias).
        ``tasks``: any of "depth", "pose", "flow"; a task left out is not computed (its
        fields are None; without "pose" every camera_to_world is the identity), so a model
        lacking a graph runs the tasks it has; depth alone also runs on a single frame. "flow"
        needs depthnet, posenet and rigidflow (without resflownet, flow = rigid flow).
        ``with_flow=False`` drops "flow" (depth and poses only; camera may then be None, or a
        Camera used only to undistort).
        ``camera_height`` (metres, needs the camera and depthnet) makes each frame's depth and its
        pose translation metric (:func:`geonet_infer.core.scale.metric_frames`: each frame's ground-fit
        factor, ``metric_scale_raw``, smoothed over ``scale_smoothing`` frames each side into
        ``metric_scale``; frames come that many frames late; 0 = each frame's own fit).
        ``flow_method="dis"`` / ``pose_method="orbvo"``: flow from OpenCV DIS, poses from ORB-VO
        instead of the networks (:mod:`geonet_infer.classical`; with DIS, ``rigid_flow`` is the
        DIS flow and ``residual_flow`` None).
        ``check`` (with flow): each frame's ``check`` says whether its flow and rigid flow explain
        the next frame better than no motion (:mod:`geonet_infer.core.check`; about 1 ms a frame).
        ``output_size="network"``: depth and flow stay at the network's size (flow in its pixels, each
        result's ``intrinsics`` K scaled to that size): no interpolation, a fraction of the bytes to write;
        the network's own methods only (DIS and ORB-VO work at the input's size).
        A missing graph or a bad request raises here, before any frame is read.
        """
        camera = _camera_keyword(camera, deprecated, "iter_sequence")
        check_output_size(output_size, flow_method, pose_method)
        check_batch_size(batch_size)
        check_methods(flow_method, pose_method)
        asked = tuple(tasks)
        classical = classical_tasks(asked, flow_method, pose_method)
        self.require_tasks(t for t in asked if t != "flow" and t not in classical)  # unknown tasks too
        tasks = tuple(t for t in TASKS if t in asked and (with_flow or t != "flow"))
        if "flow" in tasks and "flow" not in classical:
            require_graphs("flow", RIGID_FLOW_GRAPHS, self.graphs, self.model_dir)
        if "pose" in classical:
            require_graphs("pose", CLASSICAL_GRAPHS["pose"], self.graphs, self.model_dir)
        if needs_intrinsics(tasks, flow_method, pose_method) or camera_height is not None:
            camera = with_assumed(camera)  # never stop for missing intrinsics: the rule, recorded
        if camera_height is not None:
            require_graphs(METRIC_TASK, TASK_GRAPHS["depth"], self.graphs, self.model_dir)
            check_metric_request(camera_height, camera)
            ScaleSmoother(scale_smoothing)  # refuses a bad window now, not at the first frame
        kept = KeptFrames(frames) if classical else None
        results = iter_frames(
            self.graph_set,
            self.spec,
            frames if kept is None else kept,
            camera,
            batch_size=batch_size,
            names=names,
            tasks=tuple(t for t in tasks if t not in classical),
            need_depth=camera_height is not None or "pose" in classical,
            check=check,
            output_size=output_size,
            workers=self.workers,
        )
        if camera_height is not None:
            metric_camera = camera
            assert metric_camera is not None  # check_metric_request refused a missing camera
            results = metric_frames(
                results, camera_height, lambda size: camera_at(metric_camera, size).K, scale_smoothing
            )
        if kept is not None:
            check_size = (self.spec.height, self.spec.width) if check and flow_method == "dis" else None
            results = classical_frames(results, kept, camera, flow_method, pose_method, check_size)
        return results

    def predict_sequence(
        self,
        frames: Iterable[ImageLike],
        camera: Intrinsics | None = None,
        *,
        batch_size: int = DEFAULT_BATCH_SIZE,
        camera_height: float | None = None,
        check: bool = True,
        flow_method: str = "network",
        pose_method: str = "network",
        scale_smoothing: int = SCALE_HALF_WINDOW,
        **deprecated: Any,
    ) -> SequenceResult:
        """All of :meth:`iter_sequence` in memory (mind the size of flow for long videos);
        ``SequenceResult.check`` sums up the frames' flow checks."""
        camera = _camera_keyword(camera, deprecated, "predict_sequence")
        if needs_intrinsics(TASKS, flow_method, pose_method) or camera_height is not None:
            camera = with_assumed(camera)  # as iter_sequence does; here to record it in the result
        results = list(
            self.iter_sequence(
                frames,
                camera,
                batch_size=batch_size,
                camera_height=camera_height,
                flow_method=flow_method,
                pose_method=pose_method,
                scale_smoothing=scale_smoothing,
                check=check,
            )
        )
        totals: dict[str, float] = defaultdict(float)
        for r in results:
            for stage, ms in r.timings_ms.items():
                totals[stage] += ms
        depth = results[0].depth if results else None
        used = None if camera is None or depth is None else camera_at(camera, depth.shape).record()
        return SequenceResult(frames=results, timings_ms=dict(totals), intrinsics=used)
