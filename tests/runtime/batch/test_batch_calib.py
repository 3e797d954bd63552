"""batch: each input with its own calibration, from its list line or from a file beside it (issue 43, point 3)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from geonet_infer.cli import main
from geonet_infer.samples import SAMPLE_FRAMES

FRAMES = sorted(SAMPLE_FRAMES.glob("*.png"))[:3]


def sequence(root: Path, name: str) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    for f in FRAMES:
        shutil.copyfile(f, folder / f.name)
    return folder


def matrix_file(path: Path, fx: float) -> list[list[float]]:
    """A 3x3 text matrix K (one of the calibration forms --calib reads) with focal length ``fx``."""
    K = [[fx, 0.0, 208.0], [0.0, fx, 64.0], [0.0, 0.0, 1.0]]
    path.write_text("\n".join(" ".join(f"{v:g}" for v in row) for row in K) + "\n")
    return K


def test_a_batch_list_of_inputs_with_their_own_calibrations_records_each_k(tmp_path, capfd):
    root = tmp_path / "in"
    for name in ("a", "b", "c"):
        sequence(root, name)
    K_a = matrix_file(tmp_path / "cam_a.txt", 300.0)
    K_b = matrix_file(tmp_path / "cam_b.txt", 450.0)
    K_c = matrix_file(root / "c.calib.txt", 600.0)  # beside the input: its own, as a KITTI drive's
    listing = tmp_path / "inputs.txt"
    listing.write_text("# input | its calibration\nin/a | cam_a.txt\nin/b|cam_b.txt\nin/c\n")
    out = tmp_path / "out"
    # flow needs intrinsics: without the pairs (no --calib) this job would be refused (exit 2)
    rc = main(["batch", str(listing), "--out", str(out), "--workers", "1", "--no-progress", "--quiet"])
    err = capfd.readouterr().err
    assert rc == 0, err
    summary = json.loads((out / "summary.json").read_text())
    cameras = {Path(row["input"]).name: row["camera"] for row in summary["per_sequence"]}
    for name, K, source in (("a", K_a, "cam_a.txt"), ("b", K_b, "cam_b.txt"), ("c", K_c, "c.calib.txt")):
        np.testing.assert_allclose(cameras[name]["K"], K)
        assert Path(cameras[name]["source"]).name.startswith(f"{source} ")  # "cam_a.txt (3x3 matrix)"
        own = json.loads((out / name / "summary.json").read_text())
        assert own["tasks"] == ["depth", "pose", "flow"]
        np.testing.assert_allclose(own["camera"]["K_input_resolution"], K)


def test_a_list_line_with_a_bar_but_no_calibration_is_a_one_line_error(tmp_path, capfd):
    sequence(tmp_path / "in", "a")
    listing = tmp_path / "inputs.txt"
    listing.write_text("in/a |\n")
    rc = main(["batch", str(listing), "--out", str(tmp_path / "out"), "--no-progress"])
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and "inputs.txt" in lines[0] and "line 1" in lines[0], lines


def test_batch_outputs_writes_only_what_is_asked_in_every_sequence(tmp_path, capfd):
    seqs = [sequence(tmp_path / "in", name) for name in ("a", "b")]
    out = tmp_path / "out"
    argv = ["batch", *map(str, seqs), "--out", str(out), "--outputs", "depth-png16", "--no-progress", "--quiet"]
    assert main(argv) == 0, capfd.readouterr().err  # depth only: no calibration needed
    for name in ("a", "b"):
        files = {p.relative_to(out / name).as_posix() for p in (out / name).rglob("*") if p.is_file()}
        assert {f.split("/")[0] for f in files if not f.startswith(".")} == {"depth16", "summary.json"}
        assert len([f for f in files if f.startswith("depth16/")]) == len(FRAMES)
        assert json.loads((out / name / "summary.json").read_text())["tasks"] == ["depth"]
