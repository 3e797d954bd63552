"""``geonet-infer demo``: predict on the bundled sample sequence and draw one frame's results."""

from __future__ import annotations

import argparse
from pathlib import Path

from geonet_infer.cli.common import add_model_args, load_predictor, sigterm_as_interrupt, stage_table
from geonet_infer.io.calib import read_camera
from geonet_infer.io.frames import open_frames
from geonet_infer.io.images import list_images, read_image, write_image
from geonet_infer.pipeline import predict_to_dir
from geonet_infer.samples import SAMPLE_CALIB, SAMPLE_FRAMES
from geonet_infer.viz import depth_to_color, flow_to_color, side_by_side

DEMO_PICTURE = "demo.png"
PANELS = ("frame", "depth", "flow", "rigid flow", "residual flow")


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "demo",
        help="run on the bundled sample and write demo.png",
        description="Run `predict` on the bundled sample sequence (synthetic frames made by our own "
        "generator), write a side-by-side demo.png (frame | depth | flow | rigid | residual) "
        "for the middle frame and print the per-stage latency table.",
    )
    parser.add_argument("--out", type=Path, default=Path("geonet_demo"), help="output folder (default: geonet_demo)")
    add_model_args(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    predictor = load_predictor(args)
    camera = read_camera(SAMPLE_CALIB)
    with sigterm_as_interrupt():
        summary = predict_to_dir(
            predictor,
            open_frames(SAMPLE_FRAMES),
            args.out,
            camera=camera,
            progress=not args.no_progress,
            exclusive=True,
            extra_outputs=(DEMO_PICTURE,),
        )
    frames = list_images(SAMPLE_FRAMES)
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
    write_image(args.out / DEMO_PICTURE, side_by_side(panels, labels))
    print(f"model {predictor.model_dir} ({predictor.precision}, {predictor.threads} threads)")
    print(f"{summary['frames']} frames -> {args.out}; picture of frame {frames[mid].stem}: {args.out / DEMO_PICTURE}")
    print(stage_table(summary["timings_ms_per_frame"], summary["frames"]))
    return 1 if summary["failed"] else 0
