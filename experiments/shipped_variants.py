"""The bundled model directory with one graph made another way, quantised as the shipped INT8 graphs were:
what the issue-54 model experiments compare against the bundled model (``resflow_int8_plans``,
``depthnet_phase_form``, ``resflow_scale1``). The KITTI raw drive, the test set, is never read here."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch.nn as nn

from geonet_infer.convert import quantize as qz
from geonet_infer.core.predictor import Predictor
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import MANIFEST_NAME, file_sha256, load_manifest

REPO = Path(__file__).resolve().parents[1]
# How the shipped INT8 graphs were calibrated (manifest "quantization"): the first 40 frames of
# data/synth40/seq_0000, percentile, the op types of the scripts
CALIB = REPO / "data" / "synth40" / "seq_0000" / "image"
SETTINGS = qz.QuantSettings(calibrate_method="percentile", max_frames=40, op_types=("Conv", "Relu", "Add", "MaxPool"))
SYNTH, PREPARED = REPO / "data" / "synth40", REPO / "data" / "synth40_prepared"  # the held-out sequences' set
WEIGHTS = REPO / "weights" / "small_synth.pt"  # the shipped model's weights (manifest provenance)


def shipped_geonet() -> nn.Module:
    """The shipped model's trained GeoNet (eval mode), from :data:`WEIGHTS`."""
    from training.checkpoint import load_weights, model_from_checkpoint

    return model_from_checkpoint(load_weights(WEIGHTS)).eval()


def shipped_calibration() -> tuple[Path, list[dict]]:
    """The bundled model directory and its ResFlowNet's INT8 calibration inputs, made as the shipped ones were."""
    shipped = resolve_model(None)
    spec = load_manifest(shipped)
    frames, original = qz.load_frames(CALIB, spec.height, spec.width, SETTINGS.max_frames, min_frames=spec.seq_length)
    K, _ = qz.calibration_intrinsics(CALIB, original, spec.height, spec.width)
    return shipped, qz.resflow_feeds(Predictor(shipped, "fp32"), frames, K)


def quantize_into(model: Path, graph: str, plan: qz.GraphPlan, feeds: list[dict]) -> None:
    """``model``'s FP32 ``graph`` quantised with ``plan`` into its INT8 file; the manifest's sha256 follows."""
    manifest_path = model / MANIFEST_NAME
    manifest = json.loads(manifest_path.read_text())
    entry = manifest["graphs"]["int8"][graph]
    fp32_file = model / manifest["graphs"]["fp32"][graph]["file"]
    qz.quantize_graph(fp32_file, model / entry["file"], feeds, SETTINGS, plan)
    entry["sha256"] = file_sha256(model / entry["file"])
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")


def export_variant(shipped: Path, out: Path, graph: str, module: nn.Module, feeds: list[dict]) -> Path:
    """A copy of ``shipped`` with ``module`` (an ``export.wrappers`` module) as its FP32 ``graph``, quantised
    with the shipped plan (``quantize.plan_for``)."""
    from export.to_onnx import export_graph
    from export.wrappers import example_inputs, io_spec

    shutil.copytree(shipped, out)
    spec = load_manifest(shipped)
    manifest_path = out / MANIFEST_NAME
    manifest = json.loads(manifest_path.read_text())
    fp32_file = out / manifest["graphs"]["fp32"][graph]["file"]
    size = (spec.height, spec.width, spec.seq_length)
    export_graph(module, example_inputs(graph, *size), io_spec(graph, *size), fp32_file)
    manifest["graphs"]["fp32"][graph]["sha256"] = file_sha256(fp32_file)
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
    quantize_into(out, graph, qz.plan_for(graph, spec.arch), feeds)
    return out
