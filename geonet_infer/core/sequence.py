"""A whole sequence through the cascade (:func:`iter_frames`): each frame's depth once, the pose chained
by the one rule of :func:`geonet_infer.conventions.next_camera_to_world`."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from geonet_infer.conventions import next_camera_to_world
from geonet_infer.core.cascade import run_cascade
from geonet_infer.core.check import check_pair
from geonet_infer.core.graphs import GraphSet
from geonet_infer.core.results import FrameResult
from geonet_infer.core.snippets import snippet_window
from geonet_infer.core.spec import (
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
) -> Iterator[FrameResult]:
    """A sequence in the model's own (relative) scale, one :class:`FrameResult` per frame, in order.

    ``tasks`` (checked by the caller): of "depth", "pose", "flow". Each frame's depth is computed
    once (one DepthNet batch per ``batch_size`` frames) and reused by the rigid-flow op of the pair
    it is the target of; pose and flow of frame t come from the snippet centred on t (ends
    replicated, :func:`snippet_indices`) towards t + 1. Frames are read lazily, at most
    ``batch_size + seq_length // 2`` ahead. With pose or flow a sequence needs 2 frames of one size;
    depth alone runs on any number, each frame at its own size. ``need_depth``: depth is needed
    though not asked for (metric scale).
    ``check``: each flow is checked against the frames (:mod:`geonet_infer.core.check`, at the graph size).
    ``output_size``: "input" (depth and flow resized to each frame's size, K as given) or "network" (left at
    the graph's size, flow in graph pixels, ``intrinsics`` K scaled to that size: nothing is interpolated).
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
        disparity = None
        if run_depth:
            with timer.stage("depthnet"):
                images = np.stack([prepared[t] for t in batch])
                disparity = graphs.run("depthnet", image=images)["disparity"][:, 0]
        parts: dict[str, np.ndarray] = {}
        if paired:
            windows = [snippet_window(t, n_read, spec.seq_length) for t in paired]
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
        graph_size = (spec.height, spec.width)
        with timer.stage("postprocess"):
            for j, t in enumerate(batch):
                # the frame's own size (one size for a sequence with pose or flow), or the network's
                at = graph_size if output_size == "network" else sizes[t][0]
                depth, disp = (None, None) if disparity is None else disparity_to_input(disparity[j], at)
                flows = flows_to_input(parts, j, at) if t in paired and with_flow else no_flow
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
            frame_cam = at_cam = sizes[t][1]
            if at_cam is not None and output_size == "network":
                at_cam = camera_at(at_cam, graph_size)  # K where the outputs are
            yield FrameResult(
                index=t,
                name=frame_names.pop(t),
                depth=depth,
                disparity=disp,
                camera_to_world=pose_world.copy(),
                pose_to_next=pose_next,
                pose_vector_to_next=vector,
                undistorted=frame_cam is not None and frame_cam.has_distortion,
                timings_ms=dict(share),
                flow=flows[0],
                rigid_flow_at_input=flows[1],
                intrinsics=None if at_cam is None else at_cam.K,
                check=checks.get(t),
            )
            if pose_next is not None:
                pose_world = next_camera_to_world(pose_world, pose_next)
        t0 = batch[-1] + 1
        for i in [i for i in prepared if i < t0 - k]:
            del prepared[i], sizes[i]
