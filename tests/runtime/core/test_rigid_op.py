"""The rigid-flow op in numpy (geonet_infer.core.rigid) against closed-form geometry, scalar
re-implementations written here, and the exported rigidflow.onnx graph."""

from __future__ import annotations

import math

import numpy as np
import pytest

import geonet_infer
from geonet_infer.core.cascade import StageTimer, load_snippet, run_cascade
from geonet_infer.core.rigid import RigidFlowOp, photometric_error_map, pose_to_matrix, rigid_flow, warp_bilinear
from geonet_infer.engines import make_engine

K = np.array([[200.0, 0.0, 100.5], [0.0, 190.0, 40.25], [0.0, 0.0, 1.0]])


def test_pose_matrix_is_rx_ry_rz_times_points_plus_t():
    rx, ry, rz = 0.1, -0.2, 0.3
    Rx = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    Ry = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    Rz = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    T = pose_to_matrix(np.array([1.0, 2.0, 3.0, rx, ry, rz]))
    np.testing.assert_allclose(T[:3, :3], Rx @ Ry @ Rz, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_sideways_motion_over_a_plane_shifts_every_pixel_by_fx_t_over_d():
    depth = np.full((40, 60), 8.0, np.float32)
    flow = rigid_flow(depth, pose_to_matrix(np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.0])), K)
    np.testing.assert_allclose(flow[0], 200.0 * 0.4 / 8.0, atol=1e-5)
    np.testing.assert_allclose(flow[1], 0.0, atol=1e-5)


def test_forward_motion_expands_from_the_principal_point():
    depth = np.full((40, 60), 10.0, np.float32)
    flow = rigid_flow(depth, pose_to_matrix(np.array([0.0, 0.0, -2.0, 0.0, 0.0, 0.0])), K)
    v, u = np.mgrid[0:40, 0:60]
    # z' = 10 - 2 = 8: a pixel moves away from (cx, cy) by the factor 10 / 8
    np.testing.assert_allclose(flow[0], (u - K[0, 2]) * (10 / 8 - 1), atol=1e-4)
    np.testing.assert_allclose(flow[1], (v - K[1, 2]) * (10 / 8 - 1), atol=1e-4)


def _bilinear_zero_padded(image: np.ndarray, x: float, y: float) -> np.ndarray:
    """One sample, written out: the four neighbours, zero outside the image."""
    C, H, W = image.shape
    x0, y0 = math.floor(x), math.floor(y)
    out = np.zeros(C)
    for xi, wx in ((x0, x0 + 1 - x), (x0 + 1, x - x0)):
        for yi, wy in ((y0, y0 + 1 - y), (y0 + 1, y - y0)):
            if 0 <= xi < W and 0 <= yi < H:
                out += wx * wy * image[:, yi, xi]
    return out


def test_warp_matches_a_scalar_bilinear_sampler_inside_at_and_past_the_border():
    rng = np.random.default_rng(0)
    image = rng.uniform(-1, 1, (3, 9, 13)).astype(np.float32)
    flow = rng.uniform(-4, 4, (2, 9, 13)).astype(np.float32)
    flow[:, 0, 0] = (-0.5, -0.25)  # half a pixel past the top-left corner
    flow[:, 8, 12] = (30.0, 0.0)  # far outside: zero
    warped = warp_bilinear(image, flow)
    for v in range(9):
        for u in range(13):
            expected = _bilinear_zero_padded(image, u + float(flow[0, v, u]), v + float(flow[1, v, u]))
            np.testing.assert_allclose(warped[:, v, u], expected, atol=1e-5, err_msg=f"pixel ({u}, {v})")
    assert np.all(warped[:, 8, 12] == 0)


def test_warp_by_a_whole_pixel_is_a_shift_with_a_zero_column():
    image = np.arange(2 * 5 * 7, dtype=np.float32).reshape(2, 5, 7)
    flow = np.zeros((2, 5, 7), np.float32)
    flow[0] = 1.0
    warped = warp_bilinear(image, flow)
    np.testing.assert_array_equal(warped[:, :, :-1], image[:, :, 1:])
    np.testing.assert_array_equal(warped[:, :, -1], 0)


