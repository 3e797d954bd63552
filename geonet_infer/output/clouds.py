"""Point clouds of ``predict --point-cloud``: per frame (the writer) and the world cloud of a sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from geonet_infer.core.points import write_ply
from geonet_infer.core.results import FrameResult
from geonet_infer.io.calib import Camera
from geonet_infer.output.options import OutputOptions


def ply_comments(where: str, camera_height: float | None) -> tuple[str, ...]:
    unit = f"metres (camera height {camera_height:g} m)" if camera_height is not None else "relative scale"
    return (f"geonet-infer predict: {where}", f"units: {unit}", "axes: x right, y down, z forward")


def as_predicted(camera: Camera | None, rgb: np.ndarray) -> np.ndarray:
    """The frame as the networks saw it at the input size: undistorted when the camera has distortion."""
    if camera is None or not camera.has_distortion:
        return rgb
    return camera.scaled_to(rgb.shape[1], rgb.shape[0]).undistort(rgb)


class WorldCloud:
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
        write_ply(path, self.points[0], self.colours[0], ply_comments(where, camera_height))
