"""The frames ``predict`` runs on: a source's good frames, in order; the bad ones recorded and skipped."""

from __future__ import annotations

import itertools
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator

import numpy as np

from geonet_infer.core.results import FrameResult
from geonet_infer.io.frames import Frame, FrameSource

SIZE_VOTE_FRAMES = 8  # the sequence's frame size is the one most of its first frames have
READ_AHEAD = 4  # frames decoded ahead by the reader thread (issue 54): decoding overlaps the networks


class ReadAhead:
    """``frames`` iterated by a thread of its own, up to ``depth`` ahead (OpenCV decodes without the GIL,
    so a frame is decoded while the networks run on the one before). The same items in the same order;
    an exception of the source is raised here, where the frame it stopped would have come. ``close()``
    stops the thread, which closes the source (a camera or stream is released by the thread that read it).
    """

    _END = object()

    def __init__(self, frames: Iterator[Frame], depth: int = READ_AHEAD):
        self.items: queue.Queue = queue.Queue(maxsize=depth)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._read, args=(frames,), name="geonet-read-ahead", daemon=True)
        self.thread.start()

    def _read(self, frames: Iterator[Frame]) -> None:
        try:
            for frame in frames:
                if not self._put(frame):
                    return
            self._put(self._END)
        except BaseException as exc:  # noqa: BLE001 -- handed to the consumer, raised there
            self._put(exc)
        finally:
            if hasattr(frames, "close"):
                frames.close()

    def _put(self, item) -> bool:
        while not self.stop.is_set():
            try:
                self.items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator[Frame]:
        return self

    def __next__(self) -> Frame:
        item = self.items.get()
        if item is self._END:
            self.items.put(self._END)  # every later next() ends too
            raise StopIteration
        if isinstance(item, BaseException):
            raise item
        return item

    def close(self) -> None:
        self.stop.set()
        while self.thread.is_alive():
            try:
                self.items.get(timeout=0.1)  # let a blocked put see the stop
            except queue.Empty:
                pass
        self.thread.join()


class GoodFrames:
    """The source's good frames, in order; bad ones are recorded in ``failures`` and skipped.

    The sequence's size is the one most of the first :data:`SIZE_VOTE_FRAMES` readable frames
    have (ties: the earliest), so one odd frame at the start does not reject all the others.
    ``on_size(width, height)`` is called once the size is known, before any frame is yielded.
    ``one_size=False`` (depth alone: no snippets) keeps frames of any size; ``on_size`` is then
    called for each new size, before its first frame, and ``size`` stays the sequence's most common
    size among the first frames.
    """

    def __init__(
        self,
        source: FrameSource,
        progress,
        on_size: Callable[[int, int], None] | None = None,
        max_frames: int | None = None,
        keep: Callable[[np.ndarray], np.ndarray] | None = None,
        one_size: bool = True,
    ):
        self.one_size = one_size
        self.source, self.progress, self.on_size = source, progress, on_size
        self.max_frames = max_frames
        self.keep = keep  # the frames' pictures are needed after prediction (points' colours, video)
        self.kept: dict[int, np.ndarray] = {}  # position among the good frames -> keep(rgb)
        self.names: list[str] = []
        self.failures: list[dict] = []
        self.size: tuple[int, int] | None = None
        self.skipped_before: dict[str, list[str]] = {}  # good frame -> bad frames right before it
        self.read_ms = 0.0  # time the main thread waited for the reader thread's next frame

    def _timed(self, frames: Iterator[Frame]) -> Iterator[Frame]:
        """``frames``, the time each takes to come (read and decoded) added to ``read_ms``."""
        try:
            while True:
                t0 = time.perf_counter()
                frame = next(frames, None)
                self.read_ms += (time.perf_counter() - t0) * 1e3
                if frame is None:
                    return
                yield frame
        finally:
            if hasattr(frames, "close"):
                frames.close()  # a camera or stream is released now

    def __iter__(self) -> Iterator[np.ndarray]:
        frames = self._timed(ReadAhead(iter(self.source)))
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
            if rgb.shape[:2] != self.size and not self.one_size:
                if self.on_size is not None:
                    self.on_size(rgb.shape[1], rgb.shape[0])
            elif rgb.shape[:2] != self.size:
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


def unusable(result: FrameResult, tasks: tuple[str, ...]) -> str | None:
    """What is wrong with the first output of ``result`` that would be written and holds NaN or inf
    ("NaN/inf depth"), or whose depth is degenerate: every pixel the same (all zeros, all equal), which no
    scene gives ("degenerate depth ..."); None if all is well."""
    checks = (
        ("depth", "depth" in tasks and result.depth is not None, result.depth),
        ("flow", "flow" in tasks and result.flow is not None, result.flow),
        ("pose", "pose" in tasks, result.camera_to_world),
    )
    for what, written, value in checks:
        # min and max are NaN where any value is, and +-inf where one is: all finite iff both are (a
        # full-frame boolean mask for isfinite().all() cost predict's main thread ~3 ms a frame)
        if written and value is not None and value.size and not np.isfinite((value.min(), value.max())).all():
            return f"NaN/inf {what}"
    depth = result.depth
    if "depth" in tasks and depth is not None and depth.size > 1 and depth.min() == depth.max():
        return f"degenerate depth (every pixel {float(depth.flat[0]):g})"
    return None