def _ssim_at(x: np.ndarray, y: np.ndarray, v: int, u: int) -> np.ndarray:
    """SSIM of one pixel over its 3x3 window clipped to the image (count_include_pad=False)."""
    window = (slice(max(v - 1, 0), v + 2), slice(max(u - 1, 0), u + 2))
    a, b = x[(slice(None), *window)].reshape(len(x), -1), y[(slice(None), *window)].reshape(len(y), -1)
    mu_a, mu_b = a.mean(1), b.mean(1)
    var_a, var_b = (a * a).mean(1) - mu_a**2, (b * b).mean(1) - mu_b**2
    cov = (a * b).mean(1) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


@pytest.mark.parametrize("height, width", [(6, 8), (1, 5), (4, 1), (2, 2), (1, 1)])
def test_error_map_matches_ssim_and_l1_written_out_per_pixel(height, width):
    rng = np.random.default_rng(1)
    warped = rng.uniform(-1, 1, (3, height, width)).astype(np.float32)
    target = rng.uniform(-1, 1, (3, height, width)).astype(np.float32)
    alpha = 0.85
    error = photometric_error_map(warped, target, alpha)
    for v, u in np.ndindex(height, width):  # corners, edges and inside: windows of 9, 6, 4, 3, 2 and 1 pixels
        dssim = np.clip((1 - _ssim_at(warped.astype(np.float64), target.astype(np.float64), v, u)) / 2, 0, 1)
        per_channel = alpha * dssim + (1 - alpha) * np.abs(warped[:, v, u] - target[:, v, u]) + 1e-10
        assert error[v, u] == pytest.approx(np.sqrt((per_channel**2).sum()), rel=1e-4), (v, u)
    assert np.all(photometric_error_map(target, target, alpha) < 1e-6)


def test_the_numpy_op_agrees_with_rigidflow_onnx_on_real_frames(kitti_raw):
    from geonet_infer.io import list_images, read_camera, read_image
    from geonet_infer.io.layouts import find_kitti_calib

    predictor = geonet_infer.load()
    camera = read_camera(find_kitti_calib(kitti_raw))
    frames = list_images(kitti_raw / "image_02" / "data")
    op = RigidFlowOp(alpha=0.85)  # the bundled model's graph predates the manifest key: 0.85 baked in
    # all three outputs (the predictor's own rigid op computes only what its ResFlowNet reads)
    whole_graph = make_engine(predictor.graph_set.manifest.path("rigidflow", "fp32"), "onnxruntime", None)
    for start in (0, 30, 60):
        x, cam, size = load_snippet(
            predictor.spec, [read_image(f) for f in frames[start : start + 3]], camera, StageTimer()
        )
        feeds: dict = {}
        run_cascade(predictor.graph_set, predictor.spec, x[None], [1], cam.K, size, feeds=feeds)
        graph = whole_graph.run(feeds["rigidflow"])
        ours = op.run(feeds["rigidflow"])
        # the graph computes in float32 (1e-4 px from a float64 reference here); the op in float64
        np.testing.assert_allclose(ours["rigid_flow"], graph["rigid_flow"], atol=2e-4, rtol=0)
        np.testing.assert_allclose(ours["warped"], graph["warped"], atol=1e-3, rtol=0)
        np.testing.assert_allclose(ours["error"], graph["error"], atol=1e-3, rtol=0)


def test_predictor_with_the_numpy_op_gives_the_graphs_flow(kitti_raw):
    from geonet_infer.io import list_images, read_camera
    from geonet_infer.io.layouts import find_kitti_calib

    camera = read_camera(find_kitti_calib(kitti_raw))
    frames = list_images(kitti_raw / "image_02" / "data")[:3]
    graph = geonet_infer.load().flow(frames, camera=camera)
    fast = geonet_infer.load(rigid_op="numpy")
    assert fast.graph_set.engines["rigidflow"] == "numpy"
    ours = fast.flow(frames, camera=camera)
    np.testing.assert_allclose(ours.rigid_flow, graph.rigid_flow, atol=5e-4)
    np.testing.assert_allclose(ours.flow, graph.flow, atol=0.05)
    with pytest.raises(geonet_infer.InputError, match="rigid_op"):
        geonet_infer.load(rigid_op="torch")
