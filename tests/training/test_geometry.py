"""Closed-form and cross-library checks of training.geometry.

Expected values come from hand-derived formulas or from OpenCV, never from
the functions under test.
"""

import math

import cv2
import numpy as np
import pytest
import torch

from training.geometry import (
    backproject,
    euler_to_rotation,
    flow_consistency,
    flow_warp,
    in_view_mask,
    intrinsics_at_scale,
    invert_intrinsics,
    invert_rigid,
    pose_vec_to_mat,
    rigid_flow,
)

H, W = 24, 40
K_NP = np.array([[30.0, 0.0, 19.5], [0.0, 28.0, 11.5], [0.0, 0.0, 1.0]])


@pytest.fixture(autouse=True)
def float64():
    """Closed forms are checked to 1e-6 px, so run these in double precision."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def K_t(batch=1):
    return torch.tensor(K_NP).expand(batch, 3, 3).clone()


def rot_x(a):
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def rot_y(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def rot_z(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def random_depth(seed=0):
    g = torch.Generator().manual_seed(seed)
    return 2.0 + 10.0 * torch.rand(1, 1, H, W, generator=g)


def test_euler_matches_rx_ry_rz_product():
    angles = [0.3, -0.7, 1.1]
    expected = rot_x(angles[0]) @ rot_y(angles[1]) @ rot_z(angles[2])
    got = euler_to_rotation(torch.tensor([angles]))[0].numpy()
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_identity_pose_gives_zero_flow():
    flow = rigid_flow(random_depth(), pose_vec_to_mat(torch.zeros(1, 6)), K_t())
    assert flow.abs().max().item() < 1e-6  # only the official z + 1e-10 guard perturbs it


@pytest.mark.parametrize("tx,ty,Z", [(0.5, 0.0, 10.0), (0.0, -0.3, 4.0), (0.2, 0.1, 7.5)])
def test_pure_translation_constant_depth(tx, ty, Z):
    depth = torch.full((1, 1, H, W), Z)
    flow = rigid_flow(depth, pose_vec_to_mat(torch.tensor([[tx, ty, 0, 0, 0, 0]])), K_t())
    fx, fy = K_NP[0, 0], K_NP[1, 1]
    assert torch.allclose(flow[0, 0], torch.full((H, W), fx * tx / Z), atol=1e-4)
    assert torch.allclose(flow[0, 1], torch.full((H, W), fy * ty / Z), atol=1e-4)


def test_rotation_flow_is_the_homography_K_R_Kinv():
    angles = [0.02, -0.05, 0.03]
    R = rot_x(angles[0]) @ rot_y(angles[1]) @ rot_z(angles[2])
    Hmg = K_NP @ R @ np.linalg.inv(K_NP)  # pure rotation: depth-independent homography
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    pts = Hmg @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    expected = np.stack([pts[0] / pts[2] - u.ravel(), pts[1] / pts[2] - v.ravel()]).reshape(2, H, W)
    flow = rigid_flow(random_depth(1), pose_vec_to_mat(torch.tensor([[0, 0, 0, *angles]])), K_t())
    np.testing.assert_allclose(flow[0].numpy(), expected, atol=1e-6)


def test_rigid_flow_matches_opencv_projectPoints():
    pose = [0.3, -0.1, 0.8, 0.04, -0.06, 0.02]
    depth = random_depth(2)
    flow = rigid_flow(depth, pose_vec_to_mat(torch.tensor([pose])), K_t())[0].numpy()
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.linalg.inv(K_NP) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    points = (rays * depth[0, 0].numpy().ravel()).T
    R = rot_x(pose[3]) @ rot_y(pose[4]) @ rot_z(pose[5])
    rvec, _ = cv2.Rodrigues(R)
    projected, _ = cv2.projectPoints(points, rvec, np.array(pose[:3]), K_NP, None)
    expected = projected.reshape(H, W, 2) - np.stack([u, v], axis=-1)
    np.testing.assert_allclose(flow.transpose(1, 2, 0), expected, atol=1e-6)


def test_pose_round_trip_with_closed_form_inverse():
    T = pose_vec_to_mat(torch.tensor([[0.4, -1.2, 2.0, 0.5, -0.3, 1.4], [0, 0, 0, 0, 0, 0]]))
    T_inv = invert_rigid(T)
    np.testing.assert_allclose((T @ T_inv).numpy(), np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-12)
    np.testing.assert_allclose(T_inv.numpy(), np.linalg.inv(T.numpy()), atol=1e-12)


def test_forward_then_backward_rigid_flow_returns_to_start():
    depth = random_depth(3)
    T = pose_vec_to_mat(torch.tensor([[0.1, 0.05, 0.3, 0.01, 0.02, -0.01]]))
    fwd = rigid_flow(depth, T, K_t())
    # depth seen from the other camera at the landed pixel: z of the transformed point
    points = backproject(depth, invert_intrinsics(K_t())).reshape(1, 3, -1)
    z_src = (T[:, :3, :3] @ points + T[:, :3, 3:])[:, 2]
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    landed = np.stack([u, v]) + fwd[0].numpy()
    # back-project landed pixels with z_src and apply T^-1: must return to the grid
    rays = np.linalg.inv(K_NP) @ np.vstack([landed.reshape(2, -1), np.ones(H * W)])
    pts_src = rays * z_src.numpy()
    Ti = invert_rigid(T)[0].numpy()
    back = K_NP @ (Ti[:3, :3] @ pts_src + Ti[:3, 3:])
    np.testing.assert_allclose(back[:2] / back[2], np.stack([u.ravel(), v.ravel()]), atol=1e-6)


def test_invert_intrinsics_closed_form():
    K = torch.tensor([[[700.0, 1.5, 600.0], [0.0, 690.0, 180.0], [0.0, 0.0, 1.0]]])
    np.testing.assert_allclose(invert_intrinsics(K)[0].numpy(), np.linalg.inv(K[0].numpy()), rtol=1e-12)


def test_intrinsics_at_scale_divides_by_power_of_two():
    K = intrinsics_at_scale(K_t(), 2)[0].numpy()
    np.testing.assert_allclose(K, [[30 / 4, 0, 19.5 / 4], [0, 28 / 4, 11.5 / 4], [0, 0, 1]])


def test_integer_shift_warp_reproduces_shifted_image():
    g = torch.Generator().manual_seed(4)
    image = torch.rand(1, 3, H, W, generator=g)
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0], flow[:, 1] = 3.0, -2.0  # sample source at (u + 3, v - 2)
    warped = flow_warp(image, flow)
    # warped[v, u] = image[v - 2, u + 3] wherever that pixel exists
    assert torch.allclose(warped[:, :, 2:, : W - 3], image[:, :, : H - 2, 3:], atol=1e-12)


def test_fractional_warp_matches_opencv_remap():
    g = torch.Generator().manual_seed(5)
    image = torch.rand(1, 1, H, W, generator=g, dtype=torch.float32)
    flow = (torch.rand(1, 2, H, W, generator=g, dtype=torch.float32) - 0.5) * 3
    warped = flow_warp(image, flow)[0, 0].numpy()
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    map_x, map_y = u + flow[0, 0].numpy(), v + flow[0, 1].numpy()
    expected = cv2.remap(
        image[0, 0].numpy(), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    inside = (map_x >= 0) & (map_x <= W - 1) & (map_y >= 0) & (map_y <= H - 1)
    # OpenCV quantises bilinear weights to 1/32 px: allow that much interpolation error.
    assert np.abs(warped - expected)[inside].max() < 1.0 / 32 + 1e-3


def test_consistency_mask_on_hand_built_pair():
    fwd = torch.zeros(1, 2, H, W)
    fwd[:, 0] = 2.0
    consistent_bwd = -fwd
    inconsistent_bwd = torch.zeros(1, 2, H, W)
    inconsistent_bwd[:, 0] = 3.0  # round trip lands 5 px away
    interior = (slice(None), slice(None), slice(1, H - 1), slice(1, W - 3))
    diff, mask = flow_consistency(fwd, consistent_bwd, scale=0)
    assert diff[interior].max().item() < 1e-9 and mask[interior].min().item() == 1.0
    diff, mask = flow_consistency(fwd, inconsistent_bwd, scale=0)
    assert torch.allclose(diff[:, 0][interior[:1] + interior[2:]], torch.tensor(5.0))
    assert mask[interior].max().item() == 0.0  # 5 px > max(3, 0.05 * 2)
    # At scale 2 the same 5 px misfit counts 4x, and the 2 px flow bound too: still inconsistent.
    _, mask = flow_consistency(fwd, inconsistent_bwd, scale=2)
    assert mask[interior].max().item() == 0.0
    # A 1 px misfit passes at scale 0 (1 < 3) but fails at scale 2 (4 > 3).
    slight_bwd = -fwd
    slight_bwd[:, 0] += 1.0
    assert flow_consistency(fwd, slight_bwd, scale=0)[1][interior].min().item() == 1.0
    assert flow_consistency(fwd, slight_bwd, scale=2)[1][interior].max().item() == 0.0


def test_in_view_mask_for_constant_shifts():
    flow = torch.zeros(1, 2, 5, 8)
    flow[:, 0] = 2.0  # u + 2 <= 7 keeps columns 0..5 (the bound is inclusive)
    flow[:, 1] = -1.5  # v - 1.5 >= 0 keeps rows 2..4
    expected = np.zeros((5, 8))
    expected[2:, :6] = 1.0
    np.testing.assert_array_equal(in_view_mask(flow)[0, 0].numpy(), expected)


def test_in_view_mask_of_forward_motion_matches_closed_form():
    """Camera moves forward by d at constant depth Z: u' = cx + (u - cx) * Z / (Z - d)."""
    Z, d = 5.0, 1.5
    T = pose_vec_to_mat(torch.tensor([[0.0, 0.0, -d, 0.0, 0.0, 0.0]]))
    flow = rigid_flow(torch.full((1, 1, H, W), Z), T, K_t())
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    cx, cy = K_NP[0, 2], K_NP[1, 2]
    u2, v2 = cx + (u - cx) * Z / (Z - d), cy + (v - cy) * Z / (Z - d)
    expected = (u2 >= 0) & (u2 <= W - 1) & (v2 >= 0) & (v2 <= H - 1)
    assert 0 < expected.sum() < H * W  # the border band really leaves the view
    np.testing.assert_array_equal(in_view_mask(flow)[0, 0].numpy().astype(bool), expected)
