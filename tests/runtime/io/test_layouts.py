"""Dataset layouts recognised by predict, batch and eval (issue 58): each on folders the test writes,
with calibration values typed here, and on the real extracts in ../shared/realdata."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.io.frames import open_frames
from geonet_infer.io.layouts import find_layout

SAMPLE = Path(geonet_infer.__file__).resolve().parent / "samples" / "synth_seq" / "image"
P_LINE = "{k}: {f} 0 {cx} 0 0 {f} {cy} 0 0 0 1 0"


def _frames(folder: Path, n: int, suffix: str = ".png") -> list[Path]:
    folder.mkdir(parents=True)
    files = sorted(SAMPLE.glob("*.png"))
    out = []
    for i in range(n):
        dst = folder / f"{i:06d}{suffix}"
        if suffix == ".png":
            shutil.copy(files[i % len(files)], dst)
        else:
            cv2.imwrite(str(dst), cv2.imread(str(files[i % len(files)])))
        out.append(dst)
    return out


def _odometry(root: Path, colour: int, grey: int) -> Path:
    """sequences/07 with P0 (fx 700) and P2 (fx 710) told apart, times.txt, and frames."""
    seq = root / "sequences" / "07"
    if colour:
        _frames(seq / "image_2", colour)
    if grey:
        _frames(seq / "image_0", grey)
    lines = [P_LINE.format(k="P0", f=700.0, cx=200.0, cy=60.0), P_LINE.format(k="P1", f=700.0, cx=200.0, cy=60.0)]
    lines += [P_LINE.format(k="P2", f=710.0, cx=205.0, cy=61.0)]
    (seq / "calib.txt").write_text("\n".join(lines) + "\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(max(colour, grey))))
    return seq


def test_kitti_odometry_prefers_colour_and_reads_its_own_matrix(tmp_path):
    seq = _odometry(tmp_path, colour=4, grey=4)
    source = open_frames(seq)
    assert source.kind == "kitti_odometry" and source.name == "07" and len(source) == 4
    assert source.layout.images.name == "image_2" and source.layout.times == seq / "times.txt"
    K = source.own_camera().K
    assert (K[0, 0], K[0, 2], K[1, 2]) == (710.0, 205.0, 61.0)  # P2's, typed above
    bare = open_frames(seq / "image_0")  # a bare image_0 finds ../calib.txt and its P0
    assert bare.own_camera().K[0, 0] == 700.0 and bare.name == "07"


def test_kitti_odometry_extract_with_more_grey_frames_runs_the_grey_camera(tmp_path):
    seq = _odometry(tmp_path, colour=2, grey=6)
    source = open_frames(seq)
    assert source.layout.images.name == "image_0" and len(source) == 6
    assert source.own_camera().K[0, 0] == 700.0


def test_euroc_from_each_of_its_folders(require_real):
    root = require_real("euroc_v1_01_micro")
    for given in (root, root / "mav0", root / "mav0" / "cam0", root / "mav0" / "cam0" / "data"):
        source = open_frames(given)
        assert source.kind == "euroc" and source.name == "euroc_v1_01_micro" and len(source) == 20, given
        cam = source.own_camera()
        # sensor.yaml: intrinsics [458.654, 457.296, 367.215, 248.375], radial-tangential distortion
        np.testing.assert_allclose(cam.K[[0, 1, 0, 1], [0, 1, 2, 2]], [458.654, 457.296, 367.215, 248.375])
        np.testing.assert_allclose(cam.dist, [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05])
        assert cam.size == (752, 480) and cam.origin == "calibration file"


def test_tum_rgbd_takes_the_tables_camera_by_its_name(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_xyz"
    files = _frames(seq / "rgb", 3)
    (seq / "rgb.txt").write_text(
        "# timestamp filename\n" + "".join(f"{i}.0 rgb/{f.name}\n" for i, f in enumerate(files))
    )
    source = open_frames(seq)
    assert source.kind == "tum_rgbd" and len(source) == 3
    cam = source.own_camera()  # TUM's published freiburg1 intrinsics: 517.3 516.5 318.6 255.3
    np.testing.assert_allclose(cam.K[[0, 1, 0, 1], [0, 1, 2, 2]], [517.3, 516.5, 318.6, 255.3])
    assert cam.size == (640, 480) and cam.dist is not None
    unnamed = tmp_path / "my_rgbd"
    shutil.copytree(seq, unnamed)
    assert open_frames(unnamed / "rgb").kind == "tum_rgbd" and open_frames(unnamed).own_camera() is None


def test_each_layout_gives_its_frames_recording_times(tmp_path, require_real):
    """Issue 59: predict's poses_tum.txt carries the dataset's own times, so that evo associates it with
    the dataset's ground truth. Golden: the times written into the tables here, and EuRoC's file names
    (nanoseconds)."""
    seq = _odometry(tmp_path / "odom", colour=4, grey=0)
    layout = find_layout(seq)
    np.testing.assert_allclose(layout.frame_times(["000001", "000003"]), [0.1, 0.3])
    assert layout.frame_times(["000009"]) is None  # not in times.txt: the caller falls back to indices
    tum = tmp_path / "rgbd_dataset_freiburg1_xyz"
    files = _frames(tum / "rgb", 2)
    (tum / "rgb.txt").write_text(
        "# timestamp filename\n" + "".join(f"1305031102.{i}75 rgb/{f.name}\n" for i, f in enumerate(files))
    )
    np.testing.assert_allclose(find_layout(tum).frame_times([f.stem for f in files]), [1305031102.075, 1305031102.175])
    euroc = require_real("euroc_v1_01_micro")
    names = sorted(p.stem for p in (euroc / "mav0" / "cam0" / "data").glob("*.png"))
    np.testing.assert_array_equal(find_layout(euroc).frame_times(names), [int(n) / 1e9 for n in names])
    (seq / "times.txt").write_text("not a time\n")
    assert find_layout(seq).frame_times(["000000"]) is None


def test_predict_writes_euroc_times_into_poses_tum(require_real, tmp_path):
    euroc = require_real("euroc_v1_01_micro")
    out = tmp_path / "out"
    from geonet_infer.output.predict import predict_to_dir

    predict_to_dir(geonet_infer.load(), open_frames(euroc), out, tasks=("pose",), max_frames=4, progress=False)
    times = np.loadtxt(out / "poses_tum.txt")[:, 0]
    names = sorted(p.stem for p in (euroc / "mav0" / "cam0" / "data").glob("*.png"))[:4]
    np.testing.assert_allclose(times, [int(n) / 1e9 for n in names], rtol=0, atol=1e-6)


def test_a_plain_folder_has_no_layout(tmp_path):
    _frames(tmp_path / "frames", 2, ".jpg")
    assert find_layout(tmp_path / "frames") is None and open_frames(tmp_path / "frames").own_camera() is None


def test_eval_reads_the_odometry_cameras_from_the_same_place():
    from geonet_infer.eval.datasets import kitti_odometry
    from geonet_infer.io import layouts

    assert kitti_odometry.ODOMETRY_CAMERAS is layouts.ODOMETRY_CAMERAS


def test_batch_reads_each_inputs_layout_calibration(tmp_path):
    """batch: a KITTI odometry sequence and a TUM folder, each with its own K in its summary."""
    import json

    from geonet_infer.batch import run_batch

    seq = _odometry(tmp_path / "odom", colour=3, grey=3)
    tum = tmp_path / "rgbd_dataset_freiburg3_office"
    files = _frames(tum / "rgb", 3)
    (tum / "rgb.txt").write_text("".join(f"{i}.0 rgb/{f.name}\n" for i, f in enumerate(files)))
    run_batch([seq, tum], tmp_path / "out", tasks=("flow",), progress=False, log=lambda _: None)
    odom = json.loads((tmp_path / "out" / "07" / "summary.json").read_text())["camera"]
    assert odom["origin"] == "calibration file" and odom["K"][0][0] == 710.0  # P2, typed in _odometry
    fr3 = json.loads((tmp_path / "out" / tum.name / "summary.json").read_text())["camera"]
    width = fr3["size"][0]  # the TUM table's 535.4 at 640 px, rescaled to the frames' width
    assert fr3["origin"] == "calibration file" and fr3["K"][0][0] == pytest.approx(535.4 * width / 640)
