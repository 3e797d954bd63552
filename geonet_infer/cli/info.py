"""``geonet-infer info``: versions, CPU and threads, and a model's manifest summary."""

from __future__ import annotations

import argparse
import json

from geonet_infer.bench.environment import NOT_MEASURED, Environment, model_summary
from geonet_infer.cli import COMMANDS
from geonet_infer.core.predictor import RIGID_FLOW_GRAPHS
from geonet_infer.engines import ENGINES
from geonet_infer.models import DEFAULT_MODEL


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "info",
        help=COMMANDS["info"],
        description="Print versions, onnxruntime providers, the CPU and the threads "
        "geonet-infer would use, and a summary of a model's manifest.",
    )
    parser.add_argument(
        "--model", default=None, help=f"bundled model name or model directory (default: {DEFAULT_MODEL!r})"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.set_defaults(run=run)


def _score_text(s: dict) -> str:
    return (
        f"{s['task']} {s['metric']} {s['value']:.3g} vs {s['baseline_value']:.3g} for {s['baseline']} "
        f"({s['verdict']}) on {s['data']}"
    )


def run(args: argparse.Namespace) -> int:
    info = {"environment": Environment.current().as_dict(), "model": model_summary(args.model)}
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    env, model = info["environment"], info["model"]
    default, *optional = ENGINES.values()  # the default engine is always installed
    print(
        f"geonet-infer {env['geonet_infer']}  python {env['python']}  {default.name} {env[default.name]}  "
        f"numpy {env['numpy']}  opencv {env['opencv']}"
    )
    print(f"providers: {', '.join(env['providers'])}")
    for engine in optional:
        version = env[engine.name]
        print(
            f"{engine.name}: {version} (--backend {engine.name}|auto)"
            if version
            else f"{engine.name}: not installed ({engine.install_hint} for --backend {engine.name}|auto)"
        )
    print(f"cpu: {env['cpu']}; usable CPUs {env['usable_cpus']} (default threads per graph)")
    print(f"isa: {env['isa']['line']}")
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
