"""training.prepare: real KITTI extracts, a tiny synthetic tree, and bad inputs.

Golden values come from outside the code under test: P_rect_02 / P0 are parsed here from the
calibration text, the resize factors are the documented image sizes (1242x375, 1241x376), and
snippet contents are compared with frames resized independently in the test.
"""

from __future__ import annotations

import hashlib
import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer.errors import GeoNetError
from geonet_infer.io import read_flow_kitti, write_calib_K, write_depth_kitti, write_flow_kitti
from training import prepare as P
from training import synth

ROOT = Path(__file__).resolve().parents[2]


def calib_values(path: Path, key: str) -> np.ndarray:
    """Plain-text parse of 'key: v1 v2 ...' (independent of geonet_infer.io)."""
    for line in path.read_text().splitlines():
        if line.startswith(key + ":"):
            return np.array([float(v) for v in line.split(":", 1)[1].split()])
    raise KeyError(key)


def read_cam_txt(path: Path) -> np.ndarray:
    return np.array([float(v) for v in path.read_text().strip().split(",")]).reshape(3, 3)


def read_list(path: Path) -> list[str]:
    return path.read_text().splitlines()


def assert_no_partial_files(out: Path) -> None:
    """No temp files (atomic_write uses hidden '.name.*' temps) and every sample is complete."""
    for p in out.rglob("*"):
        assert not p.name.startswith("."), f"leftover temp file {p}"
    for jpg in out.rglob("*.jpg"):
        assert jpg.with_name(jpg.stem + "_cam.txt").is_file(), f"{jpg} without _cam.txt"
    for cam in out.rglob("*_cam.txt"):
        assert cam.with_name(cam.name[: -len("_cam.txt")] + ".jpg").is_file(), f"{cam} without .jpg"


