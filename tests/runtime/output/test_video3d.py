"""Video and 3-D outputs of `geonet-infer predict`: point clouds, steady colours, the result video,
live sources (stdin, cameras) and the intrinsics written out.

Golden values: a PLY parser and the back-projection written out here with numpy; depth from the
synthetic generator's ground truth; frame counts read back with OpenCV; depth from reading the
same video file directly.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.cli import main
from geonet_infer.core.points import backproject, write_ply
from geonet_infer.io import read_camera
from geonet_infer.output.viz import SteadyScale, depth_to_color
from tests.conftest import GEONET_CLI

DASHCAM_VIDEO = "test_video.mp4"
DASHCAM_CALIB = "calib_advanced_lane_lines.txt"


def read_ply(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], list[str]]:
    """A binary little-endian PLY with one vertex element: (header lines, columns by name)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "uchar": "u1"}
    count = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    fields = [(line.split()[2], types[line.split()[1]]) for line in header if line.startswith("property")]
    table = np.frombuffer(data[end:], dtype=np.dtype(fields), count=count)
    assert len(data) - end == count * table.dtype.itemsize  # nothing after the vertices
    xyz = np.stack([table["x"], table["y"], table["z"]], axis=1)
    return xyz, {name: table[name] for name, _ in fields}, header


