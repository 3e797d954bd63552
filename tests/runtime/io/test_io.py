"""geonet_infer.io: KITTI flow/depth PNG, .flo, poses, calibration, cameras, frame sources, atomic writes.

Golden values are hand-computed from the format definitions, typed from the text of real
files in ../shared/realdata (the ``realdata`` fixture of conftest.py: skipped if that folder
is absent, a failure on CI), or written with plain OpenCV / numpy, never with the code under test.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer import io as gio
from geonet_infer.errors import GeoNetError
from geonet_infer.io import Camera, Frame, list_images, open_frames, read_camera, save_npy_atomic

KITTI_RAW = "kitti_raw_2011_09_26_sfnd"


# ---------------------------------------------------------------------------- KITTI flow PNG
def test_flow_png_roundtrip_is_bit_exact_on_the_1_64_grid(tmp_path):
    rng = np.random.default_rng(0)
    flow = rng.integers(-300 * 64, 300 * 64, (37, 53, 2)) / 64.0  # exactly representable
    valid = rng.random((37, 53)) > 0.3
    gio.write_flow_kitti(tmp_path / "f.png", flow, valid)
    got, got_valid = gio.read_flow_kitti(tmp_path / "f.png")
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
    flow, valid = gio.read_flow_kitti(tmp_path / "hand.png")
    assert valid.tolist() == [[True, False, False], [True, False, True]]
    assert flow[0, 0].tolist() == [1.5, -2.25]
    assert flow[1, 0].tolist() == [-0.015625, 100.0]
    assert flow[1, 2].tolist() == [-512.0, 511.984375]


def test_flow_png_encode_writes_the_kitti_channel_values(tmp_path):
    flow = np.array([[[1.5, -2.25], [1000.0, -1000.0], [7.0, 7.0]]], np.float32)
    valid = np.array([[True, True, False]])
    gio.write_flow_kitti(tmp_path / "e.png", flow, valid)
    raw = cv2.imread(str(tmp_path / "e.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert raw[0, 0].tolist() == [1, 32624, 32864]  # B, G, R
    assert raw[0, 1].tolist() == [1, 0, 65535]  # clipped to the uint16 range
    assert raw[0, 2].tolist() == [0, 0, 0]  # invalid pixels are all zero


def test_flow_png_rejects_an_8bit_image(tmp_path):
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(GeoNetError, match="x.png"):
        gio.read_flow_kitti(tmp_path / "x.png")


def _decode_with_pypng(data: bytes) -> np.ndarray:
    """A second decoder (pure Python, no code shared with ours or OpenCV's; it checks every chunk's CRC)."""
    png = pytest.importorskip("png")
    width, height, rows, info = png.Reader(bytes=data).read()
    channels = info["planes"]
    dtype = np.uint16 if info["bitdepth"] == 16 else np.uint8
    return np.array([np.asarray(row, dtype) for row in rows]).reshape(height, width, channels)


@pytest.mark.parametrize(
    "shape, dtype",
    [
        ((37, 53), np.uint8),
        ((37, 53, 3), np.uint8),
        ((19, 7), np.uint16),
        ((19, 7, 3), np.uint16),
        ((1, 1, 3), np.uint16),
        ((19, 7, 3), ">u2"),  # big-endian, as PNG stores them (the flow writer's samples)
    ],
)
@pytest.mark.parametrize("up", [False, True], ids=["sub", "up"])
def test_png_encoder_round_trips_through_opencv_and_pypng(shape, dtype, up):
    from geonet_infer.io.png import encode_png

    rng = np.random.default_rng(len(shape) * 10 + np.dtype(dtype).itemsize)
    native = np.dtype(dtype).newbyteorder("=")
    image = rng.integers(0, np.iinfo(native).max, shape, dtype=native, endpoint=True).astype(dtype)
    image.flat[0], image.flat[-1] = 0, np.iinfo(dtype).max  # both ends of the range
    data = encode_png(image, up=up)
    by_opencv = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image.ndim == 3:
        by_opencv = by_opencv[..., ::-1]  # OpenCV decodes to BGR
    assert by_opencv.dtype == native
    np.testing.assert_array_equal(by_opencv, image)
    np.testing.assert_array_equal(_decode_with_pypng(data).reshape(image.shape), image)


def test_png_outputs_decode_to_the_pixels_opencv_would_have_written(tmp_path):
    """A KITTI flow PNG, a depth PNG and a colour picture from our writers: the same pixels as OpenCV's
    own encoder stores (decoded by OpenCV; the files' bytes differ: another deflate)."""
    rng = np.random.default_rng(3)
    flow = rng.normal(0, 40, (45, 61, 2)).astype(np.float32)
    gio.write_flow_kitti(tmp_path / "flow.png", flow)
    codes = (np.rint(flow.astype(np.float64) * 64) + 2**15).astype(np.uint16)  # the KITTI definition
    bgr = np.dstack([np.ones_like(codes[..., 0]), codes[..., 1], codes[..., 0]])
    assert cv2.imwrite(str(tmp_path / "flow_cv.png"), bgr)
    picture = rng.integers(0, 256, (45, 61, 3), dtype=np.uint8)
    gio.write_image(tmp_path / "picture.png", picture)
    assert cv2.imwrite(str(tmp_path / "picture_cv.png"), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    for ours, theirs in (("flow.png", "flow_cv.png"), ("picture.png", "picture_cv.png")):
        read = [cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED) for name in (ours, theirs)]
        assert read[0].dtype == read[1].dtype
        np.testing.assert_array_equal(read[0], read[1])


@pytest.mark.parametrize(
    "image, problem",
    [
        (np.zeros((4, 4, 3), np.float32), "float32"),
        (np.zeros((4, 4, 4), np.uint8), r"\(4, 4, 4\)"),
        (np.zeros((0, 4), np.uint8), r"\(0, 4\)"),
    ],
)
def test_png_writer_refuses_what_png_cannot_hold_naming_the_file(tmp_path, image, problem):
    from geonet_infer.io.images import _imwrite

    with pytest.raises(GeoNetError, match=rf"out\.png.*{problem}"):
        _imwrite(tmp_path / "out.png", image)
    assert not (tmp_path / "out.png").exists()


# ---------------------------------------------------------------------------- KITTI depth PNG
def test_depth_png_roundtrip_is_bit_exact_on_the_1_256_grid(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.integers(0, 65536, (19, 23)) / 256.0
    gio.write_depth_kitti(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.ndim == 2
    np.testing.assert_array_equal(raw, np.round(depth * 256).astype(np.uint16))
    got = gio.read_depth_kitti(tmp_path / "d.png")
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, depth.astype(np.float32))


def test_depth_png_marks_out_of_range_and_invalid_as_none(tmp_path):
    depth = np.array([[1.0, 300.0, np.inf, -2.0, np.nan, 255.99]])
    gio.write_depth_kitti(tmp_path / "d.png", depth)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.tolist() == [[256, 0, 0, 0, 0, 65533]]
    gio.write_depth_kitti(tmp_path / "c.png", depth, too_far="clip")
    assert cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)[0, 1] == 65535


# ---------------------------------------------------------------------------- .flo
def test_flo_reads_middlebury_grove3(realdata):
    path = realdata / "middlebury_flow/other-gt-flow/Grove3/flow10.flo"
    flow = gio.read_flo(path)
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
    gio.write_flo(tmp_path / "a.flo", flow)
    raw = (tmp_path / "a.flo").read_bytes()
    assert struct.unpack("<fii", raw[:12]) == (202021.25, 7, 5)
    np.testing.assert_array_equal(gio.read_flo(tmp_path / "a.flo"), flow)
    assert raw[:4] == b"PIEH"  # the tag 202021.25 as little-endian float32
    (tmp_path / "b.flo").write_bytes(b"HEIP" + raw[4:])
    with pytest.raises(GeoNetError, match="b.flo"):
        gio.read_flo(tmp_path / "b.flo")


# ---------------------------------------------------------------------------- poses
def test_kitti_odometry_poses_first_is_identity(realdata):
    path = realdata / "kitti_odometry_00/poses/00.txt"
    poses = gio.read_kitti_poses(path)
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
    gio.write_kitti_poses(tmp_path / "p.txt", poses)
    np.testing.assert_allclose(gio.read_kitti_poses(tmp_path / "p.txt"), poses, rtol=1e-8, atol=1e-12)
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(GeoNetError, match="bad.txt"):
        gio.read_kitti_poses(tmp_path / "bad.txt")


def test_tum_poses_quaternion_of_a_90_degree_yaw(tmp_path):
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 deg about z
    T[:3, 3] = [1, 2, 3]
    gio.write_tum_poses(tmp_path / "t.txt", [0.5], T[None])
    vals = [float(x) for x in (tmp_path / "t.txt").read_text().split()]
    s = np.sqrt(0.5)  # q = (0, 0, sin 45, cos 45)
    np.testing.assert_allclose(vals, [0.5, 1, 2, 3, 0, 0, s, s], atol=1e-9)
    ts, back = gio.read_tum_poses(tmp_path / "t.txt")
    assert ts.tolist() == [0.5]
    np.testing.assert_allclose(back[0], T, atol=1e-9)


def test_tum_poses_roundtrip_random_rotations(tmp_path):
    rng = np.random.default_rng(4)
    poses = np.tile(np.eye(4), (20, 1, 1))
    for i in range(20):
        poses[i, :3, :3] = cv2.Rodrigues(rng.uniform(-3.1, 3.1, 3))[0]
        poses[i, :3, 3] = rng.standard_normal(3)
    gio.write_tum_poses(tmp_path / "t.txt", np.arange(20) * 0.1, poses)
    _, back = gio.read_tum_poses(tmp_path / "t.txt")
    np.testing.assert_allclose(back, poses, atol=1e-8)


# ---------------------------------------------------------------------------- calibration
def test_calib_file_reads_kitti_raw_cam_to_cam(realdata):
    path = realdata / "kitti_raw_2011_09_26_sfnd/calib_cam_to_cam.txt"
    calib = gio.read_calib_file(path)
    assert calib["P_rect_02"].shape == (12,)
    assert calib["P_rect_02"][0] == pytest.approx(721.5377, abs=1e-3)
    assert isinstance(calib["calib_time"], str)  # "09-Jan-2012 13:57:47" is kept as text
    K = gio.read_calib_K(path, key="P_rect_02")
    assert K.shape == (3, 3) and K[2].tolist() == [0, 0, 1]


def test_calib_missing_key_names_file_and_key(tmp_path):
    gio.write_calib_K(tmp_path / "calib.txt", np.array([[240.0, 0, 208], [0, 245, 64], [0, 0, 1]]))
    assert (tmp_path / "calib.txt").read_text().split() == ["K:", "240", "0", "208", "0", "245", "64", "0", "0", "1"]
    np.testing.assert_array_equal(gio.read_calib_K(tmp_path / "calib.txt")[:2], [[240, 0, 208], [0, 245, 64]])
    calib = gio.read_calib_file(tmp_path / "calib.txt")
    with pytest.raises(GeoNetError) as err:
        gio.require_key(calib, "P_rect_02", tmp_path / "calib.txt")
    assert "calib.txt" in str(err.value) and "P_rect_02" in str(err.value)
    with pytest.raises(GeoNetError, match="calib.txt"):
        gio.read_calib_K(tmp_path / "calib.txt", key="P2")


def test_calib_malformed_line_names_file(tmp_path):
    (tmp_path / "c.txt").write_text("K: 1 0 0 0 1 0 0 0 1\nthis line has no colon\n")
    with pytest.raises(GeoNetError, match=r"c\.txt.*line 2"):
        gio.read_calib_file(tmp_path / "c.txt")


# ---------------------------------------------------------------------------- images, atomic writes
def test_image_roundtrip_is_rgb(tmp_path):
    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 200  # red
    gio.write_image(tmp_path / "i.png", img)
    assert cv2.imread(str(tmp_path / "i.png"))[0, 0].tolist() == [0, 0, 200]  # BGR on disk
    np.testing.assert_array_equal(gio.read_image(tmp_path / "i.png"), img)


def test_read_image_missing_names_file(tmp_path):
    with pytest.raises(GeoNetError, match="nope.png"):
        gio.read_image(tmp_path / "nope.png")
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(GeoNetError, match="junk.png"):
        gio.read_image(tmp_path / "junk.png")


def test_atomic_write_leaves_nothing_when_the_body_raises(tmp_path):
    with pytest.raises(RuntimeError):
        with gio.atomic_write(tmp_path / "out.png") as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".png"
            tmp.write_bytes(b"half")
            raise RuntimeError("crash mid-write")
    assert list(tmp_path.iterdir()) == []
    # An existing file is left untouched by a failed rewrite.
    (tmp_path / "keep.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with gio.atomic_write(tmp_path / "keep.txt") as tmp:
            tmp.write_text("new")
            raise RuntimeError
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "old"


def test_mask_roundtrip(tmp_path):
    m = np.random.default_rng(5).random((6, 9)) > 0.5
    gio.write_mask(tmp_path / "m.png", m)
    raw = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw.ndim == 2 and set(np.unique(raw)) <= {0, 255}
    np.testing.assert_array_equal(gio.read_mask(tmp_path / "m.png"), m)


def test_save_npy_atomic_roundtrip_keeps_the_exact_name(tmp_path):
    arr = np.arange(12, dtype=np.float32).reshape(3, 4) / 7
    save_npy_atomic(tmp_path / "depth.npy", arr)
    save_npy_atomic(tmp_path / "raw.bin", arr)  # np.save(path) would have written raw.bin.npy
    assert sorted(p.name for p in tmp_path.iterdir()) == ["depth.npy", "raw.bin"]
    for name in ("depth.npy", "raw.bin"):
        back = np.load(tmp_path / name)
        assert back.dtype == np.float32
        np.testing.assert_array_equal(back, arr)


def test_save_npy_atomic_leaves_no_temp_file_when_np_save_raises(tmp_path, monkeypatch):
    (tmp_path / "keep.npy").write_bytes(b"old")

    def boom(f, *args, **kwargs):
        f.write(b"\x93NUMPY half")
        raise OSError("disk full")

    monkeypatch.setattr(np, "save", boom)
    with pytest.raises(OSError, match="disk full"):
        save_npy_atomic(tmp_path / "keep.npy", np.zeros(3))
    with pytest.raises(OSError):
        save_npy_atomic(tmp_path / "new.npy", np.zeros(3))
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npy"]
    assert (tmp_path / "keep.npy").read_bytes() == b"old"
    monkeypatch.undo()
    with pytest.raises(ValueError):  # object arrays would need pickle: refused, nothing written
        save_npy_atomic(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object))
    assert [p.name for p in tmp_path.iterdir()] == ["keep.npy"]


# ---------------------------------------------------------------------------- list_images
def test_list_images_sorts_by_name_and_filters_suffixes(tmp_path):
    for name in ("b.JPG", "a.png", "c.jpeg", "d.BMP", "e.ppm", "notes.txt", ".a.tmp.png", "f.tiff"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.png").mkdir()  # a folder named like an image is not an image
    assert [p.name for p in list_images(tmp_path)] == ["a.png", "b.JPG", "c.jpeg", "d.BMP", "e.ppm"]
    assert all(isinstance(p, Path) and p.parent == tmp_path for p in list_images(str(tmp_path)))


def test_list_images_missing_or_empty_folder_names_it(tmp_path):
    with pytest.raises(GeoNetError, match="nowhere"):
        list_images(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no frames here")
    with pytest.raises(GeoNetError) as err:
        list_images(tmp_path / "empty")
    assert str(tmp_path / "empty") in str(err.value) and "no images" in str(err.value)


# ---------------------------------------------------------------------------- GeoNet _cam.txt
def test_cam_txt_is_the_official_comma_line(tmp_path):
    K = np.array([[240.5, 0, 208.25], [0, 245.0, 64.125], [0, 0, 1]])
    gio.write_cam_txt(tmp_path / "000001_cam.txt", K)
    assert (tmp_path / "000001_cam.txt").read_text() == "240.5,0.,208.25,0.,245.0,64.125,0.,0.,1.\n"
    np.testing.assert_array_equal(gio.read_cam_txt(tmp_path / "000001_cam.txt"), K)
    (tmp_path / "bad_cam.txt").write_text("1,2,3")
    with pytest.raises(GeoNetError, match="bad_cam.txt"):
        gio.read_cam_txt(tmp_path / "bad_cam.txt")


# ---------------------------------------------------------------------------- read_camera / Camera
def test_read_camera_kitti_raw_cam_to_cam(realdata):
    cam = read_camera(realdata / KITTI_RAW / "calib_cam_to_cam.txt")
    # P_rect_02 as printed in the file: 7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.728540e+02 ...
    fx, cx, fy, cy = 721.5377, 609.5593, 721.5377, 172.854
    np.testing.assert_allclose(cam.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=0, atol=1e-9)
    assert cam.K.dtype == np.float64 and cam.K.shape == (3, 3)
    assert cam.size == (1242, 375)  # S_rect_02: 1.242000e+03 3.750000e+02
    assert cam.dist is None and not cam.has_distortion  # rectified images
    assert "calib_cam_to_cam.txt" in cam.source


def test_read_camera_kitti_odometry_calib_uses_p2(realdata):
    cam = read_camera(realdata / "kitti_odometry_00/sequences/00/calib.txt")
    # P2: 7.188560000000e+02 0 6.071928000000e+02 4.538225000000e+01 0 7.188560000000e+02 1.852157000000e+02 ...
    np.testing.assert_allclose(cam.K, [[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]], rtol=0, atol=1e-9)
    assert cam.size is None and cam.dist is None


def test_read_camera_kitti_odometry_without_p2_uses_p0(tmp_path):
    (tmp_path / "calib.txt").write_text(
        "P0: 7.0e+02 0.0 6.0e+02 0.0 0.0 7.1e+02 1.8e+02 0.0 0.0 0.0 1.0 0.0\n"
        "P1: 7.0e+02 0.0 6.0e+02 -3.8e+02 0.0 7.1e+02 1.8e+02 0.0 0.0 0.0 1.0 0.0\n"
    )
    cam = read_camera(tmp_path / "calib.txt")
    np.testing.assert_array_equal(cam.K, [[700, 0, 600], [0, 710, 180], [0, 0, 1]])


def test_read_camera_udacity_key_value_file(realdata):
    cam = read_camera(realdata / "udacity_dashcam/calib_advanced_lane_lines.txt")
    np.testing.assert_allclose(
        cam.K, [[1158.774754, 0, 669.642741], [0, 1154.076607, 388.079450], [0, 0, 1]], rtol=0, atol=1e-9
    )
    np.testing.assert_allclose(
        cam.dist, [-0.25677908, 0.04338451, -0.00068745, 0.00012577, -0.11502545], rtol=0, atol=1e-12
    )
    assert cam.size == (1280, 720) and cam.has_distortion


def test_read_camera_euroc_sensor_yaml(realdata):
    cam = read_camera(realdata / "euroc_v1_01_micro/mav0/cam0/sensor.yaml")
    # intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
    np.testing.assert_allclose(cam.K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]], rtol=0, atol=1e-9)
    np.testing.assert_allclose(cam.dist, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05], rtol=0, atol=1e-12)
    assert cam.size == (752, 480) and cam.has_distortion
    # The IMU's sensor.yaml of the same recording has no camera in it.
    with pytest.raises(GeoNetError, match="imu0"):
        read_camera(realdata / "euroc_v1_01_micro/mav0/imu0/sensor.yaml")


