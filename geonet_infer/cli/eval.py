"""``geonet-infer eval``: score a model (ONNX) or a classical baseline in the paper's terms."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from geonet_infer.cli import COMMANDS
from geonet_infer.cli.common import add_model_args, load_predictor, parse_intrinsics, positive_int
from geonet_infer.errors import InputError
from geonet_infer.eval import evaluation
from geonet_infer.eval.datasets import EVAL_TASKS, LAYOUTS, REGISTRY, load_dataset, read_heldout
from geonet_infer.io.atomic import atomic_write

HELP_TEMPLATE = """\
Score depth, optical flow or camera pose against ground truth, with the GeoNet paper's
protocols, and print a table in the paper's column order (JSON with every item via --json).

  depth  Eigen metrics AbsRel SqRel RMSE RMSElog δ<1.25 δ<1.25² δ<1.25³; per-image median
         scaling, then clamp to [0.001, --max-depth]; Garg crop on KITTI, every GT pixel on
         synthetic frames (--crop to change). --camera-height M scales each frame instead so
         the ground plane fitted to the prediction lies M metres below the camera (no ground
         truth used; 1.65 for KITTI); a frame without a plausible ground plane is not scored,
         named on stderr and counted in the table (exit code 1). The line under the table
         gives the ground truth scored: frames, pixels inside the mask, depth range.
  flow   average end-point error on non-occluded (Noc) and all (All) GT pixels, and Fl
         (outliers: EPE > 3 px and > 5 %); predictions resized to the GT size (nearest,
         vectors scaled).
  pose   ATE on 5-frame snippets with the paper's alignment (first positions matched, one
         least-squares scale): the paper's value divides by N, not √N (a quirk kept for
         comparability: it is NOT an RMSE), so the true RMSE is printed beside it. Where the
         snippets follow each other frame by frame, also the whole trajectory as evo scores it:
         each snippet's first step chained, then APE RMSE after a Sim(3) (Umeyama) alignment
         and RPE per frame (evo_ape / evo_rpe -as); --trajectories DIR writes the files.

--method: model (the ONNX model, --model/--precision) or a baseline that needs no model:
  depth: constant            flow: dis (DIS medium + ultrafast), dis-medium, dis-ultrafast, zero
  pose:  orb-vo (ORB + essential matrix + recoverPose per pair, unit steps, scale-aligned), identity
Comma-separate several to get one table (--method model,dis,zero).

{layouts}
Ground truth: a frame of a KITTI raw drive without its ground-truth file (sparse depth PNG or
Velodyne scan) is not scored; a warning on stderr says how many and which, the JSON lists them
(data.frames_without_gt), and the exit code is 1 unless --allow-missing-gt accepts that. Ground
truth holding NaN or infinity (a pose file, ...) is bad data (exit 2).

exit codes: 0 done; 1 some predictions held NaN/inf (reported per item, means are NaN) or,
with --camera-height, some frames had no ground plane (named, left out of the means), or
frames without ground truth were left out (without --allow-missing-gt); 2 bad usage or data
(one line naming the file)

examples:
  geonet-infer eval depth --data ../shared/realdata/kitti_raw_2011_09_26_sfnd --allow-missing-gt
  geonet-infer eval depth --data ../shared/realdata/kitti_raw_2011_09_26_sfnd --allow-missing-gt --max-depth 50 \\
      --precision int8
  geonet-infer eval depth --data ../shared/realdata/kitti_raw_2011_09_26_sfnd --allow-missing-gt --camera-height 1.65
  geonet-infer eval depth --data ../shared/realdata/kitti_object_3frames --method model,constant
  geonet-infer eval depth --data ../shared/realdata/kitti2015_000046_stereo --fx 721.5377 --baseline 0.54
  geonet-infer eval flow --data ../shared/realdata/middlebury_flow --method dis,zero
  geonet-infer eval pose --data ../shared/realdata/kitti_odometry_00/sequences/00 --method model,orb-vo,identity
  geonet-infer eval flow --data data/synth40 --heldout data/synth40_prepared/heldout.txt --json flow.json
