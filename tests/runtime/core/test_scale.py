"""Metric scale from camera height: closed-form road scenes, and real KITTI Velodyne depth.

Golden values are independent of the code under test: a plane's depth map written in
closed form (z = h / (n . K^-1 [u, v, 1])), and KITTI's documented camera mounting
height (1.65 m above the road, KITTI setup page) checked on projected Velodyne scans.
"""

from __future__ import annotations

import numpy as np
import pytest

from geonet_infer import GeoNetError
from geonet_infer.core.scale import fit_ground_plane, metric_depth
from geonet_infer.eval.velodyne import velodyne_to_depth_map
from geonet_infer.io.calib import read_camera

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


def flatbed_scene(road_m: float = 1.65, bed_m: float = 0.6, bed_from_m: float = 5.0, bed_width: float = 0.8):
    """Metric depth of a level camera ``road_m`` above the road, behind a low flatbed (a car
    transporter) whose horizontal deck lies ``bed_m`` below the camera from ``bed_from_m`` ahead
    and fills the middle ``bed_width`` of the image; its front face is vertical. Closed form:
    a ray meeting y = h does so at z = h / ray_y."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray_y = (v - K[1, 2]) / K[1, 1]
    depth = np.full((H, W), 80.0)
    down = ray_y > 1e-6
    depth[down] = np.minimum(road_m / ray_y[down], 80.0)
    centre = np.abs(u - K[0, 2]) < 0.5 * bed_width * W
    z_deck = np.where(down, bed_m / np.maximum(ray_y, 1e-9), np.inf)
    on_deck = centre & down & (z_deck >= bed_from_m) & (z_deck < 80.0)
    on_face = centre & down & (z_deck < bed_from_m) & (depth > bed_from_m)
    depth[on_deck] = z_deck[on_deck]
    depth[on_face] = bed_from_m
    return depth


def test_a_deck_that_the_road_is_seen_beside_is_not_taken_for_the_road():
    """The deck holds more of the searched pixels than the road, and is as level as the road,
    but the road pixels beside it lie 2.75x beyond it along their rays: the road cannot be
    seen through, so the deck is not the ground."""
    metric = flatbed_scene()
    rows = slice(int((K[1, 2] / H + 0.05) * H), H)
    deck = np.isclose(metric[rows] * (np.arange(H)[rows, None] - K[1, 2]) / K[1, 1], 0.6)
    road = np.isclose(metric[rows] * (np.arange(H)[rows, None] - K[1, 2]) / K[1, 1], 1.65)
    assert deck.sum() > road.sum() > 0.1 * deck.size  # the premise: the deck wins a plain inlier count
    _, fit = metric_depth(metric * 0.3, K, 1.65)
    assert fit.height == pytest.approx(1.65 * 0.3, rel=1e-3)


def test_no_ground_is_a_clear_error():
    wall = np.full((H, W), 5.0)  # fronto-parallel wall: no plane near the camera's y axis
    with pytest.raises(GeoNetError, match="no ground plane"):
        fit_ground_plane(wall, K)
    with pytest.raises(GeoNetError, match="camera height"):
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


# ----------------------------------------------------------------------------- along a video
def _frame(index: int, depth: np.ndarray, forward_m: float | None):
    """A FrameResult in relative units whose pose to the next frame moves ``forward_m`` along z."""
    from geonet_infer.core.results import FrameResult

    pose = None
    if forward_m is not None:
        pose = np.eye(4)
        pose[2, 3] = -forward_m  # target -> next: the world moves back as the camera drives forward
    return FrameResult(
        index=index,
        name=f"{index:06d}",
        depth=depth.astype(np.float32),
        disparity=(1.0 / depth).astype(np.float32),
        camera_to_world=np.eye(4),
        pose_to_next=pose,
        pose_vector_to_next=None if pose is None else np.array([0, 0, -forward_m, 0, 0, 0], np.float32),
        flow=None,
        undistorted=False,
        timings_ms={},
    )


def test_frames_before_the_first_road_take_its_scale_and_later_ones_the_previous():
    """Frames 0-1 and 3 show a wall (no road); 2 and 4 a road in units of 1/0.25 and 1/0.5 of a
    metre. Expected factors by hand: 0.25 -> 4 for frames 0-3, 0.5 -> 2 for frame 4; each
    pair's 1-unit translation becomes that many metres, chained into the trajectory."""
    from geonet_infer.core.scale import metric_frames

    wall, road = np.full((H, W), 5.0), road_scene(1.65, 0.0)
    units = [(wall, None), (wall, None), (road, 0.25), (wall, None), (road, 0.5)]
    frames = [_frame(i, d * (c or 1.0), 1.0 if i < 4 else None) for i, (d, c) in enumerate(units)]
    out = list(metric_frames(iter(frames), 1.65, lambda size: K, half_window=0))  # each frame's own fit
    assert [f.metric_scale for f in out] == pytest.approx([4.0, 4.0, 4.0, 4.0, 2.0], rel=1e-3)
    _assert_scales([f.metric_scale_raw for f in out], [None, None, 4.0, None, 2.0])
    np.testing.assert_allclose(out[2].depth, road, rtol=1e-3)
    np.testing.assert_allclose(out[0].depth, wall * 4.0, rtol=1e-3)
    assert [f.camera_to_world[2, 3] for f in out] == pytest.approx([0.0, 4.0, 8.0, 12.0, 16.0], rel=1e-3)
    assert out[1].pose_vector_to_next[2] == pytest.approx(-4.0, rel=1e-3)


