"""The bundled model's graphs are the shipped weights' (issue 60, item 5): ``weights/small_synth.pt`` is the
checkpoint the manifest names by sha256, and exporting it again gives the bundled graphs' outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import geonet_infer
from geonet_infer.io import list_images
from geonet_infer.models import bundled_models
from geonet_infer.models.manifest import file_sha256, load_manifest
from geonet_infer.samples import SAMPLE_FRAMES

WEIGHTS = Path(__file__).resolve().parents[2] / "weights" / "small_synth.pt"


def test_the_manifest_names_the_shipped_weights_by_their_sha256():
    manifest = load_manifest(bundled_models()["small_synth"])
    assert manifest.provenance.checkpoint_sha256 == file_sha256(WEIGHTS)


def test_exporting_the_shipped_weights_again_gives_the_bundled_graphs_outputs(tmp_path):
    from export import ExportConfig, export_model

    bundled = bundled_models()["small_synth"]
    again = export_model(ExportConfig(out=tmp_path / "again", checkpoint=WEIGHTS, quiet=True))
    frames = list_images(SAMPLE_FRAMES)[:3]
    a, b = geonet_infer.load(bundled, precision="fp32"), geonet_infer.load(again, precision="fp32")
    np.testing.assert_allclose(b.depth(frames[0]).depth, a.depth(frames[0]).depth, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.pose(frames).vectors, a.pose(frames).vectors, atol=1e-6)
    K = np.array([[200.0, 0, 208], [0, 200.0, 64], [0, 0, 1]])
    np.testing.assert_allclose(b.flow(frames, K).flow, a.flow(frames, K).flow, atol=1e-4)


def test_the_manifests_int8_accuracy_delta_is_measured_again(tmp_path):
    """The bundled manifest's INT8 - FP32 delta (held-out synthetic sequences 36-39 of the seed-2026 set,
    every second frame) against a fresh measurement: the sequences made again by the deterministic
    generator, the graphs on this machine's engine and INT8 kernels."""
    from training.evaluate import evaluate_depth, evaluate_flow, onnx_depth_fn, onnx_flow_fn
    from training.synth.sequence import write_sequence

    bundled = bundled_models()["small_synth"]
    recorded = load_manifest(bundled).quantization.accuracy_delta
    assert Path(recorded["synth_dir"]).name == "synth40"  # scripts/build_bundled_model.sh: seed 2026, 40 frames
    for name in recorded["sequences"]:
        write_sequence(tmp_path, 2026, int(name.split("_")[1]), 40, 128, 416)
    fresh = {}
    for precision in ("fp32", "int8"):
        predictor = geonet_infer.load(bundled, precision=precision)
        depth = evaluate_depth(onnx_depth_fn(predictor), tmp_path, recorded["sequences"], recorded["stride"])
        flow = evaluate_flow(onnx_flow_fn(predictor), tmp_path, recorded["sequences"], recorded["stride"])
        fresh[precision] = (depth["model"]["abs_rel"], flow["noc"]["epe"])
    for i, key in enumerate(("depth_abs_rel", "flow_epe_noc")):
        for precision in ("fp32", "int8"):
            assert fresh[precision][i] == pytest.approx(recorded[key][precision], rel=1e-4), (key, precision)
        assert fresh["int8"][i] - fresh["fp32"][i] == pytest.approx(recorded[key]["delta"], abs=1e-4), key
