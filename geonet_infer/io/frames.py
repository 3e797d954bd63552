"""Frame sources for the command line: a video file, a dataset's sequence folder or a folder of images.

:func:`open_frames` picks the source from the path; iterating it yields :class:`Frame` objects
lazily (one decoded frame in memory at a time), in temporal order.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import cv2
import numpy as np

from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io import images
from geonet_infer.io.images import IMAGE_SUFFIXES, list_images, read_image
from geonet_infer.io.layouts import KITTI_CALIB_NAME, SequenceLayout, find_layout
from geonet_infer.limits import MAX_CAMERA_INDEX

__all__ = ["VIDEO_SUFFIXES", "KITTI_CALIB_NAME", "Frame", "FrameSource", "open_frames", "open_stream", "open_stdin"]


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm")  # compared lower-case
# FFmpeg (inside OpenCV) prints its own errors on stderr for a broken video ("moov atom not found"),
# which :func:`open_frames` reports as a GeoNetError naming the file anyway. Its log is quiet
# unless the user set OPENCV_FFMPEG_LOGLEVEL (e.g. 32 to see it). OpenCV reads the variable when it
# first opens a video in the process, hence at import; cv2.utils.logging.setLogLevel does not reach it.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
SIDE_CALIB_SUFFIX = ".calib.txt"  # clip.mp4 + clip.calib.txt: a video's (or folder's) own calibration
CLEAN_END_SHORTFALL_S = 1.0  # a video that stops at most this much before its header's count ended cleanly
FALLBACK_FPS = 25.0  # for that rule when the container gives no frame rate
MAX_MISSING_LISTED = 1000  # missing frames named one by one; more (a header's claim) are one record


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a :class:`FrameSource`: exactly one of ``rgb`` and ``error`` is set.

    Attributes:
        name: frame name (file stem, or the zero-padded index ``000000`` for videos).
        rgb: (H, W, 3) uint8 RGB, or None if the frame could not be decoded.
        error: GeoNetError naming the file, or None.
    """

    name: str
    rgb: np.ndarray | None = None
    error: GeoNetError | None = None

    def __post_init__(self):
        if (self.rgb is None) == (self.error is None):
            raise ValueError("a Frame holds exactly one of rgb and error")

    @property
    def ok(self) -> bool:
        return self.error is None


class FrameSource:
    """Frames of one sequence, read lazily.

    Attributes:
        path: the path given to :func:`open_frames`.
        location: where the frames come from as the user wrote it (``str(path)``; a stream's URL
            as given: a Path would fold its ``//`` into ``/``).
        name: sequence name (folder name, KITTI drive folder name or video file stem).
        kind: ``"folder"``, ``"video"``, ``"kitti_drive"``, ``"camera"``, ``"stream"`` or ``"stdin"``.
        frame_names: frame names in order; None for a video until it was read to the end, and
            for live sources (their length is 0: unknown).
        fps: frames per second of a video (None for folders or when the container does not say).
        default_calib: calibration file that belongs to these frames (a dataset layout's, e.g. KITTI
            raw ``calib_cam_to_cam.txt``, or a ``<name>.calib.txt`` beside them), or None.
        layout: the dataset layout the folder was recognised as (:mod:`geonet_infer.io.layouts`), or None.
        truncated: for a video read to the end that decoded fewer frames than its container
            lists, ``"decoded N of M frames"``; else None.
        missing: names of the frames the container lists but that did not decode (with ``truncated``).
        ended_early: for a video that ended cleanly a little before its container's frame count (a
            note, not a failure: such counts are often approximate), what happened; else None.
    """

    truncated: str | None = None
    ended_early: str | None = None
    missing: tuple[str, ...] = ()
    layout: SequenceLayout | None = None

    def own_camera(self):
        """The calibration that comes with the frames (their layout's, or the side file), or None."""
        if self.layout is not None and (self.layout.calib is not None or self.layout.tum_camera is not None):
            return self.layout.camera()
        if self.default_calib is not None:
            from geonet_infer.io.calib import read_camera

            return read_camera(self.default_calib)
        return None

    def __init__(
        self,
        path: Path,
        name: str,
        kind: str,
        frame_names: list[str] | None = None,
        fps: float | None = None,
        default_calib: Path | None = None,
    ):
        self.path = path
        self.location = str(path)
        self.name = name
        self.kind = kind
        self.frame_names = frame_names
        self.fps = fps
        self.default_calib = default_calib

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def __len__(self) -> int:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(kind={self.kind!r}, name={self.name!r}, path={str(self.path)!r})"


