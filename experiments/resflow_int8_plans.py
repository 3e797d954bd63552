"""Which parts of the shipped ResFlowNet must stay FP32 in its INT8 graph, now that it is a direct flow net?
(issue 54, point 3: its FP32 input layer and two finest decoder levels are most of its INT8 time.)

The shipped model's FP32 ResFlowNet is quantised again with each plan below, calibrated exactly as the
shipped INT8 graph was (the first 40 frames of data/synth40/seq_0000, percentile, the op types of the
scripts: Conv, Relu, Add, MaxPool); each variant is the shipped model directory with that INT8 ResFlowNet.
Per variant: the INT8 ResFlowNet's graph time on onnxruntime and OpenVINO (one ``geonet-infer bench`` run
each, one thread) and the INT8 flow against FP32 on the held-out synthetic sequences (stride 2, as the
manifest's ``accuracy_delta``) and on the KITTI 2015 pair 000010 (the INT8 rule's pair). The KITTI raw
drive, the test set, is not read.

    python -m experiments.resflow_int8_plans --json docs/resflow_int8_plans.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

from experiments.graph_bench import bench_graphs_json
from experiments.shipped_variants import PREPARED, REPO, SYNTH, quantize_into, shipped_calibration
from geonet_infer import conventions
from geonet_infer.convert import quantize as qz
from geonet_infer.core.predictor import Predictor
from geonet_infer.eval import evaluation
from geonet_infer.eval.adapters import model_flow_fn
from geonet_infer.eval.datasets import load_dataset
from geonet_infer.models.manifest import file_sha256

KITTI_2015 = REPO.parent / "shared" / "realdata" / "kitti2015_flow_000010"
# no calibration in the extract: KITTI 2011_09_26's P_rect_02, as the INT8 rule and benchmarks/eval_all.py assume
KITTI_2015_K = conventions.kitti_like_K(conventions.KITTI_HEIGHT, conventions.KITTI_WIDTH)
SHIPPED = qz.PLANS["resflownet"]
PLANS = {
    "shipped: input layer + 2 finest levels + output layer FP32": SHIPPED,
    "input layer + finest level + output layer FP32": qz.GraphPlan(
        float_output_layer=True, float_input_layer=True, float_finest_levels=1, equalize_concats=True
    ),
    "input layer + output layer FP32": qz.GraphPlan(
        float_output_layer=True, float_input_layer=True, float_finest_levels=0, equalize_concats=True
    ),
    "input layer FP32 only": qz.GraphPlan(float_input_layer=True, equalize_concats=True),
    # the op types quantised (Conv, Relu, Add, MaxPool) leave a direct ResFlowNet's photometric error FP32
    # anyway: its "input layer" is then its first convolution
    "2 finest levels + output layer FP32 (first convolution INT8)": qz.GraphPlan(
        float_output_layer=True, float_finest_levels=2, equalize_concats=True
    ),
    "output layer FP32 only (first convolution INT8)": qz.GraphPlan(float_output_layer=True, equalize_concats=True),
}


def variant(shipped: Path, plan: qz.GraphPlan, feeds: list[dict], out: Path) -> Path:
    """The shipped model directory with its INT8 ResFlowNet quantised by ``plan``."""
    shutil.copytree(shipped, out)
    quantize_into(out, "resflownet", plan, feeds)
    return out


def graph_ms(model: Path) -> dict[str, float]:
    """p50 ms of the INT8 ResFlowNet graph on each engine, one thread."""
    rows = bench_graphs_json(model, "resflow", "int8", "onnxruntime,openvino", threads=1)["results"]
    return {row["backend"]: row["p50_ms"] for row in rows}


def flow_epe(model: Path, precision: str) -> dict[str, float]:
    from training.evaluate import evaluate_flow, heldout_sequences

    predictor = Predictor(model, precision)
    synth = evaluate_flow(model_flow_fn(predictor), SYNTH, heldout_sequences(PREPARED), 2)
    kitti_pair = load_dataset("flow", KITTI_2015)
    kitti = evaluation.evaluate_flow(model_flow_fn(predictor), kitti_pair, intrinsics=KITTI_2015_K)
    return {"synthetic held-out EPE-noc": synth["noc"]["epe"], "KITTI 2015 000010 EPE-noc": kitti["metrics"]["epe_noc"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write the result here too")
    args = parser.parse_args(argv)
    shipped, feeds = shipped_calibration()
    fp32 = flow_epe(shipped, "fp32")
    result: dict = {"fp32": fp32, "calibration_inputs": len(feeds), "plans": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, plan) in enumerate(PLANS.items()):
            model = variant(shipped, plan, feeds, Path(tmp) / f"plan{i}")
            int8 = flow_epe(model, "int8")
            result["plans"][name] = {
                "int8": int8,
                "int8_vs_fp32": {k: int8[k] / fp32[k] - 1 for k in fp32},
                "graph_ms_one_thread": graph_ms(model),
                "int8_file_mib": (model / "int8" / "resflownet.onnx").stat().st_size / 2**20,
                "same_as_shipped_int8": file_sha256(model / "int8" / "resflownet.onnx")
                == file_sha256(shipped / "int8" / "resflownet.onnx"),
            }
            print(name, json.dumps(result["plans"][name]), flush=True)
    print("| plan | synthetic EPE-noc vs FP32 | KITTI 2015 EPE-noc vs FP32 | onnxruntime ms | OpenVINO ms |")
    print("|---|---|---|---|---|")
    for name, row in result["plans"].items():
        d, ms = row["int8_vs_fp32"], row["graph_ms_one_thread"]
        print(
            f"| {name} | {d['synthetic held-out EPE-noc']:+.1%} | {d['KITTI 2015 000010 EPE-noc']:+.1%} "
            f"| {ms.get('onnxruntime', float('nan')):.2f} | {ms.get('openvino', float('nan')):.2f} |"
        )
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