def test_read_camera_refuses_a_fisheye_yaml(tmp_path):
    (tmp_path / "sensor.yaml").write_text(
        "%YAML:1.0\ncamera_model: pinhole\nintrinsics: [400, 401, 320, 240]\n"
        "distortion_model: equidistant\ndistortion_coefficients: [0.1, 0.01, 0, 0]\n"
    )
    with pytest.raises(GeoNetError, match="equidistant"):
        read_camera(tmp_path / "sensor.yaml")


def test_read_camera_plain_matrix_and_k_file(tmp_path):
    (tmp_path / "K.txt").write_text("500 0 320\n0 510 240\n0 0 1\n")
    (tmp_path / "K_commas.txt").write_text("500, 0, 320,\n0, 510, 240,\n0, 0, 1\n")
    (tmp_path / "000001_cam.txt").write_text("500.0,0.,320.0,0.,510.0,240.0,0.,0.,1.")
    (tmp_path / "calib.txt").write_text("K: 500 0 320 0 510 240 0 0 1\n")
    for name in ("K.txt", "K_commas.txt", "000001_cam.txt", "calib.txt"):
        cam = read_camera(tmp_path / name)
        np.testing.assert_array_equal(cam.K, [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
        assert cam.dist is None and cam.size is None and name in cam.source
    gio.write_calib_K(tmp_path / "written.txt", np.array([[240.0, 0, 208], [0, 245, 64], [0, 0, 1]]))
    np.testing.assert_array_equal(read_camera(tmp_path / "written.txt").K, [[240, 0, 208], [0, 245, 64], [0, 0, 1]])


def test_read_camera_unrecognised_or_missing_names_the_file(tmp_path):
    (tmp_path / "notes.txt").write_text("hello world\nthis is not a calibration\n")
    (tmp_path / "eight.txt").write_text("1 2 3 4 5 6 7 8\n")
    (tmp_path / "binary.bin").write_bytes(bytes(range(256)))
    for name in ("notes.txt", "eight.txt", "binary.bin", "missing.txt"):
        with pytest.raises(GeoNetError) as err:
            read_camera(tmp_path / name)
        assert name in str(err.value)


def test_read_camera_rejects_invalid_values(tmp_path):
    (tmp_path / "zero_fy.txt").write_text("K: 500 0 320 0 0 240 0 0 1\n")
    with pytest.raises(GeoNetError, match="zero_fy.txt"):
        read_camera(tmp_path / "zero_fy.txt")
    (tmp_path / "nan.txt").write_text("500 0 nan\n0 510 240\n0 0 1\n")
    with pytest.raises(GeoNetError, match="nan.txt"):
        read_camera(tmp_path / "nan.txt")


def test_camera_scaled_to_and_validate():
    cam = Camera(np.array([[100.0, 0, 50], [0, 200, 40], [0, 0, 1]]), np.array([-0.2, 0.05, 0, 0, 0]), (100, 80), "x")
    half = cam.scaled_to(50, 80)
    np.testing.assert_array_equal(half.K, [[50, 0, 25], [0, 200, 40], [0, 0, 1]])  # fx, cx halve; fy, cy stay
    assert half.size == (50, 80) and half.source == "x"
    np.testing.assert_array_equal(half.dist, cam.dist)  # distortion acts on normalised coordinates
    quarter = cam.scaled_to(25, 20)
    np.testing.assert_array_equal(quarter.K, [[25, 0, 12.5], [0, 50, 10], [0, 0, 1]])
    unknown = Camera(np.eye(3))
    assert unknown.scaled_to(10, 10) is unknown  # size unknown: unchanged
    assert cam.validate() is cam and cam.has_distortion
    assert not Camera(np.eye(3), np.zeros(5)).has_distortion
    with pytest.raises(GeoNetError, match="fy=0"):
        Camera(np.array([[100.0, 0, 50], [0, 0, 40], [0, 0, 1]])).validate()
    with pytest.raises(GeoNetError, match="cam.txt"):
        Camera(np.array([[100.0, 0, np.nan], [0, 100, 40], [0, 0, 1]])).validate("cam.txt")
    with pytest.raises(GeoNetError):
        Camera(np.array([[np.nan, 0, 50], [0, 100, 40], [0, 0, 1]])).validate()
    with pytest.raises(GeoNetError):
        Camera(np.eye(3), dist=np.array([0.1, 0.2, 0.3])).validate()  # no OpenCV model has 3 coefficients
    with pytest.raises(ValueError):  # frozen and read-only
        cam.K[0, 0] = 1.0


# ---------------------------------------------------------------------------- open_frames
def test_open_frames_video(realdata):
    src = open_frames(realdata / "udacity_dashcam/test_video.mp4")
    assert src.kind == "video" and src.name == "test_video" and src.default_calib is None
    assert src.frame_names is None and src.fps == pytest.approx(25.0)
    frames = list(src)
    assert len(frames) == 38  # README: 38 frames, 1280x720
    assert all(f.error is None and f.rgb.shape == (720, 1280, 3) and f.rgb.dtype == np.uint8 for f in frames)
    assert [f.name for f in frames[:2]] == ["000000", "000001"] and frames[-1].name == "000037"
    assert src.frame_names == [f.name for f in frames] and len(src) == 38
    # RGB, not BGR: same pixels as OpenCV's own first frame with the channels reversed.
    cap = cv2.VideoCapture(str(realdata / "udacity_dashcam/test_video.mp4"))
    ok, bgr = cap.read()
    cap.release()
    assert ok
    np.testing.assert_array_equal(frames[0].rgb, bgr[..., ::-1])


@pytest.mark.parametrize("rel", [KITTI_RAW, f"{KITTI_RAW}/image_02/data"])
def test_open_frames_kitti_drive(realdata, rel):
    src = open_frames(realdata / rel)
    assert src.kind == "kitti_drive" and src.name == KITTI_RAW
    assert len(src) == 78 and len(src.frame_names) == 78  # README: 0000000000 ... 0000000077
    assert src.frame_names[0] == "0000000000" and src.frame_names[-1] == "0000000077"
    assert src.default_calib.resolve() == (realdata / KITTI_RAW / "calib_cam_to_cam.txt").resolve()
    first = next(iter(src))
    assert first.name == "0000000000" and first.rgb.shape == (375, 1242, 3) and first.rgb.dtype == np.uint8


def test_open_frames_kitti_layout_with_calib_in_the_date_folder(tmp_path):
    data = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync" / "image_02" / "data"
    data.mkdir(parents=True)
    for i in range(2):
        assert cv2.imwrite(str(data / f"{i:010d}.png"), np.full((4, 6, 3), i * 50, np.uint8))
    (tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").write_text("P_rect_02: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    for path in (data.parent.parent, data):
        src = open_frames(path)
        assert src.kind == "kitti_drive" and src.name == "2011_09_26_drive_0001_sync"
        assert src.frame_names == ["0000000000", "0000000001"]
        assert src.default_calib.resolve() == (tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").resolve()


def test_open_frames_folder_reports_a_corrupt_frame_and_goes_on(tmp_path):
    rng = np.random.default_rng(6)
    written = {}
    for name in ("a", "c", "d"):
        bgr = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
        assert cv2.imwrite(str(tmp_path / f"{name}.png"), bgr)
        written[name] = bgr[..., ::-1]
    (tmp_path / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    src = open_frames(tmp_path)
    assert src.kind == "folder" and src.name == tmp_path.name and src.default_calib is None
    assert src.frame_names == ["a", "b", "c", "d"] and len(src) == 4
    frames = list(src)
    assert [f.name for f in frames] == ["a", "b", "c", "d"]
    bad = frames[1]
    assert bad.rgb is None and isinstance(bad.error, GeoNetError) and "b.png" in str(bad.error)
    for f in (frames[0], frames[2], frames[3]):
        assert f.error is None
        np.testing.assert_array_equal(f.rgb, written[f.name])
    with pytest.raises(ValueError):
        Frame("x")  # neither rgb nor error


def test_open_frames_corrupt_video_missing_path_and_other_files(tmp_path):
    (tmp_path / "clip.mp4").write_bytes(np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(GeoNetError) as err:
        open_frames(tmp_path / "clip.mp4")
    assert "clip.mp4" in str(err.value) and "cannot open this video" in str(err.value)
    with pytest.raises(GeoNetError, match="not_there"):
        open_frames(tmp_path / "not_there")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(GeoNetError, match="notes.txt"):
        open_frames(tmp_path / "notes.txt")
    (tmp_path / "empty").mkdir()
    with pytest.raises(GeoNetError, match="empty"):
        open_frames(tmp_path / "empty")


def test_open_frames_video_ending_before_its_header_count_is_a_clean_end(realdata):
    # README: the container lists 210 frames, OpenCV decodes the first 201 (FFmpeg too, without an error).
    src = open_frames(realdata / "udacity_dashcam/project_video_clip_a.mp4")
    assert len(src) == 210 and src.frame_names is None  # container's count before reading
    n = sum(1 for f in src if f.rgb is not None)
    assert n == 201 and len(src) == 201 and src.frame_names[-1] == "000200"
    assert src.truncated is None and src.missing == ()
    assert "after 201 frames, 9 before its header's count of 210" in src.ended_early


def test_atomic_write_gives_the_mode_of_a_plain_open(tmp_path):
    from geonet_infer.io import atomic_write

    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    with atomic_write(tmp_path / "atomic.txt") as tmp:
        tmp.write_text("x")
    assert (tmp_path / "atomic.txt").stat().st_mode & 0o777 == plain.stat().st_mode & 0o777


def test_camera_undistort_equals_opencv_and_builds_its_maps_once(realdata):
    from geonet_infer.io import calib

    camera = read_camera(realdata / "udacity_dashcam" / "calib_advanced_lane_lines.txt")
    cap = cv2.VideoCapture(str(realdata / "udacity_dashcam" / "test_video.mp4"))
    frames = [cap.read()[1] for _ in range(2)]
    before = calib._undistort_maps.cache_info()
    for frame in frames:
        assert np.array_equal(camera.undistort(frame), cv2.undistort(frame, camera.K, camera.dist))
    after = calib._undistort_maps.cache_info()
    assert after.hits - before.hits >= 1  # the second frame reused the first frame's maps
    rectified = read_camera(realdata / "kitti_raw_2011_09_26_sfnd" / "calib_cam_to_cam.txt")
    assert rectified.undistort(frames[0]) is frames[0]  # no distortion: nothing to do


def test_an_interrupt_right_after_the_temp_is_created_leaves_no_temp(tmp_path, monkeypatch):
    """A signal handler that raises (a batch worker's SIGTERM) can fire right after the temp file's open
    returns. With tempfile.mkstemp that was inside mkstemp, before its name reached the caller: the temp
    stayed behind (seen in CI). The open is made to raise just after creating the file, as such a signal would."""
    import os as os_module

    from geonet_infer.io.atomic import atomic_write, leftover_temps

    real_open = os_module.open

    def open_then_interrupt(path, flags, *args, **kwargs):
        fd = real_open(path, flags, *args, **kwargs)
        if flags & os_module.O_EXCL:
            os_module.close(fd)
            raise KeyboardInterrupt
        return fd

    monkeypatch.setattr(os_module, "open", open_then_interrupt)
    target = tmp_path / "out.png"
    with pytest.raises(KeyboardInterrupt), atomic_write(target) as tmp:
        tmp.write_bytes(b"never")
    monkeypatch.undo()
    assert os_module.listdir(tmp_path) == [] and leftover_temps(target) == []
