"""`geonet-infer` command line: predict / demo / info, the output layout, failures and exit codes.

Commands run in-process through ``geonet_infer.cli.main(argv)`` (one subprocess test for
``python -m geonet_infer.cli``). Golden values: the files are read back with this package's
readers and compared with the Python API run here, and with facts (counts, shapes, sizes)
from the data folders' READMEs. No torch.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.cli import main
from geonet_infer.io import read_camera, read_flow_kitti, read_kitti_poses, read_tum_poses
from geonet_infer.output.layout import OUTPUT_MARKER, output_path

PKG = Path(geonet_infer.__file__).resolve().parent
SAMPLE = PKG / "samples" / "synth_seq"
SAMPLE_CALIB = SAMPLE / "calib.txt"
MODEL_DIR = PKG / "models" / "small_synth"
KITTI_RAW = "kitti_raw_2011_09_26_sfnd"
FLOW_MAX = (2**16 - 1 - 2**15) / 64  # largest u/v a KITTI flow PNG holds; the smallest is -512


@pytest.fixture(scope="module")
def predictor():
    return geonet_infer.load()


def sample_folder(tmp_path: Path, n: int = 5) -> Path:
    """A folder with the first ``n`` sample frames (copied, names kept)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in sorted((SAMPLE / "image").glob("*.png"))[:n]:
        shutil.copyfile(f, folder / f.name)
    return folder


def stems(folder: Path, pattern: str) -> list[str]:
    return sorted(p.name.split(".")[0] for p in folder.glob(pattern))


def hidden_files(root: Path) -> list[Path]:
    """Temp files of the atomic writer or a left lock: hidden files other than predict's ownership marker."""
    return [p for p in root.rglob("*") if p.name.startswith(".") and p.name != OUTPUT_MARKER]


def run_cli(capture, *argv) -> tuple[int, str, str]:
    """main(argv) in-process; ``capture`` is capsys, or capfd to also see what C libraries print."""
    rc = main([str(a) for a in argv])
    out, err = capture.readouterr()
    return rc, out, err


# ----------------------------------------------------------------------------- 1. predict on a folder
def test_predict_folder_writes_the_layout_and_matches_the_api(tmp_path, capsys, predictor):
    folder = sample_folder(tmp_path)
    out = tmp_path / "out"
    # latency mode: the API's default, the same graph calls bit for bit (throughput: tests/runtime/core/test_modes.py)
    rc, stdout, stderr = run_cli(
        capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress", "--mode", "latency"
    )
    assert rc == 0, stderr
    names = [f"{i:06d}" for i in range(5)]
    assert stems(out / "depth", "*.npy") == names and stems(out / "depth", "*.png") == names
    assert stems(out / "flow", "*.png") == names[:4] and stems(out / "flow_vis", "*.png") == names[:4]
    for f in ("poses_kitti.txt", "poses_tum.txt"):
        assert len((out / f).read_text().splitlines()) == 5, f
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 5 and summary["failed"] == 0 and summary["failures"] == []
    assert "depthnet" in stdout and hidden_files(out) == []

    seq = predictor.predict_sequence(sorted(folder.glob("*.png")), read_camera(SAMPLE_CALIB))
    for name, fr in zip(names, seq.frames):
        depth = np.load(out / "depth" / f"{name}.npy")
        assert depth.dtype == np.float32 and depth.shape == (128, 416)
        assert np.array_equal(depth, fr.depth), name
        colour = cv2.imread(str(out / "depth" / f"{name}.png"))
        assert colour is not None and colour.shape == (128, 416, 3)
    for name, fr in zip(names[:4], seq.frames[:4]):
        flow, valid = read_flow_kitti(out / "flow" / f"{name}.png")
        assert valid.all()
        expected = np.clip(fr.flow, -512.0, FLOW_MAX)
        np.testing.assert_allclose(flow, expected, rtol=0, atol=1 / 128 + 1e-4, err_msg=name)  # 1/64 px grid
    kitti = read_kitti_poses(out / "poses_kitti.txt")
    np.testing.assert_allclose(kitti, seq.trajectory, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(kitti[0], np.eye(4))
    stamps, tum = read_tum_poses(out / "poses_tum.txt")
    np.testing.assert_allclose(stamps, np.arange(5))  # a folder has no frame rate: time = frame index
    np.testing.assert_allclose(tum, seq.trajectory, rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------- 2. a corrupt frame
def test_predict_records_a_corrupt_frame_and_goes_on(tmp_path, capsys):
    folder = sample_folder(tmp_path)
    bad = folder / "000002.png"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 2000, dtype=np.uint8).tobytes())
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4 and summary["failed"] == 1
    [failure] = summary["failures"]
    assert failure["frame"] == "000002" and "000002.png" in failure["reason"]
    assert "000002" in stderr
    good = ["000000", "000001", "000003", "000004"]
    assert stems(out / "depth", "*.npy") == good and stems(out / "depth", "*.png") == good
    assert stems(out / "flow", "*.png") == good[:3] and stems(out / "flow_vis", "*.png") == good[:3]
    assert len((out / "poses_kitti.txt").read_text().splitlines()) == 4
    assert hidden_files(out) == []


