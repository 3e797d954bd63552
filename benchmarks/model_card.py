"""Write the model card (``docs/models.md``) of an exported model directory.

``python -m benchmarks.model_card --model geonet_infer/models/small_synth --synth-dir data/synth40
--prepared-dir data/synth40_prepared --kitti ../shared/realdata/kitti_raw_2011_09_26_sfnd
--out docs/models.md [--json OUT.json] [--before DIR] [--stride N] [--kitti-frames N]``

Every number in the card comes from this run: the ONNX graphs are run through the
runtime (:class:`geonet_infer.core.predictor.Predictor`), in fp32 and, when the manifest
has them, INT8, and scored by the code ``geonet-infer eval`` uses (data from
:mod:`geonet_infer.eval.datasets`, scores from :mod:`geonet_infer.eval.evaluation`, baselines
from :mod:`geonet_infer.eval.baselines`); this module only picks the data and renders:

* held-out synthetic sequences (``heldout.txt`` of the prepared dir, never trained
  on): depth (Eigen errors, per-image median scaling, 80 m cap, every pixel with
  ground truth) against the constant-depth baseline; flow EPE / Fl on noc and occ
  pixels against zero flow and OpenCV DIS (medium preset); pose ATE on 5-frame
  snippets (``metrics.ate_snippet``, the paper's divide-by-N value, and
  ``metrics.ate_rmse_true``) against the identity pose (no motion) and ORB-VO;
* real KITTI raw frames with Velodyne scans (never trained on): depth against the
  projected Velodyne ground truth, Eigen protocol with the Garg crop, 80 m cap and
  median scaling, at the frames' own resolution; and the same frames scaled by the
  camera height (1.65 m, ground plane fitted to the prediction, no ground truth),
  counting and naming the frames where no ground plane is found.

``--real JSON`` (what ``python -m benchmarks.eval_all --json`` wrote for this model: every real set in
``../shared`` with ground truth, the model at FP32 and INT8 beside the classical baselines, and the
real validation figure) adds the card's "Real data" section, rendered from that file and refused
unless its graph files are the model's; with ``--from-json`` it needs no other measurement.

``--before DIR`` (the previously shipped model directory) runs the same measurements
on that model in the same run and adds a "Before / after" table of the headline
numbers, each with its baseline and target.

The card's headline FP32 numbers (each beside its baseline) and what the model was trained
on are also written into the model directory's ``manifest.json`` as ``model_card`` (graph
files untouched; ``--no-manifest`` skips it), where ``geonet-infer info`` shows them and
``predict`` / ``batch`` warn about a synthetic-only model. ``--from-json`` does that (and
renders the card again) from an earlier run's ``--json`` without measuring.

Random-init (timing-only) model directories are refused unless
``--allow-random-init`` is given (development only; the card then carries a
warning at the top). Bad input: a one-line message naming the path, exit 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import math
import operator
import re
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from benchmarks import eval_all, teacher_experiment
from geonet_infer.bench.environment import git_commit
from geonet_infer.core.manifest import MANIFEST_NAME, Manifest, load_manifest
from geonet_infer.core.predictor import Predictor
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.eval import evaluation, metrics
from geonet_infer.eval.datasets import SNIPPET, Dataset, depth_dataset, flow_dataset, pose_dataset, read_heldout
from geonet_infer.io.atomic import atomic_write

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
def sig3(x) -> str:
    """A number to 3 significant digits, without exponent for ordinary magnitudes."""
    if x is None:
        return "n/a"
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    x = float(x)
    if not math.isfinite(x):
        return str(x)
    if x == 0:
        return "0"
    r = float(f"{x:.3g}")
    if not 1e-4 <= abs(r) < 1e6:
        return f"{r:.3g}"
    decimals = max(0, 2 - int(math.floor(math.log10(abs(r)))))
    return f"{r:.{decimals}f}"


def signed3(x: float) -> str:
    """A difference to 3 significant digits with its sign."""
    s = sig3(x)
    return s if s.startswith("-") or s in ("0", "nan", "n/a") else "+" + s


def _mib(n_bytes: int) -> str:
    """A file size in MiB, KiB or bytes."""
    if n_bytes >= 2**20:
        return f"{sig3(n_bytes / 2**20)} MiB"
    return f"{sig3(n_bytes / 2**10)} KiB" if n_bytes >= 2**10 else f"{n_bytes} B"


def _table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out


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
        "git_commit": git_commit(Path(__file__).resolve().parents[1]),
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


# ----------------------------------------------------------------------------- card
def _data_synth(result: dict) -> str:
    s = result["synthetic"]
    cfg = s.get("synth_config") or {}
    size = f", {cfg['height']}×{cfg['width']}" if "height" in cfg and "width" in cfg else ""
    return f"`{Path(s['synth_dir']).name}` held-out ({len(s['sequences'])} seq{size})"


def _frame_span(frames: list[str]) -> str:
    """The frames as a range: 0–9 for numbered frames, else the first and the last name."""
    if len(frames) == 1:
        return frames[0]
    return f"{int(frames[0])}–{int(frames[-1])}" if all(f.isdigit() for f in frames) else f"{frames[0]}…{frames[-1]}"


def _data_kitti(result: dict) -> str:
    k = result["kitti"]
    frames = k["frames"]
    pf = k["depth"]["per_frame"][0]
    return (
        f"KITTI raw `{Path(k['dir']).name}`, frames {_frame_span(frames)} ({len(frames)}, {pf['width']}×{pf['height']})"
    )


def _camera_height_label(p: str, camera_height: float) -> str:
    return f"{PRECISION_LABEL[p]}, scaled by camera height {camera_height:g} m (no median scaling)"


def _depth_table(block: dict, data: str, count_key: str) -> list[str]:
    """Median-scaled rows; with a ``camera_height`` block, each precision's camera-height row beside it."""
    rows = []
    by_height = block.get("camera_height")
    for key in ("fp32", "int8", "constant_baseline"):
        if key not in block:
            continue
        rows.append(
            [ROW_LABEL[key], data] + [sig3(block[key][c]) for c in metrics.DEPTH_KEYS] + [sig3(block[key]["count"])]
        )
        if by_height and key in by_height:
            means, failed = by_height[key], by_height[f"{key}_ground_fit_failed"]
            scored = block["frames"] - len(failed)
            count = f"{scored} of {block['frames']}" + (f", ground fit failed on {len(failed)}" if failed else "")
            rows.append(
                [_camera_height_label(key, by_height["camera_height_m"]), data]
                + [sig3(means[c] if means else None) for c in metrics.DEPTH_KEYS]
                + [count]
            )
    return _table(["predictor", "data"] + list(DEPTH_HEADERS) + [count_key], rows)


