"""Synthetic driving data: its ground truth is checked against independent computations.

* flow: warping frame t+1 with cv2.remap by the GT flow must explain frame t;
* static pixels: GT flow == closed-form rigid flow from GT depth, GT poses and K
  (projected with cv2.projectPoints, not our code);
* moving-object pixels: GT flow != rigid flow, and the motion mask marks exactly them;
* the written folder reads back through geonet_infer.io.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer import io as gio
from geonet_infer.errors import GeoNetError
from training import synth

H, W = 128, 416
SEED = 7


@pytest.fixture(scope="module")
def seq():
    return synth.generate_sequence(SEED, 0, 4, H, W)


def grid(h, w):
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return u, v


def rigid_flow(depth, T_src, T_dst, K):
    """Closed-form flow of a static scene, with OpenCV's projector.

    depth (H, W) metres; T_src, T_dst (4, 4) camera-to-world; returns (H, W, 2).
    """
    h, w = depth.shape
    u, v = grid(h, w)
    z = depth.astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1).reshape(-1, 3)
    rel = np.linalg.inv(T_dst) @ T_src  # camera src -> camera dst
    rvec, _ = cv2.Rodrigues(rel[:3, :3])
    proj, _ = cv2.projectPoints(X, rvec, rel[:3, 3].copy(), K, None)
    return proj.reshape(h, w, 2) - np.stack([u, v], -1)


def test_warping_by_gt_flow_explains_the_next_frame(seq):
    u, v = grid(H, W)
    for t in range(len(seq["flow"])):
        I0 = seq["image"][t].astype(np.float32)
        I1 = seq["image"][t + 1].astype(np.float32)
        f, noc = seq["flow"][t], seq["flow_noc"][t]
        warped = cv2.remap(
            I1,
            (u + f[..., 0]).astype(np.float32),
            (v + f[..., 1]).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
        )
        err_none = np.abs(I1 - I0).mean(-1)[noc].mean()
        err_warp = np.abs(warped - I0).mean(-1)[noc].mean()
        factor = err_none / err_warp
        assert noc.mean() > 0.5
        assert factor >= 3.0, f"frame {t}: warp only reduced error {err_none:.2f} -> {err_warp:.2f} ({factor:.2f}x)"
        # A translating camera always hides something behind depth edges; those pixels
        # (in view, hidden in t+1) must NOT be explained by the warp as well.
        occluded = seq["flow_occ"][t] & ~noc
        assert occluded.sum() > 200
        assert np.abs(warped - I0).mean(-1)[occluded].mean() > 2 * err_warp


def test_static_flow_equals_rigid_flow_from_depth_and_pose(seq):
    K, poses = seq["K"], seq["poses"]
    np.testing.assert_array_equal(poses[0], np.eye(4))
    for t in range(len(seq["flow"])):
        rigid = rigid_flow(seq["depth"][t], poses[t], poses[t + 1], K)
        static = seq["flow_occ"][t] & ~seq["motion_mask"][t]
        assert static.mean() > 0.5
        err = np.linalg.norm(seq["flow"][t] - rigid, axis=-1)[static]
        assert err.max() <= 0.05, f"frame {t}: max |GT - rigid| = {err.max():.4f} px"


def test_motion_mask_marks_exactly_the_non_rigid_pixels():
    # Sequence 1 of this seed has traffic in view (checked when the seed was chosen).
    s = synth.generate_sequence(SEED, 1, 3, H, W)
    assert s["motion_mask"].any(), "no moving car visible"
    for t in range(2):
        rigid = rigid_flow(s["depth"][t], s["poses"][t], s["poses"][t + 1], s["K"])
        dev = np.linalg.norm(s["flow"][t] - rigid, axis=-1)
        occ, mm = s["flow_occ"][t], s["motion_mask"][t]
        assert dev[occ & ~mm].max() <= 0.05
        if (occ & mm).sum() > 50:  # the cars move: their flow is not the camera's rigid flow
            assert np.median(dev[occ & mm]) > 0.5, "moving-car pixels have the camera's rigid flow"


def test_camera_motion_and_flow_magnitudes_look_like_kitti(seq):
    steps = np.linalg.norm(np.diff(seq["poses"][:, :3, 3], axis=0), axis=1)
    assert ((steps > 0.3) & (steps < 1.6)).all()
    # Camera z axis is forward: it moves mostly along its own +z.
    fwd = np.einsum("ij,i->j", seq["poses"][0, :3, :3], seq["poses"][1, :3, 3] - seq["poses"][0, :3, 3])
    assert fwd[2] > 0.9 * np.linalg.norm(fwd)
    mag = np.linalg.norm(seq["flow"], axis=-1)[seq["flow_occ"]]
    assert np.median(mag) < 40 and np.percentile(mag, 90) < 60
    assert seq["flow_noc"][seq["flow_noc"]].size <= seq["flow_occ"].sum()
    assert not (seq["flow_noc"] & ~seq["flow_occ"]).any()
    assert (seq["depth"] > 0).all() and np.isfinite(seq["depth"]).all()


def test_same_seed_same_output_different_seed_different_output(seq):
    again = synth.generate_sequence(SEED, 0, 4, H, W)
    for k in seq:
        np.testing.assert_array_equal(again[k], seq[k], err_msg=k)
    other_seed = synth.generate_sequence(SEED + 1, 0, 2, H, W)
    other_index = synth.generate_sequence(SEED, 1, 2, H, W)
    assert not np.array_equal(other_seed["image"][0], seq["image"][0])
    assert not np.array_equal(other_index["image"][0], seq["image"][0])
    assert not np.allclose(other_seed["poses"][1], seq["poses"][1])


def _tree_digest(root):
    out = {}
    for dirpath, _, files in os.walk(root):
        for name in files:
            p = os.path.join(dirpath, name)
            out[os.path.relpath(p, root)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def test_written_layout_reads_back_and_is_independent_of_workers(tmp_path, capsys):
    h, w, frames = 64, 208, 3
    args = ["--sequences", "2", "--frames", str(frames), "--seed", "3", "--height", str(h), "--width", str(w)]
    assert synth.main(["--out", str(tmp_path / "a"), "--workers", "2", *args]) == 0
    stems = [f"{i:06d}.png" for i in range(frames)]
    expected = {"poses.txt", "calib.txt"}
    expected |= {f"{d}/{s}" for d in ("image", "depth", "motion_mask") for s in stems}
    expected |= {f"{d}/{s}" for d in ("flow_occ", "flow_noc") for s in stems[:-1]}
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["seq_0000", "seq_0001", "synth_config.json"]
    digest_a = _tree_digest(tmp_path / "a")
    for name in ("seq_0000", "seq_0001"):
        assert set(_tree_digest(tmp_path / "a" / name)) == expected

    # Everything reads back through geonet_infer.io and matches the in-memory generator.
    ref = synth.generate_sequence(3, 1, frames, h, w)
    d = tmp_path / "a" / "seq_0001"
    for t in range(frames):
        np.testing.assert_array_equal(gio.read_image(d / "image" / stems[t]), ref["image"][t])
        depth = gio.read_depth_kitti(d / "depth" / stems[t])
        in_range = ref["depth"][t] < 255
        np.testing.assert_allclose(depth[in_range], ref["depth"][t][in_range], atol=1 / 512 + 1e-6)
        assert (depth[~in_range] == 0).all()  # sky / far: no measurement, as in KITTI
        np.testing.assert_array_equal(gio.read_mask(d / "motion_mask" / stems[t]), ref["motion_mask"][t])
    for t in range(frames - 1):
        for kind in ("occ", "noc"):
            flow, valid = gio.read_flow_kitti(d / f"flow_{kind}" / stems[t])
            np.testing.assert_array_equal(valid, ref[f"flow_{kind}"][t])
            np.testing.assert_allclose(flow[valid], ref["flow"][t][valid], atol=1 / 128 + 1e-6)
    np.testing.assert_allclose(gio.read_kitti_poses(d / "poses.txt"), ref["poses"], atol=1e-8)
    np.testing.assert_allclose(gio.read_calib_K(d / "calib.txt"), ref["K"], rtol=1e-8)
    assert gio.read_calib_K(d / "calib.txt")[0, 0] == pytest.approx(0.581 * w, rel=0.01)

    # Same files with one worker from the library call (the CLI only parses flags into SynthConfig);
    # a rerun skips complete sequences and redoes a half-written one.
    cfg = synth.SynthConfig(out=tmp_path / "b", sequences=2, frames=frames, seed=3, height=h, width=w, workers=1)
    assert synth.generate(cfg) == {"done": 2, "skipped": 0}
    assert _tree_digest(tmp_path / "b") == digest_a
    (tmp_path / "b" / ".tmp_seq_0002" / "image").mkdir(parents=True)
    before = os.stat(tmp_path / "b" / "seq_0000" / "poses.txt").st_mtime_ns
    assert synth.main(["--out", str(tmp_path / "b"), *args[:1], "3", *args[2:]]) == 0
    assert os.stat(tmp_path / "b" / "seq_0000" / "poses.txt").st_mtime_ns == before
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == [
        "seq_0000",
        "seq_0001",
        "seq_0002",
        "synth_config.json",
    ]
    capsys.readouterr()
    assert (
        synth.main(
            [
                "--out",
                str(tmp_path / "b"),
                "--sequences",
                "2",
                "--frames",
                "5",
                "--seed",
                "3",
                "--height",
                str(h),
                "--width",
                str(w),
            ]
        )
        == 2
    )  # other settings than the folder's
    err = capsys.readouterr().err.strip()
    assert "synth_config.json" in err and "frames=3" in err and len(err.splitlines()) == 1


def test_help_runs(capsys):
    with pytest.raises(SystemExit) as e:
        synth.main(["--help"])
    assert e.value.code == 0
    assert "KITTI" in capsys.readouterr().out


def test_dense_traffic_fills_the_view_with_near_vehicles_and_trucks():
    from training.synth.scene import make_scene
    from training.synth.sequence import sequence_rng

    def near_moving(s):  # share of the first frame covered by moving vehicles closer than 15 m
        return (s["motion_mask"][0] & (s["depth"][0] < 15)).mean()

    light, dense = [], []
    for i in range(4):
        light.append(near_moving(synth.generate_sequence(SEED, i, 2, H, W)))
        d = synth.generate_sequence(SEED, i, 2, H, W, traffic="dense")
        dense.append(near_moving(d))
        # the ground truth stays exact: static pixels move by the camera's rigid flow
        rigid = rigid_flow(d["depth"][0], d["poses"][0], d["poses"][1], d["K"])
        static = d["flow_occ"][0] & ~d["motion_mask"][0]
        assert np.linalg.norm(d["flow"][0] - rigid, axis=-1)[static].max() <= 0.05
        scene = make_scene(sequence_rng(SEED, i), 2, H, W, "dense")
        moving = scene.box_group >= 0
        tops = -(scene.box_centre[moving, 1] - scene.box_half[moving, 1])  # y points down, ground at 0
        assert tops.max() > 2.9, f"sequence {i}: no truck (tallest moving box {tops.max():.2f} m)"
    assert np.mean(dense) > 2 * np.mean(light), (light, dense)
    with pytest.raises(GeoNetError, match="traffic"):
        synth.generate(synth.SynthConfig(out=Path("unused"), traffic="jam"))


def test_queue_traffic_stops_the_camera_while_the_vehicles_beside_it_move_on():
    from training.synth.scene import make_road, make_trajectory

    # A stop (a target speed below 0) holds the camera exactly still: no step, no turn, no jitter.
    rng = np.random.default_rng(3)
    T, z, v = make_trajectory(rng, 120, make_road(rng), (-0.3, 0.6))
    assert np.isfinite(T).all() and (v >= 0).all() and v.max() <= 0.6 + 1e-9
    still = np.flatnonzero(v[:-1] == 0)
    assert still.size >= 5, "seed 3 draws no stop"
    for t in still:
        assert np.abs(T[t + 1] - T[t]).max() < 1e-12
    # The other kinds draw their trajectories exactly as before (the same seed, the same scenes).
    rng_a, rng_b = np.random.default_rng(4), np.random.default_rng(4)
    road_a, road_b = make_road(rng_a), make_road(rng_b)
    assert np.array_equal(make_trajectory(rng_a, 30, road_a)[0], make_trajectory(rng_b, 30, road_b, (0.4, 1.5))[0])

    # In a queue sequence with a still pair, the static scene does not move and vehicles still do
    # (small frames, and only a sequence whose trajectory holds a stop is rendered).
    from training.synth.scene import make_scene
    from training.synth.sequence import sequence_rng

    h, w, frames = 64, 208, 12
    for i in range(12):
        T_wc = make_scene(sequence_rng(SEED, i), frames, h, w, "queue").T_wc
        still = [t for t in range(frames - 1) if np.abs(T_wc[t + 1] - T_wc[t]).max() == 0]
        if not still:
            continue
        s = synth.generate_sequence(SEED, i, frames, h, w, traffic="queue")
        t = still[0]
        speed = np.linalg.norm(s["flow"][t], axis=-1)
        static = s["flow_occ"][t] & ~s["motion_mask"][t]
        assert static.any() and speed[static].max() < 1e-3
        moving = s["motion_mask"][t] & s["flow_occ"][t]
        assert moving.any() and np.percentile(speed[moving], 90) > 0.2
        break
    else:
        pytest.fail("no queue sequence of seed 7 (0-11) stops within its first 12 frames")
