"""What ``predict`` writes beyond the standard layout, and how its pictures are scaled."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from geonet_infer.errors import InputError
from geonet_infer.limits import MAX_WORLD_POINTS, check_fps
from geonet_infer.output.video import VIDEO_CODECS
from geonet_infer.output.viz import SteadyScale

DEFAULT_COLOUR_SCALE = "first:8"
POINT_CLOUDS = ("camera", "world")


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
        colour_scale: "first:N", "running" or "frame" (:class:`geonet_infer.output.viz.SteadyScale`).
        video_out: a side-by-side video (frame | depth | flow) written here (.mp4, .avi).
        video_fps: its frame rate; None = the input's (10 for frame folders).
        rerun: a rerun recording (.rrd) of the run written here (:mod:`geonet_infer.output.rerun_recording`).
        output_size: "input" (depth and flow at each frame's size) or "network" (at the network's size,
            nothing interpolated; the scale to the input is in summary.json's ``output_size``).
    """

    point_cloud: str | None = None
    point_stride: int = 2
    max_depth: float | None = None
    world_points: int = 500_000
    colour_scale: str = DEFAULT_COLOUR_SCALE
    video_out: Path | None = None
    video_fps: float | None = None
    rerun: Path | None = None
    output_size: str = "input"

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
        if self.output_size not in ("input", "network"):
            raise InputError(None, f"unknown output size {self.output_size!r}", "choose input or network")
        if self.video_fps is not None:
            check_fps(self.video_fps, "video frame rate (--fps)")
