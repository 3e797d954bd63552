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
from geonet_infer.engines import (
    BACKENDS,
    ENGINES,
    REFERENCE_MARGIN,
    OpenVinoEngine,
    OrtEngine,
    make_engine,
    pick_fastest,
    timing_feeds,
    usable_cpus,
)
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
    return geonet_infer.load(precision="fp32").predict_sequence(frames, camera=camera)


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
    ov = predictor.predict_sequence(frames, camera=camera)
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
    engine = predictor.graph_set.engine("depthnet")
    assert sorted(k[0][0] for k in engine._compiled) == [1, 3]


@needs_openvino
def test_openvino_in_throughput_mode_runs_one_stream_per_worker_and_keeps_the_results(sequence, ort_fp32):
    """Throughput mode calls a graph from several threads at once: OpenVINO needs a stream for each (with one,
    the calls wait for each other), each stream one thread."""
    frames, camera = sequence
    workers = min(2, usable_cpus())
    predictor = geonet_infer.load(precision="fp32", backend="openvino", mode="throughput", threads=workers)
    predictor.predict_sequence(frames, camera=camera)  # compiles
    props = predictor.graph_set.engine("depthnet").describe()["properties"]
    assert (props["NUM_STREAMS"], props["INFERENCE_NUM_THREADS"]) == (str(workers), str(workers))
    _assert_close(
        ort_fp32, predictor.predict_sequence(frames, camera=camera), depth_rtol=1e-4, flow_atol=1e-2, pose_atol=1e-5
    )


@needs_openvino
def test_auto_picks_one_engine_per_graph_and_keeps_the_results(sequence, ort_fp32):
    frames, camera = sequence
    predictor = geonet_infer.load(precision="fp32", backend="auto")
    assert set(predictor.engines) == set(predictor.graphs)
    for name, choice in predictor.backend_choice.items():
        assert choice["chosen"] == predictor.engines[name] in ENGINES
        timings = choice["min_ms_batch1"]
        best = min(timings.values())
        # the fastest, or the reference (onnxruntime) when nothing beats it by more than the margin
        assert timings[choice["chosen"]] == best or (
            choice["chosen"] == "onnxruntime" and best > (1 - REFERENCE_MARGIN) * timings["onnxruntime"]
        )
    _assert_close(
        ort_fp32, predictor.predict_sequence(frames, camera=camera), depth_rtol=1e-4, flow_atol=1e-2, pose_atol=1e-5
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
    _assert_close(ort_fp32, predictor.predict_sequence(frames, camera=camera), 1e-6, 1e-5, 1e-7)


def test_the_registry_drives_the_cli_choices():
    import argparse

    from geonet_infer.cli.common import add_model_args

    assert BACKENDS == (*ENGINES, "auto")
    parser = argparse.ArgumentParser()
    add_model_args(parser)
    backend = next(a for a in parser._actions if a.dest == "backend")
    assert tuple(backend.choices) == BACKENDS and backend.default == next(iter(ENGINES))
    for cls in ENGINES.values():
        assert cls.name in backend.help and isinstance(cls.available(), bool) and cls.install_hint


class _FakeEngine:
    """A third engine for the registry tests: onnxruntime under another name."""

    name = "fake"
    summary = "fake (tests only)"
    requires = "nothing"
    install_hint = "nothing to install"

    @staticmethod
    def available() -> bool:
        return True

    @staticmethod
    def version() -> str | None:
        return "0"

    def __init__(self, path, threads, streams=1):
        self.ort = OrtEngine(path, threads)
        self.input_names, self.output_names = self.ort.input_names, self.ort.output_names

    def run(self, feeds):
        return self.ort.run(feeds)

    def io(self):
        return self.ort.io()

    def input_shapes(self):
        return self.ort.input_shapes()

    def describe(self):
        return {"engine": self.name}


def test_an_engine_registered_in_engines_is_offered_by_make_engine_and_auto(monkeypatch):
    model = geonet_infer.models.resolve_model(None)
    monkeypatch.setitem(ENGINES, _FakeEngine.name, _FakeEngine)
    engine = make_engine(model / "depthnet.onnx", "fake", threads=1)
    assert isinstance(engine, _FakeEngine) and engine.describe() == {"engine": "fake"}
    monkeypatch.setattr(OpenVinoEngine, "available", staticmethod(lambda: False))
    chosen, record = pick_fastest(model / "depthnet.onnx", threads=1)
    assert set(record["min_ms_batch1"]) == set(record["p50_ms_batch1"]) == {"onnxruntime", "fake"}
    assert record["skipped"] == ["openvino not installed"] and chosen.name == record["chosen"]
    with pytest.raises(GeoNetError, match="unknown backend 'cuda'"):
        make_engine(model / "depthnet.onnx", "cuda", threads=1)


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
