"""``python -m benchmarks.model_card``: arguments, the recorded JSON files it reads, and the run."""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from pathlib import Path

import numpy as np

from benchmarks.model_card.measure import _dir_bytes, _quantization, run
from benchmarks.model_card.render import (
    manifest_card,
    render_card,
    write_manifest_card,
)
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.models.manifest import load_manifest


# ----------------------------------------------------------------------------- CLI
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.model_card",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model", required=True, help="model directory written by `python -m export`")
    p.add_argument("--synth-dir", help="(measuring) output of training.synth")
    p.add_argument("--prepared-dir", help="(measuring) output of training.prepare (has heldout.txt)")
    p.add_argument("--kitti", help="(measuring) KITTI raw drive folder (image_02/, velodyne_points/, calib)")
    p.add_argument("--out", required=True, help="the Markdown card to write (docs/models.md)")
    p.add_argument("--json", help="also write every number as JSON here")
    p.add_argument(
        "--before",
        metavar="DIR",
        help="the previously shipped model directory: measured the same way in this run, and the card gets a "
        "before/after table",
    )
    p.add_argument(
        "--real",
        metavar="JSON",
        help="the JSON of `python -m benchmarks.eval_all --json` for this model: rendered as the card's real-data "
        "section (every real set of ../shared with ground truth); refused if measured on other graph files",
    )
    p.add_argument(
        "--experiment",
        metavar="JSON",
        action="append",
        help="the JSON of `python -m experiments.real_pose_experiment`: its shipping rule and, once scored, its "
        "before/after numbers and verdict (repeat for each round, in order)",
    )
    p.add_argument(
        "--teacher",
        metavar="JSON",
        action="append",
        help="the JSON of `python -m experiments.teacher_experiment` (repeat for each round, in order)",
    )
    p.add_argument(
        "--stop", metavar="JSON", action="append", help="the JSON of `python -m experiments.stop_experiment`"
    )
    p.add_argument(
        "--real-training",
        metavar="TEXT",
        help="the real footage the model was also trained on, as a phrase (e.g. '45 minutes on 51 grey KITTI "
        "odometry frames'): the manifest then no longer calls it synthetic-only",
    )
    p.add_argument("--stride", type=int, default=1, help="synthetic: every n-th frame / pair / snippet")
    p.add_argument("--kitti-frames", type=int, default=10, help="KITTI frames with Velodyne scans to use (first N)")
    p.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: all usable)")
    p.add_argument(
        "--allow-random-init",
        action="store_true",
        help="accept a random-init model directory (development only; the card says so loudly)",
    )
    p.add_argument(
        "--no-manifest",
        action="store_true",
        help="leave the model directory's manifest.json as it is (by default the card's headline scores and "
        "what the model was trained on are written into it as `model_card`, which `geonet-infer info` shows)",
    )
    p.add_argument(
        "--from-json",
        metavar="JSON",
        help="measure nothing: take the numbers of an earlier run's --json (for the same graphs), write them "
        "into --model's manifest and render --out (and --json) again",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def _check_finite(obj, where: str = "") -> None:
    if isinstance(obj, dict):
        for key, value in obj.items():
            _check_finite(value, f"{where}.{key}" if where else str(key))
    elif isinstance(obj, list):
        for i, value in enumerate(obj):
            _check_finite(value, f"{where}[{i}]")
    elif isinstance(obj, float) and not math.isfinite(obj):
        raise InputError(None, f"non-finite result at {where}", "the model produced NaN/inf")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    command = ".venv/bin/python -m benchmarks.model_card " + shlex.join(argv)
    progress = (lambda msg: None) if args.quiet else (lambda msg: print(f"[model_card] {msg}", file=sys.stderr))
    try:
        if args.stride < 1:
            raise InputError(None, f"--stride must be >= 1, got {args.stride}")
        if args.kitti_frames < 1:
            raise InputError(None, f"--kitti-frames must be >= 1, got {args.kitti_frames}")
        if args.threads is not None and args.threads < 1:
            raise InputError(None, f"--threads must be >= 1, got {args.threads}")
        for out in (args.out, args.json):
            if out and not Path(out).parent.is_dir():
                raise InputError(Path(out).parent, "output folder not found", "create it first")
        if args.from_json:
            result = recorded_result(args.from_json, args.model)
        else:
            for flag in ("synth_dir", "prepared_dir", "kitti"):
                if getattr(args, flag) is None:
                    raise InputError(None, f"--{flag.replace('_', '-')} is required", "or pass --from-json")
            result = run(args, command, progress)
        if args.experiment:
            result.pop("experiment", None)  # a card of one round, before rounds were a list
            result["experiments"] = [recorded_experiment(path) for path in args.experiment]
        if args.teacher:
            result["teacher_rounds"] = [recorded_json(path, "teacher_experiment", "rule") for path in args.teacher]
        if args.stop:
            result["stop_rounds"] = [recorded_json(path, "stop_experiment", "rule") for path in args.stop]
        if args.real_training:
            result["real_training"] = args.real_training
        if args.real:
            result["real"] = recorded_real(args.real, args.model)
            result["real_render_command"] = command
            result["real_json"] = args.real
        # the manifests' own numbers (model blocks) are reported, not measured
        _check_finite({k: v for k, v in result.items() if k not in ("model", "before")})
        if result["before"]:
            _check_finite({k: v for k, v in result["before"].items() if k != "model"}, "before")
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if result["model"]["random_init"]:
        print("WARNING: random-init model: the card's numbers measure untrained weights", file=sys.stderr)
    if not args.no_manifest:
        write_manifest_card(args.model, manifest_card(result, args.out))
        result["model"]["dir_bytes"] = _dir_bytes(Path(args.model))  # the manifest just grew
    with atomic_write(args.out) as tmp:
        tmp.write_text(render_card(result))
    if args.json:
        with atomic_write(args.json) as tmp:
            tmp.write_text(json.dumps(result, indent=2, default=_json_default) + "\n")
    progress(f"wrote {args.out}" + (f" and {args.json}" if args.json else ""))
    return 0


def recorded_result(path: str | Path, model: str | Path) -> dict:
    """An earlier run's --json, refused unless its graph files are ``model``'s (same sha256)."""
    try:
        result = json.loads(Path(path).read_text())
        recorded = {(f["precision"], f["graph"]): f["sha256"] for f in result["model"]["files"]}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(path, f"not a model card's --json ({exc})", "pass the file a --json run wrote") from None
    manifest = load_manifest(model)
    current = {(p, n): manifest.graph(n, p).sha256 for p in manifest.precisions for n in manifest.graph_names(p)}
    if recorded != current:
        raise InputError(
            path, f"its numbers were measured on other graph files than those of {model}", "measure this model"
        )
    # the same graph files: how they were quantised is what their manifest says now (a re-export may
    # record more of it than the manifest measured)
    result["model"]["quantization"] = _quantization(manifest)
    return result


def recorded_json(path: str | Path, writer: str, key: str) -> dict:
    """A JSON that ``benchmarks.<writer>`` wrote (it must hold ``key``)."""
    try:
        recorded = json.loads(Path(path).read_text())
        recorded[key]  # noqa: B018
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(path, f"not a {writer} JSON ({exc})", "pass the file it wrote") from None
    return recorded


def recorded_experiment(path: str | Path) -> dict:
    """The JSON of ``experiments.real_pose_experiment`` (the rule, and the scores once measured)."""
    recorded = recorded_json(path, "real_pose_experiment", "rule")
    if "train_frames" not in recorded:
        raise InputError(path, "not a real_pose_experiment JSON (no train_frames)", "pass the file it wrote")
    return recorded


def recorded_real(path: str | Path, model: str | Path) -> dict:
    """The JSON of ``python -m benchmarks.eval_all --json``, refused unless measured on ``model``'s graph files."""
    try:
        real = json.loads(Path(path).read_text())
        recorded = real["model"]["graphs"]
        real["sets"], real["validation"]  # noqa: B018  (the keys the section renders)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(
            path, f"not a `python -m benchmarks.eval_all --json` file ({exc})", "pass the file it wrote"
        ) from None
    manifest = load_manifest(model)
    current = {p: {n: manifest.graph(n, p).sha256 for n in manifest.graph_names(p)} for p in manifest.precisions}
    if recorded != current:
        raise InputError(
            path,
            f"its numbers were measured on other graph files than those of {model}",
            "run python -m benchmarks.eval_all on this model",
        )
    for real_set in real["sets"]:  # the per-item rows stay in the eval-all JSON; the card needs the means
        for method in real_set["results"].values():
            method.pop("items", None)
    return real


def _json_default(obj):
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (tuple, Path)):
        return list(obj) if isinstance(obj, tuple) else str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
