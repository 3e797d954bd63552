"""File formats: KITTI flow/depth PNG, .flo, poses, calibration, atomic writes, visualisation.

Golden values are hand-computed from the format definitions or come from real
files in ../shared/realdata (tests skip if that folder is absent).
"""
from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer import formats as F
from geonet_infer.errors import GeoNetInputError

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "realdata"


def real(rel: str) -> Path:
    p = REAL / rel
    if not p.exists():
        pytest.skip(f"{p} not present")
    return p


# ---------------------------------------------------------------------------- KITTI flow PNG
def test_flow_png_roundtrip_is_bit_exact_on_the_1_64_grid(tmp_path):
    rng = np.random.default_rng(0)
    flow = rng.integers(-300 * 64, 300 * 64, (37, 53, 2)) / 64.0  # exactly representable
    valid = rng.random((37, 53)) > 0.3
    F.write_flow_kitti(tmp_path / "f.png", flow, valid)
    got, got_valid = F.read_flow_kitti(tmp_path / "f.png")
    assert got.dtype == np.float32 and got.shape == (37, 53, 2)
    np.testing.assert_array_equal(got_valid, valid)
    np.testing.assert_array_equal(got[valid], flow[valid].astype(np.float32))
    assert (got[~valid] == 0).all()


def test_flow_png_decode_matches_hand_built_png(tmp_path):
    # cv2 stores BGR, so channel order here is (B=valid, G=v*64+2^15, R=u*64+2^15).
    raw = np.zeros((2, 3, 3), np.uint16)
    raw[0, 0] = (1, 32768 - 144, 32768 + 96)  # u = 1.5, v = -2.25
    raw[0, 1] = (0, 0, 0)  # invalid
    raw[1, 0] = (1, 32768 + 6400, 32767)  # u = -1/64, v = 100
    raw[1, 2] = (1, 65535, 0)  # u = -512, v = (65535 - 32768) / 64 = 511.984375
    assert cv2.imwrite(str(tmp_path / "hand.png"), raw)
    flow, valid = F.read_flow_kitti(tmp_path / "hand.png")
    assert valid.tolist() == [[True, False, False], [True, False, True]]
    assert flow[0, 0].tolist() == [1.5, -2.25]
    assert flow[1, 0].tolist() == [-0.015625, 100.0]
    assert flow[1, 2].tolist() == [-512.0, 511.984375]


