"""Camera geometry and warping as small pure functions (kornia style).

Conventions (defined in :mod:`geonet_infer.conventions`, repeated here only as
shapes): pose vectors are ``[tx, ty, tz, rx, ry, rz]`` with
``R = Rx @ Ry @ Rz`` and map points from the *target* camera to the *source*
camera; pixels are ``u = 0..W-1``, ``v = 0..H-1`` at pixel centres; flow is in
pixels, channel 0 = x (u), channel 1 = y (v).

Everything here is export-safe: no ``torch.inverse`` (ONNX has no matrix
inverse); the pinhole K and rigid transforms are inverted in closed form.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from geonet_infer.conventions import INTRINSICS, SAMPLER

DEPTH_EPS = 1e-10  # official: z + 1e-10 before the perspective divide (no clamp)


def euler_to_rotation(angles: torch.Tensor) -> torch.Tensor:
    """Euler angles -> rotation matrices, ``R = Rx(rx) @ Ry(ry) @ Rz(rz)``.

    Args:
        angles: (B, 3) ``[rx, ry, rz]`` in radians, clipped to [-pi, pi] as the
            official code does.
    Returns:
        (B, 3, 3) rotation matrices.
    """
    angles = angles.clamp(-math.pi, math.pi)
    rx, ry, rz = angles.unbind(-1)
    cx, sx = torch.cos(rx), torch.sin(rx)
    cy, sy = torch.cos(ry), torch.sin(ry)
    cz, sz = torch.cos(rz), torch.sin(rz)
    # Closed-form product Rx @ Ry @ Rz, written out so the graph is elementwise.
    rows = [
        cy * cz,
        -cy * sz,
        sy,
        cx * sz + sx * sy * cz,
        cx * cz - sx * sy * sz,
        -sx * cy,
        sx * sz - cx * sy * cz,
        sx * cz + cx * sy * sz,
        cx * cy,
    ]
    return torch.stack(rows, dim=-1).reshape(angles.shape[0], 3, 3)


def pose_vec_to_mat(pose: torch.Tensor) -> torch.Tensor:
    """Pose vector -> homogeneous transform (target -> source).

    Args:
        pose: (B, 6) ``[tx, ty, tz, rx, ry, rz]``.
    Returns:
        (B, 4, 4) ``[[R, t], [0, 0, 0, 1]]``.
    """
    R_3x3 = euler_to_rotation(pose[:, 3:])
    t_3x1 = pose[:, :3].unsqueeze(-1)
    top_3x4 = torch.cat([R_3x3, t_3x1], dim=-1)
    bottom_1x4 = pose.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(pose.shape[0], 1, 4)
    return torch.cat([top_3x4, bottom_1x4], dim=1)


def invert_rigid(T: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of a rigid transform: ``[R^T, -R^T t]``.

    The official code uses a general 4x4 matrix inverse; for a rigid transform
    the two agree, and this form exports to ONNX.

    Args:
        T: (B, 4, 4) rigid transforms.
    Returns:
        (B, 4, 4) inverses.
    """
    R_t = T[:, :3, :3].transpose(1, 2)
    t_inv = -R_t @ T[:, :3, 3:]
    top_3x4 = torch.cat([R_t, t_inv], dim=-1)
    return torch.cat([top_3x4, T[:, 3:, :]], dim=1)


