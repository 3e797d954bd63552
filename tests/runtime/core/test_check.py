"""The output check (geonet_infer.core.check): flows known right pass, flows known wrong are flagged.

Golden values are independent of the code under test: pairs made with numpy (a grey-level ramp
shifted by whole pixels, whose errors are closed-form) or with ``cv2.warpAffine`` (a known affine
motion, whose flow is ``A p + b - p``), OpenCV's DIS flow on real KITTI frames, and hand-built
checks for the sequence summary. End to end: ``predict_sequence`` and ``geonet-infer predict``
carry the check (result objects, summary.json, the closing line). No torch.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import geonet_infer
from geonet_infer.cli import main
from geonet_infer.core.check import AGREE_PX, FrameCheck, SequenceCheck, check_pair
from geonet_infer.eval.baselines import dis_flow
from geonet_infer.io import read_camera

SAMPLE = Path(geonet_infer.__file__).resolve().parent / "samples" / "synth_seq"
SAMPLE_CALIB = SAMPLE / "calib.txt"
FRAMES = sorted((SAMPLE / "image").glob("*.png"))
KITTI_RAW = "kitti_raw_2011_09_26_sfnd"


def ramp_pair(height: int = 48, width: int = 64, shift: tuple[int, int] = (3, 2)):
    """Frame t = u + 2 v grey levels; frame t+1 the same scene moved by ``shift`` pixels, so the true
    flow is ``shift`` everywhere and no motion errs by shift_u + 2 shift_v on every pixel."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    du, dv = shift
    flow = np.zeros((height, width, 2), np.float32)
    flow[..., 0], flow[..., 1] = du, dv
    return u + 2 * v, (u - du) + 2 * (v - dv), flow


def rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def zoom_pair(zoom: float = 1.03, shift: tuple[float, float] = (1.0, 0.5)):
    """A sample frame and the same frame after an affine motion p -> A p + b (a zoom about the
    centre and a shift: a camera driving forward), made with cv2.warpAffine; and the true flow."""
    image = rgb(FRAMES[0])
    height, width = image.shape[:2]
    A = np.eye(2) * zoom
    centre = np.array([width / 2, height / 2])
    b = centre - A @ centre + np.array(shift)
    after = cv2.warpAffine(image, np.hstack([A, b[:, None]]), (width, height), borderMode=cv2.BORDER_REFLECT)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    flow = np.stack([A[0, 0] * u + b[0] - u, A[1, 1] * v + b[1] - v], axis=-1).astype(np.float32)
    return image, after, flow


def shuffled(flow: np.ndarray, seed: int = 0) -> np.ndarray:
    """Every pixel given another pixel's flow."""
    height, width = flow.shape[:2]
    order = np.random.default_rng(seed).permutation(height * width)
    return flow.reshape(-1, 2)[order].reshape(height, width, 2)


# ----------------------------------------------------------------------------- one pair
def test_a_whole_pixel_shift_gives_closed_form_errors():
    image, after, flow = ramp_pair(shift=(3, 2))
    right = check_pair(image, after, flow, flow)
    assert right.still_error == pytest.approx(3 + 2 * 2, abs=1e-4)  # every pixel moved by 3 + 2 * 2 levels
    assert right.flow_error == pytest.approx(0, abs=1e-4) and right.rigid_error == pytest.approx(0, abs=1e-4)
    assert right.flow_explains and right.rigid_explains
    assert right.in_view == pytest.approx((64 - 3) * (48 - 2) / (64 * 48))  # the last 3 columns, 2 rows leave
    assert (right.flow_rigid_median_px, right.flow_rigid_p95_px, right.flow_rigid_within) == (0, 0, 1)
    zero = check_pair(image, after, np.zeros_like(flow))
    assert zero.flow_error == pytest.approx(7, abs=1e-4) and zero.in_view == 1
    assert not zero.flow_explains  # a tie with no motion explains nothing


