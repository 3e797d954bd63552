"""``python -m benchmarks.eval_all``: a model and the baselines on every real set of ../shared at once.

Each set scores as the one-task ``geonet-infer eval`` scores it (the same per-frame rows, compared here), and
the real validation figure is the per-frame mean recomputed by hand; missing and unknown folders are named.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import eval_all
from benchmarks.eval_all import main
from geonet_infer.cli import main as cli_main
from geonet_infer.errors import InputError
from geonet_infer.eval import stereo


def small_real_root(realdata: Path, root: Path) -> Path:
    """A real-data folder with the small sets (links to ../shared files): KITTI object, KITTI 2015 stereo and
    flow, odometry 00, and odometry 06 cut to what the SGBM frame and 3 pose snippets need; no test drive,
    no odometry 01 (missing sets must be named), an unscored folder and an unknown one."""
    root.mkdir()
    for name in ("kitti_object_3frames", "kitti2015_000046_stereo", "kitti2015_flow_000010", "kitti_odometry_00"):
        (root / name).symlink_to((realdata / name).resolve())
    src, dst = realdata / "kitti_odometry_06", root / "kitti_odometry_06"
    keep = ["poses/06.txt", "sequences/06/calib.txt", "sequences/06/image_2/000012.png"]
    keep += ["sequences/06/image_3/000012.png"] + [f"sequences/06/image_0/{i:06d}.png" for i in range(7)]
    for rel in keep:
        (dst / rel).parent.mkdir(parents=True, exist_ok=True)
        (dst / rel).symlink_to((src / rel).resolve())
    (root / "udacity_dashcam").mkdir()
    (root / "mystery").mkdir()
    return root


def test_eval_all_scores_every_set_and_the_validation_mean_of_its_frames(realdata, tmp_path, capsys):
    root = small_real_root(realdata, tmp_path / "realdata")
    out, md = tmp_path / "all.json", tmp_path / "all.md"
    assert main(["--data", str(root), "--json", str(out), "--markdown", str(md)]) == 1
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    # the command that reproduces the numbers (output files left out), as the JSON and the markdown give it
    assert result["command"] == f"python -m benchmarks.eval_all --data {root}"
    assert f"`python -m benchmarks.eval_all --data {root}`" in printed
    assert md.read_text() == printed
    names = [s["name"] for s in result["sets"]]
    assert names == [
        "KITTI object 000000–000002",
        "KITTI 2015 stereo 000046",
        "stereo SGBM, odometry 00 + 06",
        "KITTI 2015 flow 000010",
        "KITTI odometry 00",
        "KITTI odometry 06",
    ]
    # missing sets are named (exit 1), folders without a set are listed with the reason
    assert [m["set"] for m in result["missing"]] == ["KITTI raw 2011_09_26 (test drive)", "KITTI odometry 01"]
    assert "**not scored, folder missing**: KITTI odometry 01 (kitti_odometry_01/sequences/01)" in printed
    assert {n["folder"]: n["why"] for n in result["not_scored"]} == {
        "mystery": "no entry in benchmarks.eval_all.REAL_SETS",
        "udacity_dashcam": "no ground truth",
    }
    # one row per (set, metric), the model at both precisions beside the task's baselines
    assert "| set | metric | frames | model FP32 | model INT8 | constant depth |" in printed
    assert "| set | metric | pairs | model FP32 | model INT8 | DIS medium | zero flow |" in printed
    assert "| set | metric | snippets | model FP32 | model INT8 | ORB-VO | identity pose |" in printed

    def metric_rows(name: str) -> list[str]:  # the set's rows in the task tables (not in the table of sets)
        return [row.split(" | ")[1] for row in printed.splitlines() if row.startswith(f"| {name} | ")][1:]

    assert metric_rows("KITTI object 000000–000002") == [
        "AbsRel",
        "SqRel",
        "RMSE",
        "RMSElog",
        "δ<1.25",
        "δ<1.25²",
        "δ<1.25³",
    ]
    assert metric_rows("KITTI odometry 06") == ["ATE (paper, ÷N)", "ATE RMSE"]
    counts = {s["name"]: (s["items"], s["frames"]) for s in result["sets"]}
    assert counts["KITTI object 000000–000002"] == (3, 3) and counts["KITTI odometry 06"] == (3, 7)
    # each set scores as the one-task command does: the same per-frame rows
    sgbm = tmp_path / "sgbm"
    stereo.build(root, sgbm)
    singles = {
        "KITTI object 000000–000002": ["--data", str(root / "kitti_object_3frames")],
        "KITTI 2015 stereo 000046": ["--data", str(root / "kitti2015_000046_stereo"), "--fx", "721.5377"],
        "stereo SGBM, odometry 00 + 06": ["--data", str(sgbm)],
    }
    frames = []
    for name, args in singles.items():
        if "--fx" in args:
            args += ["--baseline", "0.54"]
        one = tmp_path / "one.json"
        assert cli_main(["eval", "depth", *args, "--method", "model,constant", "--json", str(one)]) == 0
        capsys.readouterr()
        fp32, constant = json.loads(one.read_text())["results"]
        mine = next(s for s in result["sets"] if s["name"] == name)["results"]
        assert [r["abs_rel"] for r in fp32["items"]] == pytest.approx([r["abs_rel"] for r in mine["fp32"]["items"]])
        assert [r["a1"] for r in constant["items"]] == pytest.approx([r["a1"] for r in mine["constant"]["items"]])
        frames += [(f, c) for f, c in zip(fp32["items"], constant["items"])]
    # the real validation figure: every frame outside the test drive, each weighing the same
    v = result["validation"]
    assert v["frames"] == len(frames) == 6 and v["excludes"] == "kitti_raw_2011_09_26_sfnd"
    assert v["metrics"]["fp32"]["abs_rel"] == pytest.approx(np.mean([f["abs_rel"] for f, _ in frames]))
    assert v["metrics"]["constant"]["rmse"] == pytest.approx(np.mean([c["rmse"] for _, c in frames]))
    assert "**real validation** (depth frames outside the test drive) | AbsRel | 6 |" in printed


def test_eval_all_refuses_options_of_one_task(tmp_path, capsys):
    """Options of the one-task commands (each set has its own; every precision is scored) are bad usage: exit 2,
    one line naming the option."""
    for extra in (["--method", "dis"], ["--precision", "int8"], ["--fx", "700"], ["--layout", "kitti"]):
        assert main(["--data", str(tmp_path), *extra]) == 2
        err = capsys.readouterr().err
        assert f"unrecognized arguments: {extra[0]}" in err and len(err.strip().splitlines()) == 1


def test_eval_all_bad_usage_is_one_line_and_help_says_what_it_scores(tmp_path, capsys):
    assert main([]) == 2  # --data is required
    err = capsys.readouterr().err
    assert "--data" in err and len(err.strip().splitlines()) == 1
    absent = tmp_path / "absent"
    assert main(["--data", str(absent)]) == 2
    err = capsys.readouterr().err
    assert f"{absent}: real-data folder not found" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(InputError, match="real-data folder not found"):
        eval_all.run(absent, {})
    assert main(["--help"]) == 0
    printed = capsys.readouterr().out
    assert "usage: python -m benchmarks.eval_all" in printed and "real validation figure" in printed
    assert "--precision" not in printed and "--backend" in printed  # every precision is scored; model flags reused
