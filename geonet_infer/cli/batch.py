"""``geonet-infer batch``: many sequences into one folder, on a process pool or Ray Data."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from geonet_infer.batch import (
    FAILURES_NAME,
    MARKER_NAME,
    OWNER_NAME,
    RUNNERS,
    run_batch,
)
from geonet_infer.cli import COMMANDS
from geonet_infer.cli.common import (
    ESTIMATE,
    add_batch_size_arg,
    add_camera_args,
    add_method_args,
    add_model_args,
    camera_from_args,
    positive_int,
    sigterm_as_interrupt,
)
from geonet_infer.cli.outputs import add_outputs_arg, tasks_and_outputs
from geonet_infer.engines import usable_cpus
from geonet_infer.errors import InputError
from geonet_infer.output.layout import SUMMARY_NAME

HELP = f"""\
Predict depth, optical flow and camera poses for many sequences.

INPUTS are sequence folders (frames in name order, f3 before f10), videos (.mp4
.avi .mov .mkv .webm), KITTI raw drives, or .txt files listing them (one a line, # comments;
relative paths are relative to the list file's folder). Each sequence gets
`geonet-infer predict`'s layout in OUT/<sequence>/ (sequence = folder name, video
stem or drive name; inputs sharing a name become <name>__<parent folder>).

Calibration, per input, the first found: the file its list line pairs it with
("INPUT | CALIB", e.g. "clips/a.mp4 | cams/a.txt"); --calib or --intrinsics (every
input); a "<name>.calib.txt" beside it (clip.mp4 + clip.calib.txt, frames/ +
frames.calib.txt); a KITTI drive's calib_cam_to_cam.txt. Inputs from different
cameras run in one job; each sequence's K is in summary.json (per_sequence camera).

OUT must be new, empty, or made by an earlier batch (marked by OUT/{OWNER_NAME}),
and must not be, hold or be inside an input; batch only ever deletes or replaces
sequence folders it made. Next to the sequences:
  {"OUT/<sequence>/" + MARKER_NAME:<22} written last: the sequence is complete (with each
  {"":<22} output's size and sha256 and the inputs' sizes and times)
  {"OUT/" + FAILURES_NAME:<22} one JSON object a line: sequence, input, frame (null = whole
  {"":<22} sequence), reason; a failure never stops the job
  {"OUT/" + SUMMARY_NAME:<22} sequences done/failed/skipped, frames, frames/s, runner (key "engine"), workers

Every file is written to a temporary name and renamed. After a crash, Ctrl-C or a
kill, run the same command with --resume: complete sequences whose outputs and
inputs are as recorded are skipped, the others are redone. Exit codes: 0 all good,
1 something failed (see {FAILURES_NAME}), 2 bad usage (one line on stderr), 3 the
system refused a write into OUT (disk full, read-only), 130 interrupted (Ctrl-C, SIGTERM).

Engines:
  local  a process pool on this machine; each worker loads the models once. By
         default workers x threads-per-worker = the usable CPUs ({usable_cpus()} here):
         one worker per CPU, at most one per sequence. --workers is capped at the
         usable CPUs and at what the available memory holds (with a warning).
  ray    Ray Data (pip install 'geonet-infer[ray]'): an actor pool, one predictor per
         actor (num_cpus = threads per worker), sized so that actors never ask for more
         CPUs than the cluster has. Starts a local cluster, or joins --ray-address
         (outputs must then be on storage every node sees under the same path).

examples:
  geonet-infer batch runs/a runs/b runs/c --out out/batch --calib calib.txt
  geonet-infer batch sequences.txt --out out/batch --workers 2 --threads-per-worker 1
  geonet-infer batch cameras.txt --out out/batch   # lines "clip.mp4 | clip_camera.txt"
  geonet-infer batch ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/batch --resume
  geonet-infer batch videos.txt --out out/batch --runner ray --ray-address auto --tasks depth