def _camera_height_text(block: dict) -> list[str]:
    """What the camera-height rows did, with every frame whose ground fit failed."""
    h = block["camera_height"]
    out = [
        f"Scaled by camera height: per frame, a ground plane is fitted to the predicted depth "
        "(`geonet_infer.core.scale.fit_ground_plane`: RANSAC on the image below the horizon, normal within 20° of "
        "the camera's down axis, at least 10 % of the points within 2 % of the plane's distance; a plane with "
        "over 3 % of the points more than 30 % beyond it along their rays is skipped, as a car top the road is "
        f"seen beside) and the depth is multiplied so that the plane lies {h['camera_height_m']:g} m below the "
        "camera (KITTI's colour cameras); the ground truth is not used "
        '(`evaluation.evaluate_depth(..., scaling="camera_height")`, '
        "`geonet-infer eval depth --camera-height`). A frame without such a plane is not scored and never "
        "median-scaled instead: the means cover the other frames."
    ]
    for p in ("fp32", "int8"):
        failed = h.get(f"{p}_ground_fit_failed")
        if failed:
            out.append(
                f"**{PRECISION_LABEL[p]}: no ground plane in {len(failed)} of {block['frames']} frames** "
                f"({', '.join(failed)})."
            )
    return [" ".join(out), ""]


def _floor_text(block: dict, before: dict | None) -> list[str]:
    """The depth-floor diagnostic of each precision (and of the previous model)."""

    def shares(b: dict) -> str:
        return ", ".join(f"{PRECISION_LABEL[p]} {sig3(b[p]['floor_share'])}" for p in ("fp32", "int8") if p in b)

    was = f"; before: {shares(before)}" if before else ""
    return [
        "Depth floor, without ground truth: the share of the lower image half in the fullest 0.2 %-wide "
        "bin of log depth, mean over these frames (`geonet_infer.eval.metrics.depth_floor_share`). A road "
        "scene's depth spreads to a few %; a near field predicted as one value (dead decoder features "
        f"leave the disparity head's bias) shows as a large share: {shares(block)}{was}.",
        "",
    ]


def _flow_table(block: dict, data: str) -> list[str]:
    rows = []
    for key in ("fp32", "int8", "zero_flow_baseline", "dis_medium_baseline"):
        if key not in block:
            continue
        b = block[key]
        rows.append(
            [
                ROW_LABEL[key],
                data,
                sig3(b["noc"]["epe"]),
                sig3(b["occ"]["epe"]),
                sig3(b["noc"]["fl"]),
                sig3(b["occ"]["fl"]),
                sig3(b["noc"]["count"]),
            ]
        )
    return _table(["predictor", "data", "EPE noc (px)", "EPE occ (px)", "Fl noc", "Fl occ", "pairs"], rows)


def _pose_table(block: dict, data: str) -> list[str]:
    rows = []
    for key in ("fp32", "int8", "identity_baseline", "orb_vo_baseline"):
        if key not in block:
            continue
        b = block[key]
        rows.append(
            [
                ROW_LABEL[key],
                data,
                f"{sig3(b['ate_snippet']['mean'])} ± {sig3(b['ate_snippet']['std'])}",
                f"{sig3(b['ate_rmse_true']['mean'])} ± {sig3(b['ate_rmse_true']['std'])}",
                sig3(b["count"]),
            ]
        )
    return _table(["predictor", "data", "ATE, paper (÷N) mean ± std", "ATE, true RMSE mean ± std", "snippets"], rows)


def _camera_height_limitation(block: dict) -> str:
    """How far metric depth from the camera height got on the KITTI frames (FP32)."""
    h = block["camera_height"]
    failed, n = len(h["fp32_ground_fit_failed"]), block["frames"]
    if failed == n:
        return (
            f"Metric depth from the camera height ({h['camera_height_m']:g} m) found no ground plane in any of the "
            f"{n} KITTI frames, so without ground truth this model gives depth in arbitrary units."
        )
    return (
        f"Metric depth from the camera height ({h['camera_height_m']:g} m) found a ground plane in {n - failed} of "
        f"{n} KITTI frames (AbsRel {sig3(h['fp32']['abs_rel'])} on those, without median scaling)."
    )


def _compare(model: float, baseline: float, lower_is_better: bool = True) -> str:
    better = model < baseline if lower_is_better else model > baseline
    return "better than" if better else ("equal to" if model == baseline else "worse than")


