"""The side-by-side result video of ``predict --video-out`` (frame | depth | flow)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import _umask, create_temp
from geonet_infer.output.viz import side_by_side

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}  # what OpenCV's own FFmpeg writes everywhere
VIDEO_HEIGHT = 256  # panel height of the result video: three panels side by side stay under ~1400 px
FOLDER_FPS = 10.0  # the result video's rate for frame folders (KITTI raw is 10 Hz)


class VideoOut:
    """The side-by-side result video (frame | depth | flow), streamed to a temporary file next to
    ``path`` and renamed onto it at the end (removed instead on failure)."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps = path, fps
        self.writer: cv2.VideoWriter | None = None
        self.tmp: Path | None = None
        self.frames = 0

    def write(self, rgb: np.ndarray, pictures: tuple[np.ndarray | None, np.ndarray | None]) -> None:
        """One frame: its input picture beside its depth and flow pictures (:func:`colour_pictures`; None = black)."""
        depth, flow = (np.zeros_like(rgb) if p is None else p for p in pictures)
        panel = side_by_side([rgb, depth, flow], ["frame", "depth", "flow"], height=min(VIDEO_HEIGHT, rgb.shape[0]))
        panel = panel[: panel.shape[0] // 2 * 2, : panel.shape[1] // 2 * 2]  # even sizes: what codecs expect
        if self.writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            create_temp(self.path, lambda name: setattr(self, "tmp", name))  # held before it exists: close() removes it
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
                readable = decodable_frames(tmp)
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


def decodable_frames(video: Path) -> int:
    """Frames OpenCV decodes from ``video`` (0 when it cannot be opened)."""
    cap = cv2.VideoCapture(str(video))
    try:
        count = 0
        while cap.isOpened() and cap.grab():
            count += 1
        return count
    finally:
        cap.release()