# --------------------------------------------------------------------------- tiny synthetic tree
def make_synth_seq(folder: Path, n_frames: int, size=(64, 96), seed=0, K=None) -> None:
    """Generator-like folder: image/NNNNNN.png, depth/NNNNNN.png, flow_noc/NNNNNN.png, calib.txt ('K: ...')."""
    h, w = size
    rng = np.random.default_rng(seed)
    (folder / "image").mkdir(parents=True)
    for i in range(n_frames):
        img = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        cv2.imwrite(str(folder / "image" / f"{i:06d}.png"), img)
        # depth constant on 2x2 blocks, so a 2x nearest downsample picks exact block values
        blocks = rng.integers(1, 80 * 256, size=(h // 2, w // 2)).astype(np.float64) / 256.0
        write_depth_kitti(folder / "depth" / f"{i:06d}.png", np.kron(blocks, np.ones((2, 2))))
        if i + 1 < n_frames:  # flow i -> i+1, also on 2x2 blocks, in steps of 2/64 px (halves stay exact)
            uv = rng.integers(-640, 640, size=(h // 2, w // 2, 2)) * (2 / 64)
            valid = rng.uniform(size=(h // 2, w // 2)) < 0.8
            block = np.ones((2, 2, 1))
            write_flow_kitti(
                folder / "flow_noc" / f"{i:06d}.png", np.kron(uv, block), np.kron(valid, block[..., 0]) > 0
            )
    K = np.array([[80.0, 0, 47.5], [0, 78.0, 31.5], [0, 0, 1]]) if K is None else K
    write_calib_K(folder / "calib.txt", K)


# --------------------------------------------------------------------------- KITTI raw (real)
def test_kitti_raw_extract(kitti_raw, tmp_path):
    out = tmp_path / "raw"
    assert (
        P.main(
            [
                "--kind",
                "kitti_raw",
                "--src",
                str(kitti_raw),
                "--out",
                str(out),
                "--max-frames",
                "12",
                "--workers",
                "2",
                "--split",
                "eigen",
            ]
        )
        == 0
    )
    res = P.PrepareResult(out, train=read_list(out / "train.txt"), val=read_list(out / "val.txt"))
    folder = out / "kitti_raw_2011_09_26_sfnd_02"
    # 12 frames, seq 3 -> targets 1..10
    names = sorted(res.train + res.val)
    assert names == [f"kitti_raw_2011_09_26_sfnd_02 {i:010d}" for i in range(1, 11)]
    assert not set(res.train) & set(res.val) and res.val  # random split, but not empty
    lines = (out / "train.txt").read_text().split("\n")[:-1] + (out / "val.txt").read_text().split("\n")[:-1]
    assert sorted(lines) == names

    P_rect = calib_values(kitti_raw / "calib_cam_to_cam.txt", "P_rect_02").reshape(3, 4)
    K_expected = P_rect[:3, :3].copy()
    K_expected[0] *= 416 / 1242  # README: frames are 1242x375
    K_expected[1] *= 128 / 375
    src = kitti_raw / "image_02" / "data"
    frames = {
        i: cv2.resize(cv2.imread(str(src / f"{i:010d}.png")), (416, 128), interpolation=cv2.INTER_AREA).astype(
            np.float64
        )
        for i in range(12)
    }
    for t in range(1, 11):
        img = cv2.imread(str(folder / f"{t:010d}.jpg"))
        assert img.shape == (128, 1248, 3)
        np.testing.assert_allclose(read_cam_txt(folder / f"{t:010d}_cam.txt"), K_expected, rtol=0, atol=1e-6)
        # thirds are frames t-1, t, t+1 in that order (BGR vs BGR, JPEG noise ~2.5, neighbours ~11)
        for k, part in enumerate(np.split(img.astype(np.float64), 3, axis=1)):
            err = {i: np.abs(part - f).mean() for i, f in frames.items()}
            assert min(err, key=err.get) == t - 1 + k
            assert err[t - 1 + k] < 4.0
    assert_no_partial_files(out)

    # resumable: a second run writes nothing; a missing _cam.txt is redone
    (folder / "0000000004_cam.txt").unlink()
    res2 = P.prepare(P.PrepareConfig("kitti_raw", kitti_raw, out, max_frames=12))
    assert (res2.written, res2.existing) == (1, 9)
    np.testing.assert_allclose(read_cam_txt(folder / "0000000004_cam.txt"), K_expected, atol=1e-6)


def test_kitti_raw_root_layout_split_and_static(kitti_raw, tmp_path):
    """A raw root (<date>/<drive>/image_02, calib in the date folder) with a test-scene drive."""
    root = tmp_path / "raw_root" / "2011_09_26"
    root.mkdir(parents=True)
    (root / "calib_cam_to_cam.txt").write_text((kitti_raw / "calib_cam_to_cam.txt").read_text())
    for drive in ("2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync"):  # 0002 is an Eigen test scene
        d = root / drive / "image_02" / "data"
        d.mkdir(parents=True)
        for i in range(5):
            (d / f"{i:010d}.png").symlink_to((kitti_raw / "image_02" / "data" / f"{i:010d}.png").resolve())
    out = tmp_path / "out"
    res = P.prepare(P.PrepareConfig("kitti_raw", tmp_path / "raw_root", out, split="eigen"))
    assert sorted(res.train + res.val) == [f"2011_09_26_drive_0001_sync_02 {i:010d}" for i in (1, 2, 3)]
    res = P.prepare(P.PrepareConfig("kitti_raw", tmp_path / "raw_root", tmp_path / "out_none", split="none"))
    assert len(res.train + res.val) == 6

    # --remove-static: neighbours skip removed frames. Drive 0009 frames 386, 387, 390, 391 are
    # static (official static_frames.txt), 384, 385, 388, 389 are not.
    d = root / "2011_09_26_drive_0009_sync" / "image_02" / "data"
    d.mkdir(parents=True)
    for i in range(384, 392):
        (d / f"{i:010d}.png").symlink_to((kitti_raw / "image_02" / "data" / f"{i - 384:010d}.png").resolve())
    res = P.prepare(
        P.PrepareConfig(
            "kitti_raw", tmp_path / "raw_root", tmp_path / "out_static", split="stereo", remove_static=True, workers=1
        )
    )
    names = sorted(res.train + res.val)
    # 0009 is a stereo test scene -> excluded; 0001 and 0002 stay
    assert not any("drive_0009" in n for n in names) and len(names) == 6
    res = P.prepare(
        P.PrepareConfig(
            "kitti_raw", tmp_path / "raw_root", tmp_path / "out_static2", split="none", remove_static=True, workers=1
        )
    )
    kept = sorted(n.split()[1] for n in res.train + res.val if "drive_0009" in n)
    # static: 386, 387, 390, 391 -> kept 384 385 388 389 -> targets 385 (384, 388) and 388 (385, 389)
    assert kept == [f"{i:010d}" for i in (385, 388)]
    static = P.read_static_frames()
    assert ("2011_09_26_drive_0009_sync", "0000000386") in static
    assert ("2011_09_26_drive_0009_sync", "0000000388") not in static


def test_scene_lists_are_official_sizes():
    """28 Eigen test scenes, 29 KITTI-2015 scenes, 8051 static frames (spec §7)."""
    eigen = P.read_scene_list("test_scenes_eigen.txt")
    stereo = P.read_scene_list("test_scenes_stereo.txt")
    assert len(eigen) == 28 and len(stereo) == 29
    assert "2011_09_26_drive_0002" in eigen and "2011_09_26_drive_0005" in stereo
    lines = [l for l in (P.LISTS_DIR / "static_frames.txt").read_text().splitlines() if l.strip()]
    assert len(lines) == 8051 and len(set(lines)) == 8051


# --------------------------------------------------------------------------- KITTI odometry (real, grey)
def test_kitti_odom_grey_fallback(kitti_odometry, tmp_path, caplog):
    out = tmp_path / "odom"
    with caplog.at_level(logging.WARNING, logger="training.prepare"):
        res = P.prepare(P.PrepareConfig("kitti_odom", kitti_odometry, out))
    assert "greyscale" in caplog.text
    # 6 frames, seq 5 (odom default) -> targets 2, 3
    assert sorted(res.train + res.val) == ["00 000002", "00 000003"]
    K = calib_values(kitti_odometry / "sequences" / "00" / "calib.txt", "P0").reshape(3, 4)[:, :3].copy()
    K[0] *= 416 / 1241  # README: 1241x376
    K[1] *= 128 / 376
    for t in (2, 3):
        img = cv2.imread(str(out / "00" / f"{t:06d}.jpg"))
        assert img.shape == (128, 5 * 416, 3)
        assert np.abs(img.astype(int)[..., 0] - img[..., 2]).max() <= 3  # grey copied to 3 channels
        np.testing.assert_allclose(read_cam_txt(out / "00" / f"{t:06d}_cam.txt"), K, atol=1e-6)
    # the pose test sequences are left out by default
    seq09 = tmp_path / "odom_root" / "sequences" / "09"
    (seq09 / "image_0").mkdir(parents=True)
    (seq09 / "calib.txt").write_text((kitti_odometry / "sequences" / "00" / "calib.txt").read_text())
    with pytest.raises(GeoNetError, match="no sample"):
        P.prepare(P.PrepareConfig("kitti_odom", tmp_path / "odom_root", tmp_path / "o2"))


def test_kitti_odom_train_pose_writes_the_true_motion_target_to_sources(kitti_odometry, tmp_path):
    """--train-pose: <frame>_pose.txt holds inv(C_source) @ C_target for each source, from the dev
    kit's poses/00.txt parsed here with numpy (camera-to-world, 12 numbers per line)."""
    out = tmp_path / "odom"
    res = P.prepare(P.PrepareConfig("kitti_odom", kitti_odometry, out, train_pose=True))
    assert not res.skipped
    rows = np.loadtxt(kitti_odometry / "poses" / "00.txt", max_rows=6).reshape(-1, 3, 4)
    C = np.tile(np.eye(4), (len(rows), 1, 1))
    C[:, :3] = rows
    for t in (2, 3):
        written = np.loadtxt(out / "00" / f"{t:06d}_pose.txt").reshape(-1, 3, 4)
        sources = [t - 2, t - 1, t + 1, t + 2]  # seq 5, temporal order
        R, p = C[sources, :3, :3], C[sources, :3, 3]
        inverse = np.tile(np.eye(4), (4, 1, 1))
        inverse[:, :3, :3] = R.transpose(0, 2, 1)
        inverse[:, :3, 3] = -np.einsum("nji,nj->ni", R, p)  # [R | p]^-1 = [R^T | -R^T p]
        np.testing.assert_allclose(written, (inverse @ C[t])[:, :3], atol=1e-6)
        # the car drives forward (+z): a point ahead of the target camera is farther from the
        # cameras of earlier frames and nearer to those of later ones
        assert written[0, 2, 3] > written[1, 2, 3] > 0.5 and written[3, 2, 3] < written[2, 2, 3] < -0.5
    # without the dev kit's poses/ the samples are written without _pose.txt, and the skip says why
    bare = tmp_path / "bare" / "sequences"
    bare.mkdir(parents=True)
    (bare / "00").symlink_to((kitti_odometry / "sequences" / "00").resolve())
    res = P.prepare(P.PrepareConfig("kitti_odom", tmp_path / "bare", tmp_path / "o2", train_pose=True))
    assert [s.reason for s in res.skipped] == ["pose file not found"]
    assert sorted(res.train + res.val) == ["00 000002", "00 000003"] and not list((tmp_path / "o2").rglob("*_pose.txt"))
    with pytest.raises(GeoNetError, match="--train-pose only applies"):
        P.prepare(P.PrepareConfig("frames", kitti_odometry, tmp_path / "o3", train_pose=True))


def test_kitti_odom_teachers_label_flow_with_dis_and_motion_along_the_official_poses(kitti_odometry, tmp_path):
    """--teacher-flow dis / --teacher-pose orbvo on real frames: the flow PNG holds OpenCV DIS (medium) of
    the resized target -> next frame where the forward-backward check holds; the motion's direction
    agrees with the dev kit's official poses (an independent yardstick: GPS/INS)."""
    out = tmp_path / "odom"
    cfg = P.PrepareConfig("kitti_odom", kitti_odometry, out, seq_length=3, teacher_flow="dis", teacher_pose="orbvo")
    res = P.prepare(cfg)
    assert not res.skipped and sorted(res.train + res.val) == [f"00 {t:06d}" for t in (1, 2, 3, 4)]
    rows = np.loadtxt(kitti_odometry / "poses" / "00.txt", max_rows=6).reshape(-1, 3, 4)
    image_dir = kitti_odometry / "sequences" / "00" / "image_0"
    for t in (1, 2, 3, 4):
        small = [
            cv2.resize(cv2.imread(str(image_dir / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE), (416, 128),
                       interpolation=cv2.INTER_AREA)
            for k in (t, t + 1)
        ]  # fmt: skip
        dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(small[0], small[1], None)
        flow, valid = read_flow_kitti(out / "00" / f"{t:06d}_flow.png")
        assert 0.5 < valid.mean() < 1.0  # the check keeps most pixels and drops some (borders, occlusions)
        np.testing.assert_allclose(flow[valid], dis[valid], atol=1 / 64)  # KITTI PNG steps of 1/64 px
        written = np.loadtxt(out / "00" / f"{t:06d}_pose.txt").reshape(-1, 3, 4)  # target -> t-1, t+1
        for motion, source in zip(written, (t - 1, t + 1)):
            # official motion target -> source: R_s^T (R_t x + p_t - p_s)
            R_s, p_s, p_t = rows[source][:, :3], rows[source][:, 3], rows[t][:, 3]
            true_t = R_s.T @ (p_t - p_s)
            cosine = motion[:, 3] @ true_t / np.linalg.norm(motion[:, 3]) / np.linalg.norm(true_t)
            assert cosine > 0.97 and abs(np.linalg.norm(motion[:, 3]) - 1) < 1e-6  # unit steps
    with pytest.raises(GeoNetError, match="synthetic scenes have"):
        P.prepare(P.PrepareConfig("synth", tmp_path, tmp_path / "o2", teacher_flow="dis"))
    with pytest.raises(GeoNetError, match="needs full-resolution frames"):
        P.prepare(P.PrepareConfig("frames", image_dir, tmp_path / "o3", teacher_pose="orbvo"))


def test_motion_mix_labels_still_slowed_and_reversed_snippets(kitti_odometry, tmp_path):
    """--motion-mix (issue 53): a still copy is the target three times with a little noise, labelled
    zero flow and identity motion; the stride-2 copy's true motion is inv(C_{t+-2}) @ C_t and its DIS
    label goes to t+2; the reversed copy's sources are (t+1, t-1) and its label goes to t-1. Poses are
    the dev kit's poses/00.txt parsed here with numpy, flows OpenCV DIS computed here."""
    out = tmp_path / "odom"
    mix = {"static": 1.0, "stride2": 1.0, "reverse": 1.0}
    cfg = P.PrepareConfig(
        "kitti_odom", kitti_odometry, out, seq_length=3, train_pose=True, teacher_flow="dis", motion_mix=mix
    )
    res = P.prepare(cfg)
    names = set(res.train + res.val)
    assert {"00 000001_static", "00 000001_reverse", "00 000002_stride2", "00 000003_stride2"} <= names
    assert "00 000001_stride2" not in names  # t-2 would be frame -1
    rows = np.loadtxt(kitti_odometry / "poses" / "00.txt", max_rows=6).reshape(-1, 3, 4)
    C = np.tile(np.eye(4), (len(rows), 1, 1))
    C[:, :3] = rows

    def motion(t: int, s: int) -> np.ndarray:
        return (np.linalg.inv(C[s]) @ C[t])[:3]

    image_dir = kitti_odometry / "sequences" / "00" / "image_0"

    def small(k: int) -> np.ndarray:
        grey = cv2.imread(str(image_dir / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE)
        return cv2.resize(grey, (416, 128), interpolation=cv2.INTER_AREA)

    def dis(a: int, b: int) -> np.ndarray:
        return cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(small(a), small(b), None)

    still = cv2.imread(str(out / "00" / "000001_static.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
    target, sources = still[:, 416:832], (still[:, :416], still[:, 832:])
    for source in sources:  # noisy, sub-pixel-shifted copies: close to the target, not equal
        assert 0.5 < np.abs(source - target).mean() < 6.0
    assert np.abs(target - small(1)).mean() < 2.0  # the target itself is the real frame (JPEG)
    flow, valid = read_flow_kitti(out / "00" / "000001_static_flow.png")
    assert valid.all() and not flow.any()
    np.testing.assert_allclose(np.loadtxt(out / "00" / "000001_static_pose.txt").reshape(-1, 3, 4), [np.eye(4)[:3]] * 2)

    for name, t, sources, label_to in (("000002_stride2", 2, (0, 4), 4), ("000002_reverse", 2, (3, 1), 1)):
        written = np.loadtxt(out / "00" / f"{name}_pose.txt").reshape(-1, 3, 4)
        np.testing.assert_allclose(written, [motion(t, s) for s in sources], atol=1e-6)
        flow, valid = read_flow_kitti(out / "00" / f"{name}_flow.png")
        expected = dis(t, label_to)
        assert 0.3 < valid.mean() and np.abs(flow[valid] - expected[valid]).max() <= 1 / 64
    # the reversed copy drives backwards: a point ahead of its target is nearer to its first source
    assert np.loadtxt(out / "00" / "000002_reverse_pose.txt").reshape(-1, 3, 4)[0, 2, 3] < -0.5
    with pytest.raises(SystemExit):
        P.build_parser().parse_args(["--kind", "synth", "--src", ".", "--out", "o", "--motion-mix", "pause=0.5"])
    drive = tmp_path / "kitti_raw_2011_09_26_sfnd"
    drive.mkdir()
    with pytest.raises(GeoNetError, match="test drive: never train on it"):
        P.prepare(P.PrepareConfig("kitti_raw", drive, tmp_path / "o", motion_mix=mix))


def test_teachers_never_label_the_test_drive(kitti_raw, tmp_path):
    with pytest.raises(GeoNetError, match="test drive: never train on it"):
        P.prepare(P.PrepareConfig("kitti_raw", kitti_raw, tmp_path / "o", teacher_flow="dis"))
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- synthetic
def test_synth_heldout(tmp_path):
    src = tmp_path / "synth"
    for s in range(3):
        make_synth_seq(src / f"seq_{s:02d}", 5, seed=s)
    out = tmp_path / "out"
    res = P.prepare(P.PrepareConfig("synth", src, out, heldout=1, height=32, width=48))
    held = [l for l in (out / "heldout.txt").read_text().splitlines()]
    assert held == [f"seq_02 {i:06d}" for i in (1, 2, 3)] == res.heldout
    trained = set(res.train + res.val)
    assert trained == {f"seq_{s:02d} {i:06d}" for s in (0, 1) for i in (1, 2, 3)}
    listed = set((out / "train.txt").read_text().splitlines() + (out / "val.txt").read_text().splitlines())
    assert listed == trained and not listed & set(held)
    for i in (1, 2, 3):
        # held-out GT: nearest 2x downsample of 2x2-constant blocks = the blocks themselves
        src_depth = cv2.imread(str(src / "seq_02" / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        got = cv2.imread(str(out / "seq_02" / f"{i:06d}_depth.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(got, src_depth[::2, ::2])
        np.testing.assert_allclose(
            read_cam_txt(out / "seq_02" / f"{i:06d}_cam.txt"),
            [[40.0, 0, 23.75], [0, 39.0, 15.75], [0, 0, 1]],
            atol=1e-9,
        )
        assert cv2.imread(str(out / "seq_02" / f"{i:06d}.jpg")).shape == (32, 144, 3)
    assert not (out / "seq_00" / "000001_depth.png").exists()  # GT only for held-out samples
    with pytest.raises(GeoNetError, match="--heldout"):
        P.prepare(P.PrepareConfig("synth", src, tmp_path / "o2", heldout=3))
    # --train-depth: train/val samples get their target depth too, the same split and files otherwise
    sup = tmp_path / "sup"
    res_sup = P.prepare(P.PrepareConfig("synth", src, sup, heldout=1, height=32, width=48, train_depth=True))
    assert (res_sup.train, res_sup.val, res_sup.heldout) == (res.train, res.val, res.heldout)
    for s in (0, 1):
        for i in (1, 2, 3):
            src_depth = cv2.imread(str(src / f"seq_{s:02d}" / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            got = cv2.imread(str(sup / f"seq_{s:02d}" / f"{i:06d}_depth.png"), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(got, src_depth[::2, ::2])
    with pytest.raises(GeoNetError, match="--train-depth only applies"):
        P.prepare(P.PrepareConfig("frames", src / "seq_00" / "image", tmp_path / "o3", train_depth=True))
    # --train-flow: train/val samples get the generator's flow to the next frame, at H x W
    flows = tmp_path / "flows"
    res_flow = P.prepare(P.PrepareConfig("synth", src, flows, heldout=1, height=32, width=48, train_flow=True))
    assert (res_flow.train, res_flow.val, res_flow.heldout) == (res.train, res.val, res.heldout)
    for s in (0, 1):
        for i in (1, 2, 3):
            src_flow, src_valid = read_flow_kitti(src / f"seq_{s:02d}" / "flow_noc" / f"{i:06d}.png")
            got_flow, got_valid = read_flow_kitti(flows / f"seq_{s:02d}" / f"{i:06d}_flow.png")
            # nearest 2x downsample, vectors halved (the fixture's 1/64-px steps stay exact at 1/2)
            np.testing.assert_array_equal(got_valid, src_valid[::2, ::2])
            np.testing.assert_allclose(got_flow, src_flow[::2, ::2] / 2, atol=1 / 64)
    assert not list((flows / "seq_02").glob("*_flow.png"))  # held-out flow is scored from the source
    with pytest.raises(GeoNetError, match="--train-flow only applies"):
        P.prepare(P.PrepareConfig("frames", src / "seq_00" / "image", tmp_path / "o4", train_flow=True))


def test_synth_generator_output(tmp_path):
    """The real generator's tree (training.synth)."""
    src = tmp_path / "synth"
    for i in range(3):
        synth.write_sequence(src, 0, i, 4, 48, 144)
    (src / ".tmp_seq_0009" / "image").mkdir(parents=True)  # unfinished generator work is ignored
    out = tmp_path / "out"
    res = P.prepare(P.PrepareConfig("synth", src, out, height=32, width=96, heldout=1))
    names = sorted(p.name for p in src.iterdir() if not p.name.startswith("."))
    assert res.heldout == [f"{names[-1]} {i:06d}" for i in (1, 2)]
    assert sorted(res.train + res.val) == [f"{n} {i:06d}" for n in names[:-1] for i in (1, 2)]
    K = calib_values(src / names[-1] / "calib.txt", "K").reshape(3, 3)
    K[0] *= 96 / 144
    K[1] *= 32 / 48
    for i in (1, 2):
        np.testing.assert_allclose(read_cam_txt(out / names[-1] / f"{i:06d}_cam.txt"), K, atol=1e-6)
        got = cv2.imread(str(out / names[-1] / f"{i:06d}_depth.png"), cv2.IMREAD_UNCHANGED)
        full = cv2.imread(str(src / names[-1] / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert got.shape == (32, 96) and got.dtype == np.uint16
        assert set(np.unique(got)) <= set(np.unique(full))  # nearest: no blended depths


# --------------------------------------------------------------------------- bad inputs
BAD_CASES = ("a_short", "b_gap", "c_trunc", "d_mixed", "e_nokey")


def _bad_tree(root: Path, cases=BAD_CASES) -> dict[str, Path]:
    """a_short: 2 frames; b_gap: frame 3 is garbage; c_trunc: frame 5 has a PNG header but no
    data; d_mixed: one frame of another size; e_nokey: calib.txt without K."""
    files = {}
    if "a_short" in cases:
        make_synth_seq(root / "a_short", 2)
    if "b_gap" in cases:
        make_synth_seq(root / "b_gap", 7, seed=1)
        files["bad"] = root / "b_gap" / "image" / "000003.png"
        files["bad"].write_bytes(b"not a png at all")
    if "c_trunc" in cases:
        make_synth_seq(root / "c_trunc", 8, seed=2)
        files["trunc"] = root / "c_trunc" / "image" / "000005.png"
        files["trunc"].write_bytes(files["trunc"].read_bytes()[:60])
    if "d_mixed" in cases:
        make_synth_seq(root / "d_mixed", 4, seed=3)
        files["mixed"] = root / "d_mixed" / "image" / "000002.png"
        cv2.imwrite(str(files["mixed"]), np.zeros((32, 32, 3), np.uint8))
    if "e_nokey" in cases:
        make_synth_seq(root / "e_nokey", 4, seed=4)
        (root / "e_nokey" / "calib.txt").write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return files


def test_bad_inputs_are_skipped_and_named(tmp_path, capsys):
    src = tmp_path / "src"
    files = _bad_tree(src)
    out = tmp_path / "out"
    assert (
        P.main(
            [
                "--kind",
                "synth",
                "--src",
                str(src),
                "--out",
                str(out),
                "--heldout",
                "0",
                "--height",
                "32",
                "--width",
                "48",
                "--workers",
                "2",
            ]
        )
        == 1
    )  # some inputs skipped
    text = capsys.readouterr().out  # the printed summary lists every skip
    res = P.prepare(P.PrepareConfig("synth", src, out, heldout=0, height=32, width=48))  # resumes: same lists
    reasons = [str(s) for s in res.skipped]
    for r in reasons:
        assert r in text

    def find(fragment, where):
        return [r for r in reasons if r.startswith(str(where)) and fragment in r]

    assert find("too short", src / "a_short" / "image")
    assert find("unreadable", files["bad"])
    # truncated body: the header is fine, decoding fails -> the 3 snippets using it are skipped
    assert len([r for r in reasons if str(files["trunc"]) in r and "decode" in r]) == 3
    assert find("mixed resolutions", src / "d_mixed" / "image")
    assert find("'K'", src / "e_nokey" / "calib.txt")
    # the gap breaks the run: b_gap keeps targets 1 and 5 only (0-1-2 | 4-5-6)
    names = set(res.train + res.val)
    assert {n for n in names if n.startswith("b_gap")} == {"b_gap 000001", "b_gap 000005"}
    # c_trunc: frames 0..7 without 5 -> targets 1, 2, 3 (4 and 6 need frame 5)
    assert {n for n in names if n.startswith("c_trunc")} == {f"c_trunc {i:06d}" for i in (1, 2, 3)}
    assert not any(n.startswith(("a_", "d_", "e_")) for n in names)
    assert not (out / "c_trunc" / "000004.jpg").exists()
    assert_no_partial_files(out)


@pytest.mark.parametrize(
    "case, fragment",
    [
        ("a_short", "too short"),
        ("b_gap", "unreadable"),
        ("c_trunc", "decode"),
        ("d_mixed", "mixed resolutions"),
        ("e_nokey", "'K'"),
    ],
)
def test_strict_turns_skips_into_errors(tmp_path, case, fragment):
    src = tmp_path / "src"
    _bad_tree(src, cases=(case,))
    make_synth_seq(src / "z_good", 4, seed=9)  # a good sequence does not hide the bad one
    out = tmp_path / "out"
    with pytest.raises(GeoNetError) as err:
        P.prepare(P.PrepareConfig("synth", src, out, heldout=0, height=32, width=48, strict=True))
    assert str(src / case) in str(err.value) and fragment in str(err.value)
    assert_no_partial_files(out)


def test_clear_errors_and_help(tmp_path, capsys):
    with pytest.raises(GeoNetError, match="source folder not found"):
        P.prepare(P.PrepareConfig("synth", tmp_path / "missing", tmp_path / "out"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(GeoNetError, match="no KITTI raw drive"):
        P.prepare(P.PrepareConfig("kitti_raw", tmp_path / "empty", tmp_path / "out"))
    with pytest.raises(GeoNetError, match="seq-length"):
        P.prepare(P.PrepareConfig("synth", tmp_path / "empty", tmp_path / "out", seq_length=4))
    with pytest.raises(GeoNetError, match="--split eigen does not apply"):
        P.prepare(P.PrepareConfig("synth", tmp_path / "empty", tmp_path / "out", split="eigen"))
    with pytest.raises(SystemExit) as ex:
        P.main(["--help"])
    assert ex.value.code == 0
    help_text = capsys.readouterr().out
    for kind in P.KINDS:
        assert f"python -m training.prepare --kind {kind}" in help_text


# --------------------------------------------------------------------------- CLI = library
def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_cli_and_library_write_identical_files(tmp_path):
    """``python -m training.prepare`` only parses flags into a PrepareConfig and calls prepare()."""
    src = tmp_path / "synth"
    for s in range(3):
        make_synth_seq(src / f"seq_{s:02d}", 5, seed=s)
    cli, lib = tmp_path / "cli", tmp_path / "lib"
    cmd = [
        sys.executable,
        "-m",
        "training.prepare",
        "--kind",
        "synth",
        "--src",
        str(src),
        "--out",
        str(cli),
        "--heldout",
        "1",
        "--height",
        "32",
        "--width",
        "48",
        "--val-fraction",
        "0.5",
        "--seed",
        "3",
    ]
    run = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    P.prepare(P.PrepareConfig("synth", src, lib, heldout=1, height=32, width=48, val_fraction=0.5, seed=3))
    digest = tree_digest(cli)
    assert {"train.txt", "val.txt", "heldout.txt", "seq_02/000001_depth.png", "seq_00/000001.jpg"} <= set(digest)
    assert digest == tree_digest(lib)


def test_unpadded_frame_numbers_are_cut_in_numeric_order(tmp_path):
    """1.png .. 11.png: name order would put 10 and 11 before 2 and join them into one snippet."""
    seq = tmp_path / "src" / "seq"
    make_synth_seq(seq, 12)
    for p in sorted((seq / "image").iterdir()):
        p.rename(p.with_name(f"{int(p.stem)}.png"))
    res = P.prepare(P.PrepareConfig("synth", tmp_path / "src", tmp_path / "out", heldout=0, height=32, width=48))
    assert sorted(res.train + res.val, key=lambda n: int(n.split()[1])) == [f"seq {i}" for i in range(1, 11)]
    strip = cv2.imread(str(tmp_path / "out" / "seq" / "10.jpg")).astype(float)  # frames 9, 10, 11
    frames = {
        i: cv2.resize(cv2.imread(str(seq / "image" / f"{i}.png")), (48, 32), interpolation=cv2.INTER_AREA)
        for i in range(12)
    }
    for k, part in enumerate(np.split(strip, 3, axis=1)):
        err = {i: np.abs(part - f).mean() for i, f in frames.items()}
        assert min(err, key=err.get) == 9 + k


# ----------------------------------------------------------------------------- video / frames
DASHCAM_CALIB_K = (1158.774754, 1154.076607, 669.642741, 388.079450)  # fx fy cx cy, typed from the calib file


def test_video_of_a_real_dashcam_clip_scales_the_calibration(realdata, tmp_path):
    clip = realdata / "udacity_dashcam" / "test_video.mp4"
    calib = realdata / "udacity_dashcam" / "calib_advanced_lane_lines.txt"
    out = tmp_path / "dash"
    rc = P.main(
        [
            "--kind",
            "video",
            "--src",
            str(clip),
            "--calib",
            str(calib),
            "--crop",
            "0,229,1280,394",
            "--out",
            str(out),
            "--static-threshold",
            "0",
        ]
    )
    assert rc == 0
    fx, fy, cx, cy = DASHCAM_CALIB_K
    # by hand: crop moves the principal point up by 229 rows; 1280x394 -> 416x128 scales x and y
    expected = [fx * 416 / 1280, 0.0, cx * 416 / 1280, 0.0, fy * 128 / 394, (cy - 229) * 128 / 394, 0.0, 0.0, 1.0]
    samples = sorted((out / "test_video").glob("*_cam.txt"))
    assert len(samples) == 38 - 2  # 38 decoded frames (the clip's README), none static, ends lack neighbours
    for cam in samples:
        values = [float(v) for v in cam.read_text().strip().split(",")]
        np.testing.assert_allclose(values, expected, rtol=1e-5, atol=1e-4)
    strip = cv2.imread(str(out / "test_video" / "000001.jpg"))
    assert strip.shape == (128, 3 * 416, 3)
    # the middle third is frame 1 undistorted (same K), cropped and resized, as OpenCV does it directly
    cap = cv2.VideoCapture(str(clip))
    for _ in range(2):
        ok, bgr = cap.read()
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    dist = np.array([-0.25677908, 0.04338451, -0.00068745, 0.00012577, -0.11502545])
    want = cv2.resize(cv2.undistort(bgr, K, dist)[229:623], (416, 128), interpolation=cv2.INTER_AREA)
    diff = np.abs(strip[:, 416:832].astype(float) - want.astype(float))
    assert diff.mean() < 2.0  # JPEG q95 of the same pixels
    lines = (out / "train.txt").read_text().split() + (out / "val.txt").read_text().split()
    assert len(lines) == 2 * 36


def test_frames_drop_static_frames_and_keep_snippets_consecutive(tmp_path):
    rng = np.random.default_rng(0)
    src = tmp_path / "frames"
    src.mkdir()
    base = rng.integers(0, 255, (64, 208, 3), dtype=np.uint8)
    moving = [np.roll(base, 4 * i, axis=1) for i in range(6)]
    frames = [moving[0], moving[0], moving[1], moving[2], moving[2], moving[2], moving[3], moving[4], moving[5]]
    for i, f in enumerate(frames):
        cv2.imwrite(str(src / f"{i:04d}.png"), f)
    (tmp_path / "K.txt").write_text("100 0 104\n0 100 32\n0 0 1\n")
    out = tmp_path / "out"
    rc = P.main(
        [
            "--kind",
            "frames",
            "--src",
            str(src),
            "--calib",
            str(tmp_path / "K.txt"),
            "--out",
            str(out),
            "--height",
            "64",
            "--width",
            "208",
        ]
    )
    assert rc == 0
    kept = sorted((out / P.FRAME_CACHE / "frames").glob("*.png"))
    assert len(kept) == 6  # the three repeats are dropped
    for i, path in enumerate(kept):
        assert np.array_equal(cv2.imread(str(path)), moving[i])
    assert len(list((out / "frames").glob("*.jpg"))) == 6 - 2


def test_video_needs_a_calibration_and_a_crop_that_fits(realdata, tmp_path, capsys):
    clip = realdata / "udacity_dashcam" / "test_video.mp4"
    calib = realdata / "udacity_dashcam" / "calib_advanced_lane_lines.txt"
    assert P.main(["--kind", "video", "--src", str(clip), "--out", str(tmp_path / "a")]) == 2
    assert "--calib" in capsys.readouterr().err
    assert (
        P.main(
            [
                "--kind",
                "video",
                "--src",
                str(clip),
                "--calib",
                str(calib),
                "--crop",
                "0,500,1280,394",
                "--out",
                str(tmp_path / "b"),
            ]
        )
        == 2
    )
    assert "does not fit" in capsys.readouterr().err
    assert P.main(["--kind", "synth", "--src", str(tmp_path), "--calib", str(calib), "--out", str(tmp_path / "c")]) == 2
    assert "only applies" in capsys.readouterr().err