def _stage_origin(command: str | None) -> str | None:
    """Where the training run started: ``initialised from X`` (--init-checkpoint) or ``resumed from X`` (--resume)."""
    for flag, verb in (("--resume", "resumed from"), ("--init-checkpoint", "initialised from")):
        m = re.search(rf"{flag}[ =](\S+)", command or "")
        if m:
            return f"{verb} `{m.group(1)}`"
    return None


def _checkpoint_text(prov: dict) -> str:
    if prov.get("checkpoint") and prov.get("checkpoint_sha256"):
        return f"`{prov['checkpoint']}` (sha256 `{prov['checkpoint_sha256'][:12]}…`)"
    return "n/a"


class Headline(NamedTuple):
    """A row of the before/after table: one model number, the baseline it is judged by and the issue's target."""

    label: str
    where: str  # "synthetic" or "kitti"
    task: str
    metric: str  # key in the flattened block of one precision
    baseline: str  # key of the baseline's block
    baseline_name: str
    target: str
    meets: Callable[[float, float], bool]  # (model, baseline) -> the target is met


HEADLINES = (
    Headline(
        "real KITTI frames {frames} depth AbsRel",
        "kitti",
        "depth",
        "abs_rel",
        "constant_baseline",
        "constant",
        "below constant",
        operator.lt,
    ),
    Headline(
        "synthetic held-out depth AbsRel",
        "synthetic",
        "depth",
        "abs_rel",
        "constant_baseline",
        "constant",
        f"≤ {SYNTH_DEPTH_TARGET:g}",
        lambda model, _: model <= SYNTH_DEPTH_TARGET,
    ),
    Headline(
        "synthetic flow EPE-noc (px)",
        "synthetic",
        "flow",
        "noc.epe",
        "dis_medium_baseline",
        "DIS medium",
        "below DIS medium",
        operator.lt,
    ),
    Headline(
        "synthetic pose ATE (paper ÷N, mean)",
        "synthetic",
        "pose",
        "ate_snippet.mean",
        "orb_vo_baseline",
        "ORB-VO",
        "below ORB-VO",
        operator.lt,
    ),
)


def _headline(side: dict, h: Headline, precision: str) -> float | None:
    """``h``'s number of one side (the result or its "before" block); None if it has no such precision."""
    block = side[h.where][h.task]
    return _flatten(block[precision])[h.metric] if precision in block else None


def _side_text(label: str, model: dict) -> str:
    random = "; random-init weights" if model["random_init"] else ""
    return f"{label} `{model['dir']}` (checkpoint {_checkpoint_text(model['provenance'])}{random})"


def _before_after(result: dict) -> list[str]:
    """Section "Before / after": the headline numbers of the previous model and this one, with baseline,
    target and verdict; nothing without ``--before``."""
    before = result.get("before")
    if not before:
        return []
    rows = []
    for h in HEADLINES:
        baseline = _flatten(result[h.where][h.task][h.baseline])[h.metric]
        meets = h.meets(_headline(result, h, "fp32"), baseline)
        rows.append(
            [h.label.format(frames=_frame_span(result["kitti"]["frames"]))]
            + [sig3(_headline(side, h, p)) for side in (before, result) for p in ("fp32", "int8")]
            + [f"{sig3(baseline)} ({h.baseline_name})", h.target, "yes" if meets else "no"]
        )
    headers = [
        "",
        "before FP32",
        "before INT8",
        "after FP32",
        "after INT8",
        "baseline",
        "target",
        "after meets target?",
    ]
    return [
        "## Before / after",
        "",
        *_table(headers, rows),
        "",
        f"{_side_text('Before:', before['model'])}; {_side_text('after:', result['model'])}. Both were measured "
        "in this one run, on the same data and through the same code; the baselines are the rows of the tables "
        'below. Lower is better in every row; "after meets target?" judges the after model\'s FP32 number.',
        "",
    ]


# ----------------------------------------------------------------------------- manifest
METRIC_NAMES = {"abs_rel": "AbsRel", "noc.epe": "EPE-noc (px)", "ate_snippet.mean": "ATE (paper ÷N, mean)"}


def manifest_card(result: dict, card_path: str) -> dict:
    """The manifest's ``model_card`` block: what the model was trained on and the card's headline
    FP32 numbers, each beside its baseline (the same rows as the card's before/after table)."""
    m = result["model"]
    prov = m["provenance"]
    if m["random_init"]:
        trained_on, synthetic_only = "nothing: random-init weights (timing only)", False
    elif prov.get("sources"):
        trained_on, synthetic_only = f"the released GeoNet TensorFlow checkpoints ({prov['checkpoint']})", False
    elif result.get("real_training"):
        trained_on, synthetic_only = f"synthetic scenes made by training.synth, then {result['real_training']}", False
    else:
        data = f" ({prov['data_dir']})" if prov.get("data_dir") else ""
        trained_on, synthetic_only = f"synthetic scenes only{data}, made by training.synth", True
    data = {"kitti": _data_kitti(result).replace("`", ""), "synthetic": _data_synth(result).replace("`", "")}
    scores: dict[str, list] = {"real": [], "synthetic": []}
    for h in HEADLINES:
        scores["real" if h.where == "kitti" else "synthetic"].append(
            {
                "task": h.task,
                "metric": METRIC_NAMES[h.metric],
                "data": data[h.where],
                "value": _headline(result, h, "fp32"),
                "baseline": BASELINE_LABEL[h.baseline].removesuffix(" (baseline)"),
                "baseline_value": _flatten(result[h.where][h.task][h.baseline])[h.metric],
                "lower_is_better": True,
            }
        )
    return {
        "trained_on": trained_on,
        "synthetic_only": synthetic_only,
        "measured_in": card_path,
        "generated_utc": result["generated_utc"],
        **scores,
    }


