"""``python -m benchmarks.eval_all``: a model and the classical baselines on every real set with ground truth.

This repository's catalogue of real sets (:data:`REAL_SETS`, folders under ``../shared/realdata``) and
its test drive: developer tooling, not part of the wheel (issue 42). Each set is read by its
:mod:`geonet_infer.eval.datasets` layout and scored by :mod:`geonet_infer.eval.evaluation`, exactly as
``geonet-infer eval depth|flow|pose`` would score it: the model at every precision its manifest has
(FP32 and INT8) beside the baselines of the task (depth: constant depth; flow: DIS medium and zero
flow; pose: ORB-VO and identity pose).

It also computes the **real validation figure**: the mean over every real depth frame *outside*
the test drive ``kitti_raw_2011_09_26_sfnd`` (the KITTI object frames, KITTI 2015 scene 000046 and
the two stereo-SGBM frames of :mod:`geonet_infer.eval.stereo`), each frame weighing the same. Model
choices are made on that figure, never on the test drive.

:func:`run` returns a JSON-able dict; :func:`markdown` renders it (sets, then one row per (set,
metric) with the model and the baselines side by side); :func:`main` is the command line.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import shlex
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geonet_infer.cli import run_reporting_errors
from geonet_infer.cli.common import add_model_args, load_predictor
from geonet_infer.engines import BACKENDS
from geonet_infer.errors import InputError
from geonet_infer.eval import evaluation, metrics, stereo
from geonet_infer.eval.datasets import Dataset, load_dataset
from geonet_infer.io.atomic import atomic_write

PROG = "python -m benchmarks.eval_all"

TEST_DRIVE = "kitti_raw_2011_09_26_sfnd"
# Where a KITTI 2015 scene of the extract has no calibration file, eval_all uses these values and says so.
# 2011_09_26's P_rect_02 (the test drive's calibration file); KITTI 2015 scenes come from days with
# fx 707.05-721.54 px, so metric depth from it carries up to 2 % scale uncertainty (median-scaled
# metrics are unaffected: every disparity of 000046 gives a depth under 80 m with either fx).
KITTI_2015_ASSUMED_K = (721.5377, 721.5377, 609.5593, 172.854)  # fx, fy, cx, cy
KITTI_BASELINE_M = 0.54  # KITTI's documented stereo baseline


@dataclass(frozen=True)
class RealSet:
    """One real set: where it is, how to read it, and what it is."""

    name: str  # row label
    task: str  # depth, flow or pose
    path: str  # folder under the real-data root ("" for a derived set, see ``build``)
    layout: str
    drive: str
    camera: str
    scene: str
    ground_truth: str
    role: str = ""  # "test" (never choose a model on it), "validation" (the real validation figure) or ""
    options: dict = field(default_factory=dict)  # layout options (kitti-disparity: fx, baseline)
    intrinsics: tuple[float, float, float, float] | None = None  # K for the model where the folder has none
    notes: tuple[str, ...] = ()
    sources: tuple[str, ...] = ()  # folders a derived set is made from (they must all be present)
    build: Callable[[Path, Path], object] | None = None  # build(real-data root, out folder): writes the set


ASSUMED_K_NOTE = (
    "no calibration in the extract: K assumed to be KITTI 2011_09_26's P_rect_02 (fx 721.5377, cx 609.5593, "
    "cy 172.854); KITTI 2015 scenes come from days with fx 707.05–721.54 px"
)

REAL_SETS: tuple[RealSet, ...] = (
    RealSet(
        "KITTI raw 2011_09_26 (test drive)",
        "depth",
        TEST_DRIVE,
        "kitti-raw",
        "KITTI raw 2011_09_26, one drive, frames 0–9 of 78 consecutive",
        "colour cam 2, 1242×375",
        "stop-and-go traffic behind a car under a motorway overpass",
        "Velodyne scans projected with the day's calibration",
        role="test",
        notes=("the test drive: never train, calibrate or choose a model on it",),
    ),
    RealSet(
        "KITTI object 000000–000002",
        "depth",
        "kitti_object_3frames",
        "kitti-object",
        "KITTI object benchmark training 000000–000002 (two recording days: fx 707.05 and 721.54)",
        "colour cam 2, 1224×370 and 1242×375",
        "three unrelated frames: campus walkway with a pedestrian, road beside tram tracks, residential lane",
        "Velodyne scans projected with each frame's calib (P2·R0_rect·Tr_velo_to_cam)",
        role="validation",
    ),
    RealSet(
        "KITTI 2015 stereo 000046",
        "depth",
        "kitti2015_000046_stereo",
        "kitti-disparity",
        "KITTI 2015 stereo training scene 000046 (recording day unknown)",
        "colour cam 2, 1242×375",
        "urban crossroads with traffic lights, a car turning",
        "disp_occ_0 disparity, depth = fx·0.54 m/d",
        role="validation",
        options={"fx": KITTI_2015_ASSUMED_K[0], "baseline": KITTI_BASELINE_M},
        notes=(
            "no calibration in the extract: fx 721.5377 px (2011_09_26) and KITTI's 0.54 m baseline are "
            "passed as --fx/--baseline; other days' fx (707.05–721.54) would scale metric depth by ≤ 2 %, "
            "the median-scaled metrics here not at all",
        ),
    ),
    RealSet(
        "stereo SGBM, odometry 00 + 06",
        "depth",
        "",
        "kitti-raw",
        "KITTI odometry 00 frame 0 (raw 2011_10_03 drive 0027) and 06 frame 12 (2011_09_30 drive 0020)",
        "grey cams 0/1 (00) and colour cams 2/3 (06), 1241×376 and 1226×370",
        "residential streets with parked cars",
        "OpenCV SGBM depth, left-right checked (geonet_infer.eval.stereo, as training.stereo_val writes it)",
        role="validation",
        sources=("kitti_odometry_00", "kitti_odometry_06"),
        build=stereo.build,
        notes=("a noisy yardstick: SGBM errs at occlusions and on thin poles",),
    ),
    RealSet(
        "KITTI 2015 flow 000010",
        "flow",
        "kitti2015_flow_000010",
        "kitti",
        "KITTI 2015 flow training pair 000010 (_10 → _11, no _09)",
        "colour cam 2, 1242×375",
        "crossroads with traffic lights and passing cars",
        "flow_occ (all) and flow_noc",
        intrinsics=KITTI_2015_ASSUMED_K,
        notes=(ASSUMED_K_NOTE + " (the model's rigid flow needs K)",),
    ),
    RealSet(
        "KITTI odometry 00",
        "pose",
        "kitti_odometry_00/sequences/00",
        "kitti-odometry",
        "KITTI odometry 00 (raw 2011_10_03 drive 0027), frames 0–5",
        "grey cam 0, 1241×376",
        "residential street, driving straight",
        "official poses (GPS/INS)",
    ),
    RealSet(
        "KITTI odometry 06",
        "pose",
        "kitti_odometry_06/sequences/06",
        "kitti-odometry",
        "KITTI odometry 06 (raw 2011_09_30 drive 0020), frames 0–50",
        "grey cam 0, 1226×370",
        "suburban street with parked cars",
        "official poses (GPS/INS)",
    ),
    RealSet(
        "KITTI odometry 01",
        "pose",
        "kitti_odometry_01/sequences/01",
        "kitti-odometry",
        "KITTI odometry 01 (raw 2011_10_03 drive 0042), frames 0–50",
        "grey cam 0, 1241×376",
        "motorway",
        "official poses (GPS/INS)",
    ),
)

# Folders of the real-data root that eval_all does not score, and why (anything else is named as unknown).
NOT_SCORED = {
    "middlebury_flow": "rendered scenes, not real footage (score it with `geonet-infer eval flow`)",
    "euroc_v1_01_micro": "the MAV stands still on the ground in these 20 frames (and no eval layout reads TUM poses)",
    "rgbd_kinect_slambook": "indoor Kinect frames, five sparse views; no eval layout reads them",
    "udacity_dashcam": "no ground truth",
}

# The methods of each task: key, row label, and the baseline function (None: the model at one precision).
BASELINES = {
    "depth": (("constant", "constant depth", "depth", "constant"),),
    "flow": (("dis_medium", "DIS medium", "flow", "dis-medium"), ("zero_flow", "zero flow", "flow", "zero")),
    "pose": (("orb_vo", "ORB-VO", "pose", "orb-vo"), ("identity", "identity pose", "pose", "identity")),
}
PRECISION_LABEL = {"fp32": "model FP32", "int8": "model INT8"}
COUNT_LABEL = evaluation.COUNT_LABEL
METRIC_KEYS = {
    task: [(header, key, fmt) for header, key, fmt in evaluation.COLUMNS[task]] for task in evaluation.COLUMNS
}
Progress = Callable[[str], None]


def _baseline_fn(task: str, method: str) -> Callable:
    (fn,) = evaluation.baseline_fns(task, method).values()
    return fn


def _score(task: str, fn: Callable, dataset: Dataset, label: str, intrinsics) -> dict:
    if task == "depth":
        return evaluation.evaluate_depth(fn, dataset, method=label)
    if task == "flow":
        return evaluation.evaluate_flow(fn, dataset, method=label, intrinsics=intrinsics)
    return evaluation.evaluate_pose(fn, dataset, method=label)


def _frames_used(dataset: Dataset) -> int:
    """Distinct image files the items read (a pose snippet shares four of its five frames)."""
    paths: set[Path] = set()
    for item in dataset.items:
        paths.update(getattr(item, "frames", None) or [item.image])
    return len(paths)


def _model_info(predictors: dict) -> dict:
    first = next(iter(predictors.values()))
    manifest = first.manifest
    model_dir = Path(first.model_dir).resolve()
    try:  # relative to where the command ran (the repository root for the docs): no machine path in them
        shown = str(model_dir.relative_to(Path.cwd().resolve()))
    except ValueError:
        shown = str(model_dir)
    return {
        "dir": shown,
        "name": model_dir.name,
        "precisions": list(predictors),
        "graphs": {p: {name: manifest.graph(name, p).sha256 for name in manifest.graph_names(p)} for p in predictors},
    }


def run(
    root: Path,
    predictors: dict,
    *,
    command: str = "",
    progress: Progress = lambda msg: None,
    allow_random_init: bool = False,
) -> dict:
    """Score ``predictors`` ({precision: Predictor}) and the baselines on every set of :data:`REAL_SETS`
    under ``root``; a set whose folder is missing is listed in ``missing``, not silently dropped.
    ``allow_random_init``: score random-init graphs too (development and tests only)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "real-data folder not found", "pass --data ../shared/realdata")
    sets: list[dict] = []
    missing: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="geonet_eval_all_") as tmp:
        for real in REAL_SETS:
            needed = real.sources if real.build else (real.path,)
            absent = [p for p in needed if not (root / p).exists()]
            if absent:
                missing.append({"set": real.name, "task": real.task, "missing": absent})
                continue
            folder = root / real.path
            if real.build:  # derived ground truth (stereo SGBM): built as its own tool writes it, then read
                folder = Path(tmp) / f"set{len(sets)}"
                real.build(root, folder)
            progress(f"{real.name}: {real.task}")
            sets.append(_score_set(real, folder, predictors, progress, allow_random_init))
    present = {p.split("/")[0] for real in REAL_SETS for p in (real.sources or (real.path,))}
    not_scored = [
        {"folder": d.name, "why": NOT_SCORED.get(d.name, "no entry in benchmarks.eval_all.REAL_SETS")}
        for d in sorted(root.iterdir())
        if d.is_dir() and d.name not in present and not d.name.startswith(".")
    ]
    return {
        "command": command,
        "generated_utc": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        "data": str(root),
        "model": _model_info(predictors),
        "sets": sets,
        "validation": validation_figure(sets),
        "missing": missing,
        "not_scored": not_scored,
    }