"""


def layouts_help() -> str:
    """The layouts block of ``--help``, from the registry (a new layout describes itself)."""
    out = ["Layouts (--layout, default auto):"]
    width = max(len(name) for name in REGISTRY) + 1  # the descriptions start in one column
    for task in EVAL_TASKS:
        for n, name in enumerate(LAYOUTS[task]):
            first, *more = REGISTRY[name].help[task]
            label = f"{task:<6}" if n == 0 else " " * 6
            out.append(f"  {label} {name:<{width}}{first}")
            out += [" " * (9 + width) + line for line in more]
    return "\n".join(out) + "\n"


HELP = HELP_TEMPLATE.replace("{layouts}", layouts_help(), 1)


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "eval",
        help=COMMANDS["eval"],
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    # "all" only to say where it went (python -m benchmarks.eval_all, issue 42); not shown in --help
    parser.add_argument(
        "task", choices=[*EVAL_TASKS, "all"], metavar="{" + ",".join(EVAL_TASKS) + "}", help="what to score"
    )
    parser.add_argument("--data", type=Path, required=True, help="dataset folder (see layouts above)")
    parser.add_argument(
        "--layout",
        default="auto",
        choices=["auto"] + sorted({name for names in LAYOUTS.values() for name in names}),
        help="data layout (default: detected from the folder)",
    )
    parser.add_argument(
        "--method", default="model", help="comma list: model, or a baseline (see above) (default: model)"
    )
    add_model_args(parser)
    group = parser.add_argument_group("selection")
    group.add_argument(
        "--heldout", type=Path, default=None, help="synth layout: score only the sequences listed in this heldout.txt"
    )
    group.add_argument("--stride", type=positive_int, default=1, help="score every n-th item (default: 1)")
    group.add_argument("--limit", type=positive_int, default=None, help="score at most this many items")
    group.add_argument(
        "--allow-missing-gt",
        action="store_true",
        help="depth on KITTI raw: frames without ground truth are expected (still named on stderr), exit 0",
    )
    group = parser.add_argument_group("protocol")
    group.add_argument(
        "--max-depth",
        type=float,
        default=evaluation.MAX_DEPTH,
        help="depth cap in metres, GT mask and clamp (default: 80; the paper also reports 50)",
    )
    group.add_argument(
        "--crop",
        default="auto",
        choices=["auto", "garg", "eigen", "none"],
        help="depth crop (default auto: Garg on KITTI, none on synthetic)",
    )
    scaling = group.add_mutually_exclusive_group()
    scaling.add_argument(
        "--no-median-scaling", action="store_true", help="depth: score raw depths (metric or stereo-scaled models only)"
    )
    scaling.add_argument(
        "--camera-height",
        type=float,
        default=None,
        metavar="METRES",
        help="depth: scale each frame by the ground plane at this camera height instead of the GT median "
        "(KITTI: 1.65); K from the data's calibration or --intrinsics",
    )
    group.add_argument(
        "--multiview",
        type=Path,
        default=None,
        help="kitti flow: folder of the multi-view extension holding NNNNNN_09.png",
    )
    group.add_argument(
        "--intrinsics",
        default=None,
        metavar="FX,FY,CX,CY",
        help="K at the frames' size for data without calibration: flow with a model (Middlebury), "
        "depth with --camera-height",
    )
    group.add_argument(
        "--fx",
        type=float,
        default=None,
        metavar="PX",
        help="kitti-disparity: focal length for depth = fx·baseline/disparity where the folder has no "
        "calib_cam_to_cam/ (overrides it where it has; KITTI: 707.09-721.54 by recording day)",
    )
    group.add_argument(
        "--baseline",
        type=float,
        default=None,
        metavar="M",
        help="kitti-disparity: stereo baseline in metres, as --fx (KITTI documents 0.54 m)",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write every result and item here")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the printed tables here")
    parser.add_argument(
        "--trajectories",
        type=Path,
        default=None,
        metavar="DIR",
        help="pose: write the true and each method's chained trajectory here (gt_kitti.txt, <method>_kitti.txt "
        "and _tum.txt), for evo: evo_ape kitti DIR/gt_kitti.txt DIR/model_kitti.txt -as",
    )
    parser.set_defaults(run=run)


def methods_for(task: str, text: str, args) -> list[tuple[str, Callable]]:
    """[(row label, fn)] for the comma list ``text``; loads the model only if asked for."""
    out = []
    for method in [m.strip() for m in text.split(",") if m.strip()]:
        if method == "model":
            predictor = load_predictor(args)
            label = f"{Path(predictor.model_dir).name} ONNX {predictor.precision}"
            out.append((label, evaluation.model_fn(task, predictor)))
        else:
            out += list(evaluation.baseline_fns(task, method).items())
    if not out:
        raise InputError(None, "--method is empty", "e.g. --method model or --method dis")
    return out


def run(args: argparse.Namespace) -> int:
    if args.task == "all":
        raise InputError(
            None,
            "`geonet-infer eval all` moved out of the package: it scores the repository's catalogue of real sets",
            "In a checkout of the repository: python -m benchmarks.eval_all --data ../shared/realdata",
        )
    if args.max_depth <= evaluation.MIN_DEPTH:
        raise InputError(None, f"--max-depth {args.max_depth:g} must be above {evaluation.MIN_DEPTH:g} m")
    if args.camera_height is not None and args.task != "depth":
        raise InputError(None, f"--camera-height is for depth, not {args.task}")
    if args.camera_height is not None:
        scaling = "camera_height"
    else:
        scaling = "none" if args.no_median_scaling else "median"
    sequences = read_heldout(args.heldout) if args.heldout else None
    options = {"sequences": sequences, "stride": args.stride, "limit": args.limit}
    if args.task == "flow":
        options["multiview"] = args.multiview
    layout_options = {"fx": args.fx, "baseline": args.baseline}
    dataset = load_dataset(args.task, args.data, args.layout, options=layout_options, **options)
    K = None if args.intrinsics is None else parse_intrinsics(args.intrinsics).K
    results = []
    for label, fn in methods_for(args.task, args.method, args):
        if args.task == "depth":
            result = evaluation.evaluate_depth(
                fn,
                dataset,
                method=label,
                max_depth=args.max_depth,
                crop=None if args.crop == "none" else args.crop,
                scaling=scaling,
                camera_height=args.camera_height,
                intrinsics=K,
            )
        elif args.task == "flow":
            result = evaluation.evaluate_flow(fn, dataset, method=label, intrinsics=K)
        else:
            result = evaluation.evaluate_pose(fn, dataset, method=label, trajectories=args.trajectories)
        results.append((label, result))
    print(evaluation.format_table(results))
    if args.task == "depth":  # the same mask for every method: print it once
        print(evaluation.ground_truth_line(results[0][1]["ground_truth"]))
    for label, result in results:
        whole = result.get("trajectory")
        if whole and "not_scored" in whole:
            print(f"{label}: whole trajectory ({whole['frames']} frames): not scored: {whole['not_scored']}")
        elif whole:
            print(
                f"{label}: whole trajectory ({whole['frames']} frames, chained): APE {whole['ape_rmse']:.4f} "
                f"RMSE after Sim(3) alignment, RPE {whole['rpe_rmse']:.4f} per frame (as evo -as)"
            )
            if "files" in whole:
                print(f"  evo_ape kitti {whole['files']['gt_kitti']} {whole['files']['kitti']} -as")
    for note in dataset.notes:
        print(f"note: {note}")
    for label, result in results:
        failed = result.get("ground_fit_failed", [])
        if failed:
            print(
                f"note: {label}: no ground plane in {len(failed)} of {len(result['items'])} frames "
                f"({', '.join(failed)}): not scored, the means cover the other {result['metrics']['count']}"
            )
    if args.json:
        evaluation.write_json(args.json, {"task": args.task, "results": [r for _, r in results]})
        print(f"details: {args.json}")
    if args.markdown:
        with atomic_write(args.markdown) as tmp:
            tmp.write_text(evaluation.format_table(results) + "\n")
    failed = [(label, e) for label, r in results for e in r["errors"]]
    for label, error in failed:
        print(f"geonet-infer eval: {label}: {error['item']}: {error['problem']}", file=sys.stderr)
    for warning in dataset.warnings:
        accepted = "accepted (--allow-missing-gt)" if args.allow_missing_gt else "--allow-missing-gt to accept"
        print(f"geonet-infer eval: warning: {warning}; {accepted}", file=sys.stderr)
    missing_gt = bool(dataset.without_gt) and not args.allow_missing_gt
    return 1 if failed or missing_gt else 0
