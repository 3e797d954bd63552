"""Any footage, no set-up (issue 58): with no calibration flag, predict runs every task on every real
input in ../shared, and summary.json says which intrinsics it used and where they came from."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.io.camera import ASSUMED_FOCAL_PER_WIDTH
from tests.conftest import GEONET_CLI

KITTI_FX, KITTI_WIDTH = 721.5377, 1242  # KITTI raw 2011_09_26 calib_cam_to_cam.txt, P_rect_02 and S_rect_02
# input (relative to ../shared/realdata) -> the origin of its intrinsics and, where a file gives them, fx
INPUTS = {
    "udacity_dashcam/test_video.mp4": ("assumed", None),
    "kitti_odometry_06/sequences/06": ("calibration file", 707.0912),  # calib.txt P0 (grey frames 0-50 run)
    "kitti_odometry_06/sequences/06/image_0": ("calibration file", 707.0912),
    "euroc_v1_01_micro": ("calibration file", 458.654),  # mav0/cam0/sensor.yaml
    "euroc_v1_01_micro/mav0/cam0/data": ("calibration file", 458.654),
    "rgbd_kinect_slambook/color": ("assumed", None),
}


def predict(inp: Path, out: Path, *extra) -> subprocess.CompletedProcess:
    argv = [*GEONET_CLI, "predict", str(inp), "--out", str(out), "--max-frames", "6", "--no-progress", *extra]
    return subprocess.run(argv, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("name", list(INPUTS))
def test_every_real_input_runs_every_task_without_a_calibration_flag(tmp_path, require_real, name):
    origin, fx = INPUTS[name]
    proc = predict(require_real(name), tmp_path / "out")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["tasks"] == ["depth", "pose", "flow"] and summary["frames"] >= 5
    camera = summary["camera"]
    assert camera["origin"] == origin and camera["size"] == summary["image_size"]
    if fx is not None:
        assert camera["K"][0][0] == pytest.approx(fx)
    else:
        assert camera["K"][0][0] == pytest.approx(ASSUMED_FOCAL_PER_WIDTH * camera["size"][0])
        assert camera["K"][0][2] == camera["size"][0] / 2 and camera["K"][1][2] == camera["size"][1] / 2
    assert [line for line in proc.stdout.splitlines() if line.startswith("intrinsics: ")] == [
        f"intrinsics: {origin}, fx {camera['K'][0][0]:.1f} at {camera['size'][0]}x{camera['size'][1]} "
        f"({camera['source']})"
    ]


def test_a_folder_of_jpeg_frames_of_the_dashcam_clip(tmp_path, require_real):
    cap = cv2.VideoCapture(str(require_real("udacity_dashcam/test_video.mp4")))
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(6):
        ok, bgr = cap.read()
        assert ok
        cv2.imwrite(str(folder / f"frame_{i:03d}.jpg"), bgr)
    cap.release()
    proc = predict(folder, tmp_path / "out")
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["camera"]["origin"] == "assumed" and summary["frames"] == 6


def test_the_assumed_rule_is_kittis_field_of_view():
    """81.4 degrees horizontally, from KITTI's own calibration values (typed above)."""
    assert ASSUMED_FOCAL_PER_WIDTH == pytest.approx(KITTI_FX / KITTI_WIDTH)
    assert np.degrees(2 * np.arctan(0.5 / ASSUMED_FOCAL_PER_WIDTH)) == pytest.approx(81.4, abs=0.05)


def test_estimate_on_still_footage_is_refused_in_one_line(tmp_path, require_real):
    """EuRoC micro: the MAV stands on the ground. The refusal names why; the assumed intrinsics run."""
    proc = predict(require_real("euroc_v1_01_micro/mav0/cam0/data"), tmp_path / "out", "--intrinsics", "estimate")
    assert proc.returncode == 0, proc.stderr[-2000:]
    notes = [line for line in proc.stderr.splitlines() if "focal length" in line]
    assert len(notes) == 1 and "this footage cannot determine the focal length: the camera does not move" in notes[0]
    assert "assumed fx = fy = 0.5809 x width" in notes[0]
    camera = json.loads((tmp_path / "out" / "summary.json").read_text())["camera"]
    assert camera["origin"] == "assumed" and "--intrinsics estimate: this footage cannot" in camera["source"]


def test_the_api_runs_a_sequence_without_intrinsics_and_says_so():
    from geonet_infer.io import list_images

    frames = list_images(Path(geonet_infer.__file__).resolve().parent / "samples" / "synth_seq" / "image")[:3]
    predictor = geonet_infer.load()
    seq = predictor.predict_sequence(frames)
    assert seq.intrinsics["origin"] == "assumed"
    width = seq.intrinsics["size"][0]
    assert seq.intrinsics["K"][0][0] == pytest.approx(ASSUMED_FOCAL_PER_WIDTH * width)
    flow = predictor.flow(frames)
    assert flow.intrinsics["origin"] == "assumed" and np.isfinite(flow.flow).all()
    given = predictor.predict_sequence(frames, np.array(seq.intrinsics["K"]))  # the same K, given: same flow
    assert given.intrinsics["origin"] == "given"
    np.testing.assert_allclose(given.flow, seq.flow, atol=1e-4)
