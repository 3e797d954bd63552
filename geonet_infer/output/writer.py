"""Writing one frame's files (data, pictures, points) on worker threads while the next frames are predicted."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geonet_infer.core.points import write_ply
from geonet_infer.core.results import FrameResult
from geonet_infer.io.atomic import interrupts_held, save_npy_atomic
from geonet_infer.io.depth import write_depth_kitti
from geonet_infer.io.flow import write_flow_kitti
from geonet_infer.io.images import write_image
from geonet_infer.output.clouds import ply_comments
from geonet_infer.output.layout import DEFAULT_OUTPUTS, POINTS, frame_outputs, frame_path, pattern
from geonet_infer.output.options import OutputOptions
from geonet_infer.output.viz import depth_to_color, flow_to_color

WRITE_THREADS = 2  # frames written while the next are predicted; colour maps and PNGs are most of the cost


@dataclass(frozen=True)
class Written:
    """What writing one frame made, for the result video and the world cloud: each is computed once."""

    ms: float  # the write's wall time
    cpu_ms: float  # the writing thread's CPU time for it
    files: dict[str, tuple[Path, int]]  # per layout pattern (depth/*.npy: ...), the file and its bytes
    pictures: tuple[np.ndarray | None, np.ndarray | None]  # depth colour map, flow colour wheel (RGB) or None
    points: tuple[np.ndarray, np.ndarray | None] | None  # the frame's points and colours (point clouds)

    @property
    def sizes(self) -> dict[str, int]:
        """Bytes written per layout pattern."""
        return {name: size for name, (_, size) in self.files.items()}


class FrameWriter:
    """Writes each frame's files on worker threads while the next frames are predicted.

    PNG encoding (ISA-L deflate), the colour maps and file writes release the GIL, so on a 2-core machine
    the writing overlaps the networks instead of following them. Results come back in frame
    order with what the write made (:class:`Written`); at most ``in_flight`` frames wait (bounded
    memory). A failed write raises from :meth:`submit` or :meth:`drain`; :meth:`close` finishes
    the writes already started (every file is atomic) and drops the ones not started.
    ``outputs``: the --outputs names to write (:mod:`geonet_infer.output.layout`).
    ``pictures``: make the colour pictures (for the colour-map outputs, or a result video).
    """

    def __init__(
        self,
        out_dir: Path,
        tasks: tuple[str, ...],
        outputs: Collection[str],
        on_written: Callable[[FrameResult, np.ndarray | None, Written], None],
        options: OutputOptions = OutputOptions(),
        camera_height: float | None = None,
        workers: int = WRITE_THREADS,
        pictures: bool = True,
    ):
        self.on_written = on_written  # (result, its input frame or None, what was made), in frame order
        self.out_dir, self.tasks, self.outputs, self.pictures = out_dir, tasks, outputs, pictures
        self.options, self.camera_height = options, camera_height
        self.in_flight = 2 * workers
        self.pool = ThreadPoolExecutor(workers, thread_name_prefix="geonet-write")
        self.pending: deque[tuple[FrameResult, np.ndarray | None, Future[Written]]] = deque()
        self.waited_ms = 0.0  # the caller's time blocked on unfinished writes

    def _write(self, result: FrameResult, scale: tuple[float | None, float | None], rgb: np.ndarray | None) -> Written:
        t0, cpu0 = time.perf_counter(), time.thread_time()
        pictures = colour_pictures(result, self.tasks, scale) if self.pictures else (None, None)
        files = write_frame(self.out_dir, result, self.tasks, pictures, self.outputs)
        points = None
        try:
            if self.options.point_cloud and result.depth is not None and result.intrinsics is not None:
                points = result.points(rgb, self.options.point_stride, self.options.max_depth)
                path = frame_path(self.out_dir, POINTS, result.name)
                comments = ply_comments(f"frame {result.name}, in its camera's frame", self.camera_height)
                write_ply(path, *points, comments)
                files[pattern(POINTS)] = (path, path.stat().st_size)
        except BaseException:
            _remove(files)  # all of a frame's files or none
            raise
        ms, cpu_ms = (time.perf_counter() - t0) * 1e3, (time.thread_time() - cpu0) * 1e3
        return Written(ms, cpu_ms, files, pictures, points)

    def submit(
        self,
        result: FrameResult,
        scale: tuple[float | None, float | None] = (None, None),
        rgb: np.ndarray | None = None,
    ) -> None:
        """Queue ``result``'s files (pictures at ``scale``: inverse-depth max, flow max; None = the frame's
        own); frames finished meanwhile go to ``on_written`` (waits while too many are queued)."""
        with interrupts_held():  # a write the pool took is always queued, so it is always recorded
            self.pending.append((result, rgb, self.pool.submit(self._write, result, scale, rgb)))
        self._settle(self.in_flight)

    def drain(self) -> None:
        self._settle(0)

    def _settle(self, keep: int) -> None:
        # Each written frame goes to on_written as it leaves the queue, both or neither (interrupts_held):
        # an interrupt (Ctrl-C, SIGTERM) can neither drop a written frame nor count one twice. The wait
        # for a write stays outside, interruptible.
        while self.pending and (len(self.pending) > keep or self.pending[0][2].done()):
            result, rgb, future = self.pending[0]
            t0 = time.perf_counter()
            written = future.result()
            self.waited_ms += (time.perf_counter() - t0) * 1e3
            with interrupts_held():
                self.pending.popleft()
                self.on_written(result, rgb, written)

    def close(self) -> None:
        """Finish the writes already started, drop the others, and remove the files of every frame written
        but never recorded (a second interrupt stopped :meth:`drain`; a failed write before it): the
        files on disk are the frames ``on_written`` saw."""
        interrupt = None
        while True:  # an interrupt here would leave writes running while the caller cleans up after them
            try:
                self.pool.shutdown(wait=True, cancel_futures=True)
                break
            except BaseException as exc:  # Ctrl-C, SIGTERM: raised once the started writes are done
                interrupt = exc
        for _, _, future in self.pending:
            if not future.cancelled() and future.exception() is None:
                _remove(future.result().files)
        self.pending.clear()
        if interrupt is not None:
            raise interrupt


def colour_pictures(
    result: FrameResult, tasks: tuple[str, ...], scale: tuple[float | None, float | None]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The frame's depth colour map and flow colour wheel (RGB; None for a task left out) at ``scale``:
    (inverse-depth max, flow max), None = the frame's own range."""
    depth, flow = result.depth, result.flow
    return (
        depth_to_color(depth, vmax=scale[0]) if "depth" in tasks and depth is not None else None,
        flow_to_color(flow, max_flow=scale[1]) if "flow" in tasks and flow is not None else None,
    )


