"""A whole sequence through the cascade (:func:`iter_frames`): each frame's depth once, the pose chained
by the one rule of :func:`geonet_infer.conventions.next_camera_to_world`."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from geonet_infer.conventions import next_camera_to_world
from geonet_infer.core.cascade import run_cascade
from geonet_infer.core.check import check_pair
from geonet_infer.core.graphs import GraphSet
from geonet_infer.core.results import FrameResult
from geonet_infer.core.snippets import snippet_window
from geonet_infer.core.spec import (
    CASCADE_THREADS,
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
from geonet_infer.errors import InputError
from geonet_infer.io.calib import Camera
from geonet_infer.limits import check_batch_size


# ----------------------------------------------------------------------------- sequences
@dataclass
class _Batch:
    """One batch of frames, everything its computation needs (the frames it reads are held here, so the
    reader may drop them), and what the computation gives back (``results``, ``checks``)."""

    frames: list[int]  # indices of the frames whose results this batch yields
    paired: list[int]  # those with a next frame: pose and flow
    images: dict[int, np.ndarray]  # prepared (3, h, w) frames: the batch's, its snippets' and each next frame
    windows: list[list[int]]  # snippet of each paired frame
    size: tuple[int, int]
    cam: Camera | None
    sizes: dict[int, tuple[tuple[int, int], Camera | None]]
    names: dict[int, str]
    read_timer: StageTimer  # this thread's stages: read and preprocess the frames, wait for the cascade
    timer: StageTimer = field(default_factory=StageTimer)  # the cascade's stages (a cascade thread's)
    results: list = field(default_factory=list)
    checks: dict[int, Any] = field(default_factory=dict)


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
    output_size: str = "input",
    workers: int = 1,
) -> Iterator[FrameResult]:
    """A sequence in the model's own (relative) scale, one :class:`FrameResult` per frame, in order.

    ``tasks`` (checked by the caller): of "depth", "pose", "flow". Each frame's depth is computed
    once (one DepthNet batch per ``batch_size`` frames) and reused by the rigid-flow op of the pair
    it is the target of; pose and flow of frame t come from the snippet centred on t (ends
    replicated, :func:`snippet_indices`) towards t + 1. Frames are read lazily, at most
    ``workers * batch_size + seq_length // 2`` ahead. With pose or flow a sequence needs 2 frames of one size;
    depth alone runs on any number, each frame at its own size. ``need_depth``: depth is needed
    though not asked for (metric scale).
    ``check``: each flow is checked against the frames (:mod:`geonet_infer.core.check`, at the graph size).
    ``output_size``: "input" (depth and flow resized to each frame's size, K as given) or "network" (left at
    the graph's size, flow in graph pixels, ``intrinsics`` K scaled to that size: nothing is interpolated).
    ``workers``: batches computed at once (throughput mode, :data:`geonet_infer.core.predictor.MODES`), each
    on its own thread through the same engines (onnxruntime and OpenVINO run concurrent calls); 1 computes
    one batch after the other. The batches, and so the graph calls, are the same either way; the poses are
    chained on this thread, in order.
    """
    check_batch_size(batch_size)
    flow_task = "flow" in tasks
    run_pose = "pose" in tasks or flow_task
    job = partial(
        _compute,
        graphs,
        spec,
        run_depth=need_depth or "depth" in tasks or flow_task,
        with_flow=flow_task,
        check=check and flow_task,
        output_size=output_size,
    )
    batches = _read_batches(spec, frames, camera, batch_size, names, run_pose, flow_task)
    if workers == 1:
        done: Iterator[_Batch] = (job(b) for b in batches)
    else:
        done = _in_order(job, batches, workers)
    pose_world = np.eye(4)
    for batch in done:
        share = _timings(batch, workers)
        for t, depth, disp, pose_next, vector, flows, at_cam, undistorted in batch.results:
            yield FrameResult(
                index=t,
                name=batch.names[t],
                depth=depth,
                disparity=disp,
                camera_to_world=pose_world.copy(),
                pose_to_next=pose_next,
                pose_vector_to_next=vector,
                undistorted=undistorted,
                timings_ms=dict(share),
                flow=flows[0],
                rigid_flow_at_input=flows[1],
                intrinsics=None if at_cam is None else at_cam.K,
                check=batch.checks.get(t),
            )
            if pose_next is not None:
                pose_world = next_camera_to_world(pose_world, pose_next)


def _timings(batch: _Batch, workers: int) -> dict[str, float]:
    """A frame's share of its batch's stage times. With several workers the cascade's stages ran on their
    threads, beside this one's: they are named :data:`CASCADE_THREADS` + stage and left out of ``total``."""
    share = 1.0 / len(batch.frames)
    if workers == 1:
        merged = StageTimer()
        for timer in (batch.read_timer, batch.timer):
            for stage, ms in timer.ms.items():
                merged.ms[stage] += ms
        return merged.result(share)
    return {
        **{CASCADE_THREADS + stage: ms * share for stage, ms in batch.timer.ms.items()},
        **batch.read_timer.result(share),
    }


def _in_order(job: Callable[[_Batch], _Batch], batches: Iterator[_Batch], workers: int) -> Iterator[_Batch]:
    """``job`` over ``batches`` on ``workers`` threads, ``workers`` batches in flight, yielded in order; the
    time this thread waits for each is its ``cascade_wait`` stage."""

    def wait(future: Future[_Batch]) -> _Batch:
        started = time.perf_counter()
        batch = future.result()
        batch.read_timer.ms["cascade_wait"] += (time.perf_counter() - started) * 1e3
        return batch

    with ThreadPoolExecutor(workers, thread_name_prefix="geonet-cascade") as pool:
        pending: deque[Future[_Batch]] = deque()
        try:
            for batch in batches:
                pending.append(pool.submit(job, batch))
                if len(pending) >= workers:
                    yield wait(pending.popleft())
            while pending:
                yield wait(pending.popleft())
        finally:  # a consumer that stops early (or an error) leaves no work queued
            for future in pending:
                future.cancel()


def _read_batches(
    spec: InputSpec,
    frames: Iterable[ImageLike],
    camera: Intrinsics | None,
    batch_size: int,
    names: Sequence[str] | None,
    run_pose: bool,
    with_flow: bool,
) -> Iterator[_Batch]:
    """Frames read, checked and prepared on this thread, grouped into the batches :func:`_compute` runs."""
    k = spec.seq_length // 2
    source = iter(frames)
    prepared: dict[int, np.ndarray] = {}
    frame_names: dict[int, str] = {}
    cam: Camera | None = None
    size: tuple[int, int] = (0, 0)
    sizes: dict[int, tuple[tuple[int, int], Camera | None]] = {}  # depth alone: each frame its own size
    n_read, exhausted = 0, False
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
                cam = camera_at(with_assumed(camera) if with_flow else camera, size)
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
        windows = [snippet_window(t, n_read, spec.seq_length) for t in paired]
        needed = set(batch).union(*windows, (t + 1 for t in paired))
        yield _Batch(
            frames=batch,
            paired=paired,
            images={i: prepared[i] for i in needed},
            windows=windows,
            size=size,
            cam=cam,
            sizes={t: sizes[t] for t in batch},
            names={t: frame_names.pop(t) for t in batch},
            read_timer=timer,
        )
        t0 = batch[-1] + 1
        for i in [i for i in prepared if i < t0 - k]:
            del prepared[i], sizes[i]


def _compute(
    graphs: GraphSet,
    spec: InputSpec,
    batch: _Batch,
    *,
    run_depth: bool,
    with_flow: bool,
    check: bool,
    output_size: str,
) -> _Batch:
    """The cascade, the outputs at their size and the flow check of one batch (any thread)."""
    k = spec.seq_length // 2
    timer, prepared, paired, size, cam = batch.timer, batch.images, batch.paired, batch.size, batch.cam
    disparity = None
    if run_depth:
        with timer.stage("depthnet"):
            images = np.stack([prepared[t] for t in batch.frames])
            disparity = graphs.run("depthnet", image=images)["disparity"][:, 0]
    parts: dict[str, np.ndarray] = {}
    if paired:
        with timer.stage("preprocess"):  # the snippets: timed, so the latency table adds up
            snippets = np.stack([np.stack([prepared[i] for i in w]) for w in batch.windows])
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
    no_flow: tuple[np.ndarray | None, Callable[[], np.ndarray] | None] = (None, None)
    graph_size = (spec.height, spec.width)
    with timer.stage("postprocess"):
        for j, t in enumerate(batch.frames):
            # the frame's own size (one size for a sequence with pose or flow), or the network's
            at = graph_size if output_size == "network" else batch.sizes[t][0]
            depth, disp = (None, None) if disparity is None else disparity_to_input(disparity[j], at)
            flows = flows_to_input(parts, j, at) if t in paired and with_flow else no_flow
            pose_next = parts["pose_matrix"][j].astype(np.float64) if t in paired else None
            vector = parts["pose"][j] if t in paired else None
            frame_cam = at_cam = batch.sizes[t][1]
            if at_cam is not None and output_size == "network":
                at_cam = camera_at(at_cam, graph_size)  # K where the outputs are
            undistorted = frame_cam is not None and frame_cam.has_distortion
            batch.results.append((t, depth, disp, pose_next, vector, flows, at_cam, undistorted))
    if check and paired:
        with timer.stage("check"):
            units = (size[1] / spec.width, size[0] / spec.height)  # input pixels per graph pixel
            rigid = parts["rigid_flow"].transpose(0, 2, 3, 1)
            full = parts["flow"].transpose(0, 2, 3, 1) if "flow" in parts else None
            for j, t in enumerate(paired):
                frame, after = spec.to_grey(prepared[t]), spec.to_grey(prepared[t + 1])
                batch.checks[t] = (
                    check_pair(frame, after, rigid[j], units=units)  # no ResFlowNet: the flow is rigid
                    if full is None
                    else check_pair(frame, after, full[j], rigid[j], units=units)
                )
    batch.images = {}  # what the batch held for the computation goes with it
    return batch