def run_cli(capture, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capture.readouterr()
    return rc, out, err


# ----------------------------------------------------------------------------- point clouds
def test_ply_of_synthetic_ground_truth_depth_is_k_inverse_uv1_times_d(tmp_path):
    synth = pytest.importorskip("training.synth")
    frame = next(synth.iter_frames(seed=3, index=0, frames=2, height=64, width=96))
    depth, K, image = frame["depth"], frame["K"], frame["image"]
    depth = np.where(depth < 500, depth, 0).astype(np.float32)  # the sky (~1000 m) has no depth
    xyz, pixels = backproject(depth, K, stride=1)
    write_ply(tmp_path / "frame.ply", xyz, image[pixels[:, 0], pixels[:, 1]], ("relative scale",))
    points, columns, header = read_ply(tmp_path / "frame.ply")
    assert "comment relative scale" in header
    v, u = np.nonzero(depth > 0)  # row-major, the order the writer keeps
    d = depth[v, u].astype(np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    expected = np.stack([(u - cx) / fx * d, (v - cy) / fy * d, d], axis=1)
    assert len(points) == len(expected) > 1000
    np.testing.assert_allclose(points, expected, atol=1e-5, rtol=1e-6)
    np.testing.assert_array_equal(columns["red"], image[v, u, 0])
    np.testing.assert_array_equal(columns["blue"], image[v, u, 2])


def test_predict_point_clouds_match_the_depth_files_and_camera_txt(tmp_path, capsys, kitti_raw):
    frames = tmp_path / "frames"
    frames.mkdir()
    for f in sorted((kitti_raw / "image_02" / "data").glob("*.png"))[:4]:
        shutil.copyfile(f, frames / f.name)
    shutil.copyfile(kitti_raw / "calib_cam_to_cam.txt", tmp_path / "calib.txt")
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, "predict", frames, "--out", out, "--calib", tmp_path / "calib.txt", "--point-cloud", "world",
        "--point-stride", "3", "--max-depth", "40", "--world-points", "5000", "--no-progress", "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    # camera.txt: KITTI P_rect form at the input size, read back by the calibration reader
    camera = read_camera(out / "camera.txt")
    summary = json.loads((out / "summary.json").read_text())
    np.testing.assert_allclose(camera.K, summary["camera"]["K_input_resolution"], rtol=1e-9)
    assert camera.size == (1242, 375)
    name = sorted(p.stem for p in (out / "points").glob("*.ply"))[1]
    points, columns, header = read_ply(out / "points" / f"{name}.ply")
    assert any("relative scale" in line for line in header)
    depth = np.load(out / "depth" / f"{name}.npy")
    v, u = np.mgrid[0:375:3, 0:1242:3]
    d = depth[v, u].astype(np.float64)
    keep = (d > 0) & (d <= 40)
    Kinv = np.linalg.inv(camera.K)
    expected = (Kinv @ np.stack([u[keep], v[keep], np.ones(keep.sum())])).T * d[keep, None]
    np.testing.assert_allclose(points, expected, rtol=1e-5, atol=1e-5)
    rgb = cv2.cvtColor(cv2.imread(str(frames / f"{name}.png")), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(columns["green"], rgb[v[keep], u[keep], 1])
    world, _, world_header = read_ply(out / "points_world.ply")
    assert len(world) == 5000 and any("first camera" in line for line in world_header)


def test_frame_results_carry_the_intrinsics_and_back_project(kitti_raw):
    predictor = geonet_infer.load()
    camera = read_camera(kitti_raw / "calib_cam_to_cam.txt")
    images = sorted((kitti_raw / "image_02" / "data").glob("*.png"))[:2]
    first = next(predictor.iter_sequence(images, camera, tasks=("depth",)))
    np.testing.assert_allclose(first.intrinsics, camera.K)
    xyz, colours = first.points(stride=50)
    assert colours is None and xyz.shape[1] == 3
    np.testing.assert_allclose(xyz[:, 2], first.depth[::50, ::50].ravel(), rtol=1e-6)
    assert predictor.depth(images[0]).intrinsics is None
    with pytest.raises(ValueError, match="intrinsics"):
        predictor.depth(images[0]).points()


# ----------------------------------------------------------------------------- steady colours
def test_a_still_sequence_keeps_its_colours(tmp_path, capsys, kitti_raw):
    frames = tmp_path / "still"
    frames.mkdir()
    frame = sorted((kitti_raw / "image_02" / "data").glob("*.png"))[0]
    for i in range(4):
        shutil.copyfile(frame, frames / f"{i:06d}.png")
    out = tmp_path / "out"
    rc, _, err = run_cli(capsys, "predict", frames, "--out", out, "--tasks", "depth", "--no-progress", "--quiet")
    assert rc == 0, err
    pictures = [(out / "depth" / f"{i:06d}.png").read_bytes() for i in range(4)]
    assert all(p == pictures[0] for p in pictures)


def test_one_colour_range_over_a_real_sequence(tmp_path, capsys, kitti_raw):
    frames = tmp_path / "frames"
    frames.mkdir()
    for f in sorted((kitti_raw / "image_02" / "data").glob("*.png"))[:10]:
        shutil.copyfile(f, frames / f.name)
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, "predict", frames, "--out", out, "--tasks", "depth", "--colour-scale", "first:3", "--no-progress"
    )
    assert rc == 0, err
    scale = json.loads((out / "summary.json").read_text())["colour_scale"]
    assert scale["mode"] == "first:3"
    depths = [np.load(p).astype(np.float64) for p in sorted((out / "depth").glob("*.npy"))]
    own = [1 / np.percentile(1 / d, 95) for d in depths]  # each frame's own range differs...
    assert max(own) / min(own) > 1.001
    vmax = float(np.median([np.percentile(1 / d, 95) for d in depths[:3]]))  # ...the pictures use one
    assert scale["inverse_depth_max"] == pytest.approx(vmax, rel=1e-9)
    for d, png in zip(depths, sorted((out / "depth").glob("*.png"))):
        picture = cv2.cvtColor(cv2.imread(str(png)), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(picture, depth_to_color(d, vmax=vmax))


def test_steady_scale_modes():
    flat, far = np.full((4, 4), 2.0), np.full((4, 4), 4.0)
    first = SteadyScale("first:2")
    first.observe(flat, None)
    assert not first.ready
    first.observe(far, None)
    assert first.ready and first.scales()[0] == pytest.approx(np.median([0.5, 0.25]))
    first.observe(np.full((4, 4), 100.0), None)
    assert first.scales()[0] == pytest.approx(0.375)  # fixed
    running = SteadyScale("running")
    for d in (flat, far, far):
        running.observe(d, None)
    assert running.scales()[0] == pytest.approx(0.25)
    assert SteadyScale("frame").scales() == (None, None)
    for bad in ("first", "first:0", "loud"):
        with pytest.raises(ValueError):
            SteadyScale(bad)


# ----------------------------------------------------------------------------- result video
def test_result_video_has_one_frame_per_decoded_input_frame(tmp_path, capsys, dashcam):
    out = tmp_path / "out"
    video = tmp_path / "result.mp4"
    rc, _, err = run_cli(
        capsys, "predict", dashcam / DASHCAM_VIDEO, "--out", out, "--calib", dashcam / DASHCAM_CALIB,
        "--max-frames", "12", "--video-out", video, "--no-progress", "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    decoded = json.loads((out / "summary.json").read_text())["frames"]
    cap = cv2.VideoCapture(str(video))
    count = 0
    while cap.read()[0]:
        count += 1
    cap.release()
    assert count == decoded == 12
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".result")]  # no temp file left
    again = ["--out", tmp_path / "again", "--calib", dashcam / DASHCAM_CALIB, "--video-out", video]
    rc, _, err = run_cli(capsys, "predict", dashcam / DASHCAM_VIDEO, *again)
    assert rc != 0 and "does not overwrite" in err


# ----------------------------------------------------------------------------- live sources
def test_raw_frames_on_stdin_give_the_depth_of_the_file(tmp_path, dashcam, ffmpeg):
    video, calib = dashcam / DASHCAM_VIDEO, dashcam / DASHCAM_CALIB
    raw = subprocess.run(
        [ffmpeg, "-loglevel", "error", "-i", str(video), "-frames:v", "5", "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        capture_output=True,
        check=True,
    ).stdout
    assert len(raw) == 5 * 1280 * 720 * 3
    cli = [*GEONET_CLI, "predict"]
    common = ["--calib", str(calib), "--tasks", "depth", "--no-progress", "--quiet"]
    piped = subprocess.run(
        [*cli, "--stdin-frames", "1280x720", "--out", str(tmp_path / "stdin"), *common],
        input=raw,
        capture_output=True,
    )
    assert piped.returncode == 0, piped.stderr.decode()
    direct = subprocess.run(
        [*cli, str(video), "--max-frames", "5", "--out", str(tmp_path / "file"), *common], capture_output=True
    )
    assert direct.returncode == 0, direct.stderr.decode()
    names = sorted(p.name for p in (tmp_path / "stdin" / "depth").glob("*.npy"))
    assert names == [f"{i:06d}.npy" for i in range(5)]
    for name in names:
        np.testing.assert_array_equal(
            np.load(tmp_path / "stdin" / "depth" / name), np.load(tmp_path / "file" / "depth" / name)
        )


def test_a_stream_cut_inside_a_frame_keeps_the_whole_frames(tmp_path, capsys, monkeypatch):
    import io

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (3, 64, 96, 3), dtype=np.uint8)
    stream = io.BytesIO(frames.tobytes() + b"\x00" * 100)
    monkeypatch.setattr("sys.stdin", type("Stdin", (), {"buffer": stream})())
    out = tmp_path / "out"
    rc, _, err = run_cli(
        capsys, "predict", "-", "--stdin-frames", "96x64", "--out", out, "--tasks", "depth", "--no-progress", "--quiet"
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 3 and "ended inside frame 000003" in summary["truncated"]
    # the partial frame fails (exit 1, one warning): a wrong --stdin-frames size ends like this too (issue 41)
    assert rc == 1, err
    assert summary["failures"] == [{"frame": "000003", "reason": f"-: truncated: {summary['truncated']}"}]


def test_live_source_errors_are_one_line(tmp_path, capsys):
    rc, _, err = run_cli(capsys, "predict", "--source", "9", "--out", tmp_path / "o")
    assert rc != 0 and "cannot open this camera" in err and "Traceback" not in err
    rc, _, err = run_cli(capsys, "predict", "-", "--out", tmp_path / "o")
    assert rc != 0 and "--stdin-frames" in err
    rc, _, err = run_cli(capsys, "predict", "--out", tmp_path / "o")
    assert rc != 0 and "no input" in err
    rc, _, err = run_cli(capsys, "predict", "-", "--stdin-frames", "wide", "--out", tmp_path / "o")
    assert rc == 2 and "expected WxH" in err
