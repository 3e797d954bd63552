"""``predict --rerun FILE.rrd`` (issue 59): the recording reads back (rerun's own reader, rerun.chunk.RrdReader)
with every frame's RGB, depth and camera, and its camera path is predict's poses_kitti.txt.

rerun-sdk is the [viz] extra: without it these tests skip, except the one-line error that names it.
"""

from __future__ import annotations

import builtins
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from geonet_infer.errors import InputError
from geonet_infer.io.atomic import leftover_temps


def read_back(path: Path) -> dict[str, dict[int, dict]]:
    """entity path -> frame -> {column: value} of every logged row (static rows left out)."""
    import rerun.chunk

    rows: dict[str, dict[int, dict]] = defaultdict(dict)
    for chunk in rerun.chunk.RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "frame" not in batch.schema.names:
            continue
        columns = {name: batch.column(name).to_pylist() for name in batch.schema.names if ":" in name}
        for k, frame in enumerate(batch.column("frame").to_pylist()):
            rows[str(chunk.entity_path)].setdefault(frame, {}).update({n: v[k] for n, v in columns.items()})
    return rows


@pytest.mark.slow
def test_the_drive_recording_reads_back_with_every_frame_and_predicts_poses(kitti_raw, tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is the [viz] extra")
    out, rrd = tmp_path / "out", tmp_path / "drive.rrd"
    cmd = [sys.executable, "-m", "geonet_infer.cli", "predict", str(kitti_raw), "--out", str(out), "--rerun", str(rrd),
           "--no-progress", "--quiet"]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    rows = read_back(rrd)
    frames = range(78)
    assert sorted(rows["/world/camera"]) == list(frames)
    assert all("EncodedImage:blob" in rows["/world/camera/image"][f] for f in frames)  # RGB, JPEG
    assert all("Pinhole:image_from_camera" in rows["/world/camera/image"][f] for f in frames)
    assert all("DepthImage:buffer" in rows["/world/camera/image/depth"][f] for f in frames)
    assert all("Points3D:positions" in rows["/world/points"][f] for f in frames)
    assert len(rows["/check/flow_error"]) == 77  # one per pair
    poses = np.loadtxt(out / "poses_kitti.txt").reshape(-1, 3, 4)
    for f in frames:
        camera = rows["/world/camera"][f]
        translation = np.asarray(camera["Transform3D:translation"], np.float64).reshape(3)
        rotation = np.asarray(camera["Transform3D:mat3x3"], np.float64).reshape(3, 3, order="F")  # column-major
        np.testing.assert_allclose(translation, poses[f, :, 3], rtol=1e-6, atol=1e-6)  # float32 precision
        np.testing.assert_allclose(rotation, poses[f, :, :3], rtol=1e-6, atol=1e-6)
    summary = (out / "summary.json").read_text()
    assert '"rerun"' in summary and not leftover_temps(rrd)  # renamed into place


def test_without_rerun_sdk_one_line_names_the_extra(monkeypatch, tmp_path, capsys):
    real_import = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("No module named 'rerun'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    from geonet_infer.cli import main

    code = main(["predict", str(tmp_path), "--out", str(tmp_path / "out"), "--rerun", str(tmp_path / "x.rrd")])
    err = capsys.readouterr().err
    assert code == 2 and "[viz]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists() and not (tmp_path / "x.rrd").exists()


def test_a_recording_path_predict_may_not_write_is_refused(tmp_path):
    from geonet_infer.output.rerun_recording import check_rerun_path

    theirs = tmp_path / "theirs.rrd"
    theirs.write_bytes(b"someone's recording")
    with pytest.raises(InputError, match="does not overwrite"):
        check_rerun_path(theirs, tmp_path / "out")
    with pytest.raises(InputError, match=r"\.rrd"):
        check_rerun_path(tmp_path / "x.mp4", tmp_path / "out")
    with pytest.raises(InputError, match="folder not found"):
        check_rerun_path(tmp_path / "missing" / "x.rrd", tmp_path / "out")
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.rrd").write_bytes(b"an earlier run's")
    check_rerun_path(out / "mine.rrd", out)  # inside OUT: the run owns it (the marker decides)
    assert theirs.read_bytes() == b"someone's recording"


def test_the_api_records_a_sequence(tmp_path, kitti_raw):
    pytest.importorskip("rerun", reason="rerun-sdk is the [viz] extra")
    import geonet_infer
    from geonet_infer.io import list_images, read_camera, read_image
    from geonet_infer.output.rerun_recording import record_sequence

    frames = [read_image(p) for p in list_images(kitti_raw / "image_02" / "data")[:4]]
    camera = read_camera(kitti_raw / "calib_cam_to_cam.txt")
    results = list(geonet_infer.load().iter_sequence(frames, camera))
    path = record_sequence(tmp_path / "api.rrd", results, frames)
    rows = read_back(path)
    assert sorted(rows["/world/camera"]) == [0, 1, 2, 3] and len(rows["/world/camera/image/depth"]) == 4


def test_a_recording_without_frames_leaves_nothing(tmp_path):
    pytest.importorskip("rerun", reason="rerun-sdk is the [viz] extra")
    from geonet_infer.output.rerun_recording import RerunRecording

    recording = RerunRecording(tmp_path / "empty.rrd")
    recording.close(keep=True)  # no frame was logged: nothing to keep
    assert list(tmp_path.iterdir()) == []
