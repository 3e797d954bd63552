"""Run the predictor over one frame source and write the standard output layout.

``geonet-infer predict`` is a thin CLI over :func:`predict_to_dir`; batch jobs reuse it
so every sequence gets the same layout::

    OUT/depth/<frame>.npy        float32 depth (H, W) at the input resolution, relative scale
    OUT/depth/<frame>.png        colour map of inverse depth (near = bright)
    OUT/flow/<frame>.png         KITTI 16-bit flow PNG, frame -> next frame (not for the last frame)
    OUT/flow_vis/<frame>.png     flow colour wheel (Middlebury style)
    OUT/poses_kitti.txt          one line per frame: 3x4 camera-to-world, first frame = identity
    OUT/poses_tum.txt            one line per frame: time tx ty tz qx qy qz qw
    OUT/summary.json             counts, failures with reasons, per-stage timings, model, camera,
                                 the output check (does the flow explain the next frame? geonet_infer.check)

Every file is written under a temporary name and renamed, so a reader never sees a
half-written file. A frame that cannot be read, has another size than most of the first
frames, or for which the model gives NaN/inf is recorded in the summary and skipped; the
sequence goes on with the next frame. ``exclusive=True`` (the ``predict`` command) also makes
OUT a folder of one run (:class:`_OwnedFolder`): a marker ``OUT/.geonet-predict`` lists the
files the run may write, a lock file keeps a second run out, and the next run removes exactly
the listed files of the previous one before writing.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import itertools
import json
import os
import platform
import sys
import tempfile
import time
from collections import Counter, defaultdict, deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer import __version__, ownership
from geonet_infer.cascade import camera_at
from geonet_infer.check import AGREE_PX, METHOD, FrameCheck, SequenceCheck
from geonet_infer.classical import check_methods, classical_tasks
from geonet_infer.classical import describe as describe_methods
from geonet_infer.cpu import isa_line
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import _umask, atomic_write, save_npy_atomic
from geonet_infer.io.calib import Camera, write_kitti_camera
from geonet_infer.io.flow import write_flow_kitti
from geonet_infer.io.frames import FrameSource
from geonet_infer.io.images import write_image
from geonet_infer.io.poses import write_kitti_poses, write_tum_poses
from geonet_infer.limits import MAX_BATCH_SIZE as MAX_BATCH_SIZE  # where callers of 0.x looked for it
from geonet_infer.limits import MAX_HELD_PIXELS, MAX_WORLD_POINTS, check_batch_size, check_fps
from geonet_infer.manifest import file_sha256, model_notice
from geonet_infer.points import write_ply
from geonet_infer.predictor import TASKS, Predictor
from geonet_infer.results import FrameResult
from geonet_infer.scale import SCALE_HALF_WINDOW, check_metric_request, metric_scale_summary
from geonet_infer.viz import SteadyScale, depth_to_color, flow_to_color, side_by_side

SUMMARY_NAME = "summary.json"
DEFAULT_COLOUR_SCALE = "first:8"
POINT_CLOUDS = ("camera", "world")
VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}  # what OpenCV's own FFmpeg writes everywhere
VIDEO_HEIGHT = 256  # panel height of the result video: three panels side by side stay under ~1400 px
FOLDER_FPS = 10.0  # the result video's rate for frame folders (KITTI raw is 10 Hz)
CAMERA_NAME = "camera.txt"
WORLD_CLOUD_NAME = "points_world.ply"
WRITE_THREADS = 2  # frames written while the next are predicted; colour maps and PNGs are most of the cost
SIZE_VOTE_FRAMES = 8  # the sequence's frame size is the one most of its first frames have
OUTPUT_MARKER = ".geonet-predict"  # JSON: the files the run that owns OUT may write
OUTPUT_LOCK = ".geonet-predict.lock"  # the pid of the run writing into OUT now
_POSE_FILES = ("poses_kitti.txt", "poses_tum.txt")


def parse_tasks(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if unknown or not tasks:
        raise InputError(None, f"unknown task(s) {unknown or text!r}", f"choose from {','.join(TASKS)}")
    return tasks


def output_path(out_dir: Path, subdir: str, name: str, suffix: str) -> Path:
    """``out_dir/subdir/name+suffix``, refusing names that would leave ``out_dir``."""
    path = out_dir / subdir / f"{name}{suffix}"
    root = out_dir.resolve()
    if root not in path.resolve().parents or "/" in name or "\\" in name or name in ("", ".", ".."):
        raise InputError(path, f"frame name {name!r} would write outside {out_dir}", "rename the input file")
    return path


class _Frames:
    """The source's good frames, in order; bad ones are recorded in ``failures`` and skipped.

    The sequence's size is the one most of the first :data:`SIZE_VOTE_FRAMES` readable frames
    have (ties: the earliest), so one odd frame at the start does not reject all the others.
    ``on_size(width, height)`` is called once the size is known, before any frame is yielded.
    """

    def __init__(
        self,
        source: FrameSource,
        progress,
        on_size: Callable[[int, int], None] | None = None,
        max_frames: int | None = None,
        keep: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        self.source, self.progress, self.on_size = source, progress, on_size
        self.max_frames = max_frames
        self.keep = keep  # the frames' pictures are needed after prediction (points' colours, video)
        self.kept: dict[int, np.ndarray] = {}  # position among the good frames -> keep(rgb)
        self.names: list[str] = []
        self.failures: list[dict] = []
        self.size: tuple[int, int] | None = None
        self.skipped_before: dict[str, list[str]] = {}  # good frame -> bad frames right before it

    def __iter__(self) -> Iterator[np.ndarray]:
        frames = iter(self.source)
        head = list(itertools.islice(frames, SIZE_VOTE_FRAMES))
        sizes = Counter(frame.rgb.shape[:2] for frame in head if frame.ok and frame.rgb is not None)
        if sizes:
            self.size = sizes.most_common(1)[0][0]  # Counter keeps first-seen order among equal counts
            if self.on_size is not None:
                self.on_size(self.size[1], self.size[0])
        pending_bad: list[str] = []
        for frame in itertools.chain(head, frames):
            self.progress.update(1)
            if frame.error is not None:
                self.failures.append({"frame": frame.name, "reason": str(frame.error)})
                pending_bad.append(frame.name)
                continue
            rgb = frame.rgb
            assert rgb is not None  # a frame without an error has pixels
            if self.size is None:  # no readable frame among the first ones
                self.size = rgb.shape[:2]
                if self.on_size is not None:
                    self.on_size(self.size[1], self.size[0])
            if rgb.shape[:2] != self.size:
                h, w = rgb.shape[:2]
                self.failures.append(
                    {"frame": frame.name, "reason": f"frame is {w}x{h}, the sequence is {self.size[1]}x{self.size[0]}"}
                )
                pending_bad.append(frame.name)
                continue
            if pending_bad and self.names:
                self.skipped_before[frame.name] = pending_bad
            pending_bad = []
            if self.keep is not None:
                self.kept[len(self.names)] = self.keep(rgb)
            self.names.append(frame.name)
            yield rgb
            if self.max_frames is not None and len(self.names) >= self.max_frames:
                if hasattr(frames, "close"):
                    frames.close()  # a camera or stream is released now
                return


@dataclass(frozen=True)
class OutputOptions:
    """What ``predict`` writes beyond the standard layout, and how its pictures are scaled.

    Attributes:
        point_cloud: None, "camera" (``points/<frame>.ply`` per frame, camera frame) or "world"
            (those and ``points_world.ply``: every frame placed by the chained poses in the first
            camera's frame, subsampled to ``world_points``).
        point_stride: keep every n-th pixel in u and v.
        max_depth: drop points farther than this (depth units: metres with a camera height).
        world_points: points in ``points_world.ply`` at most.
        colour_scale: "first:N", "running" or "frame" (:class:`geonet_infer.viz.SteadyScale`).
        video_out: a side-by-side video (frame | depth | flow) written here (.mp4, .avi).
        video_fps: its frame rate; None = the input's (10 for frame folders).
    """

    point_cloud: str | None = None
    point_stride: int = 2
    max_depth: float | None = None
    world_points: int = 500_000
    colour_scale: str = DEFAULT_COLOUR_SCALE
    video_out: Path | None = None
    video_fps: float | None = None

    def __post_init__(self):
        if self.point_cloud not in (None, *POINT_CLOUDS):
            raise InputError(None, f"point cloud {self.point_cloud!r}", f"choose one of {', '.join(POINT_CLOUDS)}")
        if self.point_stride < 1 or not 1 <= self.world_points <= MAX_WORLD_POINTS:
            raise InputError(None, f"point stride must be >= 1 and world points from 1 to {MAX_WORLD_POINTS:,}")
        if self.max_depth is not None and not self.max_depth > 0:
            raise InputError(None, f"max depth {self.max_depth} must be > 0")
        try:
            SteadyScale(self.colour_scale)
        except ValueError as err:
            raise InputError(None, str(err), "e.g. --colour-scale first:8") from None
        if self.video_out is not None and Path(self.video_out).suffix.lower() not in VIDEO_CODECS:
            raise InputError(self.video_out, "unsupported video suffix", f"use one of {' '.join(VIDEO_CODECS)}")
        if self.video_fps is not None:
            check_fps(self.video_fps, "video frame rate (--fps)")


def _frame_files(name: str, tasks: tuple[str, ...], vis: bool, options: OutputOptions = OutputOptions()) -> set[str]:
    """The files (relative to OUT) a frame may get."""
    files = {f"points/{name}.ply"} if options.point_cloud and "depth" in tasks else set()
    if "depth" in tasks:
        files |= {f"depth/{name}.npy"} | ({f"depth/{name}.png"} if vis else set())
    if "flow" in tasks:
        files |= {f"flow/{name}.png"} | ({f"flow_vis/{name}.png"} if vis else set())
    return files


class _OwnedFolder:
    """OUT as the folder of one predict run: lock, ownership marker, removal of the previous run's files
    (the rule of :mod:`geonet_infer.ownership`, shared with batch).

    * Lock: ``OUT/.geonet-predict.lock`` created with O_EXCL holds this pid and is removed at exit;
      a lock whose pid is alive refuses the run, one whose process is gone (killed) is taken over.
    * Ownership: a non-empty OUT without ``OUT/.geonet-predict`` is refused (its files are not ours).
      With the marker, the files it lists (and temp files of an interrupted writer) are removed,
      nothing else: files a user added to OUT stay. A file this run writes that exists and is not
      listed, or that is an input, refuses the run before anything is removed.
    * The marker is written before the first output and lists every file this run may write, so a
      run that is killed still leaves a marker that covers all it wrote.
    * ``claimed_by``: names of another owner's markers in OUT (batch's): that owner holds the lock and
      vouches for OUT; its files are never touched.
    """

    def __init__(
        self,
        out_dir: Path,
        files: set[str],
        input_path,
        inputs: tuple[Path, ...] = (),
        outside: Path | None = None,
        claimed_by: tuple[str, ...] = (),
    ):
        self.out_dir, self.files, self.input = out_dir, set(files), str(input_path)
        self.inputs, self.claimed_by = inputs, claimed_by
        self.outside = None if outside is None else ownership.real(outside)  # the video, outside OUT
        self.outside_sha256: str | None = None  # once it is complete
        self.lock = out_dir / OUTPUT_LOCK
        self.marker = out_dir / OUTPUT_MARKER

    def __enter__(self) -> _OwnedFolder:
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if not self.claimed_by:
            self._take_lock()
        try:
            self._clear_previous_run()
            self._write_marker()
        except BaseException:
            if not self.claimed_by:
                self.lock.unlink(missing_ok=True)
            raise
        return self

    def __exit__(self, *exc) -> None:
        if not self.claimed_by:
            self.lock.unlink(missing_ok=True)

    def add(self, files: set[str]) -> None:
        """Record more files before writing them (a video that decodes more frames than it lists)."""
        if not files <= self.files:
            ownership.check_writes(self.out_dir, files - self.files, (), self.inputs)
            self.files |= files
            self._write_marker()

    def video_written(self, path: Path) -> None:
        """Record the digest of the finished video outside OUT: an identical re-run may replace it."""
        if self.outside is not None and ownership.real(path) == self.outside:
            self.outside_sha256 = file_sha256(path)
            self._write_marker()

    def _take_lock(self) -> None:
        for _ in range(2):
            try:
                fd = os.open(self.lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                pid = _lock_pid(self.lock)
                if pid is None or _alive(pid):
                    who = f"another geonet-infer predict (pid {pid})" if pid else "another geonet-infer predict"
                    raise InputError(
                        self.out_dir,
                        f"{who} is writing into this folder",
                        f"wait for it or pick another --out (if none is running, delete {self.lock})",
                    ) from None
                self.lock.unlink(missing_ok=True)  # its process is gone (killed): a stale lock
                continue
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()}\n")
            return
        raise InputError(self.out_dir, "another geonet-infer predict took this folder", "pick another --out")

    def _clear_previous_run(self) -> None:
        others = [p for p in self.out_dir.iterdir() if p.name not in (OUTPUT_LOCK, *self.claimed_by)]
        previous: dict = {"files": [], "outside": []}
        if self.marker.is_file():
            previous = ownership.read_marker(self.marker)
        elif others and not (set(self.claimed_by) & {p.name for p in self.out_dir.iterdir()}):
            raise InputError(
                self.out_dir,
                "this folder is not empty and was not written by geonet-infer predict",
                "pick another --out (predict never overwrites files it did not write)",
            )
        ownership.check_writes(
            self.out_dir, self.files, previous["files"], self.inputs, self.outside, previous["outside"]
        )
        ownership.remove_listed(self.out_dir, previous["files"])
        ownership.remove_outside_temps(previous["outside"])

    def _write_marker(self) -> None:
        marker: dict[str, object] = {"written_by": "geonet-infer predict", "version": __version__, "input": self.input}
        marker["files"] = sorted(self.files)
        marker["outside"] = [] if self.outside is None else [{"path": str(self.outside), "sha256": self.outside_sha256}]
        with atomic_write(self.marker) as tmp:
            tmp.write_text(json.dumps(marker) + "\n")


def _lock_pid(lock: Path) -> int | None:
    with contextlib.suppress(OSError, ValueError):
        return int(lock.read_text().strip())
    return None  # empty: its writer is between creating and filling it


def _alive(pid: int) -> bool:
    if pid < 1:  # 0 and negative numbers name process groups, not a predict run
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # Overflow: a number no pid reaches (an edited lock)
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _unusable(result: FrameResult, tasks: tuple[str, ...]) -> str | None:
    """What is wrong with the first output of ``result`` that would be written and holds NaN or inf
    ("NaN/inf depth"), or whose depth is degenerate: every pixel the same (all zeros, all equal), which no
    scene gives ("degenerate depth ..."); None if all is well."""
    checks = (
        ("depth", "depth" in tasks and result.depth is not None, result.depth),
        ("flow", "flow" in tasks and result.flow is not None, result.flow),
        ("pose", "pose" in tasks, result.camera_to_world),
    )
    for what, written, value in checks:
        if written and value is not None and not np.isfinite(value).all():
            return f"NaN/inf {what}"
    depth = result.depth
    if "depth" in tasks and depth is not None and depth.size > 1 and depth.min() == depth.max():
        return f"degenerate depth (every pixel {float(depth.flat[0]):g})"
    return None


def predict_to_dir(
    predictor: Predictor,
    source: FrameSource,
    out_dir: str | Path,
    camera: Camera | None = None,
    tasks: tuple[str, ...] | None = TASKS,
    batch_size: int = 4,
    progress: bool = True,
    camera_height: float | None = None,
    vis: bool = True,
    exclusive: bool = False,
    extra_outputs: tuple[str, ...] = (),
    options: OutputOptions = OutputOptions(),
    max_frames: int | None = None,
    check: bool = True,
    flow_method: str = "network",
    pose_method: str = "network",
    scale_smoothing: int = SCALE_HALF_WINDOW,
    claimed_by: tuple[str, ...] = (),
) -> dict:
    """Predict every frame of ``source`` into ``out_dir`` (layout in the module docstring).

    Args:
        predictor: a loaded :class:`~geonet_infer.predictor.Predictor`.
        source: frames from :func:`geonet_infer.io.frames.open_frames`.
        camera: intrinsics (and distortion) of the frames; required for "flow".
        tasks: any of "depth", "pose", "flow" (each needs its graphs, else GeoNetError before
            anything is written); None: all the model can do, the others in ``skipped_tasks``.
        camera_height: metres above a flat road: metric depth and pose translations
            (:mod:`geonet_infer.scale`; needs ``camera``).
        vis: also write the depth colour maps and flow colour wheels (PNG encoding of
            pictures is most of the write time; fleets that only need the data skip it).
        exclusive: own ``out_dir`` for this run (:class:`_OwnedFolder`): refuse a non-empty folder
            predict did not write or one another predict is writing, remove the previous run's files.
        extra_outputs: more files (relative to ``out_dir``) the caller writes there, recorded as
            this run's (``exclusive`` only).
        options: point clouds, the colour scale of the pictures, a result video (:class:`OutputOptions`).
        max_frames: stop after this many good frames (live sources).
        check: check each flow against the frames (``summary["check"]``, :mod:`geonet_infer.check`).
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
    check_batch_size(batch_size)
    check_methods(flow_method, pose_method)
    tasks, skipped_tasks = predictor.resolve_tasks(  # None: all it can
        tasks, metric=camera_height is not None, classical=classical_tasks(tasks or TASKS, flow_method, pose_method)
    )
    if "flow" in tasks and flow_method == "network" and camera is None:
        raise InputError(
            source.path,
            "flow needs camera intrinsics and none were found",
            "pass --calib FILE or --intrinsics FX,FY,CX,CY (or --tasks depth,pose)",
        )
    if "pose" in tasks and pose_method == "orbvo" and camera is None:
        raise InputError(
            source.path, "ORB-VO poses need camera intrinsics and none were found", "pass --calib FILE or --intrinsics"
        )
    if camera_height is not None:
        check_metric_request(camera_height, camera, source.path)
    if options.point_cloud and ("depth" not in tasks or camera is None):
        raise InputError(
            source.path,
            "point clouds need depth and the camera intrinsics",
            "pass --calib FILE or --intrinsics FX,FY,CX,CY, and keep depth in --tasks",
        )
    if options.point_cloud == "world" and "pose" not in tasks:
        raise InputError(
            source.path, "a world point cloud needs poses", "keep pose in --tasks, or use --point-cloud camera"
        )
    video = None if options.video_out is None else Path(options.video_out)
    video_in_out = video is not None and ownership.inside(video, out_dir)  # symlinks resolved
    if video is not None and not exclusive and video.exists():
        raise ownership.not_written(video)
    run = functools.partial(
        _predict,
        predictor, source, out_dir, camera, tasks, batch_size, progress, camera_height, vis,
        skipped_tasks=skipped_tasks, options=options, max_frames=max_frames, check=check,
        methods=(flow_method, pose_method, scale_smoothing),
    )  # fmt: skip
    if not exclusive:
        out_dir.mkdir(parents=True, exist_ok=True)
        return run(owned=None)
    names = source.frame_names if source.frame_names is not None else [f"{i:06d}" for i in range(len(source))]
    files = {SUMMARY_NAME, *extra_outputs, *(_POSE_FILES if "pose" in tasks else ())}
    files |= {CAMERA_NAME} if camera is not None else set()
    files |= {WORLD_CLOUD_NAME} if options.point_cloud == "world" else set()
    if video is not None and video_in_out:
        files.add(os.path.relpath(ownership.real(video), ownership.real(out_dir)))
    files |= set().union(*(_frame_files(name, tasks, vis, options) for name in names))
    inputs = tuple(getattr(source, "files", None) or ([Path(source.path)] if source.kind == "video" else []))
    outside = video if video is not None and not video_in_out else None
    with _OwnedFolder(out_dir, files, source.location, inputs, outside, claimed_by) as owned:
        return run(owned=owned)


