"""Velodyne -> GT depth on real KITTI raw data (2011_09_26), cross-checked with cv2.projectPoints."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer.errors import GeoNetError
from geonet_infer.eval.velodyne import (
    load_velodyne_points,
    project_velodyne,
    velodyne_to_depth_map,
    velodyne_to_image_matrix,
)

DATA = (Path(__file__).resolve().parents[4] / "shared" / "realdata" / "kitti_raw_2011_09_26_sfnd").resolve()
VELO0 = DATA / "velodyne_points" / "data" / "0000000000.bin"
IMAGE0 = DATA / "image_02" / "data" / "0000000000.png"

needs_data = pytest.mark.usefixtures("kitti_raw")  # tests/conftest.py: skips without ../shared, fails on CI


def _parse_calib(path):
    """Independent minimal parser: 'key: numbers' lines -> float arrays (non-numeric lines skipped)."""
    out = {}
    for line in path.read_text().splitlines():
        key, _, value = line.partition(":")
        try:
            out[key.strip()] = np.array(value.split(), dtype=np.float64)
        except ValueError:
            pass
    return out


@pytest.fixture(scope="module")
def depth0():
    height, width = cv2.imread(str(IMAGE0)).shape[:2]
    return velodyne_to_depth_map(DATA, VELO0, (height, width))


@needs_data
def test_depth_map_shape_and_values(depth0):
    assert depth0.shape == (375, 1242)
    assert depth0.dtype == np.float32
    valid = depth0 > 0
    # An HDL-64 scan covers ~15-20k pixels of the lower image; far more than 10k either way.
    assert valid.sum() > 10_000
    assert depth0[valid].min() > 0 and depth0[valid].max() < 120
    # The Velodyne's field of view ends well below the top of the image: no points in row 0..50.
    assert not valid[:50].any()


@needs_data
def test_velodyne_depth_vs_camera_depth(depth0):
    # vel_depth=False stores the projective camera depth instead of velodyne x; the two
    # differ by the ~0.27 m velodyne->camera offset, never by metres.
    cam = velodyne_to_depth_map(DATA, VELO0, depth0.shape, vel_depth=False)
    both = (cam > 0) & (depth0 > 0)
    assert both.sum() > 10_000
    assert np.median(np.abs(cam[both] - depth0[both])) < 0.5


@needs_data
def test_projection_matches_cv2_project_points():
    cam2cam = _parse_calib(DATA / "calib_cam_to_cam.txt")
    velo2cam = _parse_calib(DATA / "calib_velo_to_cam.txt")
    P = cam2cam["P_rect_02"].reshape(3, 4)
    R_rect = cam2cam["R_rect_00"].reshape(3, 3)
    R = velo2cam["R"].reshape(3, 3)
    T = velo2cam["T"]
    # P_rect_02 = K [I | b] with K = P[:, :3]; its 4th column K b is non-zero (camera 2 sits
    # ~6 cm from camera 0 and slightly off in z), so b = K^-1 P[:, 3] is an extra offset in
    # the rectified camera frame: X_cam = R_rect (R X_velo + T) + b.
    K = P[:, :3]
    b = np.linalg.solve(K, P[:, 3])
    assert np.abs(b).max() > 1e-3  # the offset is really there
    rvec, _ = cv2.Rodrigues(R_rect @ R)
    tvec = R_rect @ T + b

    velo = load_velodyne_points(VELO0)
    ahead = velo[velo[:, 0] > 5.0, :3].astype(np.float64)
    pts = ahead[np.linspace(0, len(ahead) - 1, 8).astype(int)]  # a handful of points ahead
    expected, _ = cv2.projectPoints(pts, rvec, tvec, K, None)
    uv, z = project_velodyne(pts, velodyne_to_image_matrix(DATA, cam=2))
    np.testing.assert_allclose(uv, expected.reshape(-1, 2), atol=1e-3)
    # projective depth = camera-frame z of the same points
    np.testing.assert_allclose(z, (pts @ (R_rect @ R).T + tvec)[:, 2], atol=1e-9)


@needs_data
def test_rounding_and_min_over_duplicates(tmp_path):
    # Three points along (almost) one ray: 15.0015 m, 15 m, 15.003 m. Scaling a point about the
    # velodyne origin moves its pixel by far less than 0.5 px here (asserted below), so all three
    # land on one pixel. First-write-wins would keep 15.0015, last-write-wins 15.003; the
    # official rule keeps the minimum, 15.0. A fourth point with x < 0 must be dropped.
    P = velodyne_to_image_matrix(DATA, cam=2)
    near = np.array([15.0, 1.0, -0.5])
    ray = np.stack([near * 1.0001, near, near * 1.0002])
    uv, _ = project_velodyne(ray, P)
    pixels = np.round(uv) - 1  # official: round, then -1 (KITTI MATLAB indexing)
    assert (pixels == pixels[0]).all()
    scan = np.zeros((4, 4), np.float32)
    scan[:3, :3] = ray
    # A point behind the sensor whose projection (through negative z) hits the same pixel:
    # solve P[:, :3] X + P[:, 3] = w (u, v, 1) with w = -15. Kept, its x < 0 would win the
    # minimum and the official "negative -> 0" clean-up would then blank the pixel.
    behind = np.linalg.solve(P[:, :3], -15.0 * np.array([*uv[1], 1.0]) - P[:, 3])
    assert behind[0] < 0
    scan[3, :3] = behind
    path = tmp_path / "scan.bin"
    scan.tofile(path)
    depth = velodyne_to_depth_map(DATA, path, (375, 1242))
    assert (depth > 0).sum() == 1
    col, row = int(pixels[0, 0]), int(pixels[0, 1])
    assert depth[row, col] == np.float32(15.0)


def test_bad_velodyne_size_names_the_file(tmp_path):
    path = tmp_path / "broken.bin"
    path.write_bytes(b"\x00" * 20)
    with pytest.raises(GeoNetError, match="multiple of 16") as err:
        load_velodyne_points(path)
    assert err.value.path == path


def test_missing_calib_key_names_the_file(tmp_path):
    (tmp_path / "calib_cam_to_cam.txt").write_text("R_rect_00: 1 0 0 0 1 0 0 0 1\n")
    (tmp_path / "calib_velo_to_cam.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    with pytest.raises(GeoNetError, match="P_rect_02") as err:
        velodyne_to_image_matrix(tmp_path, cam=2)
    assert err.value.path == tmp_path / "calib_cam_to_cam.txt"
