"""The model card's measurements: the model and its baselines on the synthetic held-out sequences and the
KITTI frames with Velodyne ground truth, through the runtime (see :mod:`benchmarks.model_card`)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from benchmarks.markdown import sig3
from geonet_infer.bench.environment import git_commit
from geonet_infer.core.predictor import Predictor
from geonet_infer.errors import InputError
from geonet_infer.eval import evaluation, metrics
from geonet_infer.eval.datasets import SNIPPET, Dataset, depth_dataset, flow_dataset, pose_dataset, read_heldout
from geonet_infer.models.manifest import MANIFEST_NAME, Manifest, load_manifest

KITTI_CROP = "garg"
KITTI_CAMERA_HEIGHT = 1.65  # metres: KITTI's colour cameras above the road (Geiger et al., IJRR 2013)
MIN_DEPTH, MAX_DEPTH = evaluation.MIN_DEPTH, evaluation.MAX_DEPTH
DEPTH_KEYS = (*metrics.DEPTH_KEYS, "scale", "n_valid")
DEPTH_HEADERS = ("AbsRel", "SqRel", "RMSE", "RMSElog", "δ<1.25", "δ<1.25²", "δ<1.25³")
PRECISION_LABEL = {"fp32": "model, FP32", "int8": "model, INT8"}
BASELINE_LABEL = {
    "constant_baseline": "constant depth (baseline)",
    "zero_flow_baseline": "zero flow (baseline)",
    "dis_medium_baseline": "DIS medium (baseline)",
    "identity_baseline": "identity pose / no motion (baseline)",
    "orb_vo_baseline": "ORB-VO (baseline)",
}
ROW_LABEL = PRECISION_LABEL | BASELINE_LABEL
SYNTH_DEPTH_TARGET = 0.15  # the target for the synthetic held-out AbsRel
Progress = Callable[[str], None]


# ----------------------------------------------------------------------------- formatting
def _mib(n_bytes: int) -> str:
    """A file size in MiB, KiB or bytes."""
    if n_bytes >= 2**20:
        return f"{sig3(n_bytes / 2**20)} MiB"
    return f"{sig3(n_bytes / 2**10)} KiB" if n_bytes >= 2**10 else f"{n_bytes} B"


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


# ----------------------------------------------------------------------------- inputs
def _require_dir(path: str | Path, what: str, hint: str = "") -> Path:
    path = Path(path)
    if not path.is_dir():
        raise InputError(path, f"{what} not found", hint)
    return path


def _checked(result: dict, what: str, allowed: Sequence[str] = ()) -> dict:
    """``result`` if no item outside ``allowed`` has an error (a NaN prediction would make the card's means NaN)."""
    for error in result["errors"]:
        if error["item"] not in allowed:
            raise InputError(error["item"], f"{what}: {error['problem']}", "the model produced NaN/inf")
    return result


def _means(rows: list[dict]) -> dict:
    """Per-frame means of the depth errors, the applied scale and the GT pixel count, plus "count"."""
    return metrics.aggregate([{k: r[k] for k in DEPTH_KEYS} for r in rows])


def _flow_block(result: dict) -> dict:
    """{"noc": ..., "occ": ...} means of a flow result (KITTI's "occ" = evaluation's "all")."""
    out = {}
    for which, key in (("noc", "noc"), ("occ", "all")):
        rows = [
            {"epe": r[f"epe_{key}"], "fl": r[f"fl_{key}"], "acc": 1.0 - r[f"fl_{key}"], "n_valid": r[f"n_valid_{key}"]}
            for r in result["items"]
        ]
        out[which] = metrics.aggregate(rows)
    return out


def pose_method(seq_length: int) -> str:
    """How the model's 5-frame snippet trajectories are obtained (sentence for the card)."""
    if seq_length == SNIPPET:
        return (
            "PoseNet run once on each 5-frame snippet (target = middle frame), its 4 target→source "
            "poses turned into first-frame coordinates with `metrics.snippet_poses_to_global` "
            "(the paper's protocol)"
        )
    return (
        f"the model takes {seq_length}-frame snippets, so PoseNet runs on the snippet's triplets [0, 1, 2] "
        "and [2, 3, 4] and the four poses are chained through frame 2 "
        "(`evaluation.snippet_from_pose_calls`; only the snippet's own frames are used)"
    )


class SynthData(NamedTuple):
    """The held-out sequences as frames (depth), pairs (flow) and 5-frame snippets (pose)."""

    depth: Dataset
    flow: Dataset
    pose: Dataset


def synth_data(synth_dir: Path, sequences: list[str], stride: int) -> SynthData:
    return SynthData(
        depth_dataset(synth_dir, "synth", sequences, stride),
        flow_dataset(synth_dir, "synth", sequences, stride),
        pose_dataset(synth_dir, "synth", sequences, stride),
    )


def evaluate_synthetic(
    predictors: dict[str, Predictor], data: SynthData, allow_random_init: bool, progress: Progress
) -> tuple[dict, dict, dict]:
    """Depth, flow and pose blocks of the card on the held-out sequences (model rows and item counts)."""
    depth_data, flow_data, pose_data = data
    depth, flow, pose = {}, {}, {}
    static = {}  # snippets where the model predicts no motion at all
    for p, predictor in predictors.items():
        progress(f"{p}: synthetic depth")
        r = evaluation.evaluate_depth(evaluation.model_depth_fn(predictor, allow_random_init), depth_data)
        depth[p] = _means(_checked(r, f"{p} depth")["items"])
        progress(f"{p}: synthetic flow")
        r = evaluation.evaluate_flow(evaluation.model_flow_fn(predictor, allow_random_init), flow_data)
        flow[p] = _flow_block(_checked(r, f"{p} flow"))
        progress(f"{p}: synthetic pose")
        static[p] = 0

        def count_static(item, gt, pred, row, p=p):
            static[p] += int(not np.any(pred[:, :3, 3] - pred[0, :3, 3]))

        r = evaluation.evaluate_pose(
            evaluation.model_pose_fn(predictor, allow_random_init), pose_data, observe=count_static
        )
        pose[p] = _pose_block(_checked(r, f"{p} pose")) | {"static_snippets": static[p]}
    depth["frames"] = len(depth_data.items)
    flow["pairs"] = len(flow_data.items)
    pose["snippets"] = len(pose_data.items)
    return depth, flow, pose


def _baseline(task: str, method: str) -> Callable:
    """The one function of a ``geonet-infer eval --method`` baseline (``evaluation.baseline_fns``)."""
    (fn,) = evaluation.baseline_fns(task, method).values()
    return fn


def synthetic_baselines(data: SynthData, progress: Progress) -> tuple[dict, dict, dict]:
    """Baseline rows of the depth, flow and pose blocks: the trivial ones, and the classical ones the
    issue's targets name (DIS medium flow, ORB-VO pose)."""
    progress("baselines")
    orb = evaluation.evaluate_pose(_baseline("pose", "orb-vo"), data.pose)
    depth = {
        "constant_baseline": _means(evaluation.evaluate_depth(_baseline("depth", "constant"), data.depth)["items"])
    }
    flow = {
        "zero_flow_baseline": _flow_block(evaluation.evaluate_flow(_baseline("flow", "zero"), data.flow)),
        "dis_medium_baseline": _flow_block(evaluation.evaluate_flow(_baseline("flow", "dis-medium"), data.flow)),
    }
    pose = {
        "identity_baseline": _pose_block(evaluation.evaluate_pose(_baseline("pose", "identity"), data.pose)),
        # a failed pair repeats the previous step: how often that happened tells how far ORB-VO really tracked
        "orb_vo_baseline": _pose_block(orb)
        | {"failed_pairs": sum(r["failed_pairs"] for r in orb["items"]), "pairs": (SNIPPET - 1) * len(orb["items"])},
    }
    return depth, flow, pose


def _pose_block(result: dict) -> dict:
    keys = ("ate_snippet", "ate_rmse_true")
    return {k: {"mean": result["metrics"][k], "std": result["std"][k]} for k in keys} | {
        "count": result["metrics"]["count"]
    }


def evaluate_kitti(
    predictors: dict[str, Predictor],
    data,
    camera_height: float,
    allow_random_init: bool,
    progress: Progress,
    constant_baseline: bool = True,
) -> dict:
    """Eigen-protocol depth (Garg crop, 80 m) on KITTI frames: median-scaled (model and, with
    ``constant_baseline``, constant depth) and scaled by the camera height (model only: a constant
    depth has no ground plane)."""
    sizes = {}
    per_frame: dict[str, dict] = {item.name: {} for item in data.items}

    floor_shares: dict[str, list[float]] = {}

    def keep_size_and_floor(key):
        def observe(item, rgb, gt, pred, row):
            sizes[item.name] = rgb.shape[:2]
            floor_shares.setdefault(key, []).append(metrics.depth_floor_share(pred))

        return observe

    out: dict = {}
    by_camera_height: dict = {"camera_height_m": camera_height}
    runs = [(p, evaluation.model_depth_fn(predictor, allow_random_init)) for p, predictor in predictors.items()]
    methods = [*runs, ("constant_baseline", _baseline("depth", "constant"))] if constant_baseline else runs
    for key, fn in methods:
        progress(f"{key}: KITTI depth")
        r = _checked(
            evaluation.evaluate_depth(fn, data, crop=KITTI_CROP, observe=keep_size_and_floor(key)),
            f"{key} KITTI depth",
        )
        out[key] = _means(r["items"])
        if key in predictors:
            out[key]["floor_share"] = float(np.mean(floor_shares[key]))
        for row in r["items"]:
            per_frame[row["name"]][key] = {k: row[k] for k in DEPTH_KEYS}
    for p, fn in runs:
        progress(f"{p}: KITTI depth scaled by camera height")
        r = evaluation.evaluate_depth(fn, data, crop=KITTI_CROP, scaling="camera_height", camera_height=camera_height)
        failed = _checked(r, f"{p} KITTI depth scaled by camera height", r["ground_fit_failed"])["ground_fit_failed"]
        scored = [row for row in r["items"] if row["name"] not in failed]
        by_camera_height[p] = _means(scored) if scored else None  # None: no frame had a ground plane
        by_camera_height[f"{p}_ground_fit_failed"] = failed
        for row in r["items"]:
            per_frame[row["name"]][f"{p}_camera_height"] = (
                {"ground_fit": "failed", "problem": row["problem"]}
                if row["name"] in failed
                else {k: row[k] for k in (*DEPTH_KEYS, "ground_height", "ground_inliers")}
            )
    out["camera_height"] = by_camera_height
    out["frames"] = len(data.items)
    out["per_frame"] = [
        {"frame": name, "height": sizes[name][0], "width": sizes[name][1]} | f for name, f in per_frame.items()
    ]
    return out


# ----------------------------------------------------------------------------- run
def _dir_bytes(model_dir: Path) -> int:
    return sum(f.stat().st_size for f in model_dir.rglob("*") if f.is_file())


def model_info(manifest: Manifest, model_dir: Path) -> dict:
    files = []
    for precision in manifest.precisions:
        for name in manifest.graph_names(precision):
            entry = manifest.graph(name, precision)
            files.append(
                {
                    "precision": precision,
                    "graph": name,
                    "file": entry.file,
                    "bytes": (model_dir / entry.file).stat().st_size,
                    "sha256": entry.sha256,
                    "file_precision": entry.precision,
                    "opset": entry.opset,
                }
            )
    return {
        "dir": str(model_dir),
        "arch": manifest.arch,
        "height": manifest.height,
        "width": manifest.width,
        "seq_length": manifest.seq_length,
        "random_init": manifest.random_init,
        "precisions": list(manifest.precisions),
        "graphs": list(manifest.graph_names("fp32")),
        "provenance": dataclasses.asdict(manifest.provenance),
        "metrics": manifest.metrics,
        "files": files,
        # every file of the directory (manifest included), as unpacked from the wheel
        "dir_bytes": _dir_bytes(model_dir),
        "quantization": _quantization(manifest),
    }


def _quantization(manifest: Manifest) -> dict | None:
    quant = manifest.quantization
    return None if quant is None else json.loads(json.dumps(dataclasses.asdict(quant), default=list))


def load_model_dir(path: str | Path, allow_random_init: bool) -> tuple[Path, Manifest]:
    model_dir = _require_dir(path, "model directory", "pass a directory written by `python -m export`")
    manifest = load_manifest(model_dir)
    if manifest.random_init and not allow_random_init:
        raise InputError(
            model_dir / MANIFEST_NAME,
            "this model directory holds random-init (timing-only) graphs",
            "export a trained --checkpoint (--allow-random-init is for development)",
        )
    return model_dir, manifest


def evaluate_model(
    model_dir: Path,
    manifest: Manifest,
    synth: SynthData,
    kitti_data: Dataset,
    args,
    progress: Progress,
    with_baselines: bool,
) -> dict:
    """Every number of one model directory, FP32 and (when exported) INT8, laid out as in the card's
    JSON; the one code path for the model and, with ``--before``, for the previous one."""
    precisions = [p for p in ("fp32", "int8") if p in manifest.precisions]
    predictors = {p: Predictor(model_dir, precision=p, threads=args.threads, manifest=manifest) for p in precisions}
    random_ok = bool(args.allow_random_init)
    depth, flow, pose = evaluate_synthetic(predictors, synth, random_ok, progress)
    if with_baselines:
        for block, rows in zip((depth, flow, pose), synthetic_baselines(synth, progress)):
            block.update(rows)
    pose["method"] = pose_method(manifest.seq_length)
    kitti = evaluate_kitti(predictors, kitti_data, KITTI_CAMERA_HEIGHT, random_ok, progress, with_baselines)
    return {
        "model": model_info(manifest, model_dir),
        "synthetic": {"depth": depth, "flow": flow, "pose": pose},
        "kitti": {"depth": kitti},
    }


def run(args, command: str, progress: Progress) -> dict:
    """Measure everything; returns the JSON-able result (raises GeoNetError on bad input)."""
    model_dir, manifest = load_model_dir(args.model, args.allow_random_init)
    before = load_model_dir(args.before, args.allow_random_init) if args.before else None
    synth_dir = _require_dir(args.synth_dir, "synthetic data folder", "generate it with `python -m training.synth`")
    prepared_dir = _require_dir(
        args.prepared_dir, "prepared data folder", "prepare it with `python -m training.prepare`"
    )
    sequences = read_heldout(prepared_dir / "heldout.txt")
    for name in sequences:
        _require_dir(synth_dir / name, "held-out sequence folder", "--synth-dir and --prepared-dir must match")
    kitti_data = depth_dataset(
        _require_dir(args.kitti, "KITTI raw folder", "expected image_02/, velodyne_points/ and the calibration"),
        "kitti-raw",
        limit=args.kitti_frames,
    )
    if len(kitti_data.items) < args.kitti_frames:
        raise InputError(
            args.kitti,
            f"only {len(kitti_data.items)} frames have ground truth, {args.kitti_frames} requested",
            "lower --kitti-frames",
        )

    synth = synth_data(synth_dir, sequences, args.stride)
    after = evaluate_model(model_dir, manifest, synth, kitti_data, args, progress, with_baselines=True)
    result = {
        "command": command,
        "generated_utc": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        "git_commit": git_commit(Path(__file__).resolve().parents[2]),  # the repository root
        "allow_random_init": bool(args.allow_random_init),
        "model": after["model"],
        "synthetic": {
            "synth_dir": str(args.synth_dir),
            "prepared_dir": str(args.prepared_dir),
            "sequences": sequences,
            "stride": args.stride,
            "synth_config": _synth_config(synth_dir),
        }
        | after["synthetic"],
        "kitti": {
            "dir": str(args.kitti),
            "frames": [item.name for item in kitti_data.items],
            "ground_truth": kitti_data.items[0].gt_kind,
            "crop": KITTI_CROP,
            "min_depth": MIN_DEPTH,
            "max_depth": MAX_DEPTH,
        }
        | after["kitti"],
        "settings": {
            "max_depth": MAX_DEPTH,
            "snippet_length": SNIPPET,
            "flow_seq_length": manifest.seq_length,
            "threads": args.threads,
        },
    }
    result["int8_delta"] = int8_deltas(result) if "int8" in manifest.precisions else []
    # the previous model on the same data; the baselines do not depend on the model, so they run once
    result["before"] = (
        evaluate_model(*before, synth, kitti_data, args, lambda msg: progress(f"before {msg}"), with_baselines=False)
        if before
        else None
    )
    return result


def _synth_config(synth_dir: Path) -> dict | None:
    path = synth_dir / "synth_config.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


DELTA_METRICS = (
    ("synthetic", "depth", ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1")),
    ("synthetic", "flow", ("noc.epe", "occ.epe", "noc.fl", "occ.fl")),
    ("synthetic", "pose", ("ate_snippet.mean", "ate_rmse_true.mean")),
    ("kitti", "depth", ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1")),
)


def int8_deltas(result: dict) -> list[dict]:
    rows = []
    for where, task, keys in DELTA_METRICS:
        block = result[where][task]
        fp32, int8 = _flatten(block["fp32"]), _flatten(block["int8"])
        for key in keys:
            delta = int8[key] - fp32[key]
            rows.append(
                {
                    "data": where,
                    "task": task,
                    "metric": key,
                    "fp32": fp32[key],
                    "int8": int8[key],
                    "delta": delta,
                    "relative": delta / fp32[key] if fp32[key] else None,
                }
            )
    return rows