def test_zero_and_shuffled_flow_are_flagged_ground_truth_passes():
    image, after, flow = zoom_pair()
    right = check_pair(image, after, flow, flow)
    assert right.flow_explains and right.rigid_explains
    assert right.flow_error < 0.25 * right.still_error  # two bilinear resamplings are all that is left
    zero = check_pair(image, after, np.zeros_like(flow), flow)
    assert not zero.flow_explains and zero.rigid_explains
    mixed = check_pair(image, after, shuffled(flow), flow)
    assert not mixed.flow_explains and mixed.rigid_explains
    assert mixed.flow_rigid_median_px > AGREE_PX and mixed.flow_rigid_within < 0.5
    bad_rigid = check_pair(image, after, flow, np.zeros_like(flow))  # depth + pose that see no motion
    assert bad_rigid.flow_explains and not bad_rigid.rigid_explains


def test_flow_rigid_distance_in_input_pixels_and_a_reduced_size():
    image, after, flow = ramp_pair(96, 128, shift=(4, 2))
    rigid = flow.copy()
    rigid[..., 0] += 1  # 1 array pixel along u
    assert check_pair(image, after, flow, rigid, units=(3.0, 2.0)).flow_rigid_median_px == pytest.approx(3)
    rigid = flow.copy()
    rigid[..., 1] -= 2  # 2 array pixels along v = 4 input pixels: none agree within 3
    at = check_pair(image, after, flow, rigid, units=(3.0, 2.0))
    assert (at.flow_rigid_median_px, at.flow_rigid_p95_px, at.flow_rigid_within) == pytest.approx((4, 4, 0))
    # checked at half the size, distances still in the given arrays' pixels
    rigid = flow.copy()
    rigid[..., 0] += 2
    half = check_pair(image, after, flow, rigid, size=(48, 64))
    assert half.flow_rigid_median_px == pytest.approx(2) and half.flow_rigid_within == 1
    assert half.flow_explains and half.flow_error == pytest.approx(0, abs=1e-3)  # a 2, 1 px shift at half size


def test_a_flow_that_leaves_the_image_or_is_not_finite_explains_nothing():
    image, after, flow = ramp_pair()
    for value in (math.nan, math.inf, 1e6):
        bad = np.full_like(flow, value)
        result = check_pair(image, after, bad, flow)
        assert result.in_view == 0 and not result.flow_explains and not result.rigid_explains
        assert result.as_dict()["flow_error"] is None and result.as_dict()["flow_explains"] is False
    with pytest.raises(ValueError, match="flow"):
        check_pair(image, after, flow[:, :-1])


# ----------------------------------------------------------------------------- a sequence
def test_sequence_summary_counts_and_words():
    good = FrameCheck(still_error=8.0, flow_error=2.0, in_view=0.9, rigid_error=4.0, flow_rigid_within=0.75)
    bad_flow = FrameCheck(still_error=2.0, flow_error=20.0, in_view=0.8, rigid_error=1.0, flow_rigid_within=0.25)
    both_bad = FrameCheck(still_error=1.0, flow_error=1.0, in_view=1.0, rigid_error=3.0, flow_rigid_within=0.5)
    mostly_bad = SequenceCheck.from_checks([good, bad_flow, both_bad])
    assert (mostly_bad.pairs, mostly_bad.flow_no_better, mostly_bad.rigid_no_better) == (3, 2, 1)
    assert (mostly_bad.median_still_error, mostly_bad.median_flow_error, mostly_bad.median_flow_rigid_within) == (
        2.0,
        2.0,
        0.5,
    )
    assert mostly_bad.trivial_wins and "no better than no motion on 2 of 3 pairs" in mostly_bad.line()
    warning = mostly_bad.warning()
    assert warning is not None and "\n" not in warning and "flow explains" in warning and "rigid" not in warning
    assert SequenceCheck.from_dict(json.loads(json.dumps(mostly_bad.as_dict()))) == mostly_bad
    mostly_good = SequenceCheck.from_checks([good, good, bad_flow])
    assert not mostly_good.trivial_wins and mostly_good.warning() is None
    flow_only = SequenceCheck.from_checks([FrameCheck(still_error=3.0, flow_error=4.0, in_view=1.0)])
    assert flow_only.rigid_no_better is None and flow_only.trivial_wins and "rigid" not in flow_only.line()