def _predict(
    predictor: Predictor,
    source: FrameSource,
    out_dir: Path,
    camera: Camera | None,
    tasks: tuple[str, ...],
    batch_size: int,
    progress: bool,
    camera_height: float | None,
    vis: bool,
    *,
    owned: _OwnedFolder | None,
    skipped_tasks: dict[str, tuple[str, ...]],
    options: OutputOptions,
    max_frames: int | None,
    check: bool,
    methods: tuple[str, str, int],
) -> dict:
    from tqdm import tqdm

    started = time.perf_counter()
    totals: dict[str, float] = defaultdict(float)
    poses: list[np.ndarray] = []
    done = 0
    scales: dict[str, list] = {"frames": [], "raw": [], "smoothed": []}
    checks: list[tuple[str, FrameCheck]] = []
    interrupted = False

    def check_camera(width: int, height: int) -> None:
        if camera is not None:
            camera.scaled_to(width, height).check_image_size(width, height, camera.source or None)

    bar = tqdm(total=len(source) or None, unit="frame", desc=source.name, disable=not progress, leave=False)
    keep = None
    if options.point_cloud or options.video_out is not None:  # the pictures are needed after prediction
        keep = functools.partial(_as_predicted, camera)
    frames = _Frames(source, bar, check_camera, max_frames, keep)
    colours = SteadyScale(options.colour_scale)
    waiting: list[FrameResult] = []  # predicted, waiting for the colour scale ("first:N")
    world = _WorldCloud(options) if options.point_cloud == "world" else None
    video = None
    if options.video_out is not None:
        video = _VideoOut(Path(options.video_out), options.video_fps or getattr(source, "fps", None) or FOLDER_FPS)

    def record(result: FrameResult, rgb: np.ndarray | None, written: _Written) -> None:
        nonlocal done
        totals["write"] += written.ms
        if video is not None and rgb is not None:
            video.write(rgb, written.pictures)
        if world is not None and rgb is not None and written.points is not None:
            world.add(result, *written.points)
        poses.append(result.camera_to_world)
        if result.metric_scale is not None:
            scales["frames"].append(result.name)
            scales["raw"].append(result.metric_scale_raw)
            scales["smoothed"].append(result.metric_scale)
        for stage, ms in result.timings_ms.items():
            totals[stage] += ms
        done += 1
        bar.set_postfix(done=done, failed=len(frames.failures), refresh=False)

    writer = _FrameWriter(out_dir, tasks, vis, record, options, camera_height, pictures=vis or video is not None)

    def emit(ready: list[FrameResult]) -> None:
        scale = colours.scales()
        while ready:
            result = ready.pop(0)  # before it is handed on: an interrupt here never submits it twice
            rgb = frames.kept.pop(result.index, None)
            if owned is not None:
                owned.add(_frame_files(result.name, tasks, vis, options))
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
        )
        for result in results:
            bad = _unusable(result, tasks)
            if bad is not None:
                frames.failures.append({"frame": result.name, "reason": f"model produced {bad}"})
                frames.kept.pop(result.index, None)
                continue
            if result.check is not None:
                checks.append((result.name, result.check))
            colours.observe(result.depth if "depth" in tasks else None, result.flow if "flow" in tasks else None)
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
        if video is not None:
            video.close(keep=done > 0 and sys.exc_info()[0] is None)
    if owned is not None and video is not None and video.frames:
        owned.video_written(video.path)
    if world is not None:
        world.write(out_dir / WORLD_CLOUD_NAME, camera_height)
    if camera is not None and frames.size is not None:
        height, width = frames.size
        write_kitti_camera(out_dir / CAMERA_NAME, camera_at(camera, frames.size).K, width, height)
    truncated = None if interrupted else getattr(source, "truncated", None)
    if truncated:
        reason = f"{source.location}: truncated: {truncated}"
        frames.failures += [{"frame": name, "reason": reason} for name in getattr(source, "missing", ())]
    totals["total"] += totals["write"]
    if "pose" in tasks and poses:
        fps = getattr(source, "fps", None)
        stamps = np.arange(len(poses)) / fps if fps else np.arange(len(poses), dtype=np.float64)
        write_kitti_poses(out_dir / _POSE_FILES[0], np.stack(poses))
        write_tum_poses(out_dir / _POSE_FILES[1], stamps, np.stack(poses))
    elapsed = time.perf_counter() - started
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
        "tasks": list(tasks),
        "skipped_tasks": {task: list(graphs) for task, graphs in skipped_tasks.items()},  # tasks=None only
        "outputs": _outputs(tasks, vis, options, camera is not None),
        "colour_scale": colours.describe() if vis or video is not None else None,
        "point_cloud": None
        if not options.point_cloud
        else {
            "mode": options.point_cloud,
            "stride": options.point_stride,
            "max_depth": options.max_depth,
            "units": "metres" if camera_height is not None else "relative scale",
        },
        "video": None if video is None else {"path": str(options.video_out), "frames": video.frames, "fps": video.fps},
        "model": {
            "dir": str(predictor.model_dir),
            "arch": predictor.manifest.arch,
            "precision": predictor.precision,
            "graphs": predictor.graph_set.runs,  # per graph: engine, precision and why
            "isa": isa_line(),
            "threads": predictor.threads,
            "graph_size": [predictor.spec.height, predictor.spec.width],
            "random_init": predictor.manifest.random_init,
        },
        "model_notice": model_notice(predictor.manifest),  # synthetic-only model: how it does on real video
        "camera": None
        if camera is None
        else {
            "K_input_resolution": (camera_at(camera, frames.size).K.tolist() if frames.size else camera.K.tolist()),
            "dist": None if camera.dist is None else camera.dist.tolist(),
            "source": camera.source,
            "undistorted": camera.has_distortion,
        },
        "image_size": None if frames.size is None else [frames.size[1], frames.size[0]],
        "methods": describe_methods(tasks, methods[0], methods[1]),
        "metric_scale": None if camera_height is None else metric_scale_summary(camera_height, methods[2], scales),
        "check": _check_summary(checks, predictor) if check and "flow" in tasks else None,
        "timings_ms_per_frame": {k: v / max(done, 1) for k, v in totals.items()},
        "wall_s": elapsed,
        "frames_per_s": done / elapsed if elapsed > 0 else None,
        "versions": {"geonet_infer": __version__, "python": platform.python_version()},
    }
    with atomic_write(out_dir / SUMMARY_NAME) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    if interrupted:
        raise KeyboardInterrupt
    return summary