def write_manifest_card(model_dir: str | Path, card: dict) -> Path:
    """Put ``card`` into the model directory's manifest as ``model_card``; every other key and the
    graph files stay as they are (the manifest is rewritten atomically, the graphs are not touched)."""
    path = Path(model_dir) / MANIFEST_NAME
    raw = json.loads(path.read_text())
    raw["model_card"] = card
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(raw, indent=2) + "\n")
    load_manifest(model_dir)  # what the runtime will read back: refuse to leave a manifest it cannot load
    return path


def _dir_bytes(model_dir: Path) -> int:
    return sum(f.stat().st_size for f in model_dir.rglob("*") if f.is_file())


def render_card(result: dict) -> str:
    """The Markdown card of a result (:func:`run`'s, or an earlier run's ``--json``), one function per section."""
    sections = (
        _header_section,
        _model_section,
        _before_after,
        _real_section,
        _experiment_section,
        _teacher_section,
        _files_section,
        _measured_section,
        _depth_section,
        _flow_pose_section,
        _int8_section,
        _limitations_section,
    )
    return "\n".join(line for section in sections for line in section(result)) + "\n"


def _real_section(result: dict) -> list[str]:
    """Section "Real data": every real set with ground truth, from ``python -m benchmarks.eval_all`` (``--real``)."""
    real = result.get("real")
    if not real:
        return []
    body = eval_all.markdown(real).rstrip("\n").splitlines()
    return [
        "## Real data: every set in ../shared with ground truth",
        "",
        f"Measured by `{real['command']} --json {result.get('real_json', 'REAL.json')}` (from the repository "
        f"root; {real['generated_utc']}) and rendered here from that JSON by "
        f"`{result.get('real_render_command', 'python -m benchmarks.model_card --real REAL.json ...')}`; every "
        "number below comes from that run, scored by the code of `geonet-infer eval` (`benchmarks/eval_all.py` on "
        "`geonet_infer.eval`).",
        "",
        *body[2:],  # its first line (model, command, date) is said above
        "",
        *_trained_real_frames_note(result),
    ]


def _experiment_rounds(result: dict) -> list[dict]:
    """The real-pose experiment's rounds in order (a card written before rounds were a list holds one)."""
    return result.get("experiments") or ([result["experiment"]] if result.get("experiment") else [])


def _trained_real_frames_note(result: dict) -> list[str]:
    """The real frames a shipped round of the real-pose experiment trained on: the pose rows of those
    sequences are not held out."""
    rounds = _experiment_rounds(result)
    shipped = [e for e in rounds if (e.get("verdict") or {}).get("ship")]
    if not shipped:
        return []
    spans = "; ".join(
        f"{name} frames {a}–{b}" for name, (a, b) in ((n, s) for n, s in shipped[-1]["train_frames"].items() if s)
    )
    return [
        f"**Not held out:** the model was fine-tuned on {spans} (the shipped round of the real-pose experiment), so "
        "the pose rows of those sequences include snippets it trained on; the experiment below scores the "
        "snippets it did not.",
        "",
    ]


EXPERIMENT_ROWS = (  # (label, key of benchmarks.real_pose_experiment.figures, judged by the rule)
    ("real pose ATE (paper ÷N), snippets not trained on", "pose_ate_held_out", True),
    ("real validation depth AbsRel", "validation_abs_rel", True),
    ("real pose ATE (paper ÷N), all snippets", "pose_ate_all", False),
)


def _experiment_section(result: dict) -> list[str]:
    """Section "Real-pose fine-tuning": per round, the rule written before scoring and, once scored,
    before/after."""
    rounds = _experiment_rounds(result)
    if not rounds:
        return []
    L = ["## Real-pose fine-tuning experiment (issue 32)", ""]
    for e in rounds:
        L += _experiment_round(e, titled=len(rounds) > 1)
    return L


def _teacher_section(result: dict) -> list[str]:
    """Section "Classical-teacher experiment" (:func:`benchmarks.teacher_experiment.render`)."""
    return teacher_experiment.render(result["teacher_rounds"]) if result.get("teacher_rounds") else []


def _experiment_round(e: dict, titled: bool) -> list[str]:
    trained = "; ".join(
        f"{name}: frames {span[0]}–{span[1]}" if span else f"{name}: none" for name, span in e["train_frames"].items()
    )
    L = [f"### Round {e.get('round', 1)}", ""] if titled else []
    L += [
        f"**Shipping rule.** {e['rule']}",
        "",
        f"Real odometry frames trained on: {trained} (`benchmarks/real_pose_experiment.py`). " + e.get("notes", ""),
        "",
    ]
    if "verdict" not in e:
        return L + ["Not scored yet.", ""]
    b, a = e["before"], e["after"]
    rows = []
    keys = [(label, key, judged) for label, key, judged in EXPERIMENT_ROWS]
    keys += [(k, k, False) for k in b["fp32"] if k not in {key for _, key, _ in EXPERIMENT_ROWS} and ":" in k]
    keys.append(("test drive depth AbsRel (not for choosing)", "test drive AbsRel", False))
    for label, key, judged in keys:
        cells = [sig3(side.get(p, {}).get(key)) for side in (b, a) for p in ("fp32", "int8")]
        rows.append([label + (" (rule)" if judged else "")] + cells)
    v = e["verdict"]
    decision = "**shipped**" if v["ship"] else "**not shipped**"
    L += _table(["", "bundled FP32", "bundled INT8", "candidate FP32", "candidate INT8"], rows)
    L += [
        "",
        f"Verdict: real pose improves: {'yes' if v['pose_improves'] else 'no'}; real validation depth not worse: "
        f"{'yes' if v['validation_not_worse'] else 'no'}: the candidate is {decision}. Candidate: {e['candidate']}; "
        f"bundled: `{e['before_command']}`, candidate: `{e['after_command']}` (snippet counts: "
        f"{a['fp32']['pose_snippets_held_out']} not trained on, {a['fp32']['pose_snippets_all']} in all).",
        "",
    ]
    return L


