"""``geonet-infer info``: versions, CPU and threads, and a model's manifest summary."""

from __future__ import annotations

import argparse
import json
import platform
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from geonet_infer import __version__
from geonet_infer.engines import check_graphs, openvino_version, usable_cpus
from geonet_infer.manifest import ModelCard, load_manifest
from geonet_infer.models import DEFAULT_MODEL, bundled_models, resolve_model
from geonet_infer.predictor import RIGID_FLOW_GRAPHS, TASK_GRAPHS, missing_graphs


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "info",
        help="versions, CPU, threads and the model's manifest",
        description="Print versions, onnxruntime providers, the CPU and the threads "
        "geonet-infer would use, and a summary of a model's manifest.",
    )
    parser.add_argument(
        "--model", default=None, help=f"bundled model name or model directory (default: {DEFAULT_MODEL!r})"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(run=run)


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def environment() -> dict:
    return {
        "geonet_infer": __version__,
        "python": platform.python_version(),
        "onnxruntime": ort.__version__,
        "openvino": openvino_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "providers": ort.get_available_providers(),
        "platform": platform.platform(),
        "cpu": cpu_model(),
        "usable_cpus": usable_cpus(),
        "default_threads": usable_cpus(),
        "bundled_models": list(bundled_models()),
    }


def model_summary(model) -> dict:
    manifest = load_manifest(resolve_model(model))
    check_graphs(manifest)  # what the Predictor would refuse at load, info refuses too
    graphs = {
        p: {
            name: {
                "file": g.file,
                "sha256": g.sha256[:16],
                "opset": g.opset,
                "mib": round((manifest.root / g.file).stat().st_size / 2**20, 2),
            }
            for name, g in manifest.graphs[p].items()
        }
        for p in manifest.graphs
    }
    prov = manifest.provenance
    present = manifest.graph_names("fp32")
    tasks = {}
    for task, needed in TASK_GRAPHS.items():
        missing = missing_graphs(task, present)
        tasks[task] = {"available": not missing, "graphs": list(needed), "missing": list(missing)}
    return {
        "dir": str(manifest.root),
        "arch": manifest.arch,
        "size": [manifest.height, manifest.width],
        "seq_length": manifest.seq_length,
        "random_init": manifest.random_init,
        "precisions": list(manifest.graphs),
        "graphs": graphs,
        "tasks": tasks,
        "provenance": {
            "checkpoint_stage": prov.checkpoint_stage,
            "checkpoint_step": prov.checkpoint_step,
            "training_command": prov.training_command,
            "data_dir": prov.data_dir,
            "git_commit": prov.git_commit,
            "export_date": prov.export_date,
        },
        "metrics": manifest.metrics,
        "model_card": card_summary(manifest.model_card),
        "int8_accuracy_delta": manifest.quantization.accuracy_delta if manifest.quantization else None,
    }


NOT_MEASURED = "not measured"


def card_summary(card: ModelCard | None) -> dict:
    """What the model was trained on and its measured scores (from the model card), or "not measured"."""
    if card is None:
        return {"trained_on": "not recorded", "real": NOT_MEASURED, "synthetic": NOT_MEASURED, "measured_in": None}
    scores = {
        key: [{**asdict(s), "verdict": s.verdict} for s in getattr(card, key)] or NOT_MEASURED
        for key in ("real", "synthetic")
    }
    return {
        "trained_on": card.trained_on,
        "synthetic_only": card.synthetic_only,
        **scores,
        "measured_in": card.measured_in,
    }


def _score_text(s: dict) -> str:
    return (
        f"{s['task']} {s['metric']} {s['value']:.3g} vs {s['baseline_value']:.3g} for {s['baseline']} "
        f"({s['verdict']}) on {s['data']}"
    )


def run(args: argparse.Namespace) -> int:
    info = {"environment": environment(), "model": model_summary(args.model)}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    env, model = info["environment"], info["model"]
    print(
        f"geonet-infer {env['geonet_infer']}  python {env['python']}  onnxruntime {env['onnxruntime']}  "
        f"numpy {env['numpy']}  opencv {env['opencv']}"
    )
    print(f"providers: {', '.join(env['providers'])}")
    print(
        f"openvino: {env['openvino']} (--backend openvino|auto)"
        if env["openvino"]
        else "openvino: not installed (pip install 'geonet-infer[openvino]' for --backend openvino|auto)"
    )
    print(f"cpu: {env['cpu']}; usable CPUs {env['usable_cpus']} (default threads per graph)")
    print(f"bundled models: {', '.join(env['bundled_models']) or 'none'}")
    print(f"model: {model['dir']}")
    print(
        f"  arch {model['arch']}, graphs {model['size'][0]}x{model['size'][1]}, snippet {model['seq_length']} "
        f"frames, precisions {', '.join(model['precisions'])}"
        + ("  [RANDOM WEIGHTS: timing only]" if model["random_init"] else "")
    )
    for task, t in model["tasks"].items():
        if t["available"]:
            print(f"  task {task}: yes ({', '.join(t['graphs'])})")
            continue
        line = f"  task {task}: no, missing {', '.join(t['missing'])} (needs {', '.join(t['graphs'])})"
        if task == "flow" and all(g not in t["missing"] for g in RIGID_FLOW_GRAPHS):
            line += "; the Python API's Predictor.flow gives rigid flow only"
        print(line)
    for precision, graphs in model["graphs"].items():
        for name, g in graphs.items():
            print(f"  {precision:5s} {name:11s} {g['file']:24s} {g['mib']:6.2f} MiB  sha256 {g['sha256']}")
    prov = model["provenance"]
    if prov["training_command"]:
        print(f"  trained: stage {prov['checkpoint_stage']} step {prov['checkpoint_step']}: {prov['training_command']}")
    for key, value in (model["metrics"] or {}).items():
        print(f"  metric {key}: {value}")
    card = model["model_card"]
    print(f"  trained on: {card['trained_on']}")
    for key, label in (("real", "real-data"), ("synthetic", "synthetic")):
        if card[key] == NOT_MEASURED:
            print(f"  {label} scores: {NOT_MEASURED}")
        for s in [] if card[key] == NOT_MEASURED else card[key]:
            print(f"  {label} score: {_score_text(s)} ({card['measured_in']})")
    return 0
