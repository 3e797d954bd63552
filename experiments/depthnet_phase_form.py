"""DepthNet's full-resolution decoder level computed at half resolution (the "phase form" of
:mod:`export.phase_form`, how the export writes the small DepthNet since issue 54): does its INT8 graph get
faster, and does its depth stay the same? (issue 54: the networks' time is mostly their 128x416 layers of
1-16 channels, where no engine's int8 kernels get near the peak.)

How the form works: :mod:`export.phase_form`.

Per variant (the shipped weights' DepthNet exported in its trained layout, and in the phase form the export
writes): the graph's time on onnxruntime and OpenVINO
(one thread, FP32 and INT8, one ``geonet-infer bench`` run each, the two models alternating), the
largest difference of the two FP32 graphs' disparities, and the INT8 depth against FP32 on the held-out
synthetic sequences (abs rel, stride 2, as the manifest's ``accuracy_delta``). INT8 is calibrated as the
shipped graph was (the first 40 frames of data/synth40/seq_0000, percentile, the plan of
``quantize.plan_for``); the phase-form variant's graphs must be the shipped ones (GraphProto compared).
The KITTI raw drive, the test set, is not read.

    python -m experiments.depthnet_phase_form --json docs/depthnet_phase_form.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch

from experiments.graph_bench import p50_ms_one_thread
from experiments.shipped_variants import CALIB, PREPARED, SETTINGS, SYNTH, export_variant, shipped_geonet
from export.phase_form import PhaseDepthNet
from export.wrappers import DepthExport
from geonet_infer.convert.frames import depth_feeds, load_frames
from geonet_infer.core.predictor import Predictor
from geonet_infer.core.spec import InputSpec
from geonet_infer.models import resolve_model
from geonet_infer.models.manifest import load_manifest


def same_graph(a: Path, b: Path) -> bool:
    """The two ONNX files hold the same GraphProto (nodes, weights, I/O)."""
    import onnx

    return onnx.load(str(a)).graph.SerializeToString() == onnx.load(str(b)).graph.SerializeToString()


def depth_abs_rel(model: Path, precision: str) -> float:
    """Abs rel of the model's depth on the held-out synthetic sequences, as the manifest's ``accuracy_delta``."""
    from training.evaluate import evaluate_depth, heldout_sequences, onnx_depth_fn

    depth = evaluate_depth(onnx_depth_fn(Predictor(model, precision)), SYNTH, heldout_sequences(PREPARED), 2)
    return depth["model"]["abs_rel"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the result here too")
    parser.add_argument("--rounds", type=int, default=2, help="timing runs per variant, alternating")
    args = parser.parse_args(argv)
    shipped = resolve_model(None)
    spec = load_manifest(shipped)
    model = shipped_geonet()
    frames, _ = load_frames(CALIB, spec.height, spec.width, SETTINGS.max_frames)
    feeds = depth_feeds(frames, InputSpec.from_conventions(spec.height, spec.width, spec.seq_length))
    image = torch.from_numpy(np.concatenate([f["image"] for f in feeds[:4]]))
    phase_net = PhaseDepthNet(model.depth_net).eval()
    with torch.no_grad():
        reference, phased = model.depth_net(image)[0], phase_net(image)[0]
    result: dict = {"torch_max_abs_disparity_difference": float((reference - phased).abs().max())}
    with tempfile.TemporaryDirectory() as tmp:
        variants = {
            name: export_variant(
                shipped, Path(tmp) / str(i), "depthnet", DepthExport(net, model.scale_normalize), feeds
            )
            for i, (name, net) in enumerate((("trained layout", model.depth_net), ("phase form", phase_net)))
        }
        result["phase_form_is_shipped"] = {  # the graphs (the files' metadata say how each was made)
            precision: same_graph(variants["phase form"] / file, shipped / file)
            for precision, file in (("fp32", "depthnet.onnx"), ("int8", "int8/depthnet.onnx"))
        }
        fp32 = {name: Predictor(path, "fp32") for name, path in variants.items()}
        disparities = [np.stack([r.disparity for r in fp32[name].depth(frames[:8])]) for name in variants]
        result["fp32_graphs_max_abs_disparity_difference"] = float(np.abs(disparities[0] - disparities[1]).max())
        for name, path in variants.items():
            result[name] = {p: depth_abs_rel(path, p) for p in ("fp32", "int8")}
            result[name]["int8_vs_fp32"] = result[name]["int8"] / result[name]["fp32"] - 1
        timings: dict[str, list[dict]] = {name: [] for name in variants}
        for _ in range(args.rounds):
            for name, path in variants.items():
                timings[name].append(p50_ms_one_thread(path, "depth"))
        for name in variants:
            result[name]["graph_ms_one_thread"] = {k: min(t[k] for t in timings[name]) for k in timings[name][0]}
        print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
