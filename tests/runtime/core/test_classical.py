"""The classical methods as choices in predict, batch and the API: DIS flow, ORB-VO poses.

Golden values: the eval's own DIS score of the KITTI 2015 pair (``python -m benchmarks.eval_all``,
docs/real_eval.json) and the eval run here on the same pair; closed-form two-view geometry for
the ORB-VO step length; the pose graph's own vector <-> matrix pairs for the Euler angles. No torch.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.classical import euler_xyz, step_length
from geonet_infer.cli import main
from geonet_infer.eval import baselines, evaluation, metrics
from geonet_infer.eval.datasets import load_dataset
from geonet_infer.io.calib import read_camera
from geonet_infer.io.flow import read_flow_kitti
from geonet_infer.io.images import list_images, read_image
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

DOCS = Path(__file__).resolve().parents[3] / "docs"


def test_dis_flow_in_predict_scores_the_evals_dis_epe_on_kitti_2015(kitti2015_flow, tmp_path, capsys):
    """predict --flow-method dis on the pair 000010_10 -> _11 at full resolution, its flow PNG read back
    and scored against flow_noc: the eval's DIS medium EPE-noc (2.98 px in docs/real_eval.json)."""
    frames = kitti2015_flow / "training" / "image_2"
    assert sorted(p.name for p in frames.iterdir()) == ["000010_10.png", "000010_11.png"]
    out = tmp_path / "dis"
    assert main(["predict", str(frames), "--out", str(out), "--flow-method", "dis", "--tasks", "flow"]) == 0
    capsys.readouterr()
    flow, valid = read_flow_kitti(out / "flow" / "000010_10.png")
    assert valid.all() and flow.shape == (375, 1242, 2)  # the input resolution, not the network's
    gt, gt_valid = read_flow_kitti(kitti2015_flow / "training" / "flow_noc" / "000010_10.png")
    epe = metrics.flow_epe(gt, gt_valid, flow)["epe"]

    dataset = load_dataset("flow", kitti2015_flow, "kitti")
    (dis,) = evaluation.baseline_fns("flow", "dis-medium").values()
    evaluated = evaluation.evaluate_flow(dis, dataset)["metrics"]["epe_noc"]
    published = next(
        s["results"]["dis_medium"]["metrics"]["epe_noc"]
        for s in json.loads((DOCS / "real_eval.json").read_text())["sets"]
        if s["path"] == "kitti2015_flow_000010"
    )
    # the PNG holds 1/64 px steps: the same number to rounding
    assert round(epe, 2) == round(evaluated, 2) == round(published, 2) == 2.98
    summary = json.loads((out / "summary.json").read_text())
    assert summary["methods"]["flow"]["method"] == "dis" and "depth" not in summary["methods"]
    # the output check judges the flow that was written, DIS's: it explains the pair (the model's did not)
    check = summary["check"]
    assert check["pairs"] == 1 and check["flow_no_better"] == 0 and check["per_pair"][0]["flow_explains"]


def _two_views(length: float):
    """Points 5-30 m ahead seen from a camera and from the camera moved ``length`` m forward-right."""
    rng = np.random.default_rng(3)
    K = np.array([[700.0, 0, 620], [0, 700, 190], [0, 0, 1]])
    z = rng.uniform(5, 30, 200)
    X = np.stack([rng.uniform(-0.8, 0.8, 200) * z, rng.uniform(-0.25, 0.25, 200) * z, z])  # inside the image
    R, _ = cv2.Rodrigues(np.array([0.0, 0.03, 0.0]))
    t = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t  # camera a -> camera b with a unit step
    X_b = R @ X + (t * length)[:, None]
    p_a, p_b = (K @ X)[:2] / X[2], (K @ X_b)[:2] / X_b[2]
    depth = np.zeros((400, 1280))
    u, v = np.round(p_a).astype(int)
    depth[v, u] = X[2]
    return T, (p_a.T, p_b.T), depth, K