def _header_section(result: dict) -> list[str]:
    """Title, the command that regenerates the card, and the random-init warning."""
    m = result["model"]
    L = [
        f"# Model card: `{Path(m['dir']).name}`",
        "",
        "Regenerate this file (from the repository root; every number below comes from that run, "
        "none is typed by hand):",
        "",
        "```bash",
        result["command"],
        "```",
        "",
        f"Generated {result['generated_utc']} at git commit `{(result['git_commit'] or 'unknown')[:12]}` "
        "by `benchmarks/model_card.py`. All models run through the pip runtime "
        "(`geonet_infer.core.predictor.Predictor` on onnxruntime), exactly as users run them.",
        "",
    ]
    if result.get("real"):
        L += [
            "The section *Real data* comes from `python -m benchmarks.eval_all` (its own command is given there) "
            f"and was added with `--real {result.get('real_json', 'REAL.json')}`.",
            "",
        ]
    if result.get("real_training"):
        L += [f'What the model was trained on says `--real-training "{result["real_training"]}"` too.', ""]
    if m["random_init"]:
        L += [
            "> **⚠️ WARNING: RANDOM-INIT MODEL. This card was generated with `--allow-random-init` for a "
            "model directory whose graphs hold random, untrained weights (`random_init: true` in the "
            "manifest). Its accuracy numbers measure noise and say nothing about GeoNet. Do not publish "
            "or compare them; regenerate the card from a trained export.**",
            "",
        ]
    return L


def _model_section(result: dict) -> list[str]:
    """Section "The model": architecture and provenance, then the manifest's training metrics and INT8 settings."""
    m = result["model"]
    prov = m["provenance"]
    origin = _stage_origin(prov.get("training_command"))
    stage = prov.get("checkpoint_stage")
    stages = (f"`{stage}`, {origin}" if origin else f"`{stage}`") if stage else "n/a"
    rows = [
        [
            "architecture",
            f"`{m['arch']}` (DepthNet, PoseNet"
            + (", ResFlowNet" if "resflownet" in m["graphs"] else "; no ResFlowNet: flow = rigid flow")
            + ")",
        ],
        ["graphs", ", ".join(f"`{g}`" for g in m["graphs"])],
        ["input size", f"{m['height']}×{m['width']}, snippets of {m['seq_length']} frames (target in the middle)"],
        ["precisions", ", ".join(m["precisions"])],
        ["random init", str(m["random_init"])],
        ["training data", f"`{prov['data_dir']}`" if prov.get("data_dir") else "n/a"],
        ["training stage", stages],
        [
            "training steps (this stage)",
            sig3(prov["checkpoint_step"]) if prov.get("checkpoint_step") is not None else "n/a",
        ],
        ["training command", f"`{prov['training_command']}`" if prov.get("training_command") else "n/a"],
        ["checkpoint", _checkpoint_text(prov)],
        ["exported", f"{prov.get('export_date')} at git commit `{(prov.get('git_commit') or 'unknown')[:12]}`"],
        ["exporter", prov.get("exporter") or "n/a"],
        ["versions", ", ".join(f"{k} {v}" for k, v in sorted(prov.get("versions", {}).items())) or "n/a"],
    ]
    L = ["## The model", "", *_table(["", ""], rows), ""]
    if m["metrics"]:
        L += [
            "Checkpoint metrics recorded by training (from the manifest; validation split of the "
            "training data, not the held-out sequences):",
            "",
        ]
        L += _table(
            ["metric", "value"],
            [[f"`{k}`", sig3(v) if isinstance(v, (int, float)) else str(v)] for k, v in _flatten(m["metrics"]).items()],
        ) + [""]
    q = m["quantization"]
    if q:
        L += [
            "INT8 quantisation (from the manifest): "
            f"{q.get('method')}, activations {q.get('activation_type')}, weights {q.get('weight_type')}, "
            f"per-channel {q.get('per_channel')}, reduce-range {q.get('reduce_range')}, calibration "
            f"`{q.get('calibrate_method')}` on `{q.get('calibration_data')}` "
            f"({', '.join(f'{g}: {n}' for g, n in (q.get('calibration_samples') or {}).items())} inputs); "
            f"graphs kept in FP32: {', '.join(q.get('fp32_graphs') or []) or 'none'}; operator types quantised: "
            f"{', '.join(q.get('op_types') or []) or 'every type onnxruntime quantises'}.",
            "",
        ]
        for graph, notes in (q.get("graph_notes") or {}).items():
            L += [f"- {graph}: {line}" for line in notes] + [""]
    return L


