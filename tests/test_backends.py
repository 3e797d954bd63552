"""Engines behind the Predictor: onnxruntime, OpenVINO (optional extra) and "auto".

OpenVINO is a second, independent implementation of the same ONNX graphs, so
agreement with onnxruntime on fp32 checks both engines' wiring (input order,
output names, batch reshapes) against each other.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

import geonet_infer
from geonet_infer import GeoNetError
from geonet_infer.engines import ENGINES, OpenVinoEngine, OrtEngine, timing_feeds
from geonet_infer.io import read_camera
from geonet_infer.io.images import list_images
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

try:
    import openvino  # noqa: F401 -- a third-party optional extra, not a module of this repo

    HAVE_OPENVINO = True
except ImportError:
    HAVE_OPENVINO = False
needs_openvino = pytest.mark.skipif(not HAVE_OPENVINO, reason="the [openvino] extra is not installed")


@pytest.fixture(scope="module")
def sequence():
    return list_images(SAMPLE_FRAMES)[:5], read_camera(SAMPLE_CALIB)


@pytest.fixture(scope="module")
def ort_fp32(sequence):
    frames, camera = sequence
    return geonet_infer.load(precision="fp32").predict_sequence(frames, K=camera)


def _assert_close(a, b, depth_rtol: float, flow_atol: float, pose_atol: float):
    rel = np.abs(a.depth - b.depth) / a.depth
    assert float(rel.max()) < depth_rtol
    assert float(np.abs(a.flow - b.flow).max()) < flow_atol
    assert float(np.abs(a.trajectory - b.trajectory).max()) < pose_atol


@needs_openvino
def test_openvino_fp32_equals_onnxruntime(sequence, ort_fp32):
    frames, camera = sequence
    predictor = geonet_infer.load(precision="fp32", backend="openvino")
    assert set(predictor.engines.values()) == {"openvino"}
    ov = predictor.predict_sequence(frames, K=camera)
    # f32 both sides; differences are summation order only
    _assert_close(ort_fp32, ov, depth_rtol=1e-4, flow_atol=1e-2, pose_atol=1e-5)


@needs_openvino
def test_openvino_compiles_each_batch_size_once(sequence):
    frames, camera = sequence
    predictor = geonet_infer.load(precision="fp32", backend="openvino")
    one = [predictor.depth(f).depth for f in frames[:3]]
    batched = predictor.depth(frames[:3])
    for single, result in zip(one, batched):
        np.testing.assert_allclose(result.depth, single, rtol=1e-4)
    engine = predictor.engine("depthnet")
    assert sorted(k[0][0] for k in engine._compiled) == [1, 3]


@needs_openvino
def test_auto_picks_one_engine_per_graph_and_keeps_the_results(sequence, ort_fp32):
    frames, camera = sequence
    predictor = geonet_infer.load(precision="fp32", backend="auto")
    assert set(predictor.engines) == set(predictor.graphs)
    for name, choice in predictor.backend_choice.items():
        assert choice["chosen"] == predictor.engines[name] in ENGINES
        timings = choice["p50_ms_batch1"]
        assert timings[choice["chosen"]] == min(timings.values())
    _assert_close(
        ort_fp32, predictor.predict_sequence(frames, K=camera), depth_rtol=1e-4, flow_atol=1e-2, pose_atol=1e-5
    )


def test_unknown_backend_is_refused():
    with pytest.raises(GeoNetError, match="unknown backend 'cuda'.*onnxruntime, openvino, auto"):
        geonet_infer.load(backend="cuda")


def test_missing_openvino_is_a_clear_error_and_auto_falls_back(monkeypatch, sequence, ort_fp32):
    monkeypatch.setitem(sys.modules, "openvino", None)  # makes `import openvino` raise ImportError
    with pytest.raises(GeoNetError, match=r"pip install 'geonet-infer\[openvino\]'"):
        geonet_infer.load(backend="openvino")
    predictor = geonet_infer.load(backend="auto")
    assert set(predictor.engines.values()) == {"onnxruntime"}
    assert all(c["reason"] == "openvino not installed" for c in predictor.backend_choice.values())
    frames, camera = sequence
    _assert_close(ort_fp32, predictor.predict_sequence(frames, K=camera), 1e-6, 1e-5, 1e-7)


def test_timing_feeds_follow_the_graph_inputs():
    model = geonet_infer.models.resolve_model(None)
    engine = OrtEngine(model / "rigidflow.onnx", threads=1)
    feeds = timing_feeds(engine)
    assert {k: v.shape for k, v in feeds.items()} == {
        "depth": (1, 1, 128, 416),
        "pose": (1, 6),
        "intrinsics": (1, 3, 3),
        "target": (1, 3, 128, 416),
        "source": (1, 3, 128, 416),
    }
    assert feeds["intrinsics"][0, 0, 2] == 208 and feeds["intrinsics"][0, 1, 2] == 64
    flow = engine.run(feeds)["rigid_flow"]
    assert np.abs(flow).max() < 1e-3  # zero pose: no rigid flow


@needs_openvino
def test_openvino_engine_names_an_unreadable_file(tmp_path):
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"not a protobuf")
    with pytest.raises(GeoNetError, match="broken.onnx"):
        OpenVinoEngine(bad, threads=1)


@needs_openvino
def test_bench_times_each_backend_and_records_the_engines(capsys, tmp_path):
    from geonet_infer.cli import main

    out = tmp_path / "bench.json"
    rc = main(
        [
            "bench",
            "--backend",
            "onnxruntime,openvino,auto",
            "--precision",
            "fp32",
            "--tasks",
            "depth,flow",
            "--iters",
            "2",
            "--warmup",
            "1",
            "--rewarm-ms",
            "0",
            "--quiet",
            "--json",
            str(out),
        ]
    )
    capsys.readouterr()
    assert rc == 0
    import json

    data = json.loads(out.read_text())
    assert {(r["backend"], r["task"]) for r in data["results"]} == {
        (b, t) for b in ("onnxruntime", "openvino", "auto") for t in ("depth", "flow")
    }
    engines = data["environment"]["engines"]
    assert {e["engine"] for e in engines["openvino/fp32"].values()} == {"openvino"}
    assert "float32" in engines["openvino/fp32"]["depthnet"]["properties"]["INFERENCE_PRECISION_HINT"]
    assert all("auto" in e for e in engines["auto/fp32"].values())