def invert_intrinsics(K: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse of an upper-triangular pinhole matrix.

    Args:
        K: (B, 3, 3) ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.
    Returns:
        (B, 3, 3) K^-1.
    """
    fx, s, cx = K[:, 0, 0], K[:, 0, 1], K[:, 0, 2]
    fy, cy = K[:, 1, 1], K[:, 1, 2]
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    rows = [
        1.0 / fx,
        -s / (fx * fy),
        (s * cy - cx * fy) / (fx * fy),
        zero,
        1.0 / fy,
        -cy / fy,
        zero,
        zero,
        one,
    ]
    return torch.stack(rows, dim=-1).reshape(-1, 3, 3)


def intrinsics_at_scale(K: torch.Tensor, scale: int) -> torch.Tensor:
    """K of pyramid level ``scale``: fx, fy, cx, cy divided by 2**scale.

    No half-pixel correction, as in the official code.

    Args:
        K: (B, 3, 3) at full resolution.
    Returns:
        (B, 3, 3) at H / 2**scale.
    """
    factor = INTRINSICS.per_scale_divisor**scale
    row_scale = K.new_tensor([1.0 / factor, 1.0 / factor, 1.0]).reshape(1, 3, 1)
    return K * row_scale


def pixel_grid(height: int, width: int, like: torch.Tensor) -> torch.Tensor:
    """Homogeneous pixel coordinates.

    Returns:
        (1, 3, H, W): channel 0 = u in 0..W-1, 1 = v in 0..H-1, 2 = ones.
    """
    v, u = torch.meshgrid(
        torch.arange(height, dtype=like.dtype, device=like.device),
        torch.arange(width, dtype=like.dtype, device=like.device),
        indexing="ij",
    )
    return torch.stack([u, v, torch.ones_like(u)], dim=0).unsqueeze(0)


def backproject(depth: torch.Tensor, K_inv: torch.Tensor) -> torch.Tensor:
    """Pixels with depth -> 3-D points in the camera frame, ``X = D * K^-1 [u, v, 1]``.

    Args:
        depth: (B, 1, H, W).
        K_inv: (B, 3, 3).
    Returns:
        points_cam: (B, 3, H, W).
    """
    B, _, H, W = depth.shape
    pix_1x3xHW = pixel_grid(H, W, depth).reshape(1, 3, H * W)
    rays_Bx3xHW = K_inv @ pix_1x3xHW
    return rays_Bx3xHW.reshape(B, 3, H, W) * depth


def project(points_cam: torch.Tensor, K: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Transform points by T, then project with K.

    Args:
        points_cam: (B, 3, H, W) in the frame T maps from.
        K: (B, 3, 3).
        T: (B, 4, 4).
    Returns:
        pixels: (B, 2, H, W) ``(x / (z + 1e-10), y / (z + 1e-10))``; no clamp on z.
    """
    B, _, H, W = points_cam.shape
    P_3x4 = K @ T[:, :3, :]
    points_Bx3xHW = points_cam.reshape(B, 3, H * W)
    projected = P_3x4[:, :, :3] @ points_Bx3xHW + P_3x4[:, :, 3:]
    xy, z = projected[:, :2], projected[:, 2:]
    return (xy / (z + DEPTH_EPS)).reshape(B, 2, H, W)


def rigid_flow(
    depth: torch.Tensor, T: torch.Tensor, K: torch.Tensor, K_inv: torch.Tensor | None = None
) -> torch.Tensor:
    """Optical flow induced by camera motion on a static scene.

    Args:
        depth: (B, 1, H, W) depth of the frame the flow starts in.
        T: (B, 4, 4) transform from that frame to the other camera.
        K: (B, 3, 3) intrinsics at H x W.
        K_inv: optional precomputed inverse of K.
    Returns:
        flow: (B, 2, H, W) in pixels, ``projected - grid``.
    """
    if K_inv is None:
        K_inv = invert_intrinsics(K)
    _, _, H, W = depth.shape
    points = backproject(depth, K_inv)
    return project(points, K, T) - pixel_grid(H, W, depth)[:, :2]


def sample_points(flow: torch.Tensor) -> torch.Tensor:
    """Where ``flow`` samples the other frame: ``(u + flow_x, v + flow_y)`` per pixel.

    Args:
        flow: (B, 2, H, W) pixels.
    Returns:
        (B, 2, H, W) pixel coordinates in the sampled frame.
    """
    _, _, H, W = flow.shape
    return pixel_grid(H, W, flow)[:, :2] + flow


def flow_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample ``image`` at ``grid + flow`` with bilinear interpolation.

    Corner-aligned: pixel u maps to ``2u / (W - 1) - 1`` with
    ``align_corners=True``, so integer flows reproduce integer shifts exactly.

    Border rule (a documented deviation): outside the image we use
    ``padding_mode='zeros'``, i.e. a sample half-way past the last column gets
    half the weight of that column. The official TF sampler instead returns 0
    (with zero gradient) for any coordinate with x < 0, x >= W-1, y < 0 or
    y >= H-1. The two agree everywhere except that one-pixel band; ours keeps
    gradients at the border and maps to ONNX GridSample (opset 16+).

    Args:
        image: (B, C, H, W) any channels (images, flows).
        flow: (B, 2, H, W) pixels, from the sampled frame's grid.
    Returns:
        warped: (B, C, H, W).
    """
    _, _, H, W = flow.shape
    coords = sample_points(flow)
    # Normalise each axis to [-1, 1]; max(., 1) guards a 1-pixel-wide axis.
    norm_x = coords[:, 0] * (2.0 / max(W - 1, 1)) - 1.0
    norm_y = coords[:, 1] * (2.0 / max(H - 1, 1)) - 1.0
    grid_BxHxWx2 = torch.stack([norm_x, norm_y], dim=-1)
    return F.grid_sample(
        image, grid_BxHxWx2, mode="bilinear", padding_mode=SAMPLER.padding, align_corners=SAMPLER.align_corners
    )


def in_view_mask(flow: torch.Tensor) -> torch.Tensor:
    """Pixels whose flow lands inside the sampled frame: ``0 <= u+fx <= W-1``, same for v.

    Args:
        flow: (B, 2, H, W) pixels.
    Returns:
        (B, 1, H, W) float 0/1, no gradient.
    """
    _, _, H, W = flow.shape
    coords = sample_points(flow)
    inside = (coords[:, 0] >= 0) & (coords[:, 0] <= W - 1) & (coords[:, 1] >= 0) & (coords[:, 1] <= H - 1)
    return inside.unsqueeze(1).to(flow.dtype)


def l2_norm(x: torch.Tensor) -> torch.Tensor:
    """Official ``L2_norm``: ``|| |x| + 1e-10 ||_2`` over channels.

    Args:
        x: (B, C, H, W).
    Returns:
        (B, 1, H, W).
    """
    return torch.sqrt(((x.abs() + 1e-10) ** 2).sum(dim=1, keepdim=True))


def flow_consistency(
    flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, scale: int, alpha: float = 3.0, beta: float = 0.05
):
    """Forward-backward consistency of a flow pair at pyramid level ``scale``.

    A pixel is consistent when ``||df|| * 2^s < max(alpha, beta * ||f|| * 2^s)``,
    where ``df = |f_bwd warped by f_fwd + f_fwd|``; the bound is constant
    (no gradient), as in the official code.

    Args:
        flow_fwd: (B, 2, H, W) flow of frame a -> b.
        flow_bwd: (B, 2, H, W) flow of frame b -> a.
    Returns:
        (diff_fwd (B, 2, H, W), mask_fwd (B, 1, H, W) float 0/1) for frame a.
        Call again with the arguments swapped for frame b.
    """
    diff = (flow_warp(flow_bwd, flow_fwd) + flow_fwd).abs()
    level = 2.0**scale
    bound = torch.clamp(beta * l2_norm(flow_fwd) * level, min=alpha).detach()
    mask = (l2_norm(diff) * level < bound).float()
    return diff, mask