def _files_section(result: dict) -> list[str]:
    """Section "Files": every graph file with its size and sha256 prefix, and the totals."""
    m = result["model"]
    L = [
        "## Files",
        "",
        f"Model directory `{m['dir']}`; sha256 from `manifest.json` (checked against the "
        "files when the model was loaded).",
        "",
    ]
    L += _table(
        ["precision", "graph", "file", "size", "sha256 (prefix)"],
        [
            [
                f["precision"],
                f["graph"],
                f"`{f['file']}`" + (" (FP32)" if f["file_precision"] != f["precision"] else ""),
                _mib(f["bytes"]),
                f"`{f['sha256'][:12]}`",
            ]
            for f in m["files"]
        ],
    ) + [""]
    totals: dict[str, int] = {}
    for f in m["files"]:
        totals[f["precision"]] = totals.get(f["precision"], 0) + f["bytes"]
    L += [
        "Total per precision (a precision's set includes the shared FP32 `rigidflow`): "
        + ", ".join(f"{p} {_mib(b)}" for p, b in totals.items())
        + f"; the whole directory, manifest included: {m['dir_bytes']:,} bytes ({_mib(m['dir_bytes'])}).",
        "",
    ]
    return L


def _measured_section(result: dict) -> list[str]:
    """Section "What was measured": data, protocol and baselines of each task."""
    s, k = result["synthetic"], result["kitti"]
    orb = s["pose"]["orb_vo_baseline"]
    return [
        "## What was measured",
        "",
        f"* **Synthetic held-out**: {_data_synth(result)}: sequences {', '.join(f'`{x}`' for x in s['sequences'])} "
        f"listed in `{s['prepared_dir']}/heldout.txt`, generated by `training.synth` and never trained on"
        + (f"; one frame / pair / snippet in {s['stride']} (`--stride {s['stride']}`)" if s["stride"] > 1 else "")
        + ". Depth: every pixel with ground truth (no crop), per-image median scaling, clamp to "
        f"[{MIN_DEPTH:g}, {result['settings']['max_depth']:g}] m "
        "(`geonet_infer.eval.evaluation.evaluate_depth`). Flow t→t+1 from the snippet "
        + (
            "[t−1, t, t+1]"
            if result["settings"]["flow_seq_length"] == 3
            else "pair [t, t+1] (padded by the runtime; `evaluate_flow` passes triplets only)"
        )
        + ", EPE and Fl (EPE > 3 px and > 5 %) on non-occluded (noc) and all in-view (occ) pixels "
        "(`geonet_infer.eval.evaluation.evaluate_flow`).",
        f"* **Pose**: ATE on {SNIPPET}-frame snippets (every target t = 2 … N−3"
        + (f", stride {s['stride']}" if s["stride"] > 1 else "")
        + ") against the synthetic ground-truth "
        "poses (`poses.txt`, camera-to-world, inverted to world→camera and put in the snippet's first-frame "
        f"coordinates with `metrics.snippet_poses_to_global`). Model trajectory: {s['pose']['method']}. "
        "`ATE, paper` is `metrics.ate_snippet`, the SfMLearner/GeoNet value with its quirk kept: "
        "√(Σ‖e‖²)/N, i.e. the true RMSE ÷ √5, with only a scale (no rotation) fitted per snippet. "
        "`ATE, true RMSE` is `metrics.ate_rmse_true` after the same alignment "
        "(`geonet_infer.eval.evaluation.evaluate_pose`). Units are the synthetic world's metres.",
        f"* **Real KITTI**: {_data_kitti(result)}, never trained on. Ground truth: "
        + (
            "the Velodyne scans projected by `geonet_infer.eval.velodyne.velodyne_to_depth_map` (camera 2, Velodyne "
            "forward distance)"
            if k["ground_truth"] == "velodyne"
            else "the sparse depth PNGs of `proj_depth/groundtruth/image_02`"
        )
        + f". Eigen protocol: {KITTI_CROP.capitalize()} crop, {k['min_depth']:g} < GT < "
        f"{k['max_depth']:g} m, per-image median scaling (or the camera height, rows so labelled), then clamp; "
        "the runtime returns depth at the input resolution.",
        "* **Baselines**: *constant depth* predicts one value per image; after median scaling that is the "
        "image's median GT depth. *Zero flow* predicts no motion; *DIS medium* is OpenCV's DIS optical flow, "
        "medium preset, on grey frames (`geonet_infer.eval.baselines.dis_flow`). *Identity pose* predicts no camera "
        "motion; its ATE is the snippet's own extent. The per-snippet least-squares scale can shrink any "
        "prediction to zero, so a model's ATE can never exceed the identity baseline's on the same snippet: "
        "the baseline is an upper bound, and the gap to it is what the pose network contributes. *ORB-VO* is "
        "two-view ORB visual odometry per consecutive pair (5-point essential matrix, `recoverPose`, unit-length "
        "steps, then the same per-snippet scale; `geonet_infer.eval.baselines.orb_vo`); "
        f"{orb['failed_pairs']} of its {orb['pairs']} pairs failed and repeated the previous step. Every baseline "
        "is the function `geonet-infer eval --method` runs (`geonet_infer.eval.evaluation.baseline_fns`).",
        "",
    ]


def _per_frame_label(key: str) -> str:
    """Column header of the per-frame AbsRel table: "FP32", "FP32, camera height", "constant depth"."""
    if key.endswith("_camera_height"):
        return f"{PRECISION_LABEL[key[: -len('_camera_height')]].removeprefix('model, ')}, camera height"
    return PRECISION_LABEL.get(key, "constant depth")


def _per_frame_cell(row: dict) -> str:
    return "no ground plane" if row.get("ground_fit") == "failed" else sig3(row["abs_rel"])