def _check_summary(checks: list[tuple[str, FrameCheck]], predictor: Predictor) -> dict:
    """summary.json's "check": the pairs summed up (:class:`SequenceCheck`), then each pair."""
    return {
        "method": METHOD,
        "size": [predictor.spec.height, predictor.spec.width],
        "agree_px": AGREE_PX,
        **SequenceCheck.from_checks(c for _, c in checks).as_dict(),
        "per_pair": [{"frame": name, **c.as_dict()} for name, c in checks],
    }


def _outputs(
    tasks: tuple[str, ...], vis: bool = True, options: OutputOptions = OutputOptions(), camera: bool = False
) -> list[str]:
    out = [CAMERA_NAME] if camera else []
    if options.point_cloud and "depth" in tasks:
        out += ["points/*.ply"] + ([WORLD_CLOUD_NAME] if options.point_cloud == "world" else [])
    if "depth" in tasks:
        out += ["depth/*.npy"] + (["depth/*.png"] if vis else [])
    if "flow" in tasks:
        out += ["flow/*.png"] + (["flow_vis/*.png"] if vis else [])
    if "pose" in tasks:
        out += ["poses_kitti.txt", "poses_tum.txt"]
    return out


@dataclass(frozen=True)
class _Written:
    """What writing one frame made, for the result video and the world cloud: each is computed once."""

    ms: float  # the write's wall time
    pictures: tuple[np.ndarray | None, np.ndarray | None]  # depth colour map, flow colour wheel (RGB) or None
    points: tuple[np.ndarray, np.ndarray | None] | None  # the frame's points and colours (point clouds)


