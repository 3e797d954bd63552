"""``geonet-infer convert``: the authors' released TensorFlow checkpoints -> a model, by name. No torch, no TF."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from geonet_infer.cli import COMMANDS
from geonet_infer.errors import InputError

EPILOG = """\
examples:
  geonet-infer convert ~/Downloads/geonet_depthnet/model --name official_depth
  geonet-infer convert ~/Downloads/geonet_depthnet/model_sn --scale-normalize --name official_depth_sn
  geonet-infer convert ~/Downloads/geonet_resflownet --name official_flow --precision fp32,int8 \\
      --calib-data path/to/your/frames
  geonet-infer predict video.mp4 --out out --model official_depth

Downloading the releases (by hand) and what each holds: docs/official_models.md.
"""


def add_parser(sub) -> None:
    parser = sub.add_parser(
        "convert",
        help=COMMANDS["convert"],
        description="Convert the released GeoNet TensorFlow checkpoints (yzcjtr/GeoNet) into a model that "
        "--model NAME and geonet_infer.load(NAME) find: the ONNX graphs at 128x416, fp32 and optionally INT8, "
        "with a manifest and sha256. Reads the checkpoint with numpy: needs neither torch nor TensorFlow.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "checkpoint",
        nargs="+",
        help="checkpoint prefix (the .index file's path without .index), one of its files, or the folder "
        "holding it; KIND=PREFIX (depth, pose, flow) takes only that network from it",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--name", help="model name (default: the release folder's name, e.g. geonet_depthnet)")
    where.add_argument("--out", type=Path, help="write the model directory here instead of the models folder")
    parser.add_argument("--precision", default="fp32", help="fp32 (default) or fp32,int8")
    parser.add_argument(
        "--calib-data",
        type=Path,
        help="INT8: a folder of consecutive frames like those you will run on (needs the [convert] extra)",
    )
    parser.add_argument("--scale-normalize", action="store_true", help="the model_sn release of geonet_depthnet")
    parser.add_argument(
        "--verify",
        nargs="?",
        type=Path,
        const=None,
        default=False,
        metavar="FRAMES",
        help="compare the graphs with the official forward pass in TensorFlow on the first frames of FRAMES "
        "(default: the bundled sample); says so when TensorFlow is not installed",
    )
    parser.add_argument("--force", action="store_true", help="replace a model of the same name")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.set_defaults(run=run)


def default_name(checkpoint: str) -> str:
    """The release folder's name (``geonet_depthnet``), plus the prefix's own name when it is not
    ``model`` or ``model-N`` (``geonet_depthnet_model_sn``)."""
    path = Path(checkpoint.partition("=")[2] if re.match(r"^[a-z,]+=", checkpoint) else checkpoint)
    folder = path if path.is_dir() else path.parent
    name = folder.resolve().name
    stem = re.sub(r"\.(index|meta|data-\d{5}-of-\d{5})$", "", path.name) if not path.is_dir() else ""
    if stem and not re.fullmatch(r"model(-\d+)?", stem):
        name = f"{name}_{stem}"
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name).strip("._-")[:64] or "converted"


def run(args: argparse.Namespace) -> int:
    import sys

    from geonet_infer.convert.build import ConvertConfig, convert
    from geonet_infer.models import check_name, user_models_dir

    if args.out is not None:
        out = args.out
    else:
        name = check_name(args.name if args.name is not None else default_name(args.checkpoint[0]))
        out = user_models_dir() / name
    precisions = tuple(p.strip() for p in args.precision.split(",") if p.strip())
    before_publish = None
    if args.verify is not False:
        before_publish = _verifier(args)
    log = (lambda _: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    cfg = ConvertConfig(
        checkpoints=tuple(args.checkpoint),
        out=out,
        precisions=precisions,
        calib_data=args.calib_data,
        scale_normalize=args.scale_normalize,
        force=args.force,
        log=log,
        before_publish=before_publish,
    )
    path = convert(cfg)
    use = path.name if args.out is None else str(path)
    print(f"converted: {path}  (geonet-infer predict VIDEO --out OUT --model {use})")
    return 0


def _verifier(args: argparse.Namespace):
    from geonet_infer.convert.official import select_networks
    from geonet_infer.convert.verify import verify
    from geonet_infer.models.manifest import load_manifest
    from geonet_infer.samples import SAMPLE_FRAMES

    frames = args.verify if args.verify is not None else SAMPLE_FRAMES

    def check(model_dir: Path) -> None:
        manifest = load_manifest(model_dir)
        sel = select_networks(args.checkpoint, log=lambda _: None)
        line = verify(
            model_dir,
            sel,
            frames,
            height=manifest.height,
            width=manifest.width,
            seq_length=manifest.seq_length,
            scale_normalize=args.scale_normalize,
        )
        print(line, flush=True)

    if frames is not None and not Path(frames).exists():
        raise InputError(frames, "no such frames folder for --verify")
    return check
