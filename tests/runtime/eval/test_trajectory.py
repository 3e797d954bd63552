"""Whole-trajectory scores (issue 59): APE after a Sim(3) alignment and RPE per frame, in closed form and
against evo (GPL-3.0: a test-only dependency, the dev extra; these tests skip without it).

Golden values: a trajectory moved by a known similarity scores 0; evo's own ``evo_ape`` / ``evo_rpe``
(``-as``) on the same files, within 1e-6.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from geonet_infer.errors import InputError
from geonet_infer.eval import metrics
from geonet_infer.io import read_kitti_poses, write_kitti_poses


def rotation(axis: str, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def curve(n: int = 40, seed: int = 0) -> np.ndarray:
    """A camera driving a bend with some heading change: (n, 4, 4) camera-to-world."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = rotation("y", 0.02 * i) @ rotation("x", 0.01 * rng.standard_normal())
        poses[i, :3, 3] = [np.sin(0.1 * i) * 5, 5 * (1 - np.cos(0.1 * i)), 0.9 * i]  # a helix: it has a hand
    return poses


def noisy(poses: np.ndarray, seed: int = 1) -> np.ndarray:
    """The same path at a third of the scale, seen from another frame, with step noise."""
    rng = np.random.default_rng(seed)
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = rotation("z", 0.7) @ rotation("x", -0.3), [3.0, -1.0, 2.0]
    out = S @ poses
    out[:, :3, 3] = (out[:, :3, 3] / 3.0) + 0.05 * rng.standard_normal((len(poses), 3))
    for i in range(len(out)):
        out[i, :3, :3] = out[i, :3, :3] @ rotation("z", 0.01 * rng.standard_normal())
    return out


def test_a_similar_trajectory_scores_zero_and_its_scale_is_found():
    gt = curve()
    S = np.eye(4)
    S[:3, :3], S[:3, 3] = rotation("y", 1.1) @ rotation("z", 0.4), [10.0, 2.0, -4.0]
    est = S @ gt
    est[:, :3, 3] *= 0.25  # a monocular scale
    aligned, scale = metrics.align_sim3(gt, est)
    assert scale == pytest.approx(4.0)
    np.testing.assert_allclose(aligned, gt, atol=1e-9)
    assert metrics.ape_rmse(gt, est) < 1e-9 and metrics.rpe_translation_rmse(gt, est) < 1e-9
    # a constant offset is removed by the alignment's translation
    shifted = gt.copy()
    shifted[:, :3, 3] += [0.0, 0.0, 5.0]
    assert metrics.ape_rmse(gt, shifted) < 1e-9


def test_a_mirrored_path_is_not_aligned_by_a_reflection():
    gt = curve()
    mirrored = gt.copy()
    mirrored[:, 0, 3] *= -1  # the helix turned the other way: no rotation maps it back
    assert metrics.ape_rmse(gt, mirrored) > 0.5
    _, R, _ = metrics.umeyama_sim3(mirrored[:, :3, 3], gt[:, :3, 3])
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_a_standing_camera_has_no_alignment():
    gt = curve()
    with pytest.raises(InputError, match="do not spread"):
        metrics.ape_rmse(gt, np.tile(np.eye(4), (len(gt), 1, 1)))


def evo_rmse(tool: str, gt_file: Path, est_file: Path) -> float:
    exe = shutil.which(tool) or str(Path(sys.executable).parent / tool)
    run = subprocess.run([exe, "kitti", str(gt_file), str(est_file), "-as"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return float(re.search(r"rmse\s+([0-9.eE+-]+)", run.stdout).group(1))


@pytest.fixture()
def evo():
    return pytest.importorskip("evo", reason="evo (GPL-3.0) is a test-only dependency: pip install '.[dev]'")


def test_ape_and_rpe_equal_evo_on_the_same_files(evo, tmp_path, kitti_odometry_06):
    """The official poses of KITTI odometry 06 and a distorted copy of them, written as KITTI files."""
    gt = read_kitti_poses(kitti_odometry_06 / "poses" / "06.txt")[:50]
    est = noisy(gt)
    write_kitti_poses(tmp_path / "gt.txt", gt)
    write_kitti_poses(tmp_path / "est.txt", est)
    gt_read, est_read = read_kitti_poses(tmp_path / "gt.txt"), read_kitti_poses(tmp_path / "est.txt")
    assert metrics.ape_rmse(gt_read, est_read) == pytest.approx(
        evo_rmse("evo_ape", tmp_path / "gt.txt", tmp_path / "est.txt"), abs=1e-6
    )
    assert metrics.rpe_translation_rmse(gt_read, est_read) == pytest.approx(
        evo_rmse("evo_rpe", tmp_path / "gt.txt", tmp_path / "est.txt"), abs=1e-6
    )


def test_eval_pose_whole_trajectory_equals_evo_ape_on_its_files(evo, tmp_path, kitti_odometry_06):
    """`geonet-infer eval pose --trajectories DIR`: the APE it prints is evo_ape's on the files it wrote."""
    out = tmp_path / "traj"
    cmd = [sys.executable, "-m", "geonet_infer.cli", "eval", "pose", "--data",
           str(kitti_odometry_06 / "sequences" / "06"), "--method", "model,orb-vo", "--limit", "20",
           "--trajectories", str(out),
           "--json", str(tmp_path / "eval.json")]  # fmt: skip
    run = subprocess.run(cmd, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    import json

    results = json.loads((tmp_path / "eval.json").read_text())["results"]
    for result in results:
        whole = result["trajectory"]
        assert whole["frames"] >= 20
        files = whole["files"]
        assert whole["ape_rmse"] == pytest.approx(
            evo_rmse("evo_ape", Path(files["gt_kitti"]), Path(files["kitti"])), abs=1e-6
        )
        assert whole["rpe_rmse"] == pytest.approx(
            evo_rmse("evo_rpe", Path(files["gt_kitti"]), Path(files["kitti"])), abs=1e-6
        )
        np.testing.assert_allclose(read_kitti_poses(files["kitti"])[0], np.eye(4), atol=1e-9)  # chained from identity
    assert "evo_ape kitti" in run.stdout