# ----------------------------------------------------------------------------- real frames
@pytest.mark.parametrize("first", [0, 70])  # moving, and nearly stopped (the frame 70 -> 71)
def test_dis_flow_passes_on_real_kitti_frames(realdata, first):
    frames = sorted((realdata / KITTI_RAW / "image_02" / "data").glob("*.png"))
    image, after = rgb(frames[first]), rgb(frames[first + 1])
    flow = dis_flow("medium")([image, after])
    checked = check_pair(image, after, flow, size=(128, 416))
    assert checked.flow_explains and checked.in_view > 0.9
    assert not check_pair(image, after, np.zeros_like(flow), size=(128, 416)).flow_explains


# ----------------------------------------------------------------------------- the runtime carries it
@pytest.fixture(scope="module")
def predictor():
    return geonet_infer.load()


def test_predict_sequence_checks_every_pair_at_the_graph_size(predictor):
    frames = FRAMES[:5]  # 416 x 128, the graphs' size: the check sees the frames and flows returned
    seq = predictor.predict_sequence(frames, read_camera(SAMPLE_CALIB))
    assert [f.check is None for f in seq.frames] == [False] * 4 + [True]
    for frame, path, after in zip(seq.frames, frames, frames[1:]):
        expected = check_pair(rgb(path).astype(np.float32), rgb(after).astype(np.float32), frame.flow, frame.rigid_flow)
        for key, value in expected.as_dict().items():
            assert frame.check.as_dict()[key] == pytest.approx(value, abs=2e-3), (frame.name, key)
    summed = seq.check
    assert summed is not None and summed.pairs == 4
    assert summed.flow_no_better == sum(not f.check.flow_explains for f in seq.frames[:4])
    unchecked = predictor.predict_sequence(frames[:2], read_camera(SAMPLE_CALIB), check=False)
    assert unchecked.check is None and all(f.check is None for f in unchecked.frames)


def run_predict(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_predict_writes_the_check_into_summary_and_its_closing_line(tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in FRAMES[:5]:
        shutil.copyfile(f, folder / f.name)
    out = tmp_path / "out"
    rc, stdout, stderr = run_predict(capsys, "predict", folder, "--out", out, "--calib", SAMPLE_CALIB, "--no-progress")
    assert rc == 0, stderr
    check = json.loads((out / "summary.json").read_text())["check"]
    assert [p["frame"] for p in check["per_pair"]] == [p.stem for p in FRAMES[:4]]
    assert check["pairs"] == 4 and check["size"] == [128, 416] and check["agree_px"] == AGREE_PX
    assert check["flow_no_better"] == sum(not p["flow_explains"] for p in check["per_pair"])
    assert check["rigid_no_better"] == sum(not p["rigid_explains"] for p in check["per_pair"])
    assert f"no better than no motion on {check['flow_no_better']} of 4 pairs" in stdout
    assert ("explains the next frame no better than no motion at all" in stderr) == check["trivial_wins"]
    assert " check " in stdout or " workers_check " in stdout  # its cost, in the stage table (throughput: apart)

    lean = tmp_path / "lean"
    rc, stdout, stderr = run_predict(
        capsys, "predict", folder, "--out", lean, "--calib", SAMPLE_CALIB, "--no-progress", "--no-check", "--no-vis"
    )
    assert rc == 0, stderr
    assert json.loads((lean / "summary.json").read_text())["check"] is None
    assert "check:" not in stdout and "no motion" not in stderr
