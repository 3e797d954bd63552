"""``geonet-infer predict``: depth, flow and poses for a video, a folder of frames or a KITTI drive."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from geonet_infer.classical import classical_tasks
from geonet_infer.cli import COMMANDS
from geonet_infer.cli.common import (
    add_batch_size_arg,
    add_camera_args,
    add_method_args,
    add_model_args,
    camera_from_args,
    load_predictor,
    open_source,
    positive_int,
    sigterm_as_interrupt,
    stage_table,
)
from geonet_infer.cli.outputs import add_outputs_arg, tasks_and_outputs
from geonet_infer.core.check import SequenceCheck
from geonet_infer.core.predictor import TASKS, describe_skipped
from geonet_infer.core.scale import MAX_FRAMES_BEFORE_GROUND, MAX_SCALE_HALF_WINDOW, SCALE_HALF_WINDOW
from geonet_infer.errors import InputError
from geonet_infer.limits import (
    MAX_COLOUR_SCALE_FRAMES,
    MAX_VIDEO_FPS,
    MAX_WORLD_POINTS,
    check_batch_size,
)
from geonet_infer.output import layout
from geonet_infer.output.layout import SUMMARY_NAME, WORLD_CLOUD_NAME
from geonet_infer.output.options import DEFAULT_COLOUR_SCALE, POINT_CLOUDS, OutputOptions
from geonet_infer.output.predict import predict_to_dir
from geonet_infer.output.video import FOLDER_FPS, VIDEO_CODECS

HELP = """\
Predict depth, optical flow and camera poses for one sequence.

INPUT is a video file (.mp4 .avi .mov .mkv .webm), a folder of frames (in name
order, numbers as numbers: f3 before f10), a KITTI raw drive folder (frames from image_02/data; calibration
calib_cam_to_cam.txt found in the folder or up to two levels up), or one image (.png .jpg .jpeg .bmp .ppm:
its depth). With --tasks depth (or one image), the frames may have any sizes, each gets its depth at
its own size; pose and flow need frames of one size (a frame of another size fails, named).

Outputs in --out (written atomically; a bad frame is recorded in summary.json and skipped).
--out must be new, empty, or an earlier predict's output folder: then exactly the files that
run wrote are replaced (files you added stay, and a run that would write over one of them or
over its own input is refused); any other folder is refused, and so is a folder another
predict is writing into. Ctrl-C or SIGTERM stops with summary.json marked interrupted:
{layout}

examples:
  geonet-infer predict ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/kitti
  geonet-infer predict ../shared/realdata/udacity_dashcam/test_video.mp4 --out out/dashcam \\
      --calib ../shared/realdata/udacity_dashcam/calib_advanced_lane_lines.txt
  geonet-infer predict frames/ --out out/frames --intrinsics 721.5,721.5,609.6,172.9 --precision int8
  geonet-infer predict photo.jpg --out out/photo
  geonet-infer predict photos/ --out out/photos --tasks depth
  geonet-infer predict ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/kitti_m --camera-height 1.65
  geonet-infer predict ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/kitti_small \
      --outputs depth-png16,flow-png,poses
  geonet-infer predict ../shared/realdata/kitti_raw_2011_09_26_sfnd --out out/kitti_dis --flow-method dis \
      --pose-method orbvo