class _ImageFolderSource(FrameSource):
    """A folder of image files (also a KITTI drive's ``image_02/data``), in file-name order."""

    def __init__(
        self,
        path: Path,
        folder: Path,
        name: str,
        kind: str,
        default_calib: Path | None = None,
        files: list[Path] | None = None,
    ):
        self.files = list_images(folder) if files is None else files
        stems = [p.stem for p in self.files]
        if len(set(stems)) != len(stems):
            dup = sorted({s for s in stems if stems.count(s) > 1})
            raise InputError(
                folder,
                f"several images share the frame name '{dup[0]}'",
                "keep one file per frame (outputs are named after the frame)",
            )
        super().__init__(path, name, kind, stems, None, default_calib)

    def __iter__(self) -> Iterator[Frame]:
        for p in self.files:
            try:
                yield Frame(p.stem, rgb=read_image(p))
            except GeoNetError as err:
                yield Frame(p.stem, error=err)
            except OSError as err:  # one unreadable frame (permission, I/O error) fails that frame only
                yield Frame(p.stem, error=InputError(p, f"cannot read it ({err.strerror or err})", ""))

    def __len__(self) -> int:
        return len(self.files)


class _VideoSource(FrameSource):
    """A video file decoded with cv2.VideoCapture; frames are named 000000, 000001, ..."""

    def __init__(self, path: Path):
        try:
            str(path).encode("utf-8")
        except UnicodeEncodeError:  # cv2.VideoCapture crashes the interpreter on such a name
            raise InputError(
                path, "OpenCV cannot open a video whose path is not valid UTF-8", "rename the file or its folders"
            ) from None
        cap = cv2.VideoCapture(str(path))
        try:
            ok = cap.isOpened()
            if ok:  # before the first decode: FFmpeg allocates whatever the header claims
                width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
                images.check_pixels(path, width, height)
            first = cap.read()[1] if ok else None
            fps = float(cap.get(cv2.CAP_PROP_FPS)) if ok else 0.0
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if ok else 0
        finally:
            cap.release()
        if first is None:
            why = "OpenCV decoded no frame" if ok else "OpenCV could not open it"
            raise InputError(
                path, f"cannot open this video ({why})", f"is it a valid video file ({' '.join(VIDEO_SUFFIXES)})?"
            )
        self._count = max(count, 1)
        super().__init__(path, path.stem, "video", None, fps if fps > 0 else None, None)

    def __iter__(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path))
        names: list[str] = []
        try:
            while True:
                ok, bgr = cap.read()
                if not ok or bgr is None:
                    break
                name = f"{len(names):06d}"
                names.append(name)
                yield Frame(name, rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        finally:
            cap.release()
        # Only reached when read to the end (not when the caller stopped early).
        if not names:
            raise InputError(
                self.path, "cannot open this video (OpenCV decoded no frame)", "the file changed since it was opened?"
            )
        if len(names) < self._count:
            self._short_end(cap, len(names))
        self.frame_names = names

    def _short_end(self, cap: cv2.VideoCapture, decoded: int) -> None:
        """The video stopped before its header's frame count: a clean end or a decode error?

        OpenCV tells neither apart directly (FFmpeg's errors only reach its log). Container counts are
        often approximate (an edit list cutting the last frames: project_video_clip_a.mp4 lists 210 frames,
        FFmpeg itself decodes 201 without an error), so a stop within :data:`CLEAN_END_SHORTFALL_S` of
        the count, after which not one more frame can be grabbed, is a clean end (``ended_early``, a
        note); a bigger shortfall, or frames that still come after the stop, is a decode error
        (``truncated``, the frames missing are failures)."""
        cap.open(str(self.path))  # the released capture: grab past the stop from a fresh one
        cap.set(cv2.CAP_PROP_POS_FRAMES, decoded)
        more = sum(1 for _ in range(4) if cap.grab())
        cap.release()
        shortfall = self._count - decoded
        if not more and shortfall <= CLEAN_END_SHORTFALL_S * (self.fps or FALLBACK_FPS):
            self.ended_early = (
                f"the video ended after {decoded} frames, {shortfall} before its header's count of "
                f"{self._count} (container counts are often approximate)"
            )
            return
        self.truncated = f"decoded {decoded} of {self._count} frames"
        if shortfall <= MAX_MISSING_LISTED:
            self.missing = tuple(f"{i:06d}" for i in range(decoded, self._count))
        else:  # a header that claims far more than the file held: one record, never one per claimed frame
            self.missing = (f"{decoded:06d}-{self._count - 1:06d}",)
            self.truncated += f" (the {shortfall} frames its header lists beyond them did not decode)"

    def __len__(self) -> int:
        """Frame count: exact once read to the end, before that the container's (may be inexact)."""
        return len(self.frame_names) if self.frame_names is not None else self._count


class _CaptureSource(FrameSource):
    """A camera (index) or a stream URL read with cv2.VideoCapture until it ends; frames 000000, ..."""

    def __init__(self, spec: str):
        self.spec = spec
        self.target = _camera_index(spec)
        kind = "camera" if isinstance(self.target, int) else "stream"
        cap = cv2.VideoCapture(self.target)
        try:
            if not cap.isOpened():
                raise InputError(
                    spec,
                    f"OpenCV cannot open this {kind}",
                    "check the camera index (0 is the first camera) or that the URL plays (e.g. with ffplay)",
                )
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            # the size INPUT has to keep to (0 where the stream does not tell before its first frame)
            width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            images.check_pixels(spec, width, height)
        finally:
            cap.release()
        super().__init__(
            Path(spec), f"{kind}_{spec}" if kind == "camera" else kind, kind, None, fps if fps > 0 else None
        )
        self.location = spec

    def __iter__(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(self.target)
        try:
            index = 0
            while True:
                ok, bgr = cap.read()
                if not ok or bgr is None:
                    return
                name = f"{index:06d}"
                index += 1
                try:  # a stream may change its size: a frame over the cap fails alone
                    images.check_pixels(self.spec, bgr.shape[1], bgr.shape[0])
                except GeoNetError as err:
                    yield Frame(name, error=err)
                    continue
                yield Frame(name, rgb=cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        finally:
            cap.release()

    def __len__(self) -> int:
        return 0  # live: unknown


class _RawStdinSource(FrameSource):
    """Raw rgb24 frames of one size on a byte stream (``ffmpeg ... -f rawvideo -pix_fmt rgb24 -``)."""

    def __init__(self, width: int, height: int, stream: BinaryIO | None = None, fps: float | None = None):
        if width < 8 or height < 8:
            raise InputError(
                "-", f"--stdin-frames {width}x{height} is too small", "give the frames' WxH, e.g. 1280x720"
            )
        images.check_pixels(Path("-"), width, height)
        self.width, self.height = width, height
        self.stream = stream
        super().__init__(Path("-"), "stdin", "stdin", None, fps)

    def __iter__(self) -> Iterator[Frame]:
        stream = self.stream if self.stream is not None else sys.stdin.buffer
        size = self.width * self.height * 3
        index = 0
        while True:
            buffer = bytearray(size)
            got = _read_into(stream, memoryview(buffer))
            if got == 0:
                return
            if got < size:  # the producer stopped inside a frame, or the frames are not WxH: fails, named
                self.truncated = (
                    f"the stream ended inside frame {index:06d} ({got} of {size} bytes); if the frames are not "
                    f"{self.width}x{self.height} (--stdin-frames), every frame was read wrong"
                )
                self.missing = (f"{index:06d}",)
                return
            rgb = np.frombuffer(buffer, np.uint8).reshape(self.height, self.width, 3)
            yield Frame(f"{index:06d}", rgb=rgb)
            index += 1

    def __len__(self) -> int:
        return 0  # live: unknown


def _read_into(stream: BinaryIO, view: memoryview) -> int:
    """Fill ``view`` from ``stream``; fewer bytes only at the end of the stream."""
    filled = 0
    while filled < len(view):
        n = stream.readinto(view[filled:])  # type: ignore[attr-defined]
        if not n:
            break
        filled += n
    return filled


def _camera_index(spec: str) -> int | str:
    """--source as a camera index (ASCII digits: '²' is a digit to str.isdigit, not to int) or a URL."""
    if not re.fullmatch(r"[0-9]+", spec):
        return spec
    if int(spec) > MAX_CAMERA_INDEX:  # OpenCV takes a C int; past it, a traceback
        raise InputError(spec, f"camera index over {MAX_CAMERA_INDEX}", "0 is the first camera, 1 the second, ...")
    return int(spec)


def open_stream(spec: str) -> FrameSource:
    """A camera index ("0") or a stream URL OpenCV can open (rtsp://, http://, a device path)."""
    return _CaptureSource(spec)


def open_stdin(width: int, height: int, stream: BinaryIO | None = None, fps: float | None = None) -> FrameSource:
    """Raw rgb24 frames of ``width`` x ``height`` read from ``stream`` (default: standard input)."""
    return _RawStdinSource(width, height, stream, fps)


def find_side_calib(path: Path) -> Path | None:
    """The calibration file beside a video, image or folder of frames: ``<name>.calib.txt`` next to
    it (``clip.mp4`` -> ``clip.calib.txt``, ``frames/`` -> ``frames.calib.txt``), or None."""
    p = Path(os.path.abspath(path))
    side = p.parent / f"{p.stem if p.is_file() else p.name}{SIDE_CALIB_SUFFIX}"
    return side if side.is_file() else None


def open_frames(path) -> FrameSource:
    """Open a video file, a KITTI raw drive or a folder of images as a :class:`FrameSource`.

    * A file with suffix .mp4 .avi .mov .mkv .webm: a video (OpenCV; BGR converted to RGB).
    * An image file (:data:`~geonet_infer.io.images.IMAGE_SUFFIXES`): a one-frame ``"image"``
      source (depth; pose and flow need a sequence).
    * A folder of a dataset layout (:mod:`geonet_infer.io.layouts`: a KITTI raw drive, a KITTI
      odometry sequence, EuRoC, TUM RGB-D), or its frames folder: its frames, ``kind`` the layout's,
      and its calibration (:meth:`FrameSource.own_camera`).
    * Any other folder: its images (:func:`~geonet_infer.io.images.list_images`), in natural order.
    * A video, an image or a folder of frames with a ``<name>.calib.txt`` beside it
      (:func:`find_side_calib`): that file is its ``default_calib``, as a KITTI drive's is.

    Iterating yields :class:`Frame`; a frame that cannot be decoded is yielded with its
    ``error`` set (naming the file), so callers can report it and go on.

    Raises:
        GeoNetError naming the path if it does not exist, is an unsupported file,
        a folder without images, or a video OpenCV cannot open or decode a frame from.
    """
    given = Path(path)
    if not given.exists():
        raise InputError(given, "not found", "pass a video file, a folder of images or a KITTI raw drive folder")
    p = Path(os.path.abspath(given))  # lexical: keeps a symlinked image_02/data inside its drive layout
    if p.is_file():
        if p.suffix.lower() in VIDEO_SUFFIXES:
            video = _VideoSource(given)
            video.default_calib = find_side_calib(given)
            return video
        if p.suffix.lower() in IMAGE_SUFFIXES:  # one photo: depth (pose and flow need a sequence)
            return _ImageFolderSource(given, given.parent, given.stem, "image", find_side_calib(given), [given])
        raise InputError(
            given,
            f"not a video or an image: expected a video ({' '.join(VIDEO_SUFFIXES)}), an image "
            f"({' '.join(IMAGE_SUFFIXES)}) or a folder of frames",
            "pass a video, an image or a folder of frames",
        )
    layout = find_layout(p)
    if layout is None:
        return _ImageFolderSource(given, given, p.name, "folder", find_side_calib(given))
    source = _ImageFolderSource(given, layout.images, layout.name, layout.kind, layout.calib)
    source.layout = layout
    return source