def _assert_scales(got: list, expected: list, rel: float = 1e-3) -> None:
    """Equal lists of factors, None (no fit) at the same places."""
    assert [g is None for g in got] == [e is None for e in expected]
    assert [g for g in got if g is not None] == pytest.approx([e for e in expected if e is not None], rel=rel)


def test_a_smoothed_sequence_takes_one_factor_for_every_frame_of_the_window():
    """The same five frames, smoothed over 7 frames each side (the default): every window holds
    both fits, 4 and 2; they lie within 2.5 robust sigmas of their median (MAD = log(2) / 2), so
    each frame gets their geometric mean sqrt(8), by hand; the raw fits stay beside it."""
    from geonet_infer.core.scale import metric_frames

    wall, road = np.full((H, W), 5.0), road_scene(1.65, 0.0)
    units = [(wall, None), (wall, None), (road, 0.25), (wall, None), (road, 0.5)]
    frames = [_frame(i, d * (c or 1.0), 1.0 if i < 4 else None) for i, (d, c) in enumerate(units)]
    out = list(metric_frames(iter(frames), 1.65, lambda size: K))
    assert [f.metric_scale for f in out] == pytest.approx([8**0.5] * 5, rel=1e-3)
    _assert_scales([f.metric_scale_raw for f in out], [None, None, 4.0, None, 2.0])
    assert [f.camera_to_world[2, 3] for f in out] == pytest.approx([i * 8**0.5 for i in range(5)], rel=1e-3)


# Golden values of the smoother, worked by hand in log units: sigma = max(1.4826 MAD, 0.05), inliers
# within 2.5 sigma of the window's median, the result exp(mean of the inliers).
@pytest.mark.parametrize(
    "raw, half_window, expected",
    [
        # one wild frame (x4) in a steady run: MAD 0, so it is 27 floors out and dropped
        ([2, 2, 2, 2, 8, 2, 2, 2, 2], 2, [2.0] * 9),
        # a real step (x2) stays a step: each window's minority side is beyond 2.5 floors
        ([2] * 6 + [4] * 6, 2, [2.0] * 6 + [4.0] * 6),
        # a 10 % wobble is kept and averaged: sqrt(1.1) at the ends, 1.1 ** (1/3) in the middle
        ([1.0, 1.1, 1.0], 1, [1.1**0.5, 1.1 ** (1 / 3), 1.1**0.5]),
        # frames without a fit: the first two wait for frame 1's window (3), frame 3 averages 3 and 5
        ([None, None, 3.0, None, 5.0], 1, [3.0, 3.0, 3.0, 15**0.5, 5.0]),
        # no fit anywhere: nothing to give
        ([None, None], 3, [None, None]),
        # window 0: each frame its own fit, a gap keeps the previous one
        ([2.0, None, 8.0], 0, [2.0, 2.0, 8.0]),
    ],
)
def test_smoother_golden_values(raw, half_window, expected):
    from geonet_infer.core.scale import smooth_scales

    _assert_scales(smooth_scales(raw, half_window), expected, rel=1e-9)


def test_smoother_decides_each_frame_half_a_window_late():
    from geonet_infer.core.scale import ScaleSmoother

    smoother = ScaleSmoother(2)
    decided = [len(smoother.push(v)) for v in [2.0, 2.0, 2.0, 2.0, 2.0]]
    assert decided == [0, 0, 1, 1, 1]  # frame t is decided when frame t + 2 is in
    assert len(smoother.finish()) == 2
    with pytest.raises(GeoNetError, match="whole number"):
        ScaleSmoother(-1)


def test_flicker_is_the_p95_of_frame_to_frame_ratios():
    from geonet_infer.core.scale import scale_flicker

    # ratios 2, 1/2, 1 -> max(r, 1/r) = 2, 2, 1; numpy's linear p95 of [1, 2, 2] is 2
    assert scale_flicker([1.0, 2.0, 1.0, 1.0]) == pytest.approx(2.0)
    assert scale_flicker([1.0, 1.0, 1.0]) == pytest.approx(1.0)
    assert scale_flicker([1.0, None, 2.0]) is None  # no consecutive pair with both fits


