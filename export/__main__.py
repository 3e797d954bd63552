"""Export GeoNet to ONNX: ``python -m export`` (the library call is :func:`export.export_model`).

From a checkpoint (stage ``flow`` for all four graphs, stage ``rigid`` for
depthnet/posenet/rigidflow)::

    python -m export --checkpoint runs/flow/last.pt --out models/geonet \\
        [--precision fp32,int8 --calib-data DIR] [--eval-synth-dir DIR --eval-prepared-dir DIR]

The authors' released TensorFlow checkpoints (docs/official_models.md; no TensorFlow needed)::

    python -m export --from-tf geonet_depthnet/model-250000 --out models/official_depth [--verify] \\
        [--from-tf pose=PREFIX --from-tf flow=PREFIX ...] [--precision fp32,int8 --calib-frames DIR]

Timing-only models with random weights (marked ``"random_init": true``)::

    python -m export --arch resnet50 --random-init --out /tmp/geonet_r50 [--height 128 --width 416]

The directory is written as ``DIR.tmp-XXXX`` beside DIR and renamed when
complete, so DIR is either absent or whole. Exit codes: 0 written, 1 an exported
graph failed its check, 2 bad usage or input (one line on stderr naming the item).
"""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
from pathlib import Path

from export.build import ExportConfig, export_model
from export.to_onnx import ExportCheckError
from export.wrappers import GRAPH_NAMES
from geonet_infer.convert.quantize import CALIBRATION_METHODS
from geonet_infer.errors import GeoNetError
from geonet_infer.samples import SAMPLE_FRAMES
from training.config import ARCHS

D = ExportConfig  # argparse defaults are the config's defaults


def _names(text: str) -> tuple[str, ...]:
    """'a,b' -> ('a', 'b'); 'all' -> every graph. Unknown names are refused by export_model."""
    return GRAPH_NAMES if text == "all" else tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))


def _count_or_folder(text: str) -> int | Path:
    """--calib-frames: a frame count, or (the spelling of issue 28) the calibration folder itself."""
    if Path(text).is_dir() or not re.fullmatch(r"[+-]?[0-9]+", text.strip()):
        return Path(text)
    if int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of frames (or a folder), got {text}")
    return int(text)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    src = p.add_argument_group("model")
    src.add_argument(
        "--checkpoint",
        type=Path,
        help="a last.pt / best.pt written by training.train, or a weights file of python -m training.checkpoint",
    )
    src.add_argument(
        "--from-tf",
        action="append",
        default=[],
        metavar="[KIND=]PREFIX",
        help="an official GeoNet TensorFlow checkpoint (prefix like .../model-250000, a file of it, or its folder): "
        "every net it holds; KIND=PREFIX (depth, pose, flow; e.g. depth,pose=PREFIX) takes only those; "
        "repeat to combine checkpoints (docs/official_models.md)",
    )
    src.add_argument(
        "--scale-normalize",
        action="store_true",
        help="with --from-tf: the model_sn depth release (each disparity map divided by its mean, in the graph)",
    )
    src.add_argument(
        "--verify",
        nargs="?",
        type=Path,
        const=SAMPLE_FRAMES,
        metavar="DIR",
        help="with --from-tf: run the first frame of DIR (default: the bundled sample sequence) through the "
        "converted fp32 graphs and against the checkpoint's own forward pass (the official graph in TensorFlow "
        "if installed, else our PyTorch nets with its tensors); prints one line of max/mean errors, exit 1 "
        "(nothing written) beyond 1e-3 of the output's range",
    )
    src.add_argument("--arch", help=f"with --random-init: one of {', '.join(ARCHS)}")
    src.add_argument(
        "--random-init",
        action="store_true",
        help="export randomly initialised nets (timing only; accuracy commands refuse them)",
    )
    src.add_argument("--seed", type=int, default=D.seed, help="torch seed of --random-init weights")
    src.add_argument("--height", type=int, help="graph height (default: the checkpoint's, or 128)")
    src.add_argument("--width", type=int, help="graph width (default: the checkpoint's, or 416)")
    src.add_argument("--seq-length", type=int, help="frames per pose snippet (--random-init only; default 3)")
    out = p.add_argument_group("output")
    out.add_argument("--out", required=True, type=Path, help="model directory to create")
    out.add_argument("--force", action="store_true", help="replace an existing --out directory")
    out.add_argument(
        "--graphs",
        type=_names,
        default=D.graphs,
        help="comma list of depthnet,posenet,rigidflow,resflownet or 'all' (default); "
        "a stage 'rigid' checkpoint needs --graphs depthnet,posenet,rigidflow",
    )
    out.add_argument(
        "--precision",
        dest="precisions",
        type=_names,
        default=D.precisions,
        help="fp32 (default) or fp32,int8 (int8 graphs go to DIR/int8/)",
    )
    q = p.add_argument_group("int8")
    q.add_argument("--calib-data", type=Path, help="folder of consecutive frames for INT8 calibration")
    q.add_argument(
        "--calib-frames",
        type=_count_or_folder,
        default=D.calib_frames,
        metavar="N|DIR",
        help="how many calibration frames to read (default %(default)s); a folder instead of a number "
        "is taken as --calib-data DIR",
    )
    q.add_argument("--calib-method", default=D.calib_method, choices=CALIBRATION_METHODS)
    q.add_argument(
        "--int8-ops",
        type=lambda text: tuple(t.strip() for t in text.split(",") if t.strip()),
        default=D.int8_ops,
        metavar="OP,OP",
        help="operator types to quantise, e.g. Conv (the glue between convolutions stays fp32); default: "
        "every type onnxruntime quantises",
    )
    q.add_argument(
        "--reduce-range", action="store_true", help="7-bit weights for CPUs without VNNI (AVX2 / plain AVX-512)"
    )
    q.add_argument(
        "--no-per-channel",
        dest="per_channel",
        action="store_false",
        help="per-tensor instead of per-channel weight scales",
    )
    ev = p.add_argument_group("int8 accuracy delta (held-out synthetic set)")
    ev.add_argument("--eval-synth-dir", type=Path, help="output of training.synth")
    ev.add_argument("--eval-prepared-dir", type=Path, help="output of training.prepare (has heldout.txt)")
    ev.add_argument("--eval-stride", type=int, default=D.eval_stride, help="evaluate every n-th frame")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if isinstance(args.calib_frames, Path):
        if args.calib_data and args.calib_data != args.calib_frames:
            print("error: --calib-frames DIR and --calib-data DIR name different folders; pass one", file=sys.stderr)
            return 2
        args.calib_data, args.calib_frames = args.calib_frames, D.calib_frames
    args.from_tf = tuple(args.from_tf)
    try:
        out = export_model(ExportConfig(**vars(args)))
    except GeoNetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ExportCheckError as err:
        print(f"error: export check failed: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # a full disk, a read-only folder: one line (the temporary folder is removed)
        where = f"{err.filename}: " if err.filename else ""
        print(f"error: {where}{err.strerror or err}", file=sys.stderr)
        return 3
    if not args.quiet:
        print(out)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())
