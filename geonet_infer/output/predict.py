"""Run the predictor over one frame source and write the standard output layout.

``geonet-infer predict`` is a thin CLI over :func:`predict_to_dir`; batch jobs reuse it so every
sequence gets the same layout (:mod:`geonet_infer.output.layout`, one entry per file).

Every file is written under a temporary name and renamed, so a reader never sees a
half-written file. A frame that cannot be read, has another size than most of the first
frames, or for which the model gives NaN/inf is recorded in the summary and skipped; the
sequence goes on with the next frame. ``exclusive=True`` (the ``predict`` command) also makes
OUT a folder of one run (:class:`geonet_infer.output.ownership.OwnedFolder`): a marker
``OUT/.geonet-predict`` lists the files the run may write, a lock file keeps a second run out,
and the next run removes exactly the listed files of the previous one before writing.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import platform
import sys
import time
from collections import defaultdict
from collections.abc import Collection
from pathlib import Path

import cv2
import numpy as np

from geonet_infer import __version__
from geonet_infer.classical import check_methods, classical_tasks
from geonet_infer.classical import describe as describe_methods
from geonet_infer.conventions import KITTI_HEIGHT, KITTI_WIDTH
from geonet_infer.core.cascade import camera_at
from geonet_infer.core.check import AGREE_PX, METHOD, FrameCheck, SequenceCheck
from geonet_infer.core.predictor import Predictor
from geonet_infer.core.results import FrameResult
from geonet_infer.core.scale import SCALE_HALF_WINDOW, ScaleSmoother, check_metric_request, metric_scale_summary
from geonet_infer.core.tasks import TASKS, needs_intrinsics
from geonet_infer.engines.cpu import isa_line
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.io.calib import Camera, write_kitti_camera
from geonet_infer.io.camera import assumed_camera
from geonet_infer.io.frames import FrameSource
from geonet_infer.io.poses import write_kitti_poses, write_tum_poses
from geonet_infer.limits import DEFAULT_BATCH_SIZE, MAX_HELD_PIXELS, check_batch_size
from geonet_infer.models.manifest import model_notice
from geonet_infer.output import ownership
from geonet_infer.output.clouds import WorldCloud, as_predicted
from geonet_infer.output.frames import GoodFrames, unusable
from geonet_infer.output.latency import latency_table, timed
from geonet_infer.output.layout import (
    CAMERA_NAME,
    OUTPUT_LOCK,
    OUTPUT_MARKER,
    POSE_FILES,
    SUMMARY_NAME,
    VIS_OUTPUTS,
    WORLD_CLOUD_NAME,
    chosen_outputs,
    frame_files,
    listed_outputs,
    run_files,
    written_summary,
)
from geonet_infer.output.options import OutputOptions
from geonet_infer.output.rerun_recording import RerunRecording, check_rerun_path, require_rerun
from geonet_infer.output.video import FOLDER_FPS, VideoOut
from geonet_infer.output.viz import SteadyScale
from geonet_infer.output.writer import FrameWriter, Written


def predict_to_dir(
    predictor: Predictor,
    source: FrameSource,
    out_dir: str | Path,
    camera: Camera | None = None,
    tasks: tuple[str, ...] | None = TASKS,
    batch_size: int = DEFAULT_BATCH_SIZE,
    progress: bool = True,
    camera_height: float | None = None,
    vis: bool = True,
    exclusive: bool = False,
    outputs: Collection[str] | None = None,
    extra_outputs: tuple[str, ...] = (),
    options: OutputOptions = OutputOptions(),
    max_frames: int | None = None,
    check: bool = True,
    flow_method: str = "network",
    pose_method: str = "network",
    scale_smoothing: int = SCALE_HALF_WINDOW,
    claimed_by: tuple[str, ...] = (),
) -> dict:
    """Predict every frame of ``source`` into ``out_dir`` (the files of :mod:`geonet_infer.output.layout`).

    Args:
        predictor: a loaded :class:`~geonet_infer.core.predictor.Predictor`.
        source: frames from :func:`geonet_infer.io.frames.open_frames`.
        camera: intrinsics (and distortion) of the frames; required for "flow".
        tasks: any of "depth", "pose", "flow" (each needs its graphs, else GeoNetError before
            anything is written); None: all the model can do, the others in ``skipped_tasks``.
        camera_height: metres above a flat road: metric depth and pose translations
            (:mod:`geonet_infer.core.scale`; needs ``camera``).
        vis: also write the depth colour maps and flow colour wheels (PNG encoding of
            pictures is most of the write time; fleets that only need the data skip it).
        outputs: the --outputs names to write (:data:`geonet_infer.output.layout.OUTPUT_NAMES`); None:
            the default set (:data:`~geonet_infer.output.layout.DEFAULT_OUTPUTS`); ``vis=False`` drops
            the colour maps from either. An output of a task that does not run is not written.
        exclusive: own ``out_dir`` for this run (:class:`geonet_infer.output.ownership.OwnedFolder`): refuse a
            non-empty folder predict did not write or one another predict is writing, remove the previous run's files.
        extra_outputs: more files (relative to ``out_dir``) the caller writes there, recorded as
            this run's (``exclusive`` only).
        options: point clouds, the colour scale of the pictures, a result video (:class:`OutputOptions`).
        max_frames: stop after this many good frames (live sources).
        check: check each flow against the frames (``summary["check"]``, :mod:`geonet_infer.core.check`).
        flow_method, pose_method: "network", or "dis" / "orbvo" (:mod:`geonet_infer.classical`).
        scale_smoothing: frames each side over which the camera-height scale is smoothed (0: none).
        claimed_by: (``exclusive``) the marker names of a caller that owns ``out_dir`` and locks it
            (batch): then no pid lock, and those files are never touched.
    Returns:
        The summary (also written to ``out_dir/summary.json``); ``summary["failed"]`` counts bad
        frames (unreadable, odd size, NaN/inf output, or missing from a truncated video).
    Raises:
        GeoNetError for unusable input (no intrinsics for flow, fewer than 2 good frames
        for pose/flow, no readable frame at all, intrinsics that do not fit the frames' size).
        KeyboardInterrupt (Ctrl-C, or SIGTERM where the caller maps it) after writing a summary
        with ``"interrupted": true`` for the frames written so far; no temp file is left.
    """
    out_dir = Path(out_dir)
    chosen = chosen_outputs(outputs, vis)
    check_batch_size(batch_size)
    check_methods(flow_method, pose_method)
    if camera_height is not None:
        ScaleSmoother(scale_smoothing)  # a bad window is the user's error, before any frame is read
    tasks, skipped_tasks = predictor.resolve_tasks(  # None: all it can
        tasks, metric=camera_height is not None, classical=classical_tasks(tasks or TASKS, flow_method, pose_method)
    )
    if camera is None and (needs_intrinsics(tasks, flow_method, pose_method) or camera_height or options.point_cloud):
        camera = assumed_camera(KITTI_WIDTH, KITTI_HEIGHT)  # never stop: the stated rule, follows the frames' size
    if camera_height is not None:
        check_metric_request(camera_height, camera, source.path)
    if options.point_cloud and "depth" not in tasks:
        raise InputError(source.path, "point clouds need depth", "keep depth in --tasks")
    if options.point_cloud == "world" and "pose" not in tasks:
        raise InputError(
            source.path, "a world point cloud needs poses", "keep pose in --tasks, or use --point-cloud camera"
        )
    if options.rerun is not None:
        require_rerun()
        check_rerun_path(Path(options.rerun), out_dir)
    video = None if options.video_out is None else Path(options.video_out)
    video_in_out = video is not None and ownership.inside(video, out_dir)  # symlinks resolved
    if video is not None and not exclusive and video.exists():
        raise ownership.not_written(video)
    run = functools.partial(
        _predict,
        predictor, source, out_dir, camera, tasks, batch_size, progress, camera_height, chosen,
        skipped_tasks=skipped_tasks, options=options, max_frames=max_frames, check=check,
        methods=(flow_method, pose_method, scale_smoothing),
    )  # fmt: skip
    if not exclusive:
        out_dir.mkdir(parents=True, exist_ok=True)
        return run(owned=None)
    # A video's names are claimed in blocks as it decodes (emit), never sized by its header's count.
    names = source.frame_names if source.frame_names is not None else [f"{i:06d}" for i in range(VIDEO_CLAIM)]
    files = run_files(tasks, options.point_cloud, camera is not None, chosen) | set(extra_outputs)
    if video is not None and video_in_out:
        files.add(os.path.relpath(ownership.real(video), ownership.real(out_dir)))
    if options.rerun is not None and ownership.inside(Path(options.rerun), out_dir):
        files.add(os.path.relpath(ownership.real(Path(options.rerun)), ownership.real(out_dir)))
    files |= set().union(*(frame_files(name, tasks, chosen, options.point_cloud) for name in names))
    inputs = tuple(getattr(source, "files", None) or ([Path(source.path)] if source.kind == "video" else []))
    outside = video if video is not None and not video_in_out else None
    owned = ownership.OwnedFolder(
        out_dir,
        files,
        source.location,
        marker=OUTPUT_MARKER,
        lock=OUTPUT_LOCK,
        record={"written_by": "geonet-infer predict", "version": __version__},
        inputs=inputs,
        outside=outside,
        claimed_by=claimed_by,
    )
    with owned:
        return run(owned=owned)


VIDEO_CLAIM = 256  # frame names of a video claimed before it is decoded (then more as it decodes)


def _output_size(mode: str, input_hw: tuple[int, int] | None, network_hw: tuple[int, int]) -> dict:
    """summary.json's record of where depth and flow are: their size, and how to scale them to the input
    (flow u, v and pixel coordinates x multiply by ``to_input``)."""
    if mode == "input" or input_hw is None:
        return {"mode": mode, "size": None if input_hw is None else [input_hw[1], input_hw[0]], "to_input": [1.0, 1.0]}
    (h, w), (H, W) = network_hw, input_hw
    return {"mode": mode, "size": [w, h], "to_input": [W / w, H / h]}


def _at_size(keep, size: tuple[int, int], frame):
    """The kept frame resized to (W, H) (``--output-size network``)."""
    rgb = keep(frame)
    return rgb if rgb is None or rgb.shape[1::-1] == size else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def _predict(
    predictor: Predictor,
    source: FrameSource,
    out_dir: Path,
    camera: Camera | None,
    tasks: tuple[str, ...],
    batch_size: int,
    progress: bool,
    camera_height: float | None,
    outputs: frozenset[str],
    *,
    owned: ownership.OwnedFolder | None,
    skipped_tasks: dict[str, tuple[str, ...]],
    options: OutputOptions,
    max_frames: int | None,
    check: bool,
    methods: tuple[str, str, int],
) -> dict:
    from tqdm import tqdm

    started = time.perf_counter()
    totals: dict[str, float] = defaultdict(float)
    sizes: dict[str, int] = defaultdict(int)  # bytes written per layout pattern
    poses: list[np.ndarray] = []
    pose_names: list[str] = []
    done = 0
    scales: dict[str, list] = {"frames": [], "raw": [], "smoothed": []}
    checks: list[tuple[str, FrameCheck]] = []
    interrupted = False

    def check_camera(width: int, height: int) -> None:
        if camera is not None:
            camera.scaled_to(width, height).check_image_size(width, height, camera.source or None)

    bar = tqdm(total=len(source) or None, unit="frame", desc=source.name, disable=not progress, leave=False)
    keep = None
    if options.point_cloud or options.video_out is not None or options.rerun is not None:  # frames kept
        keep = functools.partial(as_predicted, camera)
        if options.output_size == "network":  # pictures, point colours and video at the outputs' size
            keep = functools.partial(_at_size, keep, (predictor.spec.width, predictor.spec.height))
    one_size = bool({"pose", "flow"} & set(tasks))  # depth alone needs no snippets: photos of any size
    frames = GoodFrames(source, bar, check_camera, max_frames, keep, one_size)
    colours = SteadyScale(options.colour_scale)
    pictures = bool(outputs & set(VIS_OUTPUTS)) or options.video_out is not None
    if not pictures:
        colours.finish()  # no pictures to scale: no frame waits for the scale, none is observed for it
    waiting: list[FrameResult] = []  # predicted, waiting for the colour scale ("first:N")
    world = WorldCloud(options) if options.point_cloud == "world" else None
    video = None
    if options.video_out is not None:
        video = VideoOut(Path(options.video_out), options.video_fps or getattr(source, "fps", None) or FOLDER_FPS)
    recording = None if options.rerun is None else RerunRecording(Path(options.rerun))

    def record(result: FrameResult, rgb: np.ndarray | None, written: Written) -> None:
        nonlocal done
        totals["write"] += written.ms
        totals["write_cpu"] += written.cpu_ms
        for name, size in written.sizes.items():
            sizes[name] += size
        if video is not None and rgb is not None:
            with timed(totals, "video"):
                video.write(rgb, written.pictures)
        if recording is not None:
            with timed(totals, "rerun"):
                recording.frame(result, rgb)
        if world is not None and rgb is not None and written.points is not None:
            with timed(totals, "world_cloud"):
                world.add(result, *written.points)
        poses.append(result.camera_to_world)
        pose_names.append(result.name)
        if result.metric_scale is not None:
            scales["frames"].append(result.name)
            scales["raw"].append(result.metric_scale_raw)
            scales["smoothed"].append(result.metric_scale)
        for stage, ms in result.timings_ms.items():
            if stage != "total":  # the table's total is the wall time (latency_table)
                totals[stage] += ms
        done += 1
        bar.set_postfix(done=done, failed=len(frames.failures), refresh=False)

    writer = FrameWriter(out_dir, tasks, outputs, record, options, camera_height, pictures=pictures)

    def emit(ready: list[FrameResult]) -> None:
        scale = colours.scales()
        while ready:
            result = ready.pop(0)  # before it is handed on: an interrupt here never submits it twice
            rgb = frames.kept.pop(result.index, None)
            if owned is not None and not frame_files(result.name, tasks, outputs, options.point_cloud) <= owned.files:
                # a video's next block of frames (as many as claimed so far: one marker write per doubling)
                block = [result.name] + [f"{i:06d}" for i in range(result.index, 2 * result.index + VIDEO_CLAIM)]
                owned.add(set().union(*(frame_files(n, tasks, outputs, options.point_cloud) for n in block)))
            writer.submit(result, scale, rgb)

    try:
        results = predictor.iter_sequence(
            frames,
            camera,
            batch_size=batch_size,
            names=frames.names,
            tasks=tasks,
            camera_height=camera_height,
            check=check,
            flow_method=methods[0],
            pose_method=methods[1],
            scale_smoothing=methods[2],
            output_size=options.output_size,
        )
        for result in results:
            with timed(totals, "finite_check"):
                bad = unusable(result, tasks)
            if bad is not None:
                frames.failures.append({"frame": result.name, "reason": f"model produced {bad}"})
                frames.kept.pop(result.index, None)
                continue
            if result.check is not None:
                checks.append((result.name, result.check))
            if pictures:
                with timed(totals, "colour_scale"):
                    colours.observe(
                        result.depth if "depth" in tasks else None, result.flow if "flow" in tasks else None
                    )
            waiting.append(result)
            if not colours.ready and len(waiting) * np.prod(frames.size or (0,)) > MAX_HELD_PIXELS:
                colours.finish()  # "first:N" of huge frames: the scale from the frames memory holds
            if colours.ready:
                emit(waiting)
        colours.finish()
        emit(waiting)
        writer.drain()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: a summary of what was written, then stop
        interrupted = True
        with contextlib.suppress(KeyboardInterrupt):  # frames already predicted are finished
            colours.finish()
            emit(waiting)
            writer.drain()
    except GeoNetError as exc:
        if done == 0 and frames.size is None:
            raise InputError(
                source.path, "no readable frame", "; ".join(f["reason"] for f in frames.failures[:3]) or str(exc)
            ) from None
        raise
    finally:
        writer.close()
        bar.close()
        totals["read"] += frames.read_ms
        totals["write_wait"] += writer.waited_ms
        if video is not None:
            with timed(totals, "video"):
                video.close(keep=done > 0 and sys.exc_info()[0] is None)
        if recording is not None:
            with timed(totals, "rerun"):
                recording.close(keep=done > 0 and sys.exc_info()[0] is None)
    if owned is not None and video is not None and video.frames:
        owned.video_written(video.path)
    if world is not None:
        with timed(totals, "world_cloud"):
            world.write(out_dir / WORLD_CLOUD_NAME, camera_height)
    finish = time.perf_counter()
    if camera is not None and frames.size is not None:
        height, width = frames.size
        write_kitti_camera(out_dir / CAMERA_NAME, camera_at(camera, frames.size).K, width, height)
    truncated = None if interrupted else getattr(source, "truncated", None)
    if truncated:
        reason = f"{source.location}: truncated: {truncated}"
        frames.failures += [{"frame": name, "reason": reason} for name in getattr(source, "missing", ())]
    if "pose" in tasks and "poses" in outputs and poses:
        fps, layout = getattr(source, "fps", None), getattr(source, "layout", None)
        stamps = None if layout is None else layout.frame_times(pose_names)  # the dataset's own times
        if stamps is None:
            stamps = np.arange(len(poses)) / fps if fps else np.arange(len(poses), dtype=np.float64)
        write_kitti_poses(out_dir / POSE_FILES[0], np.stack(poses))
        write_tum_poses(out_dir / POSE_FILES[1], stamps, np.stack(poses))
    totals["finish"] += (time.perf_counter() - finish) * 1e3
    elapsed = time.perf_counter() - started
    sequential, overlapped = latency_table(totals, done, elapsed)
    summary = {
        "input": {
            "path": source.location,
            "kind": source.kind,
            "name": source.name,
            "fps": getattr(source, "fps", None),
        },
        "frames": done,
        "failed": len(frames.failures),
        "failures": frames.failures,
        "gaps": [{"frame": k, "skipped_before": v} for k, v in frames.skipped_before.items()],
        "interrupted": interrupted,
        "truncated": truncated,
        "notes": [] if interrupted or not getattr(source, "ended_early", None) else [source.ended_early],
        "tasks": list(tasks),
        "skipped_tasks": {task: list(graphs) for task, graphs in skipped_tasks.items()},  # tasks=None only
        "outputs": listed_outputs(tasks, outputs, options.point_cloud, camera is not None),
        "written": written_summary(out_dir, sizes, run_files(tasks, options.point_cloud, True, outputs), done),
        "colour_scale": colours.describe() if pictures else None,
        "point_cloud": None
        if not options.point_cloud
        else {
            "mode": options.point_cloud,
            "stride": options.point_stride,
            "max_depth": options.max_depth,
            "units": "metres" if camera_height is not None else "relative scale",
        },
        "video": None if video is None else {"path": str(options.video_out), "frames": video.frames, "fps": video.fps},
        "rerun": None
        if recording is None
        else {"path": str(options.rerun), "frames": recording.frames, "bytes": recording.bytes},
        "model": {
            "dir": str(predictor.model_dir),
            "arch": predictor.manifest.arch,
            "precision": predictor.precision,
            "graphs": predictor.graph_set.runs,  # per graph: engine, precision and why
            "isa": isa_line(),
            "threads": predictor.threads,
            "mode": predictor.mode,  # latency | throughput (geonet_infer.core.predictor.MODES)
            "workers": predictor.workers,  # sequence batches computed at once
            "batch_size": batch_size,  # frames per graph call: memory grows with it (geonet_infer.limits)
            "graph_size": [predictor.spec.height, predictor.spec.width],
            "random_init": predictor.manifest.random_init,
        },
        "model_notice": model_notice(predictor.manifest),  # synthetic-only model: how it does on real video
        "camera": None
        if camera is None
        else {
            "K_input_resolution": (camera_at(camera, frames.size).K.tolist() if frames.size else camera.K.tolist()),
            **(camera_at(camera, frames.size) if frames.size else camera).record(),  # K, size, source, origin
            "undistorted": camera.has_distortion,
        },
        "image_size": None if frames.size is None else [frames.size[1], frames.size[0]],
        "output_size": _output_size(options.output_size, frames.size, predictor.spec.size),
        "methods": describe_methods(tasks, methods[0], methods[1]),
        "metric_scale": None if camera_height is None else metric_scale_summary(camera_height, methods[2], scales),
        "check": check_summary(checks, predictor) if check and "flow" in tasks else None,
        "timings_ms_per_frame": sequential,  # the main thread's stages: they add up to "total", the wall time
        "overlapped_ms_per_frame": overlapped,  # the writer threads, alongside them
        "wall_s": elapsed,
        "frames_per_s": done / elapsed if elapsed > 0 else None,
        "versions": {"geonet_infer": __version__, "python": platform.python_version()},
    }
    with atomic_write(out_dir / SUMMARY_NAME) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    if interrupted:
        raise KeyboardInterrupt
    return summary


def check_summary(checks: list[tuple[str, FrameCheck]], predictor: Predictor) -> dict:
    """summary.json's "check": the pairs summed up (:class:`SequenceCheck`), then each pair."""
    return {
        "method": METHOD,
        "size": [predictor.spec.height, predictor.spec.width],
        "agree_px": AGREE_PX,
        **SequenceCheck.from_checks(c for _, c in checks).as_dict(),
        "per_pair": [{"frame": name, **c.as_dict()} for name, c in checks],
    }
