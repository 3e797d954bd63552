"""geonet-infer eval / geonet_infer.eval.evaluation: readers on real files, the DIS acceptance check against
an independent EPE, hand-computed golden values on hand-built folders, and bad input."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from geonet_infer.cli import main as cli_main
from geonet_infer.errors import GeoNetError
from geonet_infer.eval import baselines, evaluation, metrics
from geonet_infer.eval.datasets import depth_dataset, flow_dataset, pose_dataset
from geonet_infer.io import read_image

KITTI_RAW = "kitti_raw_2011_09_26_sfnd"
ODOMETRY = "kitti_odometry_00"
MIDDLEBURY = "middlebury_flow"


# ----------------------------------------------------------------------------- independent helpers
def read_flo_numpy(path: Path) -> np.ndarray:
    """Middlebury .flo by hand: float32 magic, int32 w, h, then (u, v) interleaved."""
    raw = np.fromfile(path, dtype="<f4")
    assert raw[0] == np.float32(202021.25)
    w, h = np.frombuffer(raw[1:3].tobytes(), dtype="<i4")
    return raw[3:].reshape(h, w, 2)


def write_kitti_flow_png(path: Path, flow: np.ndarray, valid: np.ndarray) -> None:
    """KITTI flow PNG by hand (devkit): 16-bit, R = u*64 + 2^15, G = v*64 + 2^15, B = valid; cv2 is BGR."""
    enc = np.zeros(flow.shape[:2] + (3,), np.uint16)
    enc[..., 2] = np.where(valid, np.round(flow[..., 0] * 64 + 2**15), 0)
    enc[..., 1] = np.where(valid, np.round(flow[..., 1] * 64 + 2**15), 0)
    enc[..., 0] = valid
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), enc)


def write_depth_png(path: Path, depth: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.round(depth * 256).astype(np.uint16))


def texture(seed: int, h: int = 64, w: int = 208) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 8, w // 8, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def make_synth(root: Path, frames: int = 6, h: int = 64, w: int = 208) -> Path:
    """A synth-layout sequence with hand-chosen GT: depth 10 m on the left half, 20 m on the right;
    flow (3, 4) px everywhere (noc: top half only); camera moving 1 m forward per frame."""
    seq = root / "seq_0000"
    depth = np.full((h, w), 10.0)
    depth[:, w // 2 :] = 20.0
    flow = np.zeros((h, w, 2))
    flow[..., 0], flow[..., 1] = 3.0, 4.0
    noc = np.zeros((h, w), bool)
    noc[: h // 2] = True
    lines = []
    for t in range(frames):
        (seq / "image").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(seq / "image" / f"{t:06d}.png"), texture(t, h, w))
        write_depth_png(seq / "depth" / f"{t:06d}.png", depth)
        if t < frames - 1:
            write_kitti_flow_png(seq / "flow_noc" / f"{t:06d}.png", flow, noc)
            write_kitti_flow_png(seq / "flow_occ" / f"{t:06d}.png", flow, np.ones((h, w), bool))
        lines.append(f"1 0 0 0 0 1 0 0 0 0 1 {t}.0")
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    (seq / "calib.txt").write_text(f"K: {w} 0 {w / 2} 0 {w} {h / 2} 0 0 1\n")
    return seq


# ----------------------------------------------------------------------------- readers on real files
def test_kitti_odometry_reader_matches_poses_file(require_real):
    seq = require_real(f"{ODOMETRY}/sequences/00")
    data = pose_dataset(seq)
    assert data.layout == "kitti-odometry"
    # frames 000000-000005 -> snippets starting at 0 and 1
    assert [i.name for i in data.items] == ["000000", "000001"]
    raw = np.loadtxt(seq.parent.parent / "poses" / "00.txt")[:6].reshape(6, 3, 4)
    np.testing.assert_array_equal(data.items[1].gt_c2w[:, :3, :], raw[1:6])
    assert [p.name for p in data.items[1].frames] == [f"{i:06d}.png" for i in range(1, 6)]
    # image_0 (grey, camera 0) -> P0; README: fx = fy = 718.856, cx = 607.1928, cy = 185.2157
    K = data.items[0].intrinsics()
    np.testing.assert_allclose(K, [[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]])
    # README: the car drives straight ahead about 0.86 m per frame
    gt = evaluation.gt_snippet(data.items[0].gt_c2w)
    assert gt[4, 2, 3] == pytest.approx(4 * 0.86, abs=0.1)


def test_middlebury_reader_matches_flo_by_hand(require_real):
    root = require_real(MIDDLEBURY)
    data = flow_dataset(root)
    assert data.layout == "middlebury" and [i.name for i in data.items] == ["Grove3"]
    flow, valid = data.items[0].load_gt("occ")
    expected = read_flo_numpy(root / "other-gt-flow" / "Grove3" / "flow10.flo")
    np.testing.assert_array_equal(flow, expected)
    assert flow.shape == (480, 640, 2) and valid.all()  # README: 640x480, all pixels valid
    assert np.sqrt((flow**2).sum(axis=2)).max() == pytest.approx(18.6, abs=0.05)  # README: max 18.6 px


def test_kitti_raw_velodyne_reader(require_real):
    root = require_real(KITTI_RAW)
    data = depth_dataset(root)
    assert data.layout == "kitti-raw" and len(data.items) == 10  # scans exist for frames 0-9 only
    item = data.items[3]
    assert item.name == "0000000003" and item.gt_kind == "velodyne"
    gt = item.load_gt((375, 1242))
    assert (gt > 0).sum() > 10_000 and gt.max() < 120


def test_kitti_raw_sparse_png_layout(tmp_path):
    """proj_depth/groundtruth PNGs (uint16 / 256) are read and scored; the constant baseline's
    AbsRel on a two-valued GT is worked out by hand."""
    drive = tmp_path / "drive"
    (drive / "image_02" / "data").mkdir(parents=True)
    h, w = 100, 300
    cv2.imwrite(str(drive / "image_02" / "data" / "0000000000.png"), texture(0, h, w))
    gt = np.zeros((h, w))
    gt[60:90, 20:150] = 10.0  # inside the Garg crop (rows 40..98, cols 10..289)
    gt[60:90, 150:280] = 20.0
    write_depth_png(drive / "proj_depth" / "groundtruth" / "image_02" / "0000000000.png", gt)
    data = depth_dataset(drive)
    assert data.items[0].gt_kind == "png"
    r = evaluation.evaluate_depth(baselines.constant_depth, data)
    # median 15 -> prediction 15 everywhere: AbsRel = (5/10 + 5/20) / 2
    assert r["metrics"]["abs_rel"] == pytest.approx(0.375)
    assert r["settings"]["crop"] == "garg"


# ----------------------------------------------------------------------------- KITTI object and KITTI 2015 disparity
# The calibration of each KITTI object frame, typed from kitti_object_3frames/training/calib/NNNNNN.txt
# (frames 000001 and 000002 share the 2011_09_26 calibration; 000000 is from another day).
OBJECT_CALIB_26 = {
    "P2": [721.5377, 0, 609.5593, 44.85728, 0, 721.5377, 172.854, 0.2163791, 0, 0, 1, 0.002745884],
    "R0_rect": [0.9999239, 0.00983776, -0.007445048, -0.009869795, 0.9999421, -0.004278459, 0.007402527,
                0.004351614, 0.9999631],
    "Tr_velo_to_cam": [0.007533745, -0.9999714, -0.000616602, -0.004069766, 0.01480249, 0.0007280733,
                       -0.9998902, -0.07631618, 0.9998621, 0.00752379, 0.01480755, -0.2717806],
}  # fmt: skip
OBJECT_CALIB = {
    "000000": {
        "P2": [707.0493, 0, 604.0814, 45.75831, 0, 707.0493, 180.5066, -0.3454157, 0, 0, 1, 0.004981016],
        "R0_rect": [0.9999128, 0.01009263, -0.008511932, -0.01012729, 0.9999406, -0.004037671, 0.008470675,
                    0.004123522, 0.9999556],
        "Tr_velo_to_cam": [0.006927964, -0.9999722, -0.002757829, -0.02457729, -0.001162982, 0.002749836,
                           -0.9999955, -0.06127237, 0.9999753, 0.006931141, -0.001143899, -0.3321029],
    },
    "000001": OBJECT_CALIB_26,
    "000002": OBJECT_CALIB_26,
}  # fmt: skip
GARG = (0.40810811, 0.99189189, 0.03594771, 0.96405229)  # Garg et al.'s crop: rows, then columns, as fractions
KITTI_FX_2011_09_26, KITTI_BASELINE = 721.5377, 0.54  # what the 000046 commands pass (--fx, --baseline)


def padded(m: list[float], rows: int, cols: int) -> np.ndarray:
    out = np.eye(4)
    out[:rows, :cols] = np.reshape(m, (rows, cols))
    return out


def object_depth_by_hand(scan: Path, calib: dict, h: int, w: int) -> np.ndarray:
    """The KITTI devkit's projection, written out again: x >= 0, P2·R0·Tr, round − 1, nearest point per pixel
    (here by sorting, not the code's minimum-reduction), value = Velodyne forward distance x."""
    pts = np.fromfile(scan, dtype="<f4").reshape(-1, 4).astype(np.float64)
    pts = pts[pts[:, 0] >= 0]
    M = np.reshape(calib["P2"], (3, 4)) @ padded(calib["R0_rect"], 3, 3) @ padded(calib["Tr_velo_to_cam"], 3, 4)
    hom = np.c_[pts[:, :3], np.ones(len(pts))] @ M.T
    col = np.round(hom[:, 0] / hom[:, 2]) - 1
    row = np.round(hom[:, 1] / hom[:, 2]) - 1
    keep = (col >= 0) & (row >= 0) & (col < w) & (row < h)
    pixel = row[keep].astype(int) * w + col[keep].astype(int)
    x = pts[keep, 0]
    order = np.lexsort((x, pixel))  # by pixel, nearest first
    first = np.r_[True, pixel[order][1:] != pixel[order][:-1]]
    depth = np.zeros(h * w)
    depth[pixel[order][first]] = x[order][first]
    return depth.reshape(h, w)


def scored_by_hand(depth: np.ndarray, max_depth: float = 80.0) -> np.ndarray:
    """The values inside the Eigen mask: 0.001 < d < max_depth, Garg crop."""
    h, w = depth.shape
    crop = np.zeros((h, w), bool)
    crop[int(GARG[0] * h) : int(GARG[1] * h), int(GARG[2] * w) : int(GARG[3] * w)] = True
    return depth[crop & (depth > 1e-3) & (depth < max_depth)]


def printed_ground_truth(out: str) -> tuple[int, int, float, float]:
    """(frames, pixels, min m, max m) of the `ground truth: ...` line `eval depth` prints."""
    (line,) = [line for line in out.splitlines() if line.startswith("ground truth:")]
    m = re.match(r"ground truth: (\d+) frames?, ([\d,]+) pixels \(garg crop, .*\), depth ([\d.]+)–([\d.]+) m$", line)
    assert m, line
    return int(m[1]), int(m[2].replace(",", "")), float(m[3]), float(m[4])


def test_eval_depth_kitti_object_agrees_with_a_projection_by_hand(kitti_object, tmp_path, capsys):
    out = tmp_path / "object.json"
    assert (
        cli_main(["eval", "depth", "--data", str(kitti_object), "--method", "model,constant", "--json", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "KITTI object kitti_object_3frames" in printed
    frames, pixels, lo, hi = printed_ground_truth(printed)
    expected = {}
    for name, calib in OBJECT_CALIB.items():
        h, w = cv2.imread(str(kitti_object / "training" / "image_2" / f"{name}.png")).shape[:2]  # 1224x370, 1242x375
        full = object_depth_by_hand(kitti_object / "training" / "velodyne" / f"{name}.bin", calib, h, w)
        assert 18_000 <= (full > 0).sum() <= 20_500  # README: 19-20 k points land in each image (a few share a pixel)
        expected[name] = scored_by_hand(full)
    values = np.concatenate(list(expected.values()))
    assert frames == 3 and pixels == values.size
    assert lo == pytest.approx(values.min(), abs=0.005) and hi == pytest.approx(values.max(), abs=0.005)
    results = json.loads(out.read_text())["results"]
    for result in results:  # per frame, for the model and the baseline alike
        assert {r["name"]: r["gt_pixels"] for r in result["items"]} == {n: v.size for n, v in expected.items()}
        assert result["ground_truth"]["pixels"] == values.size and result["metrics"]["count"] == 3
    assert all(math.isfinite(r["metrics"]["abs_rel"]) for r in results)


def disparity_by_hand(png: Path, fx_baseline: float) -> np.ndarray:
    raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    disparity = raw.astype(np.float64) / 256.0
    return np.where(raw > 0, fx_baseline / np.where(raw > 0, disparity, 1.0), 0.0)


def test_eval_depth_kitti2015_disparity_agrees_with_fx_baseline_by_hand(kitti2015_stereo, tmp_path, capsys):
    args = ["eval", "depth", "--data", str(kitti2015_stereo), "--method", "model,constant"]
    out = tmp_path / "disp.json"
    assert cli_main([*args, "--fx", "721.5377", "--baseline", "0.54", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    frames, pixels, lo, hi = printed_ground_truth(printed)
    depth = disparity_by_hand(kitti2015_stereo / "training" / "disp_occ_0" / "000046_10.png", 721.5377 * 0.54)
    assert 0.11 < (depth > 0).mean() < 0.125  # README: 11.8 % of the pixels hold a disparity
    values = scored_by_hand(depth)
    assert frames == 1 and pixels == values.size
    assert lo == pytest.approx(values.min(), abs=0.005) and hi == pytest.approx(values.max(), abs=0.005)
    # the output says which fx and baseline turned disparity into depth, and where they came from
    assert "fx 721.5377 px, baseline 0.54 m (fx from --fx, baseline from --baseline)" in printed
    details = json.loads(out.read_text())["results"][0]["data"]["details"]["disparity_to_depth"]
    assert details == [
        {"frame": "000046_10", "fx": 721.5377, "baseline_m": 0.54, "source": {"fx": "--fx", "baseline": "--baseline"}}
    ]
    # without a calibration file or the options, nothing is assumed: one line naming the file it looked for
    assert cli_main(args) == 2
    err = capsys.readouterr().err
    assert "calib_cam_to_cam/000046.txt" in err and "--fx and --baseline" in err and len(err.strip().splitlines()) == 1


def test_kitti2015_disparity_takes_fx_and_baseline_from_the_scene_calibration(kitti2015_stereo, tmp_path, capsys):
    """A copy of the scene with a calib_cam_to_cam/000046.txt (the 2011_09_26 rectified matrices, typed):
    fx = P_rect_02[0, 0], baseline = (P_rect_02[0, 3] − P_rect_03[0, 3]) / fx."""
    root = tmp_path / "kitti2015"
    shutil.copytree(kitti2015_stereo, root)
    (root / "training" / "calib_cam_to_cam").mkdir()
    (root / "training" / "calib_cam_to_cam" / "000046.txt").write_text(
        "calib_time: 09-Jan-2012 13:57:47\n"
        "P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 "
        "2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03\n"
        "P_rect_03: 7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 1.728540e+02 "
        "2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03\n"
    )
    baseline = (44.85728 + 339.5242) / 721.5377  # 0.5327 m
    assert cli_main(["eval", "depth", "--data", str(root), "--method", "constant"]) == 0
    printed = capsys.readouterr().out
    assert "from calib_cam_to_cam/000046.txt" in printed and f"baseline {baseline:.4g} m" in printed
    values = scored_by_hand(disparity_by_hand(root / "training" / "disp_occ_0" / "000046_10.png", 721.5377 * baseline))
    frames, pixels, lo, hi = printed_ground_truth(printed)
    assert pixels == values.size and hi == pytest.approx(values.max(), abs=0.005)
    # --baseline overrides the file, fx still from it
    assert cli_main(["eval", "depth", "--data", str(root), "--method", "constant", "--baseline", "0.54"]) == 0
    assert "fx from calib_cam_to_cam/000046.txt (P_rect_02), baseline from --baseline" in capsys.readouterr().out


def test_layout_options_and_broken_object_frames_are_named(kitti_object, kitti2015_stereo, tmp_path, capsys):
    assert cli_main(["eval", "depth", "--data", str(kitti_object), "--method", "constant", "--fx", "700"]) == 2
    err = capsys.readouterr().err
    assert "--fx does not apply to the kitti-object layout" in err and "kitti-disparity" in err
    assert cli_main(["eval", "depth", "--data", str(kitti2015_stereo), "--method", "constant", "--fx", "-1"]) == 2
    assert "--fx -1 must be a positive number" in capsys.readouterr().err
    root = tmp_path / "object"
    shutil.copytree(kitti_object, root)
    (root / "training" / "calib" / "000001.txt").unlink()
    assert cli_main(["eval", "depth", "--data", str(root), "--method", "constant"]) == 2
    err = capsys.readouterr().err
    assert "calib/000001.txt" in err and "calibration of this frame not found" in err
    calib = root / "training" / "calib" / "000002.txt"
    calib.write_text("\n".join(line for line in calib.read_text().splitlines() if not line.startswith("R0_rect")))
    (root / "training" / "calib" / "000001.txt").write_text((root / "training" / "calib" / "000000.txt").read_text())
    assert cli_main(["eval", "depth", "--data", str(root), "--method", "constant"]) == 2
    err = capsys.readouterr().err
    assert "calib/000002.txt" in err and "'R0_rect' is missing" in err
    # a frame without a scan is left out and named, as for KITTI raw
    (root / "training" / "calib" / "000002.txt").write_text((root / "training" / "calib" / "000001.txt").read_text())
    (root / "training" / "velodyne" / "000002.bin").unlink()
    assert cli_main(["eval", "depth", "--data", str(root), "--method", "constant"]) == 1
    assert "1 of 3 frames without a scan in velodyne/ (000002)" in capsys.readouterr().err


def test_grey_odometry_frames_are_scored_as_three_equal_channels(kitti_odometry_06, capsys):
    seq = kitti_odometry_06 / "sequences" / "06"
    data = pose_dataset(seq)
    # image_2/ holds frames 12, 13, 14, 17 (no 5 consecutive), image_0/ frames 0-50: grey is scored
    assert data.description.startswith("KITTI odometry seq 06 (image_0") and len(data.items) == 47
    assert any("image_2/ gives 0 snippets, image_0/ 47" in n for n in data.notes)
    assert any("grey" in n and "three equal channels" in n for n in data.notes)
    np.testing.assert_allclose(data.items[0].intrinsics()[0, 0], 707.0912)  # P0 of calib.txt
    grey = cv2.imread(str(seq / "image_0" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert grey.ndim == 2
    rgb = read_image(seq / "image_0" / "000000.png")
    assert rgb.shape == grey.shape + (3,) and all((rgb[..., c] == grey).all() for c in range(3))
    assert cli_main(["eval", "pose", "--data", str(seq), "--method", "model,identity", "--limit", "2"]) == 0
    printed = capsys.readouterr().out
    assert "note: image_0/ frames are grey" in printed and "| 2 |" in printed


# ----------------------------------------------------------------------------- DIS acceptance
def _kitti2012_from_middlebury(root: Path, out: Path) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """A KITTI 2012 layout (colored_0/NNNNNN_10.png, _11.png, flow_noc/, flow_occ/) made from the Grove3 pair:
    pair 0 the full frames, pair 1 a crop. noc marks a 40 px band at the left as occluded.
    Returns per pair (frame10 grey, frame11 grey, GT flow, noc mask) for the independent EPE."""
    f10 = cv2.imread(str(root / "other-data-gray" / "Grove3" / "frame10.png"), cv2.IMREAD_GRAYSCALE)
    f11 = cv2.imread(str(root / "other-data-gray" / "Grove3" / "frame11.png"), cv2.IMREAD_GRAYSCALE)
    flo = read_flo_numpy(root / "other-gt-flow" / "Grove3" / "flow10.flo")
    crop = (slice(100, 400), slice(150, 550))
    pairs = [(f10, f11, flo), tuple(np.ascontiguousarray(x[crop]) for x in (f10, f11, flo))]
    out_pairs = []
    for k, (a, b, flow) in enumerate(pairs):
        (out / "colored_0").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / "colored_0" / f"{k:06d}_10.png"), a)
        cv2.imwrite(str(out / "colored_0" / f"{k:06d}_11.png"), b)
        noc = np.ones(a.shape, bool)
        noc[:, :40] = False
        write_kitti_flow_png(out / "flow_noc" / f"{k:06d}_10.png", flow, noc)
        write_kitti_flow_png(out / "flow_occ" / f"{k:06d}_10.png", flow, np.ones(a.shape, bool))
        out_pairs.append((a, b, flow, noc))
    return out_pairs


def test_dis_on_kitti2012_layout_agrees_with_independent_epe(require_real, tmp_path, capsys):
    """Substitute for real KITTI 2012 pairs (none in ../shared): Middlebury Grove3 in the KITTI 2012 layout."""
    root = require_real(MIDDLEBURY)
    data_dir = tmp_path / "kitti2012"
    pairs = _kitti2012_from_middlebury(root, data_dir)
    out = tmp_path / "dis.json"
    assert cli_main(["eval", "flow", "--data", str(data_dir), "--method", "dis", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "DIS medium" in table and "KITTI 2012 layout" in table
    results = {r["method"]: r for r in json.loads(out.read_text())["results"]}
    for label, preset in (
        ("DIS medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
        ("DIS ultrafast", cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
    ):
        noc, all_ = [], []
        for a, b, flow, mask in pairs:
            pred = cv2.DISOpticalFlow_create(preset).calc(a, b, None)
            epe = np.sqrt(((pred - flow) ** 2).sum(axis=2))
            noc.append(epe[mask].mean())
            all_.append(epe.mean())
        got = results[label]["metrics"]
        # the only difference: the GT went through the PNG's 1/64 px grid (<= 1/128 px per component)
        assert got["epe_noc"] == pytest.approx(np.mean(noc), abs=0.01)
        assert got["epe_all"] == pytest.approx(np.mean(all_), abs=0.01)
        assert got["count"] == 2
    assert results["DIS medium"]["metrics"]["epe_all"] < results["DIS ultrafast"]["metrics"]["epe_all"]
    # no _09 frames here: every pair records the documented fallback
    assert all("no _09" in item["snippet"] for item in results["DIS medium"]["items"])


def read_kitti_flow_by_hand(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """KITTI 2015 flow PNG read with cv2 (devkit encoding): file channels B, G, R = valid, v, u;
    u = (R − 2^15) / 64, v = (G − 2^15) / 64."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape[2] == 3
    flow = (np.stack([raw[..., 2], raw[..., 1]], axis=2).astype(np.float64) - 2**15) / 64.0
    return flow, raw[..., 0] > 0


def test_dis_on_real_kitti2015_pair_agrees_with_independent_epe(kitti2015_flow, tmp_path, capsys):
    """The real KITTI 2015 pair 000010 (issue 10's point that had no data): `eval flow --method dis` on the
    benchmark folder as unpacked (training/ inside) against OpenCV DIS + numpy EPE written here."""
    out = tmp_path / "dis.json"
    assert cli_main(["eval", "flow", "--data", str(kitti2015_flow), "--method", "dis", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    assert "KITTI 2015 layout kitti2015_flow_000010" in table and "DIS medium" in table
    results = {r["method"]: r for r in json.loads(out.read_text())["results"]}
    base = kitti2015_flow / "training"
    grey = [cv2.cvtColor(cv2.imread(str(base / "image_2" / f"000010_{t}.png")), cv2.COLOR_BGR2GRAY) for t in (10, 11)]
    gt_all, valid_all = read_kitti_flow_by_hand(base / "flow_occ" / "000010_10.png")
    gt_noc, valid_noc = read_kitti_flow_by_hand(base / "flow_noc" / "000010_10.png")
    assert valid_all.mean() == pytest.approx(0.240, abs=0.001) and valid_noc.mean() == pytest.approx(0.234, abs=0.001)
    zero_epe = np.sqrt((gt_all**2).sum(axis=2))[valid_all].mean()
    assert zero_epe == pytest.approx(9.03, abs=0.005)  # README: zero flow has EPE 9.03 px on flow_occ
    for label, preset in (
        ("DIS medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
        ("DIS ultrafast", cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
    ):
        pred = cv2.DISOpticalFlow_create(preset).calc(grey[0], grey[1], None).astype(np.float64)
        got = results[label]["metrics"]
        for key, gt, valid in (("epe_noc", gt_noc, valid_noc), ("epe_all", gt_all, valid_all)):
            epe = np.sqrt(((pred - gt) ** 2).sum(axis=2))[valid].mean()
            assert got[key] == pytest.approx(epe, abs=0.01), (label, key)
        assert got["count"] == 1
    item = results["DIS medium"]["items"][0]
    assert item["n_valid_all"] == valid_all.sum() and item["n_valid_noc"] == valid_noc.sum()
    assert "no _09" in item["snippet"]  # the pair has no _09 frame: documented fallback for the model


def test_kitti_layout_uses_09_and_calibration_for_the_model(require_real, tmp_path):
    root = require_real(MIDDLEBURY)
    data_dir = tmp_path / "kitti2012"
    _kitti2012_from_middlebury(root, data_dir)
    cv2.imwrite(
        str(data_dir / "colored_0" / "000000_09.png"),
        cv2.imread(str(root / "other-data-gray" / "Grove3" / "frame10.png")),
    )
    (data_dir / "calib").mkdir()
    for k in range(2):
        (data_dir / "calib" / f"{k:06d}.txt").write_text(
            "".join(f"P{c}: 600 0 320 0 0 600 240 0 0 0 1 0\n" for c in range(4))
        )
    data = flow_dataset(data_dir)
    assert [len(i.frames) for i in data.items] == [3, 2]
    assert data.items[0].frames[0].name == "000000_09.png"
    np.testing.assert_allclose(data.items[0].intrinsics(), [[600, 0, 320], [0, 600, 240], [0, 0, 1]])
    assert any("1 of 2 pairs have no _09" in n for n in data.notes)


# ----------------------------------------------------------------------------- golden values, hand-built data
def test_synth_baselines_hand_computed(tmp_path):
    make_synth(tmp_path)
    depth = evaluation.evaluate_depth(baselines.constant_depth, depth_dataset(tmp_path))
    assert depth["metrics"]["abs_rel"] == pytest.approx(0.375)  # median 15: (5/10 + 5/20) / 2
    assert depth["metrics"]["count"] == 6 and depth["settings"]["crop"] is None
    flow = evaluation.evaluate_flow(baselines.zero_flow, flow_dataset(tmp_path))
    assert flow["metrics"]["epe_noc"] == pytest.approx(5.0) and flow["metrics"]["epe_all"] == pytest.approx(5.0)
    assert flow["metrics"]["fl_all"] == 1.0  # 5 px > 3 px and 5 / 5 > 5 %
    assert flow["metrics"]["count"] == 4  # triplets [t-1, t, t+1] of 6 frames
    pose = evaluation.evaluate_pose(baselines.identity_pose, pose_dataset(tmp_path))
    # GT z = 0..4 m; a still camera cannot be scaled: |e|^2 sums to 30
    assert pose["metrics"]["ate_snippet"] == pytest.approx(math.sqrt(30) / 5)
    assert pose["metrics"]["ate_rmse_true"] == pytest.approx(math.sqrt(30 / 5))
    assert pose["std"]["ate_snippet"] == pytest.approx(0.0, abs=1e-12) and pose["metrics"]["count"] == 2


def test_gt_snippet_and_ate_rows_against_hand_values():
    """A snippet not starting at the identity: GT snippet poses = inv(C_0) C_i; the GT trajectory scores
    ATE 0; the still camera scores ||gt|| / N (paper) and the RMS distance (true RMSE)."""
    rng = np.random.default_rng(1)
    c2w = []
    for i in range(5):
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rng.normal(scale=0.2, size=3))[0]
        T[:3, 3] = rng.normal(size=3) + [0, 0, 2.0 * i]
        c2w.append(T)
    gt = evaluation.gt_snippet(np.stack(c2w))
    np.testing.assert_allclose(gt, [np.linalg.inv(c2w[0]) @ c for c in c2w], atol=1e-12)
    xyz = gt[:, :3, 3]
    assert evaluation.ate_rows(xyz, 0.5 * xyz)["ate_snippet"] < 1e-12  # any scale is fitted away
    still = evaluation.ate_rows(xyz, np.zeros_like(xyz))
    assert still["ate_snippet"] == pytest.approx(np.sqrt(np.sum(xyz**2)) / 5, rel=1e-12)
    assert still["ate_rmse_true"] == pytest.approx(np.sqrt(np.mean(np.sum(xyz**2, axis=1))), rel=1e-12)


def test_snippet_from_three_frame_pose_calls_recovers_trajectory():
    """A seq-3 PoseNet's two triplet calls chained through frame 2 give the true snippet poses."""
    rng = np.random.default_rng(0)

    def rigid(angle, t):
        c, s = math.cos(angle), math.sin(angle)
        T = np.eye(4)
        T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        T[:3, 3] = t
        return T

    c2w = [rigid(0.05 * i, rng.normal(size=3) + [0, 0, i]) for i in range(5)]

    def T(target, source):  # maps target-camera points to source-camera points
        return np.linalg.inv(c2w[source]) @ c2w[target]

    calls = iter([np.stack([T(1, 0), T(1, 2)]), np.stack([T(3, 2), T(3, 4)])])
    got = evaluation.snippet_from_pose_calls(lambda frames: next(calls), list(range(5)), 3)
    expected = np.stack([np.linalg.inv(c2w[0]) @ c for c in c2w])
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_orb_vo_recovers_direction_of_a_rendered_plane_motion():
    """Frames of a textured plane rendered by homography for a camera moving along +x: ORB-VO's chained
    trajectory points along +x (unit steps) — the geometry comes from cv2.warpPerspective, not from the code."""
    h, w = 240, 320
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    tex = cv2.resize(
        np.random.default_rng(3).integers(0, 255, (60, 80), np.uint8), (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST
    )
    frames = []
    for i in range(5):
        # plane z = 5 m (plus a tilt so it is not degenerate for the essential matrix), camera at x = 0.2 i
        n, d = np.array([0.0, -0.3, 1.0]) / np.linalg.norm([0.0, -0.3, 1.0]), 5.0
        t = np.array([-0.2 * i, 0, 0])  # world -> camera translation
        H = K @ (np.eye(3) + np.outer(t, n) / d) @ np.linalg.inv(K)
        S = np.diag([0.5, 0.5, 1.0])  # texture (2w x 2h) -> reference image (w x h)
        rgb = cv2.cvtColor(cv2.warpPerspective(tex, H @ S, (w, h)), cv2.COLOR_GRAY2RGB)
        frames.append(rgb)
    poses, info = baselines.orb_vo(frames, K)
    assert info["failed_pairs"] == 0
    direction = poses[4, :3, 3] / np.linalg.norm(poses[4, :3, 3])
    assert direction[0] > 0.95  # camera moved along +x


def test_orb_vo_counts_a_standing_camera_as_failed_pairs_instead_of_raising():
    """Identical frames: every match has zero motion, which OpenCV 5's findEssentialMat rejects with an
    assertion (4.x returned no solution). ORB-VO must record failed pairs and stand still, not crash."""
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    tex = cv2.resize(np.random.default_rng(3).integers(0, 255, (60, 80), np.uint8), (320, 240))
    frame = cv2.cvtColor(tex, cv2.COLOR_GRAY2RGB)
    poses, info = baselines.orb_vo([frame] * 3, K)
    assert info["failed_pairs"] == 2
    np.testing.assert_array_equal(poses, np.stack([np.eye(4)] * 3))


# ----------------------------------------------------------------------------- depth scaled by camera height
CAM_H, FX, CY = 1.5, 100.0, 32.0  # camera 1.5 m above a flat road, level; 64x208 frames, principal row 32


def road_and_box(h: int = 64, w: int = 208) -> np.ndarray:
    """Depth of a level camera CAM_H above a flat road, by hand: a ground pixel in row v sees the road at
    z = CAM_H * fy / (v - cy); a box face 8 m ahead (columns 80-129, 1.2 m tall) hides the road behind it;
    0 (no ground truth) at and above the horizon row."""
    v = np.arange(h, dtype=np.float64)[:, None].repeat(w, axis=1)
    depth = np.zeros((h, w))
    below = v > CY
    depth[below] = CAM_H * FX / (v[below] - CY)
    box = np.zeros((h, w), bool)
    box[:, 80:130] = True
    box &= (v >= CY + FX * (CAM_H - 1.2) / 8) & (depth > 8)  # the face's rows, in front of the road
    depth[box] = 8.0
    return depth


def make_road(root: Path, frames: int = 2) -> Path:
    """A synth-layout sequence whose GT is :func:`road_and_box` (stored as KITTI depth PNGs, 1/256 m)."""
    seq = root / "seq_0000"
    (seq / "image").mkdir(parents=True)
    for t in range(frames):
        cv2.imwrite(str(seq / "image" / f"{t:06d}.png"), texture(t))
        write_depth_png(seq / "depth" / f"{t:06d}.png", road_and_box())
    (seq / "calib.txt").write_text(f"K: {FX} 0 104 0 {FX} {CY} 0 0 1\n")
    return seq


def scaled_road(rgb: np.ndarray) -> np.ndarray:
    """The exact scene in unknown units (x 0.37); 50 units of sky where the GT has none."""
    depth = road_and_box()
    return np.where(depth > 0, 0.37 * depth, 50.0).astype(np.float32)


def test_camera_height_scaling_recovers_metres_of_a_road_and_box_scene(tmp_path):
    make_road(tmp_path)
    data = depth_dataset(tmp_path)
    r = evaluation.evaluate_depth(scaled_road, data, scaling="camera_height", camera_height=CAM_H)
    assert r["errors"] == [] and r["ground_fit_failed"] == [] and r["metrics"]["count"] == 2
    # metric again: the only error left is the PNG's 1/256 m grid
    assert r["metrics"]["abs_rel"] < 1e-3 and r["metrics"]["a1"] == 1.0
    for row in r["items"]:
        assert row["scale"] == pytest.approx(1 / 0.37, rel=1e-4)
        assert row["ground_height"] == pytest.approx(0.37 * CAM_H, rel=1e-4)
    assert r["settings"]["scaling"] == "camera_height" and r["settings"]["camera_height"] == CAM_H
    # unscaled, every depth is 0.37 of the truth: AbsRel = 1 - 0.37 by hand
    raw = evaluation.evaluate_depth(scaled_road, data, scaling="none")
    assert raw["metrics"]["abs_rel"] == pytest.approx(0.63, abs=1e-3)
    # a wrong camera height scales every depth by the same ratio: AbsRel = |1 - 1.65 / 1.5|
    # (cap above the farthest road point, 150 m, so that no prediction is clamped)
    wrong = evaluation.evaluate_depth(scaled_road, data, scaling="camera_height", camera_height=1.65, max_depth=200)
    assert wrong["metrics"]["abs_rel"] == pytest.approx(0.1, abs=1e-3)


def test_camera_height_frame_without_ground_is_counted_named_and_not_median_scaled(tmp_path, monkeypatch, capsys):
    make_road(tmp_path, frames=3)
    calls = {"n": 0}

    def road_then_wall(rgb):  # frame 000001: a constant depth, a wall facing the camera, no road
        calls["n"] += 1
        return np.full(rgb.shape[:2], 5.0, np.float32) if calls["n"] == 2 else scaled_road(rgb)

    r = evaluation.evaluate_depth(road_then_wall, depth_dataset(tmp_path), scaling="camera_height", camera_height=CAM_H)
    assert r["ground_fit_failed"] == ["seq_0000/000001"]
    assert [e["item"] for e in r["errors"]] == ["seq_0000/000001"] and "ground plane" in r["errors"][0]["problem"]
    failed = r["items"][1]
    assert failed["ground_fit"] == "failed" and math.isnan(failed["abs_rel"])
    # the mean covers the 2 frames with a road (both ~0), not a median-scaled wall (AbsRel > 0.3 here)
    assert r["metrics"]["count"] == 2 and r["metrics"]["abs_rel"] < 1e-3
    # CLI: exit 1, the frame named on stderr, the table's count says what was left out
    calls["n"] = 0
    monkeypatch.setattr(baselines, "constant_depth", road_then_wall)
    out = tmp_path / "r.json"
    args = ["eval", "depth", "--data", str(tmp_path), "--method", "constant", "--camera-height", "1.5"]
    assert cli_main([*args, "--json", str(out)]) == 1
    captured = capsys.readouterr()
    assert "seq_0000/000001: ground plane fit failed" in captured.err
    assert "| 2 (+1 not scored: no ground plane) |" in captured.out
    assert "no ground plane in 1 of 3 frames (seq_0000/000001)" in captured.out
    result = json.loads(out.read_text())["results"][0]
    assert result["ground_fit_failed"] == ["seq_0000/000001"] and result["items"][1]["abs_rel"] is None


def test_camera_height_bad_input(tmp_path, capsys):
    seq = make_road(tmp_path)
    base = ["eval", "depth", "--data", str(tmp_path), "--method", "constant"]
    assert cli_main([*base, "--camera-height", "0"]) == 2
    assert "must be a positive number of metres" in capsys.readouterr().err
    assert cli_main([*base, "--camera-height", "1.5", "--no-median-scaling"]) == 2  # one scaling at a time
    assert "not allowed with argument --camera-height" in capsys.readouterr().err
    assert cli_main(["eval", "flow", "--data", str(tmp_path), "--method", "zero", "--camera-height", "1.5"]) == 2
    assert "--camera-height is for depth" in capsys.readouterr().err
    (seq / "calib.txt").unlink()
    assert cli_main([*base, "--camera-height", "1.5"]) == 2
    err = capsys.readouterr().err
    assert str(seq / "calib.txt") in err and "--intrinsics" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(GeoNetError, match="unknown depth scaling 'mean'"):
        evaluation.evaluate_depth(baselines.constant_depth, depth_dataset(tmp_path), scaling="mean")


# ----------------------------------------------------------------------------- bad input
def test_nan_prediction_is_reported_not_dropped(tmp_path, monkeypatch, capsys):
    make_synth(tmp_path)
    calls = {"n": 0}

    def sometimes_nan(rgb):
        calls["n"] += 1
        out = np.ones(rgb.shape[:2], np.float32)
        if calls["n"] == 3:
            out[0, 0] = np.nan
        return out

    monkeypatch.setattr(baselines, "constant_depth", sometimes_nan)
    out = tmp_path / "r.json"
    assert cli_main(["eval", "depth", "--data", str(tmp_path), "--method", "constant", "--json", str(out)]) == 1
    err = capsys.readouterr().err
    assert "seq_0000/000002" in err and "NaN/inf" in err
    result = json.loads(out.read_text())["results"][0]
    assert result["metrics"]["abs_rel"] is None  # NaN mean, written as null
    assert result["errors"][0]["item"] == "seq_0000/000002"
    # in Python the mean is NaN, not the mean of the 5 finite frames
    calls["n"] = 0
    r = evaluation.evaluate_depth(sometimes_nan, depth_dataset(tmp_path))
    assert math.isnan(r["metrics"]["abs_rel"])


def test_missing_data_folder_exit_2(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert cli_main(["eval", "depth", "--data", str(missing), "--method", "constant"]) == 2
    err = capsys.readouterr().err.strip()
    assert str(missing) in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(
    "task,breakage,named",
    [
        ("depth", lambda s: (s / "depth" / "000003.png").unlink(), "depth/000003.png"),
        ("depth", lambda s: write_depth_png(s / "depth" / "000001.png", np.ones((10, 10))), "depth/000001.png"),
        ("depth", lambda s: write_depth_png(s / "depth" / "000002.png", np.zeros((64, 208))), "depth/000002.png"),
        ("flow", lambda s: (s / "flow_occ" / "000002.png").unlink(), "flow_occ/000002.png"),
        (
            "flow",
            lambda s: write_kitti_flow_png(
                s / "flow_noc" / "000001.png", np.zeros((64, 208, 2)), np.zeros((64, 208), bool)
            ),
            "flow_noc/000001.png",
        ),
        ("pose", lambda s: (s / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 4), "poses.txt"),
    ],
)
def test_bad_data_names_the_file(tmp_path, capsys, task, breakage, named):
    seq = make_synth(tmp_path)
    breakage(seq)
    method = {"depth": "constant", "flow": "zero", "pose": "identity"}[task]
    assert cli_main(["eval", task, "--data", str(tmp_path), "--method", method]) == 2
    err = capsys.readouterr().err
    assert named in err and len(err.strip().splitlines()) == 1


def test_unknown_method_is_a_usage_error(tmp_path, capsys):
    make_synth(tmp_path)
    assert cli_main(["eval", "flow", "--data", str(tmp_path), "--method", "orb-vo"]) == 2
    assert "no flow method 'orb-vo'" in capsys.readouterr().err


def test_nonfinite_metric_means_propagate():
    rows = [{"epe": 1.0}, {"epe": math.nan}]
    assert math.isnan(metrics.aggregate(rows)["epe"])


def test_intrinsics_needed_for_model_flow_without_calibration(require_real, tmp_path):
    root = require_real(MIDDLEBURY)
    fn = evaluation._needs_K(lambda frames, K: np.zeros(frames[-1].shape[:2] + (2,), np.float32))
    with pytest.raises(GeoNetError, match="--intrinsics"):
        evaluation.evaluate_flow(fn, flow_dataset(root))
    r = evaluation.evaluate_flow(fn, flow_dataset(root), intrinsics=np.eye(3))
    assert r["metrics"]["count"] == 1


# ----------------------------------------------------------------------------- checkpoints, same code path
@pytest.mark.train_extra
def test_training_evaluate_scores_a_checkpoint_through_the_shared_loops(tmp_path):
    torch = pytest.importorskip("torch")
    from training.checkpoint import save_checkpoint
    from training.config import TrainConfig
    from training.evaluate import main as train_eval_main
    from training.model import GeoNet

    make_synth(tmp_path / "data")
    torch.manual_seed(0)
    model = GeoNet("small", 2, with_flow=True).eval()
    cfg = TrainConfig(stage="flow", arch="small", height=64, width=208, data_dir="x", out_dir=str(tmp_path))
    ckpt = tmp_path / "c.pt"
    save_checkpoint(ckpt, model, torch.optim.Adam(model.parameters()), 7, cfg, {})
    out = tmp_path / "r.json"
    assert train_eval_main(["--checkpoint", str(ckpt), "--data", str(tmp_path / "data"), "--out", str(out)]) == 0
    results = json.loads(out.read_text())["results"]
    assert [r["task"] for r in results] == ["depth", "flow", "pose"]
    assert [r["metrics"]["count"] for r in results] == [6, 4, 2]
    assert all(r["method"] == "checkpoint c.pt (step 7)" for r in results)
    # a weights-only file (what training.checkpoint writes) scores through the same path
    from training.checkpoint import load_checkpoint, save_weights

    weights = tmp_path / "w.pt"
    save_weights(load_checkpoint(ckpt), weights, source={"note": "no step"})
    out_w = tmp_path / "w.json"
    assert train_eval_main(["--checkpoint", str(weights), "--data", str(tmp_path / "data"), "--out", str(out_w)]) == 0
    from_weights = json.loads(out_w.read_text())["results"]
    assert all(r["method"] == "weights w.pt" for r in from_weights)
    for full, light in zip(results, from_weights):  # conv kernels stored as float16: close, not equal
        for key, value in full["metrics"].items():
            assert light["metrics"][key] == pytest.approx(value, rel=0.02, abs=1e-3), (full["task"], key)


def test_eval_all_says_in_one_line_where_it_went(tmp_path, capsys):
    """`eval all` left the package (issue 42): an old command gets exit 2 and the new one, not a usage dump."""
    assert cli_main(["eval", "all", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "python -m benchmarks.eval_all" in err