def write_frame(
    out_dir: Path,
    result: FrameResult,
    tasks: tuple[str, ...],
    pictures: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    outputs: Collection[str] = DEFAULT_OUTPUTS,
) -> dict[str, tuple[Path, int]]:
    """All files of one frame, or none: an interrupt or a failed write removes the ones already written.

    ``outputs``: the --outputs names to write (:mod:`geonet_infer.output.layout`); the colour maps
    only with their ``pictures`` (:func:`colour_pictures`). Returns per layout pattern the file and its bytes."""
    data: dict[str, np.ndarray | None] = {
        "depth-npy": result.depth,
        "depth-npy16": result.depth,
        "depth-png16": result.depth,
        "depth-vis": pictures[0],
        "flow-png": result.flow,
        "flow-vis": pictures[1],
    }
    writes = []
    for output in frame_outputs(tasks, outputs):
        array = data.get(output.name or "")
        if array is not None:
            writes.append((output, array))
    files: dict[str, tuple[Path, int]] = {}
    try:
        for output, array in writes:
            path = frame_path(out_dir, output, result.name)
            _WRITERS[output.name](path, array)
            files[pattern(output)] = (path, 0)  # removed on a failure from here on
            files[pattern(output)] = (path, path.stat().st_size)
    except BaseException:
        _remove(files)
        raise
    return files


def _remove(files: dict[str, tuple[Path, int]]) -> None:
    for path, _ in files.values():
        path.unlink(missing_ok=True)


_WRITERS: dict[str | None, Callable[[Path, np.ndarray], object]] = {  # --outputs name -> how its file is written
    "depth-npy": save_npy_atomic,
    "depth-npy16": lambda path, depth: save_npy_atomic(path, _float16(depth)),
    "depth-png16": lambda path, depth: write_depth_kitti(path, depth, too_far="clip"),
    "depth-vis": write_image,
    "flow-png": write_flow_kitti,
    "flow-vis": write_image,
}


def _float16(depth: np.ndarray) -> np.ndarray:
    """Depth as float16, the farthest values held at float16's largest instead of becoming inf."""
    return np.minimum(depth, np.finfo(np.float16).max).astype(np.float16)
