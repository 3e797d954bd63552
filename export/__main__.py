"""Export GeoNet to ONNX: ``python -m export``.

From a checkpoint (stage ``flow`` for all four graphs, stage ``rigid`` for
depthnet/posenet/rigidflow)::

    python -m export --checkpoint runs/flow/last.pt --out models/geonet \\
        [--precision fp32,int8 --calib-data DIR] [--eval-synth-dir DIR --eval-prepared-dir DIR]

Timing-only models with random weights (marked ``"random_init": true``)::

    python -m export --arch resnet50 --random-init --out /tmp/geonet_r50 [--height 128 --width 416]

The directory is written as ``DIR.tmp-XXXX`` beside DIR and renamed when
complete, so DIR is either absent or whole. Bad input -> message and exit 2.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from export import manifest as mf
from export import quantize as qz
from export.to_onnx import OPSET, ExportCheckError, export_graph
from export.wrappers import GRAPH_NAMES, RIGID_GRAPHS, build_wrapper, example_inputs, io_spec
from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH
from geonet_infer.errors import GeoNetInputError
from geonet_infer.manifest import PRECISIONS, load_manifest, write_manifest
from training.config import ARCHS

DEFAULT_SEQ_LENGTH = 3
SIZE_MULTIPLE = 8  # DepthNet/ResFlowNet need H and W divisible by 8


@dataclass
class Source:
    """The model to export and where it came from."""

    model: object  # training.model.GeoNet, eval mode
    arch: str
    height: int
    width: int
    seq_length: int
    random_init: bool
    checkpoint: Path | None = None
    ckpt: dict | None = None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_argument_group("model")
    src.add_argument("--checkpoint", help="a last.pt / best.pt written by training.train")
    src.add_argument("--arch", help=f"with --random-init: one of {', '.join(ARCHS)}")
    src.add_argument("--random-init", action="store_true",
                     help="export randomly initialised nets (timing only; accuracy commands refuse them)")
    src.add_argument("--seed", type=int, default=0, help="torch seed of --random-init weights")
    src.add_argument("--height", type=int, help="graph height (default: the checkpoint's, or 128)")
    src.add_argument("--width", type=int, help="graph width (default: the checkpoint's, or 416)")
    src.add_argument("--seq-length", type=int, help="frames per pose snippet (--random-init only; default 3)")
    out = p.add_argument_group("output")
    out.add_argument("--out", required=True, help="model directory to create")
    out.add_argument("--force", action="store_true", help="replace an existing --out directory")
    out.add_argument("--graphs", default="all",
                     help="comma list of depthnet,posenet,rigidflow,resflownet or 'all' (default); "
                          "a stage 'rigid' checkpoint needs --graphs depthnet,posenet,rigidflow")
    out.add_argument("--precision", default="fp32", help="fp32 or fp32,int8 (int8 graphs go to DIR/int8/)")
    q = p.add_argument_group("int8")
    q.add_argument("--calib-data", help="folder of consecutive frames for INT8 calibration")
    q.add_argument("--calib-frames", type=int, default=qz.QuantSettings.max_frames,
                   help="calibration frames to read from --calib-data")
    q.add_argument("--calib-method", default=qz.QuantSettings.calibrate_method,
                   choices=("minmax", "entropy", "percentile"))
    q.add_argument("--reduce-range", action="store_true",
                   help="7-bit weights for CPUs without VNNI (AVX2 / plain AVX-512)")
    q.add_argument("--no-per-channel", dest="per_channel", action="store_false",
                   help="per-tensor instead of per-channel weight scales")
    ev = p.add_argument_group("int8 accuracy delta (held-out synthetic set)")
    ev.add_argument("--eval-synth-dir", help="output of training.synth")
    ev.add_argument("--eval-prepared-dir", help="output of training.prepare (has heldout.txt)")
    ev.add_argument("--eval-stride", type=int, default=1, help="evaluate every n-th frame")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


# ------------------------------------------------------------------------------ checks
def _parse_list(text: str, allowed: tuple, what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise GeoNetInputError(None, f"unknown {what} {bad or text!r}", f"choose from {', '.join(allowed)}")
    return list(dict.fromkeys(items))


def _check_args(args) -> tuple[list[str], list[str]]:
    graphs = list(GRAPH_NAMES) if args.graphs == "all" else _parse_list(args.graphs, GRAPH_NAMES, "graph")
    graphs = [g for g in GRAPH_NAMES if g in graphs]  # canonical order
    precisions = _parse_list(args.precision, PRECISIONS, "precision")
    if "fp32" not in precisions:
        raise GeoNetInputError(None, "--precision must include fp32",
                               "int8 graphs are calibrated with the fp32 ones: use --precision fp32,int8")
    if bool(args.checkpoint) == bool(args.random_init):
        raise GeoNetInputError(None, "pass exactly one of --checkpoint or --random-init")
    if args.random_init and args.arch not in ARCHS:
        raise GeoNetInputError(None, f"unknown arch {args.arch!r}", f"--arch must be one of {', '.join(ARCHS)}")
    if args.random_init and (args.eval_synth_dir or args.eval_prepared_dir):
        raise GeoNetInputError(None, "--random-init graphs have no accuracy to evaluate",
                               "drop --eval-synth-dir/--eval-prepared-dir or export a trained --checkpoint")
    if bool(args.eval_synth_dir) != bool(args.eval_prepared_dir):
        raise GeoNetInputError(None, "--eval-synth-dir and --eval-prepared-dir go together")
    if "int8" in precisions:
        if not args.calib_data:
            raise GeoNetInputError(None, "--precision int8 needs --calib-data DIR",
                                   "a folder of consecutive frames, e.g. ../shared/realdata/kitti_raw_2011_09_26_sfnd/image_02/data")
        qz.list_images(args.calib_data)  # fail now, not after minutes of export
    elif args.calib_data or args.eval_synth_dir:
        raise GeoNetInputError(None, "--calib-data / --eval-* only apply to --precision fp32,int8")
    if args.eval_synth_dir:
        from training.evaluate import heldout_sequences

        if not Path(args.eval_synth_dir).is_dir():
            raise GeoNetInputError(args.eval_synth_dir, "synthetic data folder not found",
                                   "pass the --out folder of `python -m training.synth`")
        heldout_sequences(args.eval_prepared_dir)  # raises naming heldout.txt
    if args.seq_length is not None and (args.seq_length < 3 or args.seq_length % 2 == 0):
        raise GeoNetInputError(None, f"--seq-length {args.seq_length}: need an odd number >= 3",
                               "the target is the middle frame of the snippet")
    out = Path(args.out)
    if out.exists() and not args.force:
        raise GeoNetInputError(out, "output directory already exists", "pass --force to replace it, or choose another --out")
    if out.exists() and not out.is_dir():
        raise GeoNetInputError(out, "output path exists and is not a directory", "choose another --out")
    return graphs, precisions


def _load_source(args, graphs: list[str]) -> Source:
    from training.model import GeoNet

    if args.random_init:
        height, width = args.height or REFERENCE_HEIGHT, args.width or REFERENCE_WIDTH
        seq_length = args.seq_length or DEFAULT_SEQ_LENGTH
        torch.manual_seed(args.seed)
        model = GeoNet(args.arch, seq_length - 1, with_flow="resflownet" in graphs).eval()
        source = Source(model, args.arch, height, width, seq_length, random_init=True)
    else:
        from training.train import load_checkpoint, model_from_checkpoint

        path = Path(args.checkpoint)
        ckpt = load_checkpoint(path)
        if "resflownet" in graphs and ckpt["stage"] != "flow":
            rigid_only = ",".join(RIGID_GRAPHS)
            raise GeoNetInputError(path, f"resflownet.onnx needs a stage 'flow' checkpoint, this one is stage "
                                   f"'{ckpt['stage']}'", f"pass --graphs {rigid_only} to export the rigid graphs only, "
                                   "or train stage flow first")
        if args.arch and args.arch != ckpt["arch"]:
            raise GeoNetInputError(path, f"checkpoint arch is '{ckpt['arch']}', --arch says '{args.arch}'",
                                   "drop --arch when exporting a checkpoint")
        if args.seq_length and args.seq_length != ckpt["config"]["seq_length"]:
            raise GeoNetInputError(path, f"checkpoint was trained with seq_length {ckpt['config']['seq_length']}",
                                   "drop --seq-length; PoseNet's input width is fixed by training")
        cfg = ckpt["config"]
        model = model_from_checkpoint(ckpt)
        source = Source(model, ckpt["arch"], args.height or cfg["height"], args.width or cfg["width"],
                        cfg["seq_length"], random_init=False, checkpoint=path, ckpt=ckpt)
    if source.height % SIZE_MULTIPLE or source.width % SIZE_MULTIPLE or source.height <= 0 or source.width <= 0:
        raise GeoNetInputError(None, f"graph size {source.height}x{source.width} is not a positive multiple of "
                               f"{SIZE_MULTIPLE}", "pass --height/--width divisible by 8 (GeoNet uses 128x416)")
    return source


def _make_tmp_dir(out: Path) -> Path:
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f"{out.name}.tmp-", dir=parent))
    except OSError as exc:
        raise GeoNetInputError(parent, f"cannot create the output directory here ({exc.strerror or exc})",
                               "choose a writable --out location") from None
    os.chmod(tmp, 0o755)
    return tmp


def _publish(tmp: Path, out: Path, force: bool) -> None:
    """Rename the finished tmp dir onto ``out`` (an existing ``out`` is replaced only with force)."""
    old = None
    if out.exists():
        if not force:
            raise GeoNetInputError(out, "output directory appeared during the export", "pass --force or choose another --out")
        old = Path(tempfile.mkdtemp(prefix=f"{out.name}.old-", dir=out.parent))
        os.rmdir(old)
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# ------------------------------------------------------------------------------ export
def _log(args, msg: str) -> None:
    if not args.quiet:
        print(msg, file=sys.stderr, flush=True)


def _export_fp32(args, src: Source, graphs: list[str], tmp: Path) -> tuple[dict, str]:
    entries, exporters = {}, set()
    for graph in graphs:
        started = time.perf_counter()
        wrapper = build_wrapper(graph, src.model)
        spec = io_spec(graph, src.height, src.width, src.seq_length)
        example = example_inputs(graph, src.height, src.width, src.seq_length, batch=1)
        meta = mf.graph_metadata(graph, src.arch, src.height, src.width, src.seq_length, "fp32", src.random_init)
        result = export_graph(wrapper, example, spec, tmp / f"{graph}.onnx", meta)
        exporters.add(result.exporter)
        entries[graph] = mf.graph_entry(tmp, f"{graph}.onnx", graph, src.height, src.width, src.seq_length,
                                        OPSET, "fp32", result.exporter)
        size = (tmp / f"{graph}.onnx").stat().st_size / 2 ** 20
        _log(args, f"  fp32 {graph}.onnx  {size:.1f} MiB  ({time.perf_counter() - started:.1f} s)")
    return entries, "; ".join(sorted(exporters))


def _export_int8(args, src: Source, fp32: dict, tmp: Path):
    from geonet_infer.predictor import Predictor
    from geonet_infer.preprocess import InputSpec

    settings = qz.QuantSettings(per_channel=args.per_channel, reduce_range=args.reduce_range,
                                calibrate_method=args.calib_method, max_frames=args.calib_frames)
    frames, original = qz.load_frames(args.calib_data, src.height, src.width, settings.max_frames,
                                      min_frames=src.seq_length)
    K, k_source = qz.calibration_intrinsics(args.calib_data, original, src.height, src.width)
    # An interim manifest lets the fp32 cascade run from the tmp dir (it validates hashes too).
    interim = mf.build_manifest(height=src.height, width=src.width, seq_length=src.seq_length, arch=src.arch,
                                random_init=src.random_init, graphs={"fp32": fp32},
                                prov=mf.provenance(src.arch, src.random_init, ""), metrics={}, quantization=None)
    write_manifest(interim, tmp)
    spec = InputSpec.from_conventions(src.height, src.width, src.seq_length)
    feeds = {"depthnet": qz.depth_feeds(frames, spec), "posenet": qz.pose_feeds(frames, spec)}
    if "resflownet" in fp32:
        feeds["resflownet"] = qz.resflow_feeds(Predictor(tmp, "fp32"), frames, K)
    entries = {}
    for graph in fp32:
        if graph in qz.FP32_ONLY_GRAPHS:
            entries[graph] = fp32[graph]  # same file: the int8 set reuses fp32 rigidflow.onnx
            continue
        started = time.perf_counter()
        qz.quantize_graph(tmp / fp32[graph].file, tmp / "int8" / f"{graph}.onnx", feeds[graph], settings,
                          float_after=qz.FLOAT_AFTER.get(graph, ()))
        entries[graph] = mf.graph_entry(tmp, f"int8/{graph}.onnx", graph, src.height, src.width, src.seq_length,
                                        OPSET, "int8", f"onnxruntime quantize_static QDQ of {fp32[graph].file}")
        size = (tmp / "int8" / f"{graph}.onnx").stat().st_size / 2 ** 20
        _log(args, f"  int8 {graph}.onnx  {size:.1f} MiB  ({len(feeds[graph])} calibration inputs, "
                   f"{time.perf_counter() - started:.1f} s)")
    samples = {g: len(f) for g, f in feeds.items() if g in entries}
    return entries, settings, samples, k_source


def _accuracy_delta(args, src: Source, graphs: dict, tmp: Path) -> tuple[dict | None, str | None]:
    if not args.eval_synth_dir:
        return None, "not measured: pass --eval-synth-dir and --eval-prepared-dir (held-out synthetic set)"
    from geonet_infer.predictor import Predictor
    from training.evaluate import evaluate_depth, evaluate_flow, heldout_sequences, onnx_depth_fn, onnx_flow_fn

    interim = mf.build_manifest(height=src.height, width=src.width, seq_length=src.seq_length, arch=src.arch,
                                random_init=src.random_init, graphs=graphs,
                                prov=mf.provenance(src.arch, src.random_init, ""), metrics={}, quantization=None)
    write_manifest(interim, tmp)
    sequences = heldout_sequences(args.eval_prepared_dir)
    result: dict = {"synth_dir": str(args.eval_synth_dir), "sequences": sequences, "stride": args.eval_stride}
    predictors = {p: Predictor(tmp, p) for p in ("fp32", "int8")}
    depth = {p: evaluate_depth(onnx_depth_fn(c), args.eval_synth_dir, sequences, args.eval_stride)
             for p, c in predictors.items()}
    result["depth_abs_rel"] = _delta(depth, "model", "abs_rel")
    result["depth_frames"] = depth["fp32"]["frames"]
    reason = None
    if "resflownet" in graphs["fp32"] and src.seq_length == 3:
        flow = {p: evaluate_flow(onnx_flow_fn(c), args.eval_synth_dir, sequences, args.eval_stride)
                for p, c in predictors.items()}
        result["flow_epe_noc"] = _delta(flow, "noc", "epe")
        result["flow_epe_occ"] = _delta(flow, "occ", "epe")
        result["flow_pairs"] = flow["fp32"]["pairs"]
    else:
        reason = "flow EPE not measured: needs resflownet (stage flow checkpoint) and seq_length 3"
    return result, reason


def _delta(results: dict, group: str, key: str) -> dict:
    fp32, int8 = results["fp32"][group][key], results["int8"][group][key]
    return {"fp32": fp32, "int8": int8, "delta": int8 - fp32}


def run_export(args) -> Path:
    """Everything ``main`` does, raising GeoNetInputError on bad input; returns the model directory."""
    graphs, precisions = _check_args(args)
    src = _load_source(args, graphs)
    out = Path(args.out)
    tmp = _make_tmp_dir(out)
    try:
        _log(args, f"exporting {src.arch} {src.height}x{src.width} seq {src.seq_length} "
                   f"({'random init' if src.random_init else src.checkpoint}) -> {out}")
        fp32, exporter = _export_fp32(args, src, graphs, tmp)
        all_graphs = {"fp32": fp32}
        quant = None
        if "int8" in precisions:
            int8, settings, samples, k_source = _export_int8(args, src, fp32, tmp)
            all_graphs["int8"] = int8
            delta, reason = _accuracy_delta(args, src, all_graphs, tmp)
            quant = mf.quantization_record(settings.describe(), str(args.calib_data), samples, k_source, delta, reason)
        manifest = mf.build_manifest(
            height=src.height, width=src.width, seq_length=src.seq_length, arch=src.arch,
            random_init=src.random_init, graphs=all_graphs,
            prov=mf.provenance(src.arch, src.random_init, exporter, src.checkpoint, src.ckpt),
            metrics=(src.ckpt or {}).get("metrics", {}), quantization=quant)
        write_manifest(manifest, tmp)
        load_manifest(tmp)  # the directory must validate before it is published
        _publish(tmp, out, args.force)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _log(args, f"done: {out}")
    return out


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        out = run_export(args)
    except GeoNetInputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ExportCheckError as err:
        print(f"error: export check failed: {err}", file=sys.stderr)
        return 1
    if args.quiet:
        return 0
    print(out)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())