# ----------------------------------------------------------------------------- 3. video input
def test_predict_video_depth_only_undistorts(tmp_path, capsys, realdata):
    dashcam = realdata / "udacity_dashcam"
    out = tmp_path / "out"
    rc, _, stderr = run_cli(
        capsys,
        "predict",
        dashcam / "test_video.mp4",
        "--out",
        out,
        "--calib",
        dashcam / "calib_advanced_lane_lines.txt",
        "--tasks",
        "depth",
        "--no-progress",
    )
    assert rc == 0, stderr
    files = sorted((out / "depth").glob("*.npy"))
    assert len(files) == 38  # README: 38 frames decoded by OpenCV, 1280x720
    assert [f.stem for f in files[:2]] == ["000000", "000001"]
    for f in files:
        d = np.load(f)
        assert d.shape == (720, 1280) and d.dtype == np.float32
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 38 and summary["failed"] == 0
    assert summary["camera"]["undistorted"] is True
    assert not (out / "flow").exists() and not (out / "poses_kitti.txt").exists()


# ----------------------------------------------------------------------------- 4. KITTI drive
def test_predict_kitti_drive_finds_its_calibration(tmp_path, capsys, realdata):
    src = realdata / KITTI_RAW
    drive = tmp_path / "2011_09_26_drive_0001_sync"
    data = drive / "image_02" / "data"
    data.mkdir(parents=True)
    for f in sorted((src / "image_02" / "data").glob("*.png"))[:3]:
        (data / f.name).symlink_to(f.resolve())
    (drive / "calib_cam_to_cam.txt").symlink_to((src / "calib_cam_to_cam.txt").resolve())
    out = tmp_path / "out"
    rc, _, stderr = run_cli(capsys, "predict", drive, "--out", out, "--no-progress")
    assert rc == 0, stderr
    assert len(list((out / "depth").glob("*.npy"))) == 3 and len(list((out / "flow").glob("*.png"))) == 2
    assert np.load(out / "depth" / "0000000000.npy").shape == (375, 1242)
    flow, valid = read_flow_kitti(out / "flow" / "0000000000.png")
    assert flow.shape == (375, 1242, 2) and valid.all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["image_size"] == [1242, 375] and summary["input"]["kind"] == "kitti_drive"
    assert "calib_cam_to_cam.txt" in summary["camera"]["source"]
    # K = left 3x3 of P_rect_02, parsed here from the file
    line = next(l for l in (src / "calib_cam_to_cam.txt").read_text().splitlines() if l.startswith("P_rect_02:"))
    P = np.array([float(v) for v in line.split(":")[1].split()]).reshape(3, 4)
    np.testing.assert_allclose(summary["camera"]["K_input_resolution"], P[:, :3], rtol=1e-9)


# ----------------------------------------------------------------------------- 5. usage errors
def _folder_without_calib(tmp_path):
    return sample_folder(tmp_path, 3)


