"""What INT8 is calibrated on (issue 60, item 4): the K each kind of calibration folder gives, and the
feeds of each graph, against values typed or built here (the spec's snippet order: [t, t-1, t+1] and
[t, t-2, t-1, t+1, t+2]; ResFlowNet's 12 channels: target, source, warped source, rigid flow, error)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.convert.frames import calibration_intrinsics, depth_feeds, pose_feeds, resflow_feeds
from geonet_infer.core.spec import InputSpec

H, W = 128, 416
ORIGINAL = (375, 1242)  # (H, W) of the frames
SX, SY = W / 1242, H / 375


def _frames(folder: Path, n: int = 2) -> Path:
    folder.mkdir(parents=True)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.full((375, 1242, 3), 40 * i, np.uint8))
    return folder


def _expected(fx, fy, cx, cy) -> np.ndarray:
    return np.array([[fx * SX, 0, cx * SX], [0, fy * SY, cy * SY], [0, 0, 1]], np.float32)


def test_k_of_a_synthetic_sequence_folder(tmp_path):
    images = _frames(tmp_path / "seq" / "image")
    (tmp_path / "seq" / "calib.txt").write_text("K: 600 0 620 0 610 180 0 0 1\n")
    K, source = calibration_intrinsics(images, ORIGINAL, H, W)
    np.testing.assert_allclose(K, _expected(600, 610, 620, 180), rtol=1e-6)
    assert source == f"{tmp_path / 'seq' / 'calib.txt'} (K)"


def test_k_of_a_kitti_raw_drive(tmp_path):
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync"
    images = _frames(drive / "image_02" / "data")
    (tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").write_text(
        "S_rect_02: 1.242000e+03 3.750000e+02\nP_rect_02: 700 0 610 45 0 705 170 0.2 0 0 1 0.003\n"
    )
    K, source = calibration_intrinsics(images, ORIGINAL, H, W)
    np.testing.assert_allclose(K, _expected(700, 705, 610, 170), rtol=1e-6)
    assert "calib_cam_to_cam.txt" in source and "P_rect_02" in source


def test_k_of_a_kitti_odometry_grey_camera_is_p0(tmp_path):
    seq = tmp_path / "sequences" / "09"
    images = _frames(seq / "image_0")
    (seq / "calib.txt").write_text("P0: 718 0 607 0 0 718 185 0 0 0 1 0\nP2: 720 0 609 46 0 720 186 0 0 0 1 0\n")
    K, source = calibration_intrinsics(images, ORIGINAL, H, W)
    np.testing.assert_allclose(K, _expected(718, 718, 607, 185), rtol=1e-6)
    assert source.endswith("calib.txt (KITTI, P0)")


def test_k_without_any_calibration_is_kittis_scaled(tmp_path):
    K, source = calibration_intrinsics(_frames(tmp_path / "frames"), ORIGINAL, H, W)
    # KITTI 2011_09_26 P_rect_02 (721.5377, 172.854 at 1242x375), scaled to 416x128
    np.testing.assert_allclose(K, _expected(721.5377, 721.5377, 609.5593, 172.854), rtol=1e-6)
    assert source.startswith("assumed KITTI-like")


def _constant_frames(n: int) -> list[np.ndarray]:
    return [np.full((H, W, 3), 20 * (i + 1), np.uint8) for i in range(n)]


def _which(block: np.ndarray) -> int:
    """The frame a (3, H, W) network-range block came from: value 20 * (i + 1) -> i."""
    return int(round((float(block.mean()) + 1) / 2 * 255 / 20)) - 1


@pytest.mark.parametrize("seq_length, order", [(3, [1, 0, 2]), (5, [2, 0, 1, 3, 4])])
def test_posenet_feeds_follow_the_spec_order(seq_length, order):
    spec = InputSpec.from_conventions(H, W, seq_length)
    frames = _constant_frames(seq_length + 1)
    feeds = pose_feeds(frames, spec)
    assert len(feeds) == 2  # every window of seq_length consecutive frames
    for start, feed in enumerate(feeds):
        x = feed["snippet"][0]
        assert x.shape == (3 * seq_length, H, W)
        assert [_which(x[3 * k : 3 * k + 3]) for k in range(seq_length)] == [start + i for i in order]
    assert [_which(f["image"][0]) for f in depth_feeds(frames, spec)] == list(range(seq_length + 1))


def test_resflownet_feeds_are_target_then_each_source():
    predictor = geonet_infer.load()  # the bundled model: seq 3
    frames = _constant_frames(3)
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    feeds = resflow_feeds(predictor, frames, K)
    assert len(feeds) == 2  # one window, its two sources
    for source, feed in zip((0, 2), feeds):  # sources in temporal order: t-1, then t+1
        x = feed["flow_input"][0]
        assert x.shape == (12, H, W)
        assert _which(x[0:3]) == 1 and _which(x[3:6]) == source
        assert np.isfinite(x[6:12]).all()