@pytest.mark.parametrize("length", [0.4, 1.7])
def test_orbvo_step_length_matches_the_depth_of_its_points(length):
    """A unit step triangulates the points at depth / length; matching them to the depth gives length."""
    T, pixels, depth, K = _two_views(length)
    assert step_length(T, pixels, depth, K) == pytest.approx(length, rel=0.02)  # pixels rounded to the map
    assert step_length(T, (pixels[0][:5], pixels[1][:5]), depth, K) is None  # too few points


def test_euler_angles_are_the_pose_vectors_convention():
    """PoseNet's graph turns its vector into its matrix: the angles read back are its vector's."""
    predictor = geonet_infer.load()
    frames = list_images(SAMPLE_FRAMES)[: predictor.seq_length]
    pose = predictor.pose(frames)
    for matrix, vector in zip(pose.matrices, pose.vectors):
        np.testing.assert_allclose(euler_xyz(matrix[:3, :3]), vector[3:], atol=1e-5)


def test_api_methods_replace_flow_and_poses_with_the_evals_code():
    """DIS flow equals the eval's DIS on the (undistorted) frames; ORB-VO's rotations and unit
    directions equal the eval's orb_vo on the same frames, its steps scaled to the depth."""
    predictor = geonet_infer.load()
    camera = read_camera(SAMPLE_CALIB)
    frames = list_images(SAMPLE_FRAMES)[:5]
    seq = predictor.predict_sequence(frames, camera, flow_method="dis", pose_method="orbvo")
    rgbs = [read_image(f) for f in frames]
    dis = baselines.dis_flow("medium")
    for i, f in enumerate(seq.frames[:-1]):
        np.testing.assert_array_equal(f.flow, dis(rgbs[i : i + 2]))
    assert seq.frames[-1].flow is None and seq.frames[-1].pose_to_next is None
    K = camera.scaled_to(rgbs[0].shape[1], rgbs[0].shape[0]).K
    eval_poses, info = baselines.orb_vo(rgbs, K)
    assert info["failed_pairs"] == 0
    for i, f in enumerate(seq.frames[:-1]):
        step = metrics.rigid_inverse(eval_poses[i + 1]) @ eval_poses[i]  # the eval's unit step i -> i+1
        np.testing.assert_allclose(f.pose_to_next[:3, :3], step[:3, :3], atol=1e-9)
        length = np.linalg.norm(f.pose_to_next[:3, 3])
        assert length > 0
        np.testing.assert_allclose(f.pose_to_next[:3, 3] / length, step[:3, 3], atol=1e-9)
        np.testing.assert_allclose(
            seq.frames[i + 1].camera_to_world, f.camera_to_world @ metrics.rigid_inverse(f.pose_to_next), atol=1e-12
        )
    # flow stays the network's and poses ORB-VO's: methods are chosen per task
    mixed = predictor.predict_sequence(frames, camera, pose_method="orbvo")
    net = predictor.predict_sequence(frames, camera)
    np.testing.assert_array_equal(mixed.frames[0].flow, net.frames[0].flow)
    np.testing.assert_allclose(mixed.frames[1].pose_to_next, seq.frames[1].pose_to_next)


def test_orbvo_a_camera_standing_still_does_not_move():
    """Frames 1 and 2 are the same picture: the step 1 -> 2 is the identity (the eval's orb_vo, whose
    essential matrix fails there, repeats the step 0 -> 1: a car driving on through a stop)."""
    predictor = geonet_infer.load()
    camera = read_camera(SAMPLE_CALIB)
    frames = list_images(SAMPLE_FRAMES)
    seq = predictor.predict_sequence([frames[0], frames[1], frames[1]], camera, pose_method="orbvo")
    assert np.linalg.norm(seq.frames[0].pose_to_next[:3, 3]) > 0
    np.testing.assert_array_equal(seq.frames[1].pose_to_next, np.eye(4))
    np.testing.assert_array_equal(seq.frames[2].camera_to_world, seq.frames[1].camera_to_world)
    rgbs = [read_image(f) for f in (frames[0], frames[1], frames[1])]
    eval_poses, info = baselines.orb_vo(rgbs, camera.scaled_to(rgbs[0].shape[1], rgbs[0].shape[0]).K)
    assert info["failed_pairs"] == 1 and not np.allclose(eval_poses[2], eval_poses[1])


