"""KITTI Velodyne scans -> sparse ground-truth depth maps (official Eigen protocol).

Numpy only. Reproduces ``generate_depth_map`` of GeoNet's
kitti_eval/depth_evaluation_utils.py (itself from monodepth), which the
published Eigen-split numbers were computed with:

* P_velo2im = P_rect_0c @ R_rect_00 (padded to 4x4) @ [R | T] (velo -> cam 0);
  the KITTI object benchmark stores the same three matrices per frame as
  ``P2``, ``R0_rect`` and ``Tr_velo_to_cam`` (:func:`object_velodyne_to_image_matrix`),
  and both go through the one projection :func:`points_to_depth_map`;
* points with velodyne x < 0 (behind the sensor; x points forward) dropped;
* u, v = projection / z, then ``round(.) - 1`` to match the KITTI MATLAB code;
* pixels outside the image dropped; several points on one pixel keep the minimum;
* value = velodyne forward distance x (``vel_depth=True``, what GeoNet uses)
  or the projective depth (third row of P_velo2im) otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io.calib import read_calib_file


def load_velodyne_points(bin_path):
    """Read a KITTI Velodyne scan. Returns (N, 4) float32: x forward, y left, z up, reflectance."""
    bin_path = Path(bin_path)
    if not bin_path.is_file():
        raise InputError(bin_path, "Velodyne scan not found", "expected <drive>/velodyne_points/data/<frame>.bin")
    size = os.path.getsize(bin_path)
    if size % 16 != 0:
        # 4 float32 per point = 16 bytes; anything else is truncated or not a scan.
        raise InputError(
            bin_path,
            f"size {size} bytes is not a multiple of 16 (4 float32 per point)",
            "the scan is truncated or not a KITTI Velodyne .bin file",
        )
    return np.fromfile(bin_path, dtype=np.float32).reshape(-1, 4)


RAW_CALIB_HINT = "use the official KITTI raw calib_cam_to_cam.txt / calib_velo_to_cam.txt of the drive's date"
OBJECT_CALIB_HINT = "use the frame's KITTI object calib/NNNNNN.txt (P0-P3, R0_rect, Tr_velo_to_cam, Tr_imu_to_velo)"


def _calib_matrix(calib, key, shape, path, hint=RAW_CALIB_HINT):
    """calib[key] as a float64 array of ``shape``; GeoNetError naming ``path`` if absent or malformed."""
    if key not in calib:
        raise InputError(path, f"calibration key {key!r} is missing", hint)
    try:
        values = np.asarray(calib[key], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        values = np.empty(0)  # a non-numeric value: reported as a wrong count below
    if values.size != int(np.prod(shape)):
        raise InputError(
            path,
            f"calibration key {key!r} has {values.size} numbers, expected {int(np.prod(shape))}",
            f"the calibration file is truncated or not this kind of KITTI calibration; {hint}",
        )
    return values.reshape(shape)


def velodyne_to_image_matrix(calib_dir, cam=2):
    """The (3, 4) matrix P_rect_0{cam} @ R_rect_00 @ [R | T] mapping homogeneous velodyne points to pixels.

    calib_dir: folder holding calib_cam_to_cam.txt and calib_velo_to_cam.txt
    (the KITTI raw date folder).
    """
    calib_dir = Path(calib_dir)
    cam_path = calib_dir / "calib_cam_to_cam.txt"
    velo_path = calib_dir / "calib_velo_to_cam.txt"
    cam2cam = read_calib_file(cam_path)
    velo2cam = read_calib_file(velo_path)

    velo_to_cam = np.eye(4)
    velo_to_cam[:3, :3] = _calib_matrix(velo2cam, "R", (3, 3), velo_path)
    velo_to_cam[:3, 3] = _calib_matrix(velo2cam, "T", (3,), velo_path)

    # R_rect_00 rectifies camera 0; every P_rect_0c is expressed in that frame.
    rect = np.eye(4)
    rect[:3, :3] = _calib_matrix(cam2cam, "R_rect_00", (3, 3), cam_path)
    P_rect = _calib_matrix(cam2cam, f"P_rect_0{cam}", (3, 4), cam_path)
    return P_rect @ rect @ velo_to_cam


def object_velodyne_to_image_matrix(calib_path):
    """The (3, 4) matrix ``P2 @ R0_rect @ Tr_velo_to_cam`` of one KITTI object-benchmark frame.

    calib_path: the frame's ``calib/NNNNNN.txt``. It holds the KITTI raw matrices under other
    names: ``P2`` = P_rect_02, ``R0_rect`` = R_rect_00, ``Tr_velo_to_cam`` = [R | T] of
    calib_velo_to_cam.txt (3x4), so the result is what :func:`velodyne_to_image_matrix` gives
    for the drive the frame came from.
    """
    calib_path = Path(calib_path)
    calib = read_calib_file(calib_path)
    velo_to_cam = np.eye(4)
    velo_to_cam[:3, :] = _calib_matrix(calib, "Tr_velo_to_cam", (3, 4), calib_path, OBJECT_CALIB_HINT)
    rect = np.eye(4)
    rect[:3, :3] = _calib_matrix(calib, "R0_rect", (3, 3), calib_path, OBJECT_CALIB_HINT)
    P2 = _calib_matrix(calib, "P2", (3, 4), calib_path, OBJECT_CALIB_HINT)
    return P2 @ rect @ velo_to_cam


def project_velodyne(points, P_velo2im):
    """Continuous projection of velodyne points (no rounding, no filtering).

    points: (N, 3+) velodyne x, y, z (extra columns ignored). P_velo2im: (3, 4).
    Returns uv (N, 2) float64 pixel coordinates and z (N,) the third
    homogeneous coordinate (projective depth, includes P_rect[2, 3]).
    """
    xyz1 = np.ones((len(points), 4))
    xyz1[:, :3] = np.asarray(points, dtype=np.float64)[:, :3]
    proj = xyz1 @ np.asarray(P_velo2im, dtype=np.float64).T
    z = proj[:, 2]
    return proj[:, :2] / z[:, None], z


def velodyne_to_depth_map(calib_dir, velo_path, image_shape, cam=2, vel_depth=True):
    """Sparse GT depth map of one KITTI raw frame, exactly as the official evaluation.

    calib_dir: KITTI raw date folder with the two calibration files.
    velo_path: the frame's velodyne_points/data/<frame>.bin.
    image_shape: (H, W) of the camera image (375 x 1242 for 2011_09_26).
    Returns (H, W) float32 depth in metres, 0 where no point landed.
    """
    P_velo2im = velodyne_to_image_matrix(calib_dir, cam)
    return points_to_depth_map(load_velodyne_points(velo_path), P_velo2im, image_shape, vel_depth)


def object_velodyne_to_depth_map(calib_path, velo_path, image_shape, vel_depth=True):
    """Sparse GT depth map of one KITTI object-benchmark frame (``velodyne/NNNNNN.bin`` with the
    frame's ``calib/NNNNNN.txt``), by the same protocol as :func:`velodyne_to_depth_map`."""
    P_velo2im = object_velodyne_to_image_matrix(calib_path)
    return points_to_depth_map(load_velodyne_points(velo_path), P_velo2im, image_shape, vel_depth)


def points_to_depth_map(velo, P_velo2im, image_shape, vel_depth=True):
    """The official projection of Velodyne points (N, 3+) with the (3, 4) ``P_velo2im`` to an
    (H, W) float32 depth map in metres, 0 where no point landed (see the module docstring)."""
    height, width = int(image_shape[0]), int(image_shape[1])
    velo = np.asarray(velo)
    # Official "remove all behind image plane (approximation)": velodyne x >= 0.
    velo = velo[velo[:, 0] >= 0]

    uv, z = project_velodyne(velo, P_velo2im)
    depth_values = velo[:, 0].astype(np.float64) if vel_depth else z

    # np.round(.) - 1: the official "-1 to get the exact same value as KITTI matlab code".
    # (np.round rounds halves to even, like the official numpy code.)
    col = np.round(uv[:, 0]) - 1
    row = np.round(uv[:, 1]) - 1
    inside = (col >= 0) & (row >= 0) & (col < width) & (row < height)
    col = col[inside].astype(np.int64)
    row = row[inside].astype(np.int64)
    depth_values = depth_values[inside]

    # Several points on one pixel: keep the closest, as the official duplicate loop.
    depth = np.full((height, width), np.inf)
    np.minimum.at(depth, (row, col), depth_values)
    depth[np.isinf(depth)] = 0.0
    depth[depth < 0] = 0.0  # official clean-up (only reachable with vel_depth=False)
    return depth.astype(np.float32)