class _FrameWriter:
    """Writes each frame's files on worker threads while the next frames are predicted.

    PNG encoding (ISA-L deflate), the colour maps and file writes release the GIL, so on a 2-core machine
    the writing overlaps the networks instead of following them. Results come back in frame
    order with what the write made (:class:`_Written`); at most ``in_flight`` frames wait (bounded
    memory). A failed write raises from :meth:`submit` or :meth:`drain`; :meth:`close` finishes
    the writes already started (every file is atomic) and drops the ones not started.
    ``pictures``: make the colour pictures (for the PNGs with ``vis``, or a result video).
    """

    def __init__(
        self,
        out_dir: Path,
        tasks: tuple[str, ...],
        vis: bool,
        on_written: Callable[[FrameResult, np.ndarray | None, _Written], None],
        options: OutputOptions = OutputOptions(),
        camera_height: float | None = None,
        workers: int = WRITE_THREADS,
        pictures: bool = True,
    ):
        self.on_written = on_written  # (result, its input frame or None, what was made), in frame order
        self.out_dir, self.tasks, self.vis, self.pictures = out_dir, tasks, vis, pictures
        self.options, self.camera_height = options, camera_height
        self.in_flight = 2 * workers
        self.pool = ThreadPoolExecutor(workers, thread_name_prefix="geonet-write")
        self.pending: deque[tuple[FrameResult, np.ndarray | None, Future[_Written]]] = deque()

    def _write(self, result: FrameResult, scale: tuple[float | None, float | None], rgb: np.ndarray | None) -> _Written:
        t0 = time.perf_counter()
        pictures = _pictures(result, self.tasks, scale) if self.pictures else (None, None)
        _write_frame(self.out_dir, result, self.tasks, pictures if self.vis else (None, None))
        points = None
        if self.options.point_cloud and result.depth is not None and result.intrinsics is not None:
            points = result.points(rgb, self.options.point_stride, self.options.max_depth)
            write_ply(
                output_path(self.out_dir, "points", result.name, ".ply"),
                *points,
                _ply_comments(f"frame {result.name}, in its camera's frame", self.camera_height),
            )
        return _Written((time.perf_counter() - t0) * 1e3, pictures, points)

    def submit(
        self,
        result: FrameResult,
        scale: tuple[float | None, float | None] = (None, None),
        rgb: np.ndarray | None = None,
    ) -> None:
        """Queue ``result``'s files (pictures at ``scale``: inverse-depth max, flow max; None = the frame's
        own); frames finished meanwhile go to ``on_written`` (waits while too many are queued)."""
        self.pending.append((result, rgb, self.pool.submit(self._write, result, scale, rgb)))
        self._settle(self.in_flight)

    def drain(self) -> None:
        self._settle(0)

    def _settle(self, keep: int) -> None:
        # Each written frame goes to on_written right as it leaves the queue: an interrupt (Ctrl-C,
        # SIGTERM) between two frames can neither drop a written frame nor count one twice.
        while self.pending and (len(self.pending) > keep or self.pending[0][2].done()):
            result, rgb, future = self.pending[0]
            written = future.result()
            self.pending.popleft()
            self.on_written(result, rgb, written)

    def close(self) -> None:
        interrupt = None
        while True:  # an interrupt here would leave writes running while the caller cleans up after them
            try:
                self.pool.shutdown(wait=True, cancel_futures=True)
                break
            except BaseException as exc:  # Ctrl-C, SIGTERM: raised once the started writes are done
                interrupt = exc
        if interrupt is not None:
            raise interrupt


