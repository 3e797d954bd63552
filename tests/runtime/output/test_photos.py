"""One photo, and a folder of photos of any sizes: depth needs no snippet (issue 43, point 2)."""

from __future__ import annotations

import json

import cv2
import numpy as np

import geonet_infer
from geonet_infer.cli import main
from geonet_infer.samples import SAMPLE_FRAMES

FRAMES = sorted(SAMPLE_FRAMES.glob("*.png"))


def run(capsys, *argv) -> tuple[int, str]:
    rc = main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def photo(path, frame, size) -> np.ndarray:
    """Write ``frame`` resized to ``size`` (W, H) at ``path`` (format from its suffix); the RGB that
    OpenCV decodes back from it."""
    bgr = cv2.resize(cv2.imread(str(frame)), size, interpolation=cv2.INTER_AREA)
    assert cv2.imwrite(str(path), bgr)
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def test_a_single_jpeg_gives_its_depth(tmp_path, capsys):
    rgb = photo(tmp_path / "photo.jpg", FRAMES[3], (500, 300))
    out = tmp_path / "out"
    rc, err = run(capsys, "predict", tmp_path / "photo.jpg", "--out", out, "--no-progress", "--quiet")
    assert rc == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 1 and summary["tasks"] == ["depth"] and summary["input"]["kind"] == "image"
    depth = np.load(out / "depth" / "photo.npy")
    assert depth.shape == (300, 500)
    expected = geonet_infer.load().depth(rgb).depth  # the API on the pixels OpenCV decodes
    np.testing.assert_allclose(depth, expected, rtol=1e-5)


def test_a_folder_of_3_photos_of_3_sizes_gives_3_depths(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    sizes = {"a": (416, 128), "b": (640, 480), "c": (300, 500)}
    for (name, size), frame in zip(sizes.items(), FRAMES):
        photo(folder / f"{name}.jpg", frame, size)
    out = tmp_path / "out"
    rc, err = run(capsys, "predict", folder, "--out", out, "--tasks", "depth", "--no-progress", "--quiet")
    assert rc == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 3 and summary["failed"] == 0
    for name, (w, h) in sizes.items():
        assert np.load(out / "depth" / f"{name}.npy").shape == (h, w)
        assert cv2.imread(str(out / "depth" / f"{name}.png")).shape[:2] == (h, w)


def test_sequence_tasks_keep_their_one_size_rule(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    for i, frame in enumerate(FRAMES[:4]):
        photo(folder / f"{i}.png", frame, (416, 128) if i != 2 else (300, 200))
    out = tmp_path / "out"
    rc, err = run(capsys, "predict", folder, "--out", out, "--tasks", "depth,pose", "--no-progress", "--quiet")
    assert rc == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 3
    assert summary["failures"] == [{"frame": "2", "reason": "frame is 300x200, the sequence is 416x128"}]
    assert [line for line in err.splitlines() if line.startswith("failed:")] == [
        "failed: 2: frame is 300x200, the sequence is 416x128"
    ]


def test_one_photo_for_a_sequence_task_is_a_one_line_error(tmp_path, capsys):
    photo(tmp_path / "photo.png", FRAMES[0], (416, 128))
    out = tmp_path / "out"
    rc, err = run(capsys, "predict", tmp_path / "photo.png", "--out", out, "--tasks", "pose", "--no-progress")
    assert rc == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "photo.png" in lines[0] and "--tasks depth" in lines[0], err
    assert not out.exists()