"""


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "predict",
        help=COMMANDS["predict"],
        description=HELP.format(layout=layout.describe(width=96)),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "input",
        type=Path,
        nargs="?",
        metavar="INPUT",
        help="video file, folder of frames, KITTI drive or one image; '-' = raw frames on stdin (with --stdin-frames)",
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="output folder: new, empty, or an earlier predict's (created)"
    )
    add_model_args(parser, mode="throughput")
    add_camera_args(parser)
    add_method_args(parser)
    parser.add_argument(
        "--tasks",
        default=None,
        help=f"comma list of {','.join(TASKS)} (default: every task the model's graphs can do, the others "
        "named in one line and in summary.json; flow needs intrinsics)",
    )
    add_batch_size_arg(parser)
    parser.add_argument(
        "--camera-height",
        type=float,
        default=None,
        metavar="METRES",
        help="camera height above a flat road: depth and pose translations in metres, from a "
        "ground plane fitted to each frame's depth, smoothed over the video (--scale-smoothing); a video "
        f"with no road in its first {MAX_FRAMES_BEFORE_GROUND} frames stops (needs intrinsics; e.g. 1.65 "
        "for KITTI)",
    )
    parser.add_argument(
        "--scale-smoothing",
        type=_frames,
        default=None,
        metavar="FRAMES",
        help="with --camera-height: each frame's scale is the robust mean (outliers dropped) of the ground "
        "fits of this many frames before and after it, so metric depth does not flicker; frames are "
        f"written this many frames late; 0 = each frame's own fit; summary.json keeps both (default: "
        f"{SCALE_HALF_WINDOW}, at most {MAX_SCALE_HALF_WINDOW}: the frames are held until their window closes)",
    )
    add_outputs_arg(parser)
    parser.add_argument(
        "--no-vis",
        action="store_true",
        help="skip the depth colour maps and flow colour wheels (the data files only; much faster writes)",
    )
    parser.add_argument(
        "--output-size",
        choices=("input", "network"),
        default="input",
        help="input (default): depth and flow resized to the frames' size; network: left at the network's "
        "size (e.g. 416x128, flow in its pixels), nothing interpolated and a fraction of the bytes to write; "
        "summary.json's output_size gives the scale to the input. The networks' methods only",
    )
    live = parser.add_argument_group("live sources")
    live.add_argument(
        "--source",
        default=None,
        metavar="CAMERA|URL",
        help="read a camera (its index: 0 is the first) or a stream URL OpenCV can open, instead of INPUT",
    )
    live.add_argument(
        "--stdin-frames",
        type=_size,
        default=None,
        metavar="WxH",
        help="raw rgb24 frames of this size on stdin (INPUT '-' or none; ffmpeg ... -f rawvideo -pix_fmt rgb24 -)",
    )
    live.add_argument("--max-frames", type=positive_int, default=None, help="stop after this many good frames")
    live.add_argument(
        "--fps",
        type=float,
        default=None,
        help=f"frame rate of stdin frames and of --video-out, at most {MAX_VIDEO_FPS:g} (default: the input's; "
        f"{FOLDER_FPS:g} for folders)",
    )
    extra = parser.add_argument_group("3-D, pictures and video")
    extra.add_argument(
        "--point-cloud",
        choices=POINT_CLOUDS,
        default=None,
        help="write points/<frame>.ply (binary PLY, x y z + colour, camera frame: x right, y down, z forward); "
        f"'world' also writes {WORLD_CLOUD_NAME}, every frame placed by the predicted poses in the first "
        "camera's frame (needs intrinsics; metres with --camera-height, else relative scale)",
    )
    extra.add_argument(
        "--point-stride", type=positive_int, default=OutputOptions.point_stride, help="every n-th pixel (default: 2)"
    )
    extra.add_argument("--max-depth", type=float, default=None, help="drop points farther than this")
    extra.add_argument(
        "--world-points",
        type=positive_int,
        default=OutputOptions.world_points,
        help=f"points in {WORLD_CLOUD_NAME} at most, randomly kept, up to {MAX_WORLD_POINTS:,} "
        f"(default: {OutputOptions.world_points})",
    )
    extra.add_argument(
        "--colour-scale",
        default=DEFAULT_COLOUR_SCALE,
        metavar="first:N|running|frame",
        help="one colour scale for the depth and flow pictures of the whole video, so a still scene keeps "
        f"its colours: fixed from the first N frames (N at most {MAX_COLOUR_SCALE_FRAMES}; fewer for huge frames), "
        "or the running median of the frames' ranges; 'frame' "
        f"= each frame its own (the .npy and KITTI flow files never change) (default: {DEFAULT_COLOUR_SCALE})",
    )
    extra.add_argument(
        "--video-out",
        type=Path,
        default=None,
        metavar="FILE",
        help=f"also write a side-by-side video, frame | depth | flow ({' '.join(VIDEO_CODECS)}), streamed, "
        "at the input's frame rate, and read back to count its frames; an existing FILE is replaced only "
        "when an earlier run into the same --out wrote it",
    )
    extra.add_argument(
        "--rerun",
        type=Path,
        default=None,
        metavar="FILE.rrd",
        help="also write a rerun recording (frame, depth, flow, the camera and its path, a point cloud, the "
        "output check's errors, and a layout), to open with `rerun FILE.rrd`; needs the [viz] extra "
        "(pip install 'geonet-infer[viz]'). An existing FILE outside --out is refused",
    )
    parser.add_argument(
        "--no-check",
        action="store_true",
        help="skip the output check (each flow and rigid flow against no motion, from the frames; about "
        "2 ms a frame, see docs/runtime.md)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--quiet",
        action="store_true",
        help="no notes on stderr (the model's notice, skipped tasks; summary.json keeps them); warnings, "
        "failures and errors still print",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.rerun is not None:  # before anything is loaded: one line naming the extra
        from geonet_infer.output.rerun_recording import require_rerun

        require_rerun()
    tasks, outputs = tasks_and_outputs(args)
    check_batch_size(args.batch_size, "--batch-size")
    if args.scale_smoothing is not None and args.camera_height is None:
        raise InputError(None, "--scale-smoothing smooths the metric scale", "pass --camera-height METRES with it")
    source = open_source(args)
    if source.kind == "image":  # one photo: depth, the task that needs no sequence
        tasks = tasks or ("depth",)
        if set(tasks) & {"pose", "flow"}:
            raise InputError(
                source.path, "one image has no next frame for pose or flow", "pass --tasks depth, or a folder or video"
            )
    options = OutputOptions(
        point_cloud=args.point_cloud,
        point_stride=args.point_stride,
        max_depth=args.max_depth,
        world_points=args.world_points,
        colour_scale=args.colour_scale,
        video_out=args.video_out,
        rerun=args.rerun,
        output_size=args.output_size,
        video_fps=args.fps,
    )
    camera = camera_from_args(args, source, lambda msg: print(f"geonet-infer predict: note: {msg}", file=sys.stderr))
    predictor = load_predictor(args)
    if tasks is None:
        doable, skipped = predictor.resolve_tasks(classical=classical_tasks(TASKS, args.flow_method, args.pose_method))
        if skipped and not args.quiet:
            print(
                f"geonet-infer predict: skipping {describe_skipped(skipped)} in {predictor.model_dir}; "
                f"running {', '.join(doable)}",
                file=sys.stderr,
            )
    with sigterm_as_interrupt():
        summary = predict_to_dir(
            predictor,
            source,
            args.out,
            camera=camera,
            tasks=tasks,
            batch_size=args.batch_size,
            progress=not args.no_progress,
            camera_height=args.camera_height,
            vis=not args.no_vis,
            outputs=outputs,
            exclusive=True,
            options=options,
            max_frames=args.max_frames,
            check=not args.no_check,
            flow_method=args.flow_method,
            pose_method=args.pose_method,
            scale_smoothing=SCALE_HALF_WINDOW if args.scale_smoothing is None else args.scale_smoothing,
        )
    print(
        f"{summary['frames']} frames -> {args.out} ({summary['frames_per_s']:.1f} frames/s, "
        f"{summary['failed']} failed); details in {args.out / SUMMARY_NAME}"
    )
    print(stage_table(summary["timings_ms_per_frame"], summary["frames"], summary["overlapped_ms_per_frame"]))
    if summary["camera"] is not None:  # where the intrinsics came from, once
        used = summary["camera"]
        at = f" at {used['size'][0]}x{used['size'][1]}" if used["size"] else ""
        print(f"intrinsics: {used['origin']}, fx {used['K'][0][0]:.1f}{at} ({used['source']})")
    check = None if summary["check"] is None else SequenceCheck.from_dict(summary["check"])
    if check is not None:
        print(f"check: {check.line()}")
    if summary.get("rerun"):
        rrd = summary["rerun"]
        print(f"rerun: {rrd['path']} ({rrd['frames']} frames); open it with `rerun {rrd['path']}`")
    print(f"to look at it: geonet-infer report {args.out}   (one HTML page; the [viz] extra)")
    if summary["model_notice"] and not args.quiet:
        print(f"geonet-infer predict: note: {predictor.model_dir.name}: {summary['model_notice']}", file=sys.stderr)
    if check is not None and check.warning():
        print(f"warning: {predictor.model_dir.name}: {check.warning()}", file=sys.stderr)
    missing = set(source.missing) if summary["truncated"] else set()
    for failure in summary["failures"]:
        if failure["frame"] not in missing:
            print(f"failed: {failure['frame']}: {failure['reason']}", file=sys.stderr)
    if missing:  # one line for the frames a truncated video lacks (each is in summary.json)
        print(f"warning: {source.location}: truncated: {summary['truncated']}", file=sys.stderr)
    for note in [] if args.quiet else summary["notes"]:  # a clean end before the header's frame count: not a failure
        print(f"geonet-infer predict: note: {source.location}: {note}", file=sys.stderr)
    return 1 if summary["failed"] else 0


def _frames(text: str) -> int:
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a whole number of frames >= 0, got {text!r}")
    return int(text)


def _size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    if not (re.fullmatch(r"[0-9]+", width) and re.fullmatch(r"[0-9]+", height)):
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 1280x720, got {text!r}")
    return int(width), int(height)
