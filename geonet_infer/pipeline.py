"""Run the predictor over one frame source and write the standard output layout.

``geonet-infer predict`` is a thin CLI over :func:`predict_to_dir`; batch jobs reuse it
so every sequence gets the same layout::

    OUT/depth/<frame>.npy        float32 depth (H, W) at the input resolution, relative scale
    OUT/depth/<frame>.png        colour map of inverse depth (near = bright)
    OUT/flow/<frame>.png         KITTI 16-bit flow PNG, frame -> next frame (not for the last frame)
    OUT/flow_vis/<frame>.png     flow colour wheel (Middlebury style)
    OUT/poses_kitti.txt          one line per frame: 3x4 camera-to-world, first frame = identity
    OUT/poses_tum.txt            one line per frame: time tx ty tz qx qy qz qw
    OUT/summary.json             counts, failures with reasons, per-stage timings, model, camera

Every file is written under a temporary name and renamed, so a reader never sees a
half-written file. A frame that cannot be read (or has another size than the first)
is recorded in the summary and skipped; the sequence goes on with the next frame.
"""

from __future__ import annotations

import json
import platform
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from geonet_infer import __version__
from geonet_infer.errors import GeoNetInputError
from geonet_infer.io.atomic import atomic_write, save_npy_atomic
from geonet_infer.io.calib import Camera
from geonet_infer.io.flow import write_flow_kitti
from geonet_infer.io.frames import FrameSource
from geonet_infer.io.images import write_image
from geonet_infer.io.poses import write_kitti_poses, write_tum_poses
from geonet_infer.predictor import FrameResult, Predictor, metric_frames
from geonet_infer.scale import check_metric_request
from geonet_infer.viz import depth_to_color, flow_to_color

TASKS = ("depth", "pose", "flow")
SUMMARY_NAME = "summary.json"


def parse_tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise GeoNetInputError(None, f"unknown task(s) {unknown or text!r}", f"choose from {','.join(TASKS)}")
    return tasks


def output_path(out_dir: Path, subdir: str, name: str, suffix: str) -> Path:
    """``out_dir/subdir/name+suffix``, refusing names that would leave ``out_dir``."""
    path = out_dir / subdir / f"{name}{suffix}"
    root = out_dir.resolve()
    if root not in path.resolve().parents or "/" in name or "\\" in name or name in ("", ".", ".."):
        raise GeoNetInputError(path, f"frame name {name!r} would write outside {out_dir}", "rename the input file")
    return path


class _Frames:
    """The source's good frames, in order; bad ones are recorded in ``failures`` and skipped."""

    def __init__(self, source: FrameSource, progress):
        self.source, self.progress = source, progress
        self.names: list[str] = []
        self.failures: list[dict] = []
        self.size: tuple[int, int] | None = None
        self.skipped_before: dict[str, list[str]] = {}  # good frame -> bad frames right before it

    def __iter__(self) -> Iterator[np.ndarray]:
        pending_bad: list[str] = []
        for frame in self.source:
            self.progress.update(1)
            if frame.error is not None:
                self.failures.append({"frame": frame.name, "reason": str(frame.error)})
                pending_bad.append(frame.name)
                continue
            if self.size is None:
                self.size = frame.rgb.shape[:2]
            elif frame.rgb.shape[:2] != self.size:
                h, w = frame.rgb.shape[:2]
                self.failures.append(
                    {"frame": frame.name, "reason": f"frame is {w}x{h}, the sequence is {self.size[1]}x{self.size[0]}"}
                )
                pending_bad.append(frame.name)
                continue
            if pending_bad and self.names:
                self.skipped_before[frame.name] = pending_bad
            pending_bad = []
            self.names.append(frame.name)
            yield frame.rgb


