"""Writing one frame's files (data, pictures, points) on worker threads while the next frames are predicted."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geonet_infer.core.points import write_ply
from geonet_infer.core.results import FrameResult
from geonet_infer.io.atomic import save_npy_atomic
from geonet_infer.io.flow import write_flow_kitti
from geonet_infer.io.images import write_image
from geonet_infer.output.clouds import ply_comments
from geonet_infer.output.layout import output_path
from geonet_infer.output.options import OutputOptions
from geonet_infer.viz import depth_to_color, flow_to_color

WRITE_THREADS = 2  # frames written while the next are predicted; colour maps and PNGs are most of the cost


@dataclass(frozen=True)
class Written:
    """What writing one frame made, for the result video and the world cloud: each is computed once."""

    ms: float  # the write's wall time
    pictures: tuple[np.ndarray | None, np.ndarray | None]  # depth colour map, flow colour wheel (RGB) or None
    points: tuple[np.ndarray, np.ndarray | None] | None  # the frame's points and colours (point clouds)


class FrameWriter:
    """Writes each frame's files on worker threads while the next frames are predicted.

    PNG encoding (ISA-L deflate), the colour maps and file writes release the GIL, so on a 2-core machine
    the writing overlaps the networks instead of following them. Results come back in frame
    order with what the write made (:class:`Written`); at most ``in_flight`` frames wait (bounded
    memory). A failed write raises from :meth:`submit` or :meth:`drain`; :meth:`close` finishes
    the writes already started (every file is atomic) and drops the ones not started.
    ``pictures``: make the colour pictures (for the PNGs with ``vis``, or a result video).
    """

    def __init__(
        self,
        out_dir: Path,
        tasks: tuple[str, ...],
        vis: bool,
        on_written: Callable[[FrameResult, np.ndarray | None, Written], None],
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
        self.pending: deque[tuple[FrameResult, np.ndarray | None, Future[Written]]] = deque()

    def _write(self, result: FrameResult, scale: tuple[float | None, float | None], rgb: np.ndarray | None) -> Written:
        t0 = time.perf_counter()
        pictures = colour_pictures(result, self.tasks, scale) if self.pictures else (None, None)
        write_frame(self.out_dir, result, self.tasks, pictures if self.vis else (None, None))
        points = None
        if self.options.point_cloud and result.depth is not None and result.intrinsics is not None:
            points = result.points(rgb, self.options.point_stride, self.options.max_depth)
            write_ply(
                output_path(self.out_dir, "points", result.name, ".ply"),
                *points,
                ply_comments(f"frame {result.name}, in its camera's frame", self.camera_height),
            )
        return Written((time.perf_counter() - t0) * 1e3, pictures, points)

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
) -> None:
    """All files of one frame, or none: an interrupt or a failed write removes the ones already written.

    ``pictures``: the depth and flow colour pictures to write beside the data (:func:`colour_pictures`), or None."""
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