def test_orbvo_without_intrinsics_assumes_them_and_unknown_methods_are_refused(tmp_path, capsys):
    base = ["predict", str(SAMPLE_FRAMES), "--no-progress"]
    assert main([*base, "--out", str(tmp_path / "a"), "--pose-method", "orbvo", "--tasks", "pose"]) == 0
    out = capsys.readouterr().out
    assert "intrinsics: assumed" in out and "--tasks depth,pose" not in out  # no hint at what was asked for
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["camera"]["origin"] == "assumed"
    assert main([*base, "--out", str(tmp_path / "b"), "--flow-method", "farneback"]) == 2
    assert "invalid choice: 'farneback'" in capsys.readouterr().err
    with pytest.raises(geonet_infer.GeoNetError, match="unknown pose method"):
        geonet_infer.load().predict_sequence(list_images(SAMPLE_FRAMES)[:2], pose_method="orb")


def test_predict_and_batch_write_the_classical_outputs_in_the_usual_layout(tmp_path, capsys):
    seq = tmp_path / "in" / "seq_a"
    seq.mkdir(parents=True)
    for f in list_images(SAMPLE_FRAMES)[:4]:
        shutil.copyfile(f, seq / Path(f).name)
    methods = ["--flow-method", "dis", "--pose-method", "orbvo", "--calib", str(SAMPLE_CALIB), "--no-progress"]
    assert main(["predict", str(seq), "--out", str(tmp_path / "p"), *methods]) == 0
    assert main(["batch", str(seq), "--out", str(tmp_path / "b"), "--workers", "1", *methods]) == 0
    capsys.readouterr()
    for out in (tmp_path / "p", tmp_path / "b" / "seq_a"):
        summary = json.loads((out / "summary.json").read_text())
        assert {k: v["method"] for k, v in summary["methods"].items()} == {
            "depth": "network",
            "flow": "dis",
            "pose": "orbvo",
        }
        assert len(list((out / "flow").glob("*.png"))) == len(list((out / "flow_vis").glob("*.png"))) == 3
        assert len((out / "poses_kitti.txt").read_text().splitlines()) == 4
        assert len((out / "poses_tum.txt").read_text().splitlines()) == 4
    for name in ("flow/000000.png", "poses_kitti.txt"):
        assert (tmp_path / "p" / name).read_bytes() == (tmp_path / "b" / "seq_a" / name).read_bytes()
    # the methods are options of the job: resuming it with the networks is refused
    rerun = [
        "batch",
        str(seq),
        "--out",
        str(tmp_path / "b"),
        "--workers",
        "1",
        "--resume",
        "--calib",
        str(SAMPLE_CALIB),
    ]
    assert main([*rerun, "--no-progress"]) == 2
    assert "flow or pose method" in capsys.readouterr().err
    assert main([*rerun, *methods]) == 0  # the same options: complete already, skipped
    capsys.readouterr()


def test_dis_on_frames_too_thin_for_its_pyramid_is_one_line(tmp_path, capsys):
    """Issue 55: a 500x12 frame made OpenCV's DIS raise cv2.error from inside its pyramid."""
    import cv2

    folder = tmp_path / "thin"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.full((12, 500, 3), 60 * i, np.uint8))
    rc = main(["predict", str(folder), "--out", str(tmp_path / "out"), "--flow-method", "dis", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "DIS optical flow cannot run on 500x12 frames" in err, err
    assert len([line for line in err.splitlines() if "error" in line]) == 1
