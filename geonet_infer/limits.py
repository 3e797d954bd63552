"""The limits of every size or count a user sets, defined once and checked at every entrance.

The CLI commands (predict, batch, bench), the Python API (:func:`geonet_infer.load`,
:class:`~geonet_infer.core.predictor.Predictor`, :func:`~geonet_infer.output.predict.predict_to_dir`,
:func:`~geonet_infer.batch.run_batch`), live sources and the colour scale all call the checks
here, so a value refused at one door is refused at every other (issue 41). Pixel counts of
frames are capped by :data:`geonet_infer.io.images.MAX_IMAGE_PIXELS` (checked by
:func:`geonet_infer.io.images.check_pixels`), camera heights in :mod:`geonet_infer.core.scale`.
"""

from __future__ import annotations

import math

from geonet_infer.errors import InputError

# Frames per network batch: memory grows with it, speed does not past a few (batch 100000
# held 4.85 GB on 312 frames). Also the most images one Predictor.depth() call takes.
MAX_BATCH_SIZE = 64
# The default frames per network batch (predict, batch, the Predictor's sequence calls). One: on the
# 2-core Intel Xeon of docs/performance.md larger batches were no faster in either mode (predict in
# throughput mode: 15.5 frames/s at 1, 15.4 at 2, 15.7 at 4, run-to-run spread 14-17) and held more
# (peak RSS 318, 375, 496 MiB): every intermediate of DepthNet and ResFlowNet grows with the batch (issue 54).
DEFAULT_BATCH_SIZE = 1
# "--colour-scale first:N" holds N frames' results until the scale is fixed; beyond a few dozen
# the median does not change, the memory does ("first:1000000" held 2.65 GB on 312 KITTI frames).
MAX_COLOUR_SCALE_FRAMES = 64
# ... and at most this many pixels of them: the scale of huge frames is fixed from fewer frames
# (first:8 of 49-Mpx frames held 4-5 GB). 32 Mpx of depth + flow is ~400 MB; KITTI frames fit 68.
MAX_HELD_PIXELS = 32_000_000
MAX_VIDEO_FPS = 1000.0  # no camera or player runs faster; MPEG-4 refuses more than 65535
MAX_WORLD_POINTS = 10_000_000  # points_world.ply: twice this is held in memory (~300 MB)
MAX_CAMERA_INDEX = 9999  # --source N: OpenCV's camera indices are C ints (and 10000 more than any machine has)
MAX_SEQUENCE_FRAMES = 256  # bench --seq-frames: the frames of one timed sequence call are held in memory


def check_count(value, name: str, limit: int, hint: str = "") -> int:
    """``value`` as an int in [1, ``limit``], else InputError naming ``name`` (the flag or keyword)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError(None, f"{name} must be a positive integer, got {value!r}", hint)
    if value > limit:
        raise InputError(None, f"{name} {value} is over the limit of {limit}", hint)
    return value


def check_batch_size(value, name: str = "batch_size") -> int:
    return check_count(value, name, MAX_BATCH_SIZE, "4 to 16 is plenty on a CPU")


def check_fps(value, name: str = "fps") -> float:
    """A frame rate in (0, :data:`MAX_VIDEO_FPS`]."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and 0 < value <= MAX_VIDEO_FPS):
        shown = f"{value:g}" if ok else repr(value)
        raise InputError(
            None, f"{name} {shown} is not a frame rate above 0 and at most {MAX_VIDEO_FPS:g}", "e.g. 10 or 30"
        )
    return float(value)