def test_flow_png_encode_writes_the_kitti_channel_values(tmp_path):
    flow = np.array([[[1.5, -2.25], [1000.0, -1000.0], [7.0, 7.0]]], np.float32)
    valid = np.array([[True, True, False]])
    F.write_flow_kitti(tmp_path / "e.png", flow, valid)
    raw = cv2.imread(str(tmp_path / "e.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw[0, 0].tolist() == [1, 32624, 32864]  # B, G, R
    assert raw[0, 1].tolist() == [1, 0, 65535]  # clipped to the uint16 range
    assert raw[0, 2].tolist() == [0, 0, 0]  # invalid pixels are all zero


def test_flow_png_rejects_an_8bit_image(tmp_path):
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(GeoNetInputError, match="x.png"):
        F.read_flow_kitti(tmp_path / "x.png")


# ---------------------------------------------------------------------------- KITTI depth PNG
def test_depth_png_roundtrip_is_bit_exact_on_the_1_256_grid(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.integers(0, 65536, (19, 23)) / 256.0
    F.write_depth_kitti(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.ndim == 2
    np.testing.assert_array_equal(raw, np.round(depth * 256).astype(np.uint16))
    got = F.read_depth_kitti(tmp_path / "d.png")
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, depth.astype(np.float32))


def test_depth_png_marks_out_of_range_and_invalid_as_none(tmp_path):
    depth = np.array([[1.0, 300.0, np.inf, -2.0, np.nan, 255.99]])
    F.write_depth_kitti(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.tolist() == [[256, 0, 0, 0, 0, 65533]]
    F.write_depth_kitti(tmp_path / "c.png", depth, too_far="clip")
    assert cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)[0, 1] == 65535


# ---------------------------------------------------------------------------- .flo
def test_flo_reads_middlebury_grove3():
    path = real("middlebury_flow/other-gt-flow/Grove3/flow10.flo")
    flow = F.read_flo(path)
    assert flow.shape == (480, 640, 2) and flow.dtype == np.float32
    assert np.isfinite(flow).all()
    # README: all pixels valid, max 18.6 px.
    assert abs(np.hypot(flow[..., 0], flow[..., 1]).max() - 18.6) < 0.05
    # First (u, v) straight from the bytes: tag, width, height, u, v.
    tag, w, h, u0, v0 = struct.unpack("<fii2f", path.read_bytes()[:20])
    assert (tag, w, h) == (202021.25, 640, 480)
    assert flow[0, 0].tolist() == [u0, v0]


def test_flo_roundtrip_and_bad_magic(tmp_path):
    flow = np.random.default_rng(2).standard_normal((5, 7, 2)).astype(np.float32)
    F.write_flo(tmp_path / "a.flo", flow)
    raw = (tmp_path / "a.flo").read_bytes()
    assert struct.unpack("<fii", raw[:12]) == (202021.25, 7, 5)
    np.testing.assert_array_equal(F.read_flo(tmp_path / "a.flo"), flow)
    assert raw[:4] == b"PIEH"  # the tag 202021.25 as little-endian float32
    (tmp_path / "b.flo").write_bytes(b"HEIP" + raw[4:])
    with pytest.raises(GeoNetInputError, match="b.flo"):
        F.read_flo(tmp_path / "b.flo")


# ---------------------------------------------------------------------------- poses
def test_kitti_odometry_poses_first_is_identity():
    path = real("kitti_odometry_00/poses/00.txt")
    poses = F.read_kitti_poses(path)
    n_lines = len(path.read_text().splitlines())
    assert poses.shape == (n_lines, 4, 4) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)
    assert (poses[:, 3] == [0, 0, 0, 1]).all()
    # Second pose, x translation, as printed in the file.
    assert poses[1, 0, 3] == pytest.approx(-4.690294e-02)


def test_kitti_poses_roundtrip_and_bad_file(tmp_path):
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :] = rng.standard_normal((3, 3, 4))
    F.write_kitti_poses(tmp_path / "p.txt", poses)
    np.testing.assert_allclose(F.read_kitti_poses(tmp_path / "p.txt"), poses, rtol=1e-8, atol=1e-12)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(GeoNetInputError, match="bad.txt"):
        F.read_kitti_poses(tmp_path / "bad.txt")


def test_tum_poses_quaternion_of_a_90_degree_yaw(tmp_path):
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 deg about z
    T[:3, 3] = [1, 2, 3]
    F.write_tum_poses(tmp_path / "t.txt", [0.5], T[None])
    vals = [float(x) for x in (tmp_path / "t.txt").read_text().split()]
    s = np.sqrt(0.5)  # q = (0, 0, sin 45, cos 45)
    np.testing.assert_allclose(vals, [0.5, 1, 2, 3, 0, 0, s, s], atol=1e-9)
    ts, back = F.read_tum_poses(tmp_path / "t.txt")
    assert ts.tolist() == [0.5]
    np.testing.assert_allclose(back[0], T, atol=1e-9)


def test_tum_poses_roundtrip_random_rotations(tmp_path):
    rng = np.random.default_rng(4)
    poses = np.tile(np.eye(4), (20, 1, 1))
    for i in range(20):
        poses[i, :3, :3] = cv2.Rodrigues(rng.uniform(-3.1, 3.1, 3))[0]
        poses[i, :3, 3] = rng.standard_normal(3)
    F.write_tum_poses(tmp_path / "t.txt", np.arange(20) * 0.1, poses)
    _, back = F.read_tum_poses(tmp_path / "t.txt")
    np.testing.assert_allclose(back, poses, atol=1e-8)


# ---------------------------------------------------------------------------- calibration
def test_calib_file_reads_kitti_raw_cam_to_cam():
    path = real("kitti_raw_2011_09_26_sfnd/calib_cam_to_cam.txt")
    calib = F.read_calib_file(path)
    assert calib["P_rect_02"].shape == (12,)
    assert calib["P_rect_02"][0] == pytest.approx(721.5377, abs=1e-3)
    assert isinstance(calib["calib_time"], str)  # "09-Jan-2012 13:57:47" is kept as text
    K = F.read_calib_K(path, key="P_rect_02")
    assert K.shape == (3, 3) and K[2].tolist() == [0, 0, 1]


def test_calib_missing_key_names_file_and_key(tmp_path):
    F.write_calib_K(tmp_path / "calib.txt", np.array([[240.0, 0, 208], [0, 245, 64], [0, 0, 1]]))
    assert (tmp_path / "calib.txt").read_text().split() == ["K:", "240", "0", "208", "0", "245", "64", "0", "0", "1"]
    np.testing.assert_array_equal(F.read_calib_K(tmp_path / "calib.txt")[:2], [[240, 0, 208], [0, 245, 64]])
    calib = F.read_calib_file(tmp_path / "calib.txt")
    with pytest.raises(GeoNetInputError) as err:
        F.require_key(calib, "P_rect_02", tmp_path / "calib.txt")
    assert "calib.txt" in str(err.value) and "P_rect_02" in str(err.value)
    with pytest.raises(GeoNetInputError, match="calib.txt"):
        F.read_calib_K(tmp_path / "calib.txt", key="P2")


def test_calib_malformed_line_names_file(tmp_path):
    (tmp_path / "c.txt").write_text("K: 1 0 0 0 1 0 0 0 1\nthis line has no colon\n")
    with pytest.raises(GeoNetInputError, match=r"c\.txt.*line 2"):
        F.read_calib_file(tmp_path / "c.txt")


# ---------------------------------------------------------------------------- images, atomic writes
def test_image_roundtrip_is_rgb(tmp_path):
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # red
    F.write_image(tmp_path / "i.png", img)
    assert cv2.imread(str(tmp_path / "i.png"))[0, 0].tolist() == [0, 0, 200]  # BGR on disk
    np.testing.assert_array_equal(F.read_image(tmp_path / "i.png"), img)


def test_read_image_missing_names_file(tmp_path):
    with pytest.raises(GeoNetInputError, match="nope.png"):
        F.read_image(tmp_path / "nope.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(GeoNetInputError, match="junk.png"):
        F.read_image(tmp_path / "junk.png")


def test_atomic_write_leaves_nothing_when_the_body_raises(tmp_path):
    with pytest.raises(RuntimeError):
        with F.atomic_write(tmp_path / "out.png") as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".png"
            tmp.write_bytes(b"half")
            raise RuntimeError("crash mid-write")
    assert list(tmp_path.iterdir()) == []
    # An existing file is left untouched by a failed rewrite.
    (tmp_path / "keep.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with F.atomic_write(tmp_path / "keep.txt") as tmp:
            tmp.write_text("new")
            raise RuntimeError
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "old"


def test_mask_roundtrip(tmp_path):
    m = np.random.default_rng(5).random((6, 9)) > 0.5
    F.write_mask(tmp_path / "m.png", m)
    raw = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw.ndim == 2 and set(np.unique(raw)) <= {0, 255}
    np.testing.assert_array_equal(F.read_mask(tmp_path / "m.png"), m)


# ---------------------------------------------------------------------------- visualisation
def _hue_deg(rgb: np.ndarray) -> float:
    hsv = cv2.cvtColor(rgb.reshape(1, 1, 3).astype(np.uint8), cv2.COLOR_RGB2HSV_FULL)
    return hsv[0, 0, 0] * 360.0 / 256.0


def test_flow_to_color_hues_follow_the_middlebury_wheel():
    def colour(u, v):
        return F.flow_to_color(np.full((2, 2, 2), (u, v), np.float32))[0, 0]

    right, left, up = colour(1, 0), colour(-1, 0), colour(0, -1)
    assert right.tolist() == [255, 0, 0]  # +x is pure red at full magnitude
    assert _hue_deg(left) == pytest.approx(191, abs=15)  # cyan-blue, opposite side of the wheel
    assert 230 < _hue_deg(up) < 290  # blue-violet
    # Zero flow is white; half the max magnitude is a lighter (less saturated) red.
    f = np.zeros((1, 2, 2), np.float32)
    f[0, 1] = (2, 0)
    img = F.flow_to_color(f)
    assert img[0, 0].tolist() == [255, 255, 255] and img[0, 1].tolist() == [255, 0, 0]
    half = F.flow_to_color(f, max_flow=4.0)[0, 1]
    assert half[0] == 255 and 120 < half[1] == half[2] < 135


def test_depth_to_color_near_is_brighter_and_missing_is_black():
    depth = np.array([[2.0, 20.0, 0.0]])
    img = F.depth_to_color(depth)
    assert img.shape == (1, 3, 3) and img.dtype == np.uint8
    assert img[0, 0].sum() > img[0, 1].sum()
    assert img[0, 2].tolist() == [0, 0, 0]
