"""``geonet-infer demo``: predict on the bundled sample sequence and draw one frame's results."""

from __future__ import annotations

import argparse
from pathlib import Path

import geonet_infer
from geonet_infer.cli import COMMANDS
from geonet_infer.cli.common import add_model_args, load_predictor, sigterm_as_interrupt, stage_table
from geonet_infer.errors import InputError
from geonet_infer.io.calib import read_camera
from geonet_infer.io.frames import open_frames
from geonet_infer.io.images import list_images, read_image, write_image
from geonet_infer.output.predict import predict_to_dir
from geonet_infer.output.viz import depth_to_color, flow_to_color, side_by_side
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES

DEMO_PICTURE = "demo.png"
PANELS = ("frame", "depth", "flow", "rigid flow", "residual flow")
# --real: the KITTI raw extract of the shared reference data, frames 0-9 (those the model card scores)
REAL_DRIVE = Path("shared") / "realdata" / "kitti_raw_2011_09_26_sfnd"
REAL_FRAMES = 10
REAL_PANEL_HEIGHT = 160  # of KITTI's 375 rows: five panels about as wide as the synthetic picture, PNG < 500 KB


def find_real_drive() -> Path:
    """../shared/realdata/<drive> next to the current folder or next to the repository holding this package."""
    repo = Path(geonet_infer.__file__).resolve().parents[1]
    candidates = [Path("..") / REAL_DRIVE, repo.parent / REAL_DRIVE]
    for drive in candidates:
        if (drive / "image_02" / "data").is_dir():
            return drive
    raise InputError(
        candidates[0],
        f"KITTI raw extract not found (nor at {candidates[1]})",
        "--real needs the shared reference data (../shared/realdata) beside the repository or the current folder",
    )


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "demo",
        help=COMMANDS["demo"],
        description="Run `predict` on the bundled sample sequence (synthetic frames made by our own "
        "generator), write a side-by-side demo.png (frame | depth | flow | rigid | residual) "
        "for the middle frame and print the per-stage latency table. With --real: the same on "
        f"frames 0-{REAL_FRAMES - 1} of the real KITTI raw extract in ../shared/realdata.",
    )
    parser.add_argument("--out", type=Path, default=Path("geonet_demo"), help="output folder (default: geonet_demo)")
    parser.add_argument(
        "--real",
        action="store_true",
        help=f"real video instead: frames 0-{REAL_FRAMES - 1} of ../{REAL_DRIVE} (looked for beside the current "
        "folder, then beside the repository)",
    )
    add_model_args(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.real:
        drive = find_real_drive()
        source = open_frames(drive)
        # the first frames only: a demo, not the whole drive
        files, names = source.files[:REAL_FRAMES], source.frame_names[:REAL_FRAMES]  # type: ignore[attr-defined,index]
        source.files, source.frame_names = files, names  # type: ignore[attr-defined]  # a drive: an image folder
        if source.default_calib is None:
            raise InputError(drive, "no calib_cam_to_cam.txt in the drive or above it", "restore ../shared")
        frames, camera, height = files, read_camera(source.default_calib), REAL_PANEL_HEIGHT
    else:
        source, frames, camera, height = (
            open_frames(SAMPLE_FRAMES),
            list_images(SAMPLE_FRAMES),
            read_camera(SAMPLE_CALIB),
            None,
        )
    predictor = load_predictor(args)
    with sigterm_as_interrupt():
        summary = predict_to_dir(
            predictor,
            source,
            args.out,
            camera=camera,
            progress=not args.no_progress,
            exclusive=True,
            extra_outputs=(DEMO_PICTURE,),
        )
    mid = len(frames) // 2
    snippet = frames[mid - predictor.seq_length // 2 : mid + predictor.seq_length // 2 + 1]
    result = predictor.flow(snippet, camera)
    max_flow = float(max(abs(result.flow).max(), 1e-6))
    panels = [
        read_image(frames[mid]),
        depth_to_color(result.depth),
        flow_to_color(result.flow, max_flow),
        flow_to_color(result.rigid_flow, max_flow),
    ]
    labels = list(PANELS[:4])
    if result.residual_flow is not None:
        panels.append(flow_to_color(result.residual_flow))
        labels.append(PANELS[4] + " (own scale)")
    write_image(args.out / DEMO_PICTURE, side_by_side(panels, labels, height=height))
    print(f"model {predictor.model_dir} ({predictor.precision}, {predictor.threads} threads)")
    print(f"{summary['frames']} frames -> {args.out}; picture of frame {frames[mid].stem}: {args.out / DEMO_PICTURE}")
    print(stage_table(summary["timings_ms_per_frame"], summary["frames"], summary["overlapped_ms_per_frame"]))
    return 1 if summary["failed"] else 0