def test_a_video_without_a_road_names_its_first_frame(monkeypatch):
    from geonet_infer.core import scale as scale_module

    wall = np.full((H, W), 5.0)
    with pytest.raises(GeoNetError, match="no ground plane in any of the 3 frames") as err:
        list(scale_module.metric_frames(iter([_frame(i, wall, None) for i in range(3)]), 1.65, lambda size: K))
    assert str(err.value.path) == "000000"
    monkeypatch.setattr(scale_module, "MAX_FRAMES_BEFORE_GROUND", 2)
    endless = (_frame(i, wall, None) for i in range(10**6))
    with pytest.raises(GeoNetError, match="no ground plane in the first 3 frames"):
        list(scale_module.metric_frames(endless, 1.65, lambda size: K))


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
    rel = predictor.predict_sequence(frames, camera=camera)
    met = predictor.predict_sequence(frames, camera=camera, camera_height=1.65)
    for a, b in zip(rel.frames, met.frames):
        np.testing.assert_allclose(b.depth, a.depth * b.metric_scale, rtol=1e-6)
        if a.pose_to_next is not None:
            np.testing.assert_allclose(b.pose_to_next[:3, :3], a.pose_to_next[:3, :3])
            np.testing.assert_allclose(b.pose_to_next[:3, 3], a.pose_to_next[:3, 3] * b.metric_scale, rtol=1e-6)
            np.testing.assert_allclose(b.flow, a.flow)  # flow is in pixels: unchanged


def test_camera_height_needs_a_positive_height_and_assumes_a_missing_camera(sample):
    from geonet_infer.io.camera import ASSUMED_FOCAL_PER_WIDTH

    predictor, frames, camera = sample
    with pytest.raises(GeoNetError, match="smoothing window"):
        predictor.iter_sequence(frames, camera, camera_height=1.65, scale_smoothing=-1)  # before any frame
    result = predictor.depth(frames[0], camera_height=1.65)  # no camera: the assumed intrinsics
    width = result.depth.shape[1]
    assert result.intrinsics[0, 0] == pytest.approx(ASSUMED_FOCAL_PER_WIDTH * width)
    with pytest.raises(GeoNetError, match="positive number of metres"):
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
    scales = summary["metric_scale"]
    assert scales["per_frame_min"] <= ratio.mean() <= scales["per_frame_max"]
    # summary.json keeps each frame's own ground fit beside the smoothed factor that was applied
    per_frame = scales["per_frame"]
    names = sorted(p.stem for p in (tmp_path / "met" / "depth").glob("*.npy"))
    assert per_frame["frames"] == names and len(per_frame["raw"]) == len(per_frame["smoothed"]) == len(names)
    camera = read_camera(SAMPLE_CALIB)
    for i, name in enumerate(names):
        rel_i, met_i = (np.load(tmp_path / d / "depth" / f"{name}.npy") for d in ("rel", "met"))
        assert float(np.median(met_i / rel_i)) == pytest.approx(per_frame["smoothed"][i], rel=1e-5)
        own = fit_ground_plane(rel_i, camera.scaled_to(rel_i.shape[1], rel_i.shape[0]).K).scale_for(1.65)
        assert per_frame["raw"][i] == pytest.approx(own, rel=1e-5)
    assert per_frame["raw"] != pytest.approx(per_frame["smoothed"])  # the frames' fits differ: smoothing acted
    assert scales["smoothing"]["half_window_frames"] == 7
    rc = main(["predict", str(SAMPLE_FRAMES), "--out", str(tmp_path / "x"), "--scale-smoothing", "3"])
    assert rc == 2 and "pass --camera-height" in capsys.readouterr().err


def test_the_smoothing_window_is_capped(sample):
    """Issue 55: a window of 100,000 held every frame of the video in memory."""
    from geonet_infer.core.scale import MAX_SCALE_HALF_WINDOW

    predictor, frames, camera = sample
    with pytest.raises(GeoNetError, match=f"over the cap of {MAX_SCALE_HALF_WINDOW} frames each side"):
        predictor.iter_sequence(frames, camera, camera_height=1.65, scale_smoothing=100_000)
    predictor.iter_sequence(frames, camera, camera_height=1.65, scale_smoothing=MAX_SCALE_HALF_WINDOW)


def test_predict_refuses_a_window_over_the_cap_in_one_line_before_any_frame(tmp_path, capsys):
    from geonet_infer.cli import main
    from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

    out = tmp_path / "out"
    argv = ["predict", str(SAMPLE_FRAMES), "--out", str(out), "--calib", str(SAMPLE_CALIB), "--camera-height", "1.65"]
    assert main([*argv, "--scale-smoothing", "100000", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err.startswith("geonet-infer predict: error: scale smoothing window 100000 is over the cap") and "\n" not in err
    )
    assert not out.exists()
