"""Real validation depth from rectified KITTI stereo pairs (OpenCV SGBM), outside the test drive.

The library half of ``python -m training.stereo_val`` (which writes these frames to a folder) and
of the repository's ``python -m benchmarks.eval_all`` (which scores them): it lives in the runtime
because the runtime's evaluation needs it too (the kitti-disparity layout reads
:func:`focal_and_baseline`) and must never import ``training``. numpy + OpenCV only.

:func:`build` writes the stereo pairs of ``../shared/realdata/kitti_odometry_{00,06}`` as a
KITTI-raw layout folder: ``image_02/data/<name>.png`` (the left image) and
``proj_depth/groundtruth/image_02/<name>.png`` (depth in KITTI's 1/256 m PNG, 0 = no value).

Why: the only real Velodyne depth in ../shared is the test drive (``kitti_raw_2011_09_26_sfnd``),
and recipes must not be chosen on it. These two frames come from two other KITTI drives
(odometry sequences 00 and 06). Their depth is OpenCV's semi-global matching, kept only where
the left and right disparities agree within one pixel: ``depth = fx * baseline / disparity``,
with fx and the baseline read from the sequence's ``calib.txt`` projection matrices. It is a
noisy yardstick (two frames, SGBM errors at occlusions and on thin poles), fit for comparing
recipes, not for publishing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io import read_calib_file, read_image, require_key, write_depth_kitti, write_image

MAX_DISPARITY = 128  # px at full KITTI resolution: depths down to fx * 0.54 / 128 ≈ 3 m
BLOCK = 5
LR_TOLERANCE = 1.0  # px: left-right consistency check


@dataclass(frozen=True)
class StereoPair:
    """One rectified pair inside a KITTI odometry sequence folder."""

    name: str
    left: str  # paths relative to the sequence folder
    right: str
    left_key: str  # projection matrices in calib.txt
    right_key: str


# Colour pair where the sequence has one, else the grey pair (the net sees grey as 3 equal channels).
PAIRS = {
    "kitti_odometry_00/sequences/00": StereoPair(
        "odometry00_000000", "image_0/000000.png", "image_1/000000.png", "P0", "P1"
    ),
    "kitti_odometry_06/sequences/06": StereoPair(
        "odometry06_000012", "image_2/000012.png", "image_3/000012.png", "P2", "P3"
    ),
}


def focal_and_baseline(calib_path: Path, left_key: str, right_key: str) -> tuple[float, float]:
    """(fx in px, baseline in m) of two rectified KITTI projection matrices.

    KITTI writes ``P[0, 3] = -fx * t_x`` for a camera ``t_x`` metres right of camera 0, so the
    baseline is ``(P_left[0, 3] - P_right[0, 3]) / fx``.
    """
    calib = read_calib_file(calib_path)
    P_left = require_key(calib, left_key, calib_path).reshape(3, 4)
    P_right = require_key(calib, right_key, calib_path).reshape(3, 4)
    fx = float(P_left[0, 0])
    if not np.isclose(P_right[0, 0], fx) or not np.isclose(P_right[0, 2], P_left[0, 2]):
        raise InputError(calib_path, f"{left_key} and {right_key} are not a rectified pair", "check calib.txt")
    baseline = (P_left[0, 3] - P_right[0, 3]) / fx
    if baseline <= 0:
        raise InputError(calib_path, f"{right_key} is not right of {left_key}", "swap the keys")
    return fx, float(baseline)


def sgbm_disparity(left_grey: np.ndarray, right_grey: np.ndarray) -> np.ndarray:
    """(H, W) float32 left-image disparity in px, 0 where SGBM or the left-right check fails.

    left_grey, right_grey: (H, W) uint8 rectified images. The right image's disparity comes from
    matching the mirrored pair, so both maps come from one matcher configuration.
    """
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0,
        numDisparities=MAX_DISPARITY,
        blockSize=BLOCK,
        P1=8 * BLOCK * BLOCK,
        P2=32 * BLOCK * BLOCK,
        disp12MaxDiff=-1,  # our own left-right check below
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )
    disp_left = sgbm.compute(left_grey, right_grey).astype(np.float32) / 16.0  # OpenCV: fixed point, 4 bits
    disp_right = sgbm.compute(right_grey[:, ::-1].copy(), left_grey[:, ::-1].copy())[:, ::-1].astype(np.float32) / 16.0
    h, w = disp_left.shape
    xs = np.arange(w)[None, :].repeat(h, 0)
    x_right = np.round(xs - disp_left).astype(int)
    inside = (disp_left > 0) & (x_right >= 0)
    back = np.zeros_like(disp_left)
    rows = np.nonzero(inside)
    back[rows] = disp_right[rows[0], x_right[rows]]
    keep = inside & (np.abs(back - disp_left) <= LR_TOLERANCE)
    keep[:, :MAX_DISPARITY] = False  # the matcher cannot see these columns in the right image
    return np.where(keep, disp_left, 0.0).astype(np.float32)


def stereo_depth(left_rgb: np.ndarray, right_rgb: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """(H, W) float32 metres from a rectified pair, 0 where there is no reliable disparity."""
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (left_rgb, right_rgb)]
    disp = sgbm_disparity(*grey)
    return np.where(disp > 0, fx * baseline / np.maximum(disp, 1e-6), 0.0).astype(np.float32)


def build(realdata: Path, out: Path) -> list[dict]:
    """Write every pair of :data:`PAIRS` found under ``realdata``; returns one summary per frame."""
    image_dir = out / "image_02" / "data"
    depth_dir = out / "proj_depth" / "groundtruth" / "image_02"
    image_dir.mkdir(parents=True, exist_ok=True)
    depth_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for seq, pair in PAIRS.items():
        seq_dir = realdata / seq
        left, right = read_image(seq_dir / pair.left), read_image(seq_dir / pair.right)
        if left.shape != right.shape:
            raise InputError(seq_dir / pair.right, f"size {right.shape} differs from the left image", "")
        fx, baseline = focal_and_baseline(seq_dir / "calib.txt", pair.left_key, pair.right_key)
        depth = stereo_depth(left, right, fx, baseline)
        write_image(image_dir / f"{pair.name}.png", left)
        write_depth_kitti(depth_dir / f"{pair.name}.png", depth, too_far="zero")
        valid = depth > 0
        written.append(
            {
                "name": pair.name,
                "source": f"{seq}/{pair.left}",
                "fx": fx,
                "baseline_m": baseline,
                "valid_fraction": float(valid.mean()),
                "median_depth_m": float(np.median(depth[valid])),
            }
        )
    (out / "README.md").write_text(
        "# Stereo validation depth (written by `python -m training.stereo_val`)\n\n"
        "Left images and OpenCV SGBM depth (left-right checked) of KITTI odometry sequences 00 and 06,\n"
        "copied from ../shared/realdata. KITTI Vision Benchmark Suite, CC BY-NC-SA 3.0; cite Geiger,\n"
        "Lenz, Urtasun, CVPR 2012. Do not redistribute with the package.\n"
    )
    return written
