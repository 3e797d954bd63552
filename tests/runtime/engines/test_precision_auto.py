"""`--precision auto` (issue 45): per graph, the fastest of the model's precisions that is exact on
this CPU, timed at load. The timings are replaced by fixed numbers here (speed is measured in
`experiments/precision_auto.py`, never asserted), so the choice itself is what is tested."""

from __future__ import annotations

import numpy as np
import pytest

import geonet_infer
import geonet_infer.engines as engines
from geonet_infer import GeoNetError
from geonet_infer.core import int8_safety
from geonet_infer.engines import OpenVinoEngine
from geonet_infer.io import read_camera
from geonet_infer.io.images import list_images
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

HAVE_OPENVINO = OpenVinoEngine.available()
needs_openvino = pytest.mark.skipif(not HAVE_OPENVINO, reason="the [openvino] extra is not installed")


def _fake_timings(monkeypatch, ms: dict[str, float]):
    """Make every load-time timing report ``ms[label]`` (labels as pick_fastest makes them)."""
    timed: list[list[str]] = []

    def fake_time_interleaved(cases, **_):
        timed.append([c.name for c in cases])
        for case in cases:
            case.samples_ns = [int(ms[case.name] * 1e6)] * 8
        return cases

    monkeypatch.setattr(engines, "time_interleaved", fake_time_interleaved)
    return timed


@pytest.fixture(scope="module")
def sequence():
    return list_images(SAMPLE_FRAMES)[:4], read_camera(SAMPLE_CALIB)


def test_auto_takes_int8_where_it_is_faster_and_fp32_where_it_is_not(monkeypatch, sequence):
    timed = _fake_timings(monkeypatch, {"onnxruntime fp32": 10.0, "onnxruntime int8": 12.0})
    predictor = geonet_infer.load(precision="auto", backend="onnxruntime", threads=1)
    assert {n: r["precision"] for n, r in predictor.graph_set.runs.items()} == dict.fromkeys(predictor.graphs, "fp32")
    # the rigid-flow op has one file in both sets: nothing to choose, nothing timed
    assert len(timed) == 3 and all(t == ["onnxruntime fp32", "onnxruntime int8"] for t in timed)
    assert "rigidflow" not in predictor.backend_choice

    _fake_timings(monkeypatch, {"onnxruntime fp32": 10.0, "onnxruntime int8": 4.0})
    auto = geonet_infer.load(precision="auto", backend="onnxruntime", threads=1)
    runs = {n: r["precision"] for n, r in auto.graph_set.runs.items()}
    assert runs == {"depthnet": "int8", "posenet": "int8", "rigidflow": "fp32", "resflownet": "int8"}
    # the graphs that run are the INT8 set's: the outputs are those of --precision int8
    frames, camera = sequence
    int8 = geonet_infer.load(precision="int8", threads=1).predict_sequence(frames, camera=camera)
    got = auto.predict_sequence(frames, camera=camera)
    np.testing.assert_array_equal(int8.depth, got.depth)
    np.testing.assert_array_equal(int8.flow, got.flow)
    np.testing.assert_array_equal(int8.trajectory, got.trajectory)


@needs_openvino
def test_auto_never_takes_an_int8_engine_that_saturates_on_this_cpu(monkeypatch, capsys):
    # an AVX2-only CPU: OpenVINO's INT8 adds u8 x s8 products in saturating int16 pairs, and the
    # bundled graphs have weights beyond +-64 (manifest quantization.int8_kernels)
    monkeypatch.setattr(int8_safety, "cpu_info", lambda: {"int8_kernel": "avx2"})
    timed = _fake_timings(
        monkeypatch, {"onnxruntime fp32": 10.0, "openvino fp32": 6.0, "onnxruntime int8": 9.0, "openvino int8": 2.0}
    )
    predictor = geonet_infer.load(precision="auto", backend="auto", threads=1)
    for name in ("depthnet", "posenet", "resflownet"):
        run = predictor.graph_set.runs[name]
        assert (run["engine"], run["precision"]) == ("openvino", "fp32")  # fastest EXACT choice
        assert "skipped openvino int8: openvino INT8 without VNNI" in run["why"]
        assert predictor.backend_choice[name]["skipped"] == [f"openvino int8: {run['why'].split(': ', 2)[-1]}"]
    assert all("openvino int8" not in labels for labels in timed)
    assert "warning" not in capsys.readouterr().err  # auto says it in the record, not on stderr

    # on a CPU with VNNI, the same timings take OpenVINO's INT8
    monkeypatch.setattr(int8_safety, "cpu_info", lambda: {"int8_kernel": "avx512_vnni"})
    predictor = geonet_infer.load(precision="auto", backend="auto", threads=1)
    assert (predictor.graph_set.runs["depthnet"]["engine"], predictor.graph_set.runs["depthnet"]["precision"]) == (
        "openvino",
        "int8",
    )


def test_auto_never_beats_fp32_by_choosing_something_slower(monkeypatch):
    """The choice is the minimum of what was timed, and FP32 is always timed."""
    _fake_timings(monkeypatch, {"onnxruntime fp32": 7.0, "onnxruntime int8": 7.5})
    predictor = geonet_infer.load(precision="auto", backend="onnxruntime", threads=1)
    for name, choice in predictor.backend_choice.items():
        timings = choice["min_ms_batch1"]
        assert "onnxruntime fp32" in timings
        assert timings[f"{choice['chosen']} {choice['precision']}"] == min(timings.values())
        assert predictor.graph_set.runs[name]["precision"] == "fp32"


def test_a_tie_within_timing_noise_keeps_fp32(monkeypatch):
    _fake_timings(monkeypatch, {"onnxruntime fp32": 10.0, "onnxruntime int8": 9.6})  # 4 % faster: noise
    runs = geonet_infer.load(precision="auto", backend="onnxruntime", threads=1).graph_set.runs
    assert {runs[n]["precision"] for n in ("depthnet", "posenet", "resflownet")} == {"fp32"}
    _fake_timings(monkeypatch, {"onnxruntime fp32": 10.0, "onnxruntime int8": 9.0})  # 10 % faster
    runs = geonet_infer.load(precision="auto", backend="onnxruntime", threads=1).graph_set.runs
    assert {runs[n]["precision"] for n in ("depthnet", "posenet", "resflownet")} == {"int8"}


def test_unknown_precision_names_auto_among_the_choices():
    with pytest.raises(GeoNetError, match="unknown precision 'int4'.*fp32, int8, auto"):
        geonet_infer.load(precision="int4")


def test_predict_precision_auto_records_each_graphs_choice(monkeypatch, tmp_path, capsys):
    import json
    import shutil

    from geonet_infer.cli import main

    _fake_timings(monkeypatch, {"onnxruntime fp32": 10.0, "onnxruntime int8": 4.0})
    out = tmp_path / "out"
    frames = tmp_path / "frames"
    frames.mkdir()
    for f in list_images(SAMPLE_FRAMES)[:3]:
        shutil.copy(f, frames)
    argv = ["predict", frames, "--out", out, "--calib", SAMPLE_CALIB, "--precision", "auto", "--no-progress"]
    assert main([str(a) for a in argv]) == 0, capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["model"]["precision"] == "auto"
    graphs = summary["model"]["graphs"]
    assert graphs["depthnet"]["precision"] == "int8" and graphs["rigidflow"]["precision"] == "fp32"
    assert graphs["depthnet"]["why"].startswith("auto: fastest exact engine and precision at load")