def _score_set(real: RealSet, folder: Path, predictors: dict, progress: Progress, allow_random_init: bool) -> dict:
    dataset = load_dataset(real.task, folder, real.layout, options=real.options)
    K = None
    if real.intrinsics is not None:
        fx, fy, cx, cy = real.intrinsics
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    methods: list[tuple[str, str, Callable]] = []
    skipped = []
    for precision, predictor in predictors.items():
        lacking = predictor.missing_graphs(real.task)
        if lacking:
            skipped.append(f"{PRECISION_LABEL[precision]}: the model has no {', '.join(lacking)} graph")
            continue
        fn = evaluation.model_fn(real.task, predictor, allow_random_init)
        methods.append((precision, PRECISION_LABEL[precision], fn))
    for key, label, task, method in BASELINES[real.task]:
        methods.append((key, label, _baseline_fn(task, method)))
    results = {}
    for key, label, fn in methods:
        progress(f"  {label}")
        r = _score(real.task, fn, dataset, label, K)
        results[key] = {
            "label": label,
            "metrics": r["metrics"],
            "std": r.get("std"),
            "errors": r["errors"],
            "items": r["items"],
        }
        if "ground_truth" in r:  # depth: the same for every method
            gt = r["ground_truth"]
    out = {
        "name": real.name,
        "task": real.task,
        "path": real.path or " + ".join(real.sources),
        "layout": dataset.layout,
        "drive": real.drive,
        "camera": real.camera,
        "scene": real.scene,
        "ground_truth": real.ground_truth,
        "role": real.role,
        "items": len(dataset.items),
        "item_label": COUNT_LABEL[real.task],
        "frames": _frames_used(dataset),
        "description": dataset.description,
        "notes": list(real.notes) + list(dataset.notes) + skipped,
        "warnings": list(dataset.warnings),
        "frames_without_gt": len(dataset.without_gt),
        "details": dataset.details,
        "results": results,
    }
    if real.task == "depth":
        out["gt"] = gt
    return out


