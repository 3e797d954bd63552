"""Metric scale from camera height: closed-form road scenes, and real KITTI Velodyne depth.

Golden values are independent of the code under test: a plane's depth map written in
closed form (z = h / (n . K^-1 [u, v, 1])), and KITTI's documented camera mounting
height (1.65 m above the road, KITTI setup page) checked on projected Velodyne scans.
"""

from __future__ import annotations

import numpy as np
import pytest

from geonet_infer import GeoNetInputError
from geonet_infer.io.calib import read_camera
from geonet_infer.scale import fit_ground_plane, metric_depth
from geonet_infer.velodyne import velodyne_to_depth_map

H, W = 128, 416
K = np.array([[0.58 * W, 0, 0.5 * W], [0, 1.92 * H, 0.5 * H], [0, 0, 1.0]])


def road_scene(height_m: float, pitch_deg: float, with_car: bool = True) -> np.ndarray:
    """Metric depth of a flat road ``height_m`` below a camera pitched down by ``pitch_deg``; sky at 80 m."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    p = np.deg2rad(pitch_deg)
    normal = np.array([0.0, np.cos(p), -np.sin(p)])  # the road's normal in camera coordinates
    denom = rays @ normal
    depth = np.full((H, W), 80.0)
    ground = denom > 1e-6
    depth[ground] = np.minimum(height_m / denom[ground], 80.0)
    if with_car:  # a box 8 m ahead covering a quarter of the road pixels
        depth[int(0.55 * H) : int(0.8 * H), int(0.35 * W) : int(0.6 * W)] = 8.0
    return depth


@pytest.mark.parametrize("pitch", [0.0, 3.0, -2.0])
def test_scale_recovers_the_camera_height_of_a_closed_form_road(pitch):
    metric = road_scene(1.65, pitch)
    relative = metric * 0.137  # what a monocular net gives: right shape, unknown scale
    scaled, fit = metric_depth(relative, K, 1.65)
    assert fit.height == pytest.approx(1.65 * 0.137, rel=1e-3)
    np.testing.assert_allclose(scaled, metric, rtol=1e-3)
    tilt = np.rad2deg(np.arccos(fit.normal[1]))
    assert tilt == pytest.approx(abs(pitch), abs=0.05)


def test_noise_and_obstacles_leave_the_scale_within_two_percent():
    rng = np.random.default_rng(1)
    metric = road_scene(1.5, 1.0)
    noisy = metric * np.exp(rng.normal(0, 0.01, metric.shape))
    noisy[rng.random(metric.shape) < 0.1] *= 3.0  # 10 % wild outliers
    _, fit = metric_depth(noisy * 2.0, K, 1.5)
    assert fit.scale_for(1.5) == pytest.approx(0.5, rel=0.02)


def test_no_ground_is_a_clear_error():
    wall = np.full((H, W), 5.0)  # fronto-parallel wall: no plane near the camera's y axis
    with pytest.raises(GeoNetInputError, match="no ground plane"):
        fit_ground_plane(wall, K)
    with pytest.raises(GeoNetInputError, match="camera height"):
        metric_depth(road_scene(1.65, 0), K, -1.0)


def test_kitti_velodyne_ground_is_1_65_m_below_the_camera(realdata):
    """Projected Velodyne depth (metric) of real KITTI frames: the road lies about 1.65 m down."""
    drive = realdata / "kitti_raw_2011_09_26_sfnd"
    K2 = read_camera(drive / "calib_cam_to_cam.txt").K
    heights = []
    for velo in sorted((drive / "velodyne_points" / "data").glob("*.bin"))[:5]:
        gt = velodyne_to_depth_map(drive, velo, (375, 1242))
        heights.append(fit_ground_plane(gt, K2).height)
    assert np.median(heights) == pytest.approx(1.65, abs=0.1)


# ----------------------------------------------------------------------------- wiring in the runtime
@pytest.fixture(scope="module")
def sample():
    import geonet_infer
    from geonet_infer.io.images import list_images
    from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

    return geonet_infer.load(), list_images(SAMPLE_FRAMES)[:5], read_camera(SAMPLE_CALIB)


def test_depth_with_camera_height_is_the_relative_depth_times_one_factor(sample):
    predictor, frames, camera = sample
    relative = predictor.depth(frames[0], camera=camera)
    metric = predictor.depth(frames[0], camera=camera, camera_height=1.65)
    assert relative.metric_scale is None and metric.metric_scale > 0
    np.testing.assert_allclose(metric.depth, relative.depth * metric.metric_scale, rtol=1e-6)
    np.testing.assert_allclose(metric.disparity * metric.depth, 1.0, rtol=1e-5)
    assert fit_ground_plane(metric.depth, camera.K).height == pytest.approx(1.65, rel=1e-3)


def test_sequence_with_camera_height_scales_depth_and_translations_per_frame(sample):
    predictor, frames, camera = sample
    rel = predictor.predict_sequence(frames, K=camera)
    met = predictor.predict_sequence(frames, K=camera, camera_height=1.65)
    for a, b in zip(rel.frames, met.frames):
        np.testing.assert_allclose(b.depth, a.depth * b.metric_scale, rtol=1e-6)
        if a.pose_to_next is not None:
            np.testing.assert_allclose(b.pose_to_next[:3, :3], a.pose_to_next[:3, :3])
            np.testing.assert_allclose(b.pose_to_next[:3, 3], a.pose_to_next[:3, 3] * b.metric_scale, rtol=1e-6)
            np.testing.assert_allclose(b.flow, a.flow)  # flow is in pixels: unchanged


def test_camera_height_needs_a_camera_and_a_positive_height(sample):
    predictor, frames, camera = sample
    with pytest.raises(GeoNetInputError, match="needs the camera intrinsics"):
        predictor.depth(frames[0], camera_height=1.65)
    with pytest.raises(GeoNetInputError, match="positive number of metres"):
        predictor.depth(frames[0], camera=camera, camera_height=0)


def test_predict_cli_camera_height(tmp_path, capsys):
    import json

    from geonet_infer.cli import main
    from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

    rc = main(
        [
            "predict",
            str(SAMPLE_FRAMES),
            "--out",
            str(tmp_path / "rel"),
            "--calib",
            str(SAMPLE_CALIB),
            "--tasks",
            "depth",
            "--no-progress",
        ]
    )
    rc2 = main(
        [
            "predict",
            str(SAMPLE_FRAMES),
            "--out",
            str(tmp_path / "met"),
            "--calib",
            str(SAMPLE_CALIB),
            "--tasks",
            "depth",
            "--no-progress",
            "--camera-height",
            "1.65",
        ]
    )
    capsys.readouterr()
    assert rc == rc2 == 0
    summary = json.loads((tmp_path / "met" / "summary.json").read_text())
    assert summary["metric_scale"]["camera_height_m"] == 1.65
    rel = np.load(tmp_path / "rel" / "depth" / "000000.npy")
    met = np.load(tmp_path / "met" / "depth" / "000000.npy")
    ratio = met / rel
    assert ratio.std() / ratio.mean() < 1e-5  # one factor per frame
    assert summary["metric_scale"]["per_frame_min"] <= ratio.mean() <= summary["metric_scale"]["per_frame_max"]