def _pictures(
    result: FrameResult, tasks: tuple[str, ...], scale: tuple[float | None, float | None]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The frame's depth colour map and flow colour wheel (RGB; None for a task left out) at ``scale``:
    (inverse-depth max, flow max), None = the frame's own range."""
    depth, flow = result.depth, result.flow
    return (
        depth_to_color(depth, vmax=scale[0]) if "depth" in tasks and depth is not None else None,
        flow_to_color(flow, max_flow=scale[1]) if "flow" in tasks and flow is not None else None,
    )


def _write_frame(
    out_dir: Path,
    result: FrameResult,
    tasks: tuple[str, ...],
    pictures: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
) -> None:
    """All files of one frame, or none: an interrupt or a failed write removes the ones already written.

    ``pictures``: the depth and flow colour pictures to write beside the data (:func:`_pictures`), or None."""
    writes: list[tuple[Path, Callable[[Path], object]]] = []
    depth, flow = result.depth, result.flow
    depth_rgb, flow_rgb = pictures
    if "depth" in tasks and depth is not None:
        writes.append((output_path(out_dir, "depth", result.name, ".npy"), lambda p: save_npy_atomic(p, depth)))
        if depth_rgb is not None:
            path = output_path(out_dir, "depth", result.name, ".png")
            writes.append((path, lambda p: write_image(p, depth_rgb)))
    if "flow" in tasks and flow is not None:
        writes.append((output_path(out_dir, "flow", result.name, ".png"), lambda p: write_flow_kitti(p, flow)))
        if flow_rgb is not None:
            path = output_path(out_dir, "flow_vis", result.name, ".png")
            writes.append((path, lambda p: write_image(p, flow_rgb)))
    written: list[Path] = []
    try:
        for path, write in writes:
            write(path)
            written.append(path)
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise


def _ply_comments(where: str, camera_height: float | None) -> tuple[str, ...]:
    unit = f"metres (camera height {camera_height:g} m)" if camera_height is not None else "relative scale"
    return (f"geonet-infer predict: {where}", f"units: {unit}", "axes: x right, y down, z forward")


def _as_predicted(camera: Camera | None, rgb: np.ndarray) -> np.ndarray:
    """The frame as the networks saw it at the input size: undistorted when the camera has distortion."""
    if camera is None or not camera.has_distortion:
        return rgb
    return camera.scaled_to(rgb.shape[1], rgb.shape[0]).undistort(rgb)


class _WorldCloud:
    """Every frame's points placed in the first camera's frame by the chained poses, subsampled.

    Memory stays bounded: whenever more than twice ``world_points`` are held, a random half goes.
    """

    def __init__(self, options: OutputOptions):
        self.options = options
        self.rng = np.random.default_rng(0)
        self.points: list[np.ndarray] = []
        self.colours: list[np.ndarray] = []
        self.held = 0

    def add(self, result: FrameResult, xyz: np.ndarray, colours: np.ndarray | None) -> None:
        """``result``'s points in its camera's frame (:meth:`FrameResult.points`), placed by its pose."""
        R, t = result.camera_to_world[:3, :3], result.camera_to_world[:3, 3]
        self.points.append((xyz @ R.T + t).astype(np.float32))
        self.colours.append(colours if colours is not None else np.full((len(xyz), 3), 255, np.uint8))
        self.held += len(xyz)
        if self.held > 2 * self.options.world_points:
            self._subsample(self.options.world_points)

    def _subsample(self, n: int) -> None:
        points, colours = np.concatenate(self.points), np.concatenate(self.colours)
        if len(points) > n:
            keep = np.sort(self.rng.choice(len(points), n, replace=False))
            points, colours = points[keep], colours[keep]
        self.points, self.colours, self.held = [points], [colours], len(points)

    def write(self, path: Path, camera_height: float | None) -> None:
        if not self.points:
            return
        self._subsample(self.options.world_points)
        where = "every frame in the first camera's frame, placed by the predicted poses"
        write_ply(path, self.points[0], self.colours[0], _ply_comments(where, camera_height))


class _VideoOut:
    """The side-by-side result video (frame | depth | flow), streamed to a temporary file next to
    ``path`` and renamed onto it at the end (removed instead on failure)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.writer: cv2.VideoWriter | None = None
        self.tmp: Path | None = None
        self.frames = 0

    def write(self, rgb: np.ndarray, pictures: tuple[np.ndarray | None, np.ndarray | None]) -> None:
        """One frame: its input picture beside its depth and flow pictures (:func:`_pictures`; None = black)."""
        depth, flow = (np.zeros_like(rgb) if p is None else p for p in pictures)
        panel = side_by_side([rgb, depth, flow], ["frame", "depth", "flow"], height=min(VIDEO_HEIGHT, rgb.shape[0]))
        panel = panel[: panel.shape[0] // 2 * 2, : panel.shape[1] // 2 * 2]  # even sizes: what codecs expect
        if self.writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.stem}.", suffix=self.path.suffix)
            os.close(fd)
            self.tmp = Path(name)
            codec = cv2.VideoWriter.fourcc(*VIDEO_CODECS[self.path.suffix.lower()])
            self.writer = cv2.VideoWriter(str(self.tmp), codec, self.fps, (panel.shape[1], panel.shape[0]))
            if not self.writer.isOpened():
                self.close(keep=False)
                raise InputError(
                    self.path, "OpenCV cannot write this video", f"try another suffix ({' '.join(VIDEO_CODECS)})"
                )
        self.writer.write(cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self, keep: bool) -> None:
        """Finish the video (``keep``) or remove it. A kept video is re-opened and its frames counted
        first: OpenCV's writer ignores a failed write (a full disk), so that is where it shows (OSError)."""
        if self.writer is not None:
            self.writer.release()
            self.writer = None
        if self.tmp is not None:
            tmp, self.tmp = self.tmp, None
            try:
                if not (keep and self.frames):
                    return
                readable = _decodable_frames(tmp)
                if readable != self.frames:
                    raise OSError(
                        errno.EIO,
                        f"the video reads back with {readable} of its {self.frames} frames (the disk may be "
                        "full); it was not kept",
                        str(self.path),
                    )
                os.chmod(tmp, 0o666 & ~_umask())
                os.replace(tmp, self.path)
            finally:
                tmp.unlink(missing_ok=True)


def _decodable_frames(video: Path) -> int:
    """Frames OpenCV decodes from ``video`` (0 when it cannot be opened)."""
    cap = cv2.VideoCapture(str(video))
    try:
        count = 0
        while cap.isOpened() and cap.grab():
            count += 1
        return count
    finally:
        cap.release()