def _depth_section(result: dict) -> list[str]:
    """Section "Depth": synthetic and KITTI tables, the depth-floor and camera-height notes, AbsRel per KITTI frame."""
    d, kd = result["synthetic"]["depth"], result["kitti"]["depth"]
    L = ["## Depth", "", "### Synthetic held-out sequences", ""]
    L += _depth_table(d, _data_synth(result), "frames") + [""]
    L += ["### Real KITTI (Velodyne ground truth)", ""]
    L += _depth_table(kd, _data_kitti(result), "frames") + [""]
    L += _floor_text(kd, result["before"]["kitti"]["depth"] if result["before"] else None)
    L += _camera_height_text(kd)
    L += ["Per KITTI frame (AbsRel):", ""]
    keys = [c for p in ("fp32", "int8") if p in kd for c in (p, f"{p}_camera_height")]
    keys.append("constant_baseline")
    L += _table(
        ["frame"] + [_per_frame_label(c) for c in keys] + ["GT pixels"],
        [
            [f["frame"]] + [_per_frame_cell(f[c]) for c in keys] + [sig3(f["constant_baseline"]["n_valid"])]
            for f in kd["per_frame"]
        ],
    ) + [""]
    return L


def _flow_pose_section(result: dict) -> list[str]:
    """Sections "Optical flow" and "Camera pose": their tables, and a warning per precision whose camera stays put."""
    s = result["synthetic"]
    synth_data = _data_synth(result)
    L = ["## Optical flow (synthetic held-out sequences)", ""]
    L += _flow_table(s["flow"], synth_data) + [""]
    L += ["## Camera pose (synthetic held-out sequences, 5-frame snippets)", ""]
    L += _pose_table(s["pose"], synth_data) + [""]
    for p in ("fp32", "int8"):
        n = s["pose"].get(p, {}).get("static_snippets", 0)
        if n:
            L += [
                f"**{PRECISION_LABEL[p]}: in {n} of {s['pose']['snippets']} snippets the predicted camera "
                "does not move at all** (every chained position exactly 0), so there its ATE is the identity "
                "baseline's. The pose matrices this precision returns carry no motion there; check its "
                "PoseNet graph.",
                "",
            ]
    return L


INT8_METRIC_NAMES = {
    "abs_rel": "AbsRel",
    "sq_rel": "SqRel",
    "rmse": "RMSE",
    "rmse_log": "RMSElog",
    "a1": "δ<1.25",
    "noc.epe": "EPE noc",
    "occ.epe": "EPE occ",
    "noc.fl": "Fl noc",
    "occ.fl": "Fl occ",
    "ate_snippet.mean": "ATE paper (mean)",
    "ate_rmse_true.mean": "ATE true RMSE (mean)",
}


def _int8_section(result: dict) -> list[str]:
    """Section "INT8 versus FP32": this run's differences, then the check the export recorded in the manifest."""
    m = result["model"]
    L = ["## INT8 versus FP32", ""]
    if result["int8_delta"]:
        data = {"synthetic": _data_synth(result), "kitti": _data_kitti(result)}
        L += [
            "Difference INT8 − FP32 on the same frames (positive = INT8 larger; for δ<1.25 larger is "
            "better, for the errors smaller is better):",
            "",
        ]
        L += _table(
            ["data", "task", "metric", "FP32", "INT8", "INT8 − FP32", "relative"],
            [
                [
                    data["synthetic"] if r["data"] == "synthetic" else data["kitti"],
                    r["task"],
                    INT8_METRIC_NAMES[r["metric"]],
                    sig3(r["fp32"]),
                    sig3(r["int8"]),
                    signed3(r["delta"]),
                    "n/a" if r["relative"] is None else signed3(100 * r["relative"]) + " %",
                ]
                for r in result["int8_delta"]
            ],
        ) + [""]
    else:
        L += [f"This model directory has no INT8 graphs (the manifest lists only {', '.join(m['precisions'])}).", ""]
    q = m["quantization"]
    if q and isinstance(q.get("accuracy_delta"), dict):
        acc = q["accuracy_delta"]
        rows = [
            [f"`{k}`", sig3(v["fp32"]), sig3(v["int8"]), signed3(v["delta"])]
            for k, v in acc.items()
            if isinstance(v, dict) and {"fp32", "int8", "delta"} <= set(v)
        ]
        if rows:
            L += [
                "For comparison, the INT8 check the export itself recorded in the manifest "
                "(`quantization.accuracy_delta`, also through the runtime's Predictor; "
                f"data `{acc.get('synth_dir')}`, stride {acc.get('stride')}):",
                "",
            ]
            L += _table(["metric", "FP32", "INT8", "INT8 − FP32"], rows) + [""]
    if q and q.get("accuracy_delta_reason"):
        L += [f"Export note on the INT8 check: {q['accuracy_delta_reason']}.", ""]
    return L