# capfd, not capsys: the user sees what OpenCV / FFmpeg print on file descriptor 2 as well.
# truncated_mp4_video (an MP4 'ftyp' header followed by random bytes, like a cut-off download) once
# printed FFmpeg's "moov atom not found" on fd 2 before the CLI's own line; geonet_infer/io/frames.py
# quiets FFmpeg's log (OPENCV_FFMPEG_LOGLEVEL) since, and the one-line check below holds for it.
@pytest.mark.parametrize(
    "case",
    [
        "missing_input",
        "bad_intrinsics",
        "bad_tasks",
        "missing_model",
        "random_bytes_video",
        "truncated_mp4_video",
    ],
)
def test_usage_errors_exit_2_with_one_line_naming_the_item(tmp_path, capfd, case):
    out = tmp_path / "out"
    if case == "missing_input":
        item = tmp_path / "no_such_input"
        argv = ["predict", item, "--out", out]
    elif case == "bad_intrinsics":
        item = "--intrinsics"
        argv = ["predict", _folder_without_calib(tmp_path), "--out", out, "--intrinsics", "1,2,3"]
    elif case == "bad_tasks":
        item = "bogus"
        argv = ["predict", _folder_without_calib(tmp_path), "--out", out, "--tasks", "bogus"]
    elif case == "missing_model":
        item = tmp_path / "nonexistent_model"
        argv = ["predict", _folder_without_calib(tmp_path), "--out", out, "--model", item]
    else:
        item = tmp_path / "clip.mp4"
        header = b"\x00\x00\x00\x18ftypisom\x00\x00\x02\x00isomiso2" if case == "truncated_mp4_video" else b""
        item.write_bytes(header + np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
        argv = ["predict", item, "--out", out]
    rc, stdout, stderr = run_cli(capfd, *argv, "--no-progress")
    assert rc == 2
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert str(item) in lines[0] and lines[0].startswith("geonet-infer predict: error:"), lines[0]
    if case == "bad_intrinsics":
        assert "1,2,3" in lines[0]
    assert not (out / "summary.json").exists()


# ----------------------------------------------------------------------------- 6. demo and info
def test_demo_writes_a_picture_and_a_latency_table(tmp_path, capsys):
    out = tmp_path / "demo"
    rc, stdout, stderr = run_cli(capsys, "demo", "--out", out, "--no-progress")
    assert rc == 0, stderr
    img = cv2.imread(str(out / "demo.png"))
    assert img is not None and img.ndim == 3 and img.shape[1] > img.shape[0]
    assert "latency" in stdout and "depthnet" in stdout and "total" in stdout
    assert json.loads((out / "summary.json").read_text())["failed"] == 0


def test_info_text_and_json(capsys):
    arch = json.loads((MODEL_DIR / "manifest.json").read_text())["arch"]
    rc, stdout, _ = run_cli(capsys, "info")
    assert rc == 0 and f"arch {arch}" in stdout
    assert any(line.startswith("isa: ") and "INT8 kernel" in line for line in stdout.splitlines())
    rc, stdout, _ = run_cli(capsys, "info", "--json")
    assert rc == 0
    info = json.loads(stdout)
    assert {"environment", "model"} <= set(info)
    assert info["model"]["arch"] == arch and info["model"]["size"] == [128, 416]
    assert "small_synth" in info["environment"]["bundled_models"]
    assert set(info["environment"]["isa"]["isa"]) == {"avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8"}


def test_no_command_prints_help_and_exits_2(capsys):
    rc, stdout, _ = run_cli(capsys)
    assert rc == 2 and "predict" in stdout


# `python -m geonet_infer.cli` needs geonet_infer/cli/__main__.py (a package cannot run without it).
def test_module_entry_point_help_in_a_subprocess(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "geonet_infer.cli", "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert "predict" in result.stdout and "demo" in result.stdout and "info" in result.stdout


# ----------------------------------------------------------------------------- 7. output names
def test_output_path_refuses_names_that_leave_the_output_folder(tmp_path):
    assert output_path(tmp_path, "depth", "000001", ".npy") == tmp_path / "depth" / "000001.npy"
    for name in ("..", ".", "", "../x", "a/b", "..\\x"):
        with pytest.raises(GeoNetError):
            output_path(tmp_path, "depth", name, ".npy")


def test_no_vis_writes_the_same_data_without_the_pictures(tmp_path, capsys):
    src = sample_folder(tmp_path, 4)
    common = ["--calib", str(SAMPLE_CALIB), "--no-progress"]
    assert main(["predict", str(src), "--out", str(tmp_path / "full"), *common]) == 0
    assert main(["predict", str(src), "--out", str(tmp_path / "lean"), "--no-vis", *common]) == 0
    assert main(["batch", str(src), "--out", str(tmp_path / "batch"), "--no-vis", "--no-progress", *common[:2]]) == 0
    capsys.readouterr()
    full, lean, batch = tmp_path / "full", tmp_path / "lean", tmp_path / "batch" / src.name
    for out in (lean, batch):
        assert not list(out.glob("depth/*.png")) and not (out / "flow_vis").exists()
        for npy in sorted(full.glob("depth/*.npy")):
            np.testing.assert_array_equal(np.load(out / "depth" / npy.name), np.load(npy))
        for png in sorted(full.glob("flow/*.png")):
            assert (out / "flow" / png.name).read_bytes() == png.read_bytes()
    assert len(list(full.glob("depth/*.png"))) == 4 and len(list(full.glob("flow_vis/*.png"))) == 3
    summary = json.loads((lean / "summary.json").read_text())
    assert "depth/*.png" not in summary["outputs"] and "flow_vis/*.png" not in summary["outputs"]