def validation_figure(sets: list[dict]) -> dict:
    """Per-frame means over the depth frames of every "validation" set, per method (each frame weighs
    the same; the sets' own means weigh by their frame count). NaN frames stay NaN in the mean."""
    chosen = [s for s in sets if s["task"] == "depth" and s["role"] == "validation"]
    keys = [k for _, k, _ in METRIC_KEYS["depth"]]
    methods = [m for m in ("fp32", "int8", "constant") if chosen and all(m in s["results"] for s in chosen)]
    out: dict = {
        "sets": [s["name"] for s in chosen],
        "frames": sum(s["items"] for s in chosen),
        "frames_per_set": {s["name"]: s["items"] for s in chosen},
        "excludes": TEST_DRIVE,
        "metrics": {},
    }
    for m in methods:
        rows = [{k: row[k] for k in keys} for s in chosen for row in s["results"][m]["items"]]
        out["metrics"][m] = metrics.aggregate(rows) | {"label": chosen[0]["results"][m]["label"]}
    return out


# ----------------------------------------------------------------------------- markdown
def _fmt(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a" if value is None else "nan"
    return fmt.format(value)


def _method_order(task: str, results: dict) -> list[str]:
    order = ["fp32", "int8"] + [key for key, *_ in BASELINES[task]]
    return [k for k in order if k in results]


def markdown(result: dict) -> str:
    """The eval-all result as markdown: what each set is, then per task one row per (set, metric)."""
    model = result["model"]
    L = [
        f"Model `{model['name']}` ({', '.join(p.upper() for p in model['precisions'])}) on every real set of "
        f"`{result['data']}` with ground truth, beside the classical baselines; "
        f"`{result['command']}`, {result['generated_utc']}.",
        "",
        "| set | task | drive / frames | camera | scene | ground truth | scored | role |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in result["sets"]:
        scored = _count(s["items"], s["item_label"]) + (f" ({s['frames']} frames)" if s["task"] != "depth" else "")
        L.append(
            f"| {s['name']} | {s['task']} | {s['drive']} | {s['camera']} | {s['scene']} | {s['ground_truth']} "
            f"| {scored} | {s['role'] or '–'} |"
        )
    L.append("")
    for task in ("depth", "flow", "pose"):
        sets = [s for s in result["sets"] if s["task"] == task]
        if not sets:
            continue
        L += _task_table(task, sets, result["validation"] if task == "depth" else None)
    L += _notes(result)
    return "\n".join(L) + "\n"


def _count(n: int, label: str) -> str:
    """``3 frames``, ``1 frame``, ``1 pair``."""
    return f"{n} {label if n != 1 else label.removesuffix('s')}"


def _task_table(task: str, sets: list[dict], validation: dict | None) -> list[str]:
    methods = _method_order(task, sets[0]["results"])
    labels = [sets[0]["results"][m]["label"] for m in methods]
    title = {"depth": "Depth (per-image median scaling, Garg crop, 80 m)", "flow": "Optical flow", "pose": "Pose"}
    extra = {"depth": "", "flow": "", "pose": " (5-frame snippets; mean ± std)"}
    L = [f"### {title[task]}{extra[task]}", ""]
    L.append("| set | metric | " + COUNT_LABEL[task] + " | " + " | ".join(labels) + " |")
    L.append("|---|---|---|" + "---|" * len(labels))
    for s in sets:
        for header, key, fmt in METRIC_KEYS[task]:
            cells = []
            for m in methods:
                r = s["results"].get(m)
                if r is None:
                    cells.append("–")
                    continue
                cell = _fmt(r["metrics"].get(key), fmt)
                if task == "pose" and r.get("std"):
                    cell += " ± " + _fmt(r["std"].get(key), fmt)
                cells.append(cell)
            L.append(f"| {s['name']} | {header} | {s['items']} | " + " | ".join(cells) + " |")
    if validation and validation["metrics"]:
        name = "**real validation** (depth frames outside the test drive)"
        for header, key, fmt in METRIC_KEYS["depth"]:
            cells = [
                f"**{_fmt(validation['metrics'][m][key], fmt)}**" if m in validation["metrics"] else "–"
                for m in methods
            ]
            L.append(f"| {name} | {header} | {validation['frames']} | " + " | ".join(cells) + " |")
    L.append("")
    return L


def _notes(result: dict) -> list[str]:
    L = []
    v = result["validation"]
    if v["sets"]:
        per_set = ", ".join(f"{name}: {_count(n, 'frames')}" for name, n in v["frames_per_set"].items())
        L.append(
            f"**Real validation**: the mean over the {v['frames']} real depth frames outside the test drive "
            f"`{v['excludes']}` ({per_set}), each frame weighing the same. Model choices are made on it, never "
            "on the test drive."
        )
        L.append("")
    for s in result["sets"]:
        notes = [*s["notes"], *(f"warning: {w}" for w in s["warnings"])]
        if s["task"] == "depth":
            notes.append(evaluation.ground_truth_line(s["gt"]))
        errors = [f"{r['label']}: {e['item']}: {e['problem']}" for r in s["results"].values() for e in r["errors"]]
        notes += [f"error: {e}" for e in errors]
        for note in notes:
            L.append(f"* {s['name']}: {note}")
    for m in result["missing"]:
        L.append(f"* **not scored, folder missing**: {m['set']} ({', '.join(m['missing'])})")
    for n in result["not_scored"]:
        L.append(f"* not scored: `{n['folder']}`: {n['why']}")
    return L + [""] if L else L


# ----------------------------------------------------------------------------- command line
HELP = """\
Score a model at every precision it has (FP32 and INT8) and the classical baselines (constant
depth; DIS medium, zero flow; ORB-VO, identity pose) on each real set with ground truth of this
repository's real-data folder: KITTI raw 2011_09_26 (the test drive), KITTI object 000000-000002,
KITTI 2015 stereo 000046 and the stereo-SGBM frames of odometry 00/06 (depth), KITTI 2015 flow
000010 (flow), KITTI odometry 00, 06, 01 (pose). One row per (set, metric), frames counted, what
each set is (drive, camera, scene), and the real validation figure: the mean over the real depth
frames outside the test drive, on which models are chosen. --markdown FILE and --json FILE keep
it; the JSON records the command that reproduces its numbers.

Each set is scored as `geonet-infer eval depth|flow|pose` scores its folder (those commands take
one folder and its own options). This catalogue of ../shared folders is the repository's, not the
wheel's: run it from the repository root.

exit codes: 0 done; 1 a set's folder is missing or a prediction held NaN/inf; 2 bad usage or data
(one line naming the file); 3 a file could not be read or written; 130 interrupted

examples (from the repository root):
  python -m benchmarks.eval_all --data ../shared/realdata --json docs/real_eval.json --markdown docs/real_eval.md
  python -m benchmarks.eval_all --data ../shared/realdata --model runs/real_pose/model --threads 1
"""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # bad usage: one line, as the geonet-infer errors are
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="the real-data folder (../shared/realdata)")
    # every precision of the model is scored, and the rigid-flow op is the reference graph: no flags for them
    add_model_args(parser, precision=False, rigid_op=False)
    parser.add_argument("--json", type=Path, default=None, help="also write every result and item here")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the printed tables here")
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # 2 on bad usage, 0 on --help
        return int(exc.code or 0)
    return run_reporting_errors(PROG, lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    predictors = {"fp32": load_predictor(argparse.Namespace(**vars(args), precision="fp32"))}
    for precision in predictors["fp32"].manifest.precisions:
        if precision != "fp32":
            predictors[precision] = load_predictor(argparse.Namespace(**vars(args), precision=precision))
    # the command that reproduces the numbers (output files left out: they do not change them)
    words = ["python", "-m", "benchmarks.eval_all", "--data", str(args.data)]
    for flag, value in (("--model", args.model), ("--backend", args.backend), ("--threads", args.threads)):
        if value is not None and not (flag == "--backend" and value == BACKENDS[0]):
            words += [flag, str(value)]
    result = run(args.data, predictors, command=shlex.join(words), progress=_progress)
    text = markdown(result)
    print(text, end="")
    if args.markdown:
        with atomic_write(args.markdown) as tmp:
            tmp.write_text(text)
    if args.json:
        evaluation.write_json(args.json, result)
    errors = [e for s in result["sets"] for r in s["results"].values() for e in r["errors"]]
    return 1 if errors or result["missing"] else 0


def _progress(message: str) -> None:
    print(f"{PROG}: {message}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