def _limitations_section(result: dict) -> list[str]:
    """Section "Limitations", with the FP32 numbers each one rests on."""
    m = result["model"]
    prov = m["provenance"]
    s, kd = result["synthetic"], result["kitti"]["depth"]
    best = "fp32"
    L = ["## Limitations", ""]
    if m["random_init"]:
        L += ["* **The weights are random (development card).** Nothing below describes a trained model."]
    trained_on = f" (`{prov['data_dir']}`)" if prov.get("data_dir") else ""
    if result.get("real_training"):
        data = (
            f"* **Mostly synthetic training data.** The model learned on procedurally generated driving sequences "
            "(`training.synth`: boxes on a flat road, Lambertian shading, no sensor noise; see "
            f"`docs/synthetic_data.md`), then {result['real_training']}; its last stage trained on{trained_on}."
        )
    else:
        data = (
            "* **Synthetic training data.** The model is trained only on procedurally generated driving "
            f"sequences{trained_on} (`training.synth`: boxes on a flat road, Lambertian shading, no sensor noise; "
            "see `docs/synthetic_data.md`)."
        )
    L += [
        data + " The held-out synthetic numbers come from the same generator and overstate what to expect on "
        "real video.",
        _real_depth_limitation(result),
        "* **Relative scale.** Depth and camera translation are known only up to an unknown scale. Every "
        "depth number except the camera-height rows uses per-image median scaling with the ground truth and "
        "every ATE a per-snippet scale fit, so those do not measure metric scale. " + _camera_height_limitation(kd),
        "* **Pose ATE on 5-frame snippets** hides drift and most rotation error, and the paper's value "
        "divides by N (it is the true RMSE ÷ √5). " + _real_pose_limitation(result),
        "* **Flow** is compared with zero flow and OpenCV DIS (medium preset), not with a learned flow method "
        f"(FP32 EPE noc {sig3(s['flow'][best]['noc']['epe'])} px vs "
        f"{sig3(s['flow']['zero_flow_baseline']['noc']['epe'])} px for zero flow and "
        f"{sig3(s['flow']['dis_medium_baseline']['noc']['epe'])} px for DIS medium" + _real_flow_limitation(result),
        "",
    ]
    return L


def _real_sets(result: dict, task: str) -> list[dict]:
    return [x for x in (result.get("real") or {}).get("sets", []) if x["task"] == task]


def _real_depth_limitation(result: dict) -> str:
    """The real-depth bullet: the test drive, and with ``--real`` the real validation frames."""
    kd, sd = result["kitti"]["depth"], result["synthetic"]["depth"]
    model, const = kd["fp32"]["abs_rel"], kd["constant_baseline"]["abs_rel"]
    synth_model, synth_const = sd["fp32"]["abs_rel"], sd["constant_baseline"]["abs_rel"]
    synth = (
        f"on the synthetic held-out set it is {sig3(synth_model)} vs {sig3(synth_const)} "
        f"({_compare(synth_model, synth_const)} the baseline)"
    )
    v = (result.get("real") or {}).get("validation") or {}
    if not v.get("metrics", {}).get("fp32"):
        return (
            f"* **Real-data depth is measured on {kd['frames']} KITTI frames only** (one drive, consecutive "
            f"frames, so they are far from independent). On them the FP32 model's AbsRel ({sig3(model)}) is "
            f"{_compare(model, const)} the constant-depth baseline ({sig3(const)}); {synth}. This is no "
            "substitute for the 697-image Eigen split."
        )
    vm, vc = v["metrics"]["fp32"]["abs_rel"], v["metrics"]["constant"]["abs_rel"]
    return (
        f"* **Real-data depth is measured on few frames.** On the test drive ({kd['frames']} consecutive frames "
        f"of one drive) the FP32 model's AbsRel ({sig3(model)}) is {_compare(model, const)} the constant-depth "
        f"baseline ({sig3(const)}); on the real validation frames ({v['frames']} frames of other drives and "
        f"scenes, see Real data) it is {sig3(vm)} vs {sig3(vc)} ({_compare(vm, vc)} the baseline); {synth}. "
        "This is no substitute for the 697-image Eigen split."
    )


def _real_pose_limitation(result: dict) -> str:
    sets = _real_sets(result, "pose")
    if not sets:
        return (
            "There is no real-data pose or flow evaluation here (the KITTI frames have no poses and no flow "
            "ground truth)."
        )
    per_set = "; ".join(
        f"{x['name']}: {sig3(x['results']['fp32']['metrics']['ate_snippet'])} vs ORB-VO "
        f"{sig3(x['results']['orb_vo']['metrics']['ate_snippet'])} and identity "
        f"{sig3(x['results']['identity']['metrics']['ate_snippet'])}"
        for x in sets
        if "fp32" in x["results"]
    )
    snippets = sum(x["items"] for x in sets)
    return f"On real KITTI odometry ({snippets} snippets, grey frames) the FP32 ATE (paper) is {per_set}."


def _real_flow_limitation(result: dict) -> str:
    """The end of the flow bullet: synthetic only, or also the real pairs of ``--real``."""
    sets = [x for x in _real_sets(result, "flow") if "fp32" in x["results"]]
    if not sets:
        return "), on synthetic data only."
    real = "; ".join(
        f"{x['name']} ({_count(x['items'], 'pairs')}): {sig3(x['results']['fp32']['metrics']['epe_noc'])} px vs "
        f"{sig3(x['results']['zero_flow']['metrics']['epe_noc'])} px and "
        f"{sig3(x['results']['dis_medium']['metrics']['epe_noc'])} px"
        for x in sets
    )
    return f" on synthetic data; on real KITTI flow, {real})."


def _count(n: int, label: str) -> str:
    return f"{n} {label if n != 1 else label.removesuffix('s')}"


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
        help="the JSON of `python -m benchmarks.real_pose_experiment`: its shipping rule and, once scored, its "
        "before/after numbers and verdict (repeat for each round, in order)",
    )
    p.add_argument(
        "--teacher",
        metavar="JSON",
        action="append",
        help="the JSON of `python -m benchmarks.teacher_experiment` (repeat for each round, in order)",
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
    """The JSON of ``benchmarks.real_pose_experiment`` (the rule, and the scores once measured)."""
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


if __name__ == "__main__":
    sys.exit(main())