def predict_to_dir(
    predictor: Predictor,
    source: FrameSource,
    out_dir: str | Path,
    camera: Camera | None = None,
    tasks: tuple[str, ...] = TASKS,
    batch_size: int = 4,
    progress: bool = True,
    camera_height: float | None = None,
    vis: bool = True,
) -> dict:
    """Predict every frame of ``source`` into ``out_dir`` (layout in the module docstring).

    Args:
        predictor: a loaded :class:`~geonet_infer.predictor.Predictor`.
        source: frames from :func:`geonet_infer.io.frames.open_frames`.
        camera: intrinsics (and distortion) of the frames; required for "flow".
        tasks: any of "depth", "pose", "flow".
        camera_height: metres above a flat road: metric depth and pose translations
            (:mod:`geonet_infer.scale`; needs ``camera``).
        vis: also write the depth colour maps and flow colour wheels (PNG encoding of
            pictures is most of the write time; fleets that only need the data skip it).
    Returns:
        The summary (also written to ``out_dir/summary.json``); ``summary["failed"]`` counts bad frames.
    Raises:
        GeoNetInputError for unusable input (no intrinsics for flow, fewer than 2 good frames
        for pose/flow, no readable frame at all).
    """
    from tqdm import tqdm

    out_dir = Path(out_dir)
    tasks = tuple(t for t in TASKS if t in tasks)
    if "flow" in tasks and camera is None:
        raise GeoNetInputError(
            source.path,
            "flow needs camera intrinsics and none were found",
            "pass --calib FILE or --intrinsics FX,FY,CX,CY (or --tasks depth,pose)",
        )
    check_metric_request(camera_height, camera, source.path)
    out_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    totals: dict[str, float] = defaultdict(float)
    poses: list[np.ndarray] = []
    done = 0
    scales: list[float] = []
    bar = tqdm(total=len(source) or None, unit="frame", desc=source.name, disable=not progress, leave=False)
    frames = _Frames(source, bar)
    try:
        if tasks == ("depth",):
            results = _depth_only(predictor, frames, camera, batch_size)
            if camera_height is not None:
                results = metric_frames(results, camera_height, lambda size: camera.scaled_to(size[1], size[0]).K)
        else:
            results = predictor.iter_sequence(
                frames,
                camera,
                batch_size=batch_size,
                names=frames.names,
                with_flow="flow" in tasks,
                camera_height=camera_height,
            )
        for result in results:
            t0 = time.perf_counter()
            _write_frame(out_dir, result, tasks, vis)
            totals["write"] += (time.perf_counter() - t0) * 1e3
            poses.append(result.camera_to_world)
            if result.metric_scale is not None:
                scales.append(result.metric_scale)
            for stage, ms in result.timings_ms.items():
                totals[stage] += ms
            done += 1
            bar.set_postfix(done=done, failed=len(frames.failures), refresh=False)
    except GeoNetInputError as exc:
        if done == 0 and frames.size is None:
            raise GeoNetInputError(
                source.path, "no readable frame", "; ".join(f["reason"] for f in frames.failures[:3]) or str(exc)
            ) from None
        raise
    finally:
        bar.close()
    totals["total"] += totals["write"]
    if "pose" in tasks and poses:
        fps = getattr(source, "fps", None)
        stamps = np.arange(len(poses)) / fps if fps else np.arange(len(poses), dtype=np.float64)
        write_kitti_poses(out_dir / "poses_kitti.txt", np.stack(poses))
        write_tum_poses(out_dir / "poses_tum.txt", stamps, np.stack(poses))
    elapsed = time.perf_counter() - started
    summary = {
        "input": {
            "path": str(source.path),
            "kind": source.kind,
            "name": source.name,
            "fps": getattr(source, "fps", None),
        },
        "frames": done,
        "failed": len(frames.failures),
        "failures": frames.failures,
        "gaps": [{"frame": k, "skipped_before": v} for k, v in frames.skipped_before.items()],
        "tasks": list(tasks),
        "outputs": _outputs(tasks, vis),
        "model": {
            "dir": str(predictor.model_dir),
            "arch": predictor.manifest.arch,
            "precision": predictor.precision,
            "threads": predictor.threads,
            "graph_size": [predictor.spec.height, predictor.spec.width],
            "random_init": predictor.manifest.random_init,
        },
        "camera": None
        if camera is None
        else {
            "K_input_resolution": (
                camera.scaled_to(frames.size[1], frames.size[0]).K.tolist() if frames.size else camera.K.tolist()
            ),
            "dist": None if camera.dist is None else camera.dist.tolist(),
            "source": camera.source,
            "undistorted": camera.has_distortion,
        },
        "image_size": None if frames.size is None else [frames.size[1], frames.size[0]],
        "metric_scale": None
        if camera_height is None
        else {
            "camera_height_m": camera_height,
            "per_frame_median": float(np.median(scales)) if scales else None,
            "per_frame_min": min(scales, default=None),
            "per_frame_max": max(scales, default=None),
        },
        "timings_ms_per_frame": {k: v / max(done, 1) for k, v in totals.items()},
        "wall_s": elapsed,
        "frames_per_s": done / elapsed if elapsed > 0 else None,
        "versions": {"geonet_infer": __version__, "python": platform.python_version()},
    }
    with atomic_write(out_dir / SUMMARY_NAME) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _outputs(tasks: tuple[str, ...], vis: bool = True) -> list[str]:
    out = []
    if "depth" in tasks:
        out += ["depth/*.npy"] + (["depth/*.png"] if vis else [])
    if "flow" in tasks:
        out += ["flow/*.png"] + (["flow_vis/*.png"] if vis else [])
    if "pose" in tasks:
        out += ["poses_kitti.txt", "poses_tum.txt"]
    return out


def _depth_only(predictor: Predictor, frames: _Frames, camera: Camera | None, batch_size: int) -> Iterator[FrameResult]:
    """Depth in batches of ``batch_size`` frames, in the model's relative scale; works on a single image too."""
    batch: list[np.ndarray] = []
    index = 0

    def flush():
        nonlocal index
        for rgb_result in predictor.depth(batch, camera=camera):
            yield FrameResult(
                index=index,
                name=frames.names[index],
                depth=rgb_result.depth,
                disparity=rgb_result.disparity,
                camera_to_world=np.eye(4),
                pose_to_next=None,
                pose_vector_to_next=None,
                flow=None,
                rigid_flow=None,
                residual_flow=None,
                undistorted=rgb_result.undistorted,
                timings_ms=rgb_result.timings_ms,
            )
            index += 1

    for rgb in frames:
        batch.append(rgb)
        if len(batch) == batch_size:
            yield from flush()
            batch = []
    if batch:
        yield from flush()


def _write_frame(out_dir: Path, result: FrameResult, tasks: tuple[str, ...], vis: bool = True) -> None:
    if "depth" in tasks:
        save_npy_atomic(output_path(out_dir, "depth", result.name, ".npy"), result.depth)
        if vis:
            write_image(output_path(out_dir, "depth", result.name, ".png"), depth_to_color(result.depth))
    if "flow" in tasks and result.flow is not None:
        write_flow_kitti(output_path(out_dir, "flow", result.name, ".png"), result.flow)
        if vis:
            write_image(output_path(out_dir, "flow_vis", result.name, ".png"), flow_to_color(result.flow))
