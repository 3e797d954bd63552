"""A predict run as a rerun recording (``predict --rerun FILE.rrd``, :func:`record_sequence`; issue 59).

On the ``frame`` time line, under ``world/`` (x right, y down, z forward: the first camera's frame):

* ``world/camera``          the camera's pose (``Transform3D``, camera-to-world);
* ``world/camera/image``    its pinhole (K, size), the RGB frame (JPEG), ``depth`` (``DepthImage``, float16;
                            metres with ``--camera-height``) and ``flow`` (the flow's colour wheel, JPEG);
* ``world/points``          a subsampled coloured point cloud of the frame, placed by the pose;
* ``check/*``               the output check per pair: flow, rigid flow and no-motion errors (grey levels).

A blueprint saved in the file lays out a 3-D view, the frame, depth and flow, and the check's series.
rerun-sdk is the ``[viz]`` extra; without it :func:`require_rerun` says what to install. The file is
written under a temporary name beside its place and renamed when the recording is closed (a file whose
stream was only flushed has no footer and does not read back; :func:`geonet_infer.io.atomic.atomic_write`), so
no half-written file is left.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import ModuleType

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.output import ownership
from geonet_infer.output.viz import flow_to_color

INSTALL = "pip install 'geonet-infer[viz]' (rerun-sdk)"
POINT_STRIDE = 8  # every 8th pixel in u and v: ~7,000 points of a 1242x375 frame
JPEG_QUALITY = 85
APPLICATION_ID = "geonet-infer"


def require_rerun() -> ModuleType:
    """The rerun module, or an InputError saying which extra to install."""
    try:
        import rerun
    except ImportError:
        raise InputError(None, "--rerun needs rerun-sdk, which is not installed", INSTALL) from None
    return rerun


def check_rerun_path(path: Path, out_dir: Path) -> None:
    """Refuse a path predict may not write: a folder, a missing parent, or an existing file outside
    ``out_dir`` (predict never overwrites what it did not write; inside OUT the run owns its files)."""
    path = Path(path)
    if path.suffix.lower() != ".rrd":
        raise InputError(path, "a rerun recording must end in .rrd", "e.g. --rerun drive.rrd")
    if not path.parent.is_dir():
        raise InputError(path.parent, "folder not found", "create it first")
    if path.exists() and not ownership.inside(path, out_dir):
        raise InputError(path, "exists: predict does not overwrite a file it did not write", "choose a new name")


def blueprint(rr: ModuleType):
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="camera path and points"),
            rrb.Vertical(
                rrb.Spatial2DView(origin="world/camera/image", contents=["$origin", "$origin/depth"], name="frame"),
                rrb.Spatial2DView(origin="world/camera/image/flow", name="flow"),
                rrb.TimeSeriesView(origin="check", name="output check (grey levels)"),
            ),
        ),
        collapse_panels=True,
    )


class RecordingDropped(Exception):
    """Ends the recording's atomic write without keeping the file (no frame, or the run failed)."""


class RerunRecording:
    """One predict run's recording; :meth:`frame` per result, :meth:`close` at the end."""

    def __init__(self, path: Path, point_stride: int = POINT_STRIDE):
        rr = require_rerun()
        self.rr, self.path, self.point_stride = rr, Path(path), point_stride
        self._write = contextlib.ExitStack()  # the temp file of atomic_write: renamed in close(keep=True)
        tmp = self._write.enter_context(atomic_write(self.path))
        self.stream = rr.RecordingStream(APPLICATION_ID)
        self.stream.save(tmp, default_blueprint=blueprint(rr))
        self.frames = 0
        self.bytes = 0

    def frame(self, result, rgb: np.ndarray | None) -> None:
        """Log one :class:`~geonet_infer.core.results.FrameResult` (and its input frame, RGB uint8)."""
        rr, log = self.rr, self.stream.log
        self.stream.set_time("frame", sequence=result.index)
        pose = np.asarray(result.camera_to_world, np.float64)
        log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        size = None
        if rgb is not None:
            size = rgb.shape[:2]
            log("world/camera/image", rr.Image(np.ascontiguousarray(rgb)).compress(jpeg_quality=JPEG_QUALITY))
        if result.depth is not None:
            size = result.depth.shape
            meter = 1.0 if result.metric_scale is not None else None  # metres with --camera-height
            # float16: ~3 significant digits (the depth16 output's), half the bytes of float32
            log("world/camera/image/depth", rr.DepthImage(result.depth.astype(np.float16), meter=meter))
        if result.flow is not None:
            log("world/camera/image/flow", rr.Image(flow_to_color(result.flow)).compress(jpeg_quality=JPEG_QUALITY))
        if result.intrinsics is not None and size is not None:
            log("world/camera/image", rr.Pinhole(image_from_camera=result.intrinsics, resolution=[size[1], size[0]]))
        if result.depth is not None and result.intrinsics is not None:
            xyz, colours = result.points(rgb, stride=self.point_stride)
            world = xyz.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            log("world/points", rr.Points3D(world.astype(np.float32), colors=colours))
        check = result.check
        if check is not None:
            for name in ("flow_error", "rigid_error", "still_error"):
                value = getattr(check, name, None)
                if value is not None:
                    log(f"check/{name}", rr.Scalars(float(value)))
        self.frames += 1

    def close(self, keep: bool) -> None:
        """End the stream (it writes the footer); keep the file under its name, or remove it."""
        with contextlib.suppress(Exception):
            self.stream.disconnect()
        if keep and self.frames:
            self._write.close()  # atomic_write renames the temp onto the path, with a new file's mode
            self.bytes = self.path.stat().st_size
        else:  # atomic_write removes its temp when its body ends in an exception
            self._write.__exit__(RecordingDropped, RecordingDropped(), None)


def record_sequence(path: str | Path, results, frames=None, point_stride: int = POINT_STRIDE) -> Path:
    """Write the results of :meth:`Predictor.iter_sequence` (and their frames, RGB uint8) as a rerun
    recording: the API's ``--rerun``. Returns the path."""
    recording = RerunRecording(Path(path), point_stride)
    ok = False
    try:
        for k, result in enumerate(results):
            recording.frame(result, None if frames is None else np.asarray(frames[k]))
        ok = True
    finally:
        recording.close(keep=ok)
    return Path(path)