"""


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "batch",
        help=COMMANDS["batch"],
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "inputs",
        type=Path,
        nargs="+",
        metavar="INPUTS",
        help="sequence folders, videos, KITTI drives, or .txt files listing them",
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="output folder (created; or empty, or made by an earlier batch)"
    )
    run = parser.add_argument_group("workers")
    run.add_argument(
        "--runner", choices=list(RUNNERS), default=None, help="local process pool or Ray Data (default: local)"
    )
    run.add_argument("--engine", choices=list(RUNNERS), default=None, help="deprecated name of --runner")
    run.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="worker processes / Ray actors (default: usable CPUs / threads, at most one per sequence; "
        "capped at the usable CPUs and by memory)",
    )
    run.add_argument(
        "--threads-per-worker",
        type=positive_int,
        default=None,
        metavar="T",
        help="onnxruntime threads of each worker (default: usable CPUs / workers)",
    )
    run.add_argument(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="join this Ray cluster (e.g. auto, HOST:6379, ray://HOST:10001); default: start a local one",
    )
    run.add_argument(
        "--resume",
        action="store_true",
        help="skip the sequences OUT already has complete (outputs and inputs as recorded); redo the others",
    )
    add_model_args(parser, threads=False, rigid_op=False)
    add_camera_args(parser)
    add_method_args(parser)
    parser.add_argument(
        "--tasks",
        help="comma list of depth,pose,flow (default: every task the model can do; flow needs intrinsics: --calib, "
        "--intrinsics, or a KITTI drive's own calibration)",
    )
    add_batch_size_arg(parser)
    add_outputs_arg(parser)
    parser.add_argument(
        "--no-vis",
        action="store_true",
        help="skip the depth colour maps and flow colour wheels (the data files only; much faster writes)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no notes on stderr (the model's notice, skipped tasks; summary.json keeps them); warnings, "
        "failures and errors still print",
    )
    parser.set_defaults(run=run_command)


def run_command(args: argparse.Namespace) -> int:
    tasks, outputs = tasks_and_outputs(args)  # resolved against the model by run_batch
    if args.engine is not None:
        print("geonet-infer batch: note: --engine is deprecated, use --runner", file=sys.stderr)
        if args.runner not in (None, args.engine):
            raise InputError(None, f"--engine {args.engine} and --runner {args.runner} disagree", "pass --runner only")
    runner = args.runner or args.engine or "local"
    if args.ray_address and runner != "ray":
        raise InputError(None, "--ray-address needs --runner ray")
    camera = camera_from_args(args)  # --calib / --intrinsics for every input; else each input's own (or estimate)
    with sigterm_as_interrupt():  # SIGTERM is handled like Ctrl-C: workers stopped, summary written
        summary = run_batch(
            args.inputs,
            args.out,
            runner=runner,
            workers=args.workers,
            threads=args.threads_per_worker,
            model=args.model,
            precision=args.precision,
            backend=args.backend,
            tasks=tasks,
            batch_size=args.batch_size,
            camera=camera,
            vis=not args.no_vis,
            outputs=outputs,
            flow_method=args.flow_method,
            pose_method=args.pose_method,
            estimate_intrinsics=args.intrinsics == ESTIMATE,
            resume=args.resume,
            ray_address=args.ray_address,
            progress=not args.no_progress,
            log=(lambda msg: None) if args.quiet else None,  # --quiet: no notes
        )
    seqs = summary["sequences"]
    redone = f", {len(summary['redone'])} redone (changed since their run)" if summary["resume"] else ""
    print(
        f"{seqs['done']} sequences done, {seqs['failed']} failed, {seqs['skipped']} skipped (complete already)"
        f"{redone}; "
        f"{summary['frames']} frames, {summary['frames_per_s']:.1f} frames/s "
        f"({summary['engine']}: {summary['workers']} workers x {summary['threads_per_worker']} threads) "
        f"-> {args.out}; details in {args.out / SUMMARY_NAME}"
    )
    if summary["model_notice"] and not args.quiet:
        print(f"geonet-infer batch: note: {Path(summary['model']).name}: {summary['model_notice']}", file=sys.stderr)
    if summary["failures"]:
        print(
            f"{summary['failures']} failures (sequences or frames) listed in {args.out / FAILURES_NAME}",
            file=sys.stderr,
        )
    return summary["exit_code"]
