"""Export GeoNet to a model directory: :class:`ExportConfig` in, the directory out.

    from export import ExportConfig, export_model
    export_model(ExportConfig(out=Path("/tmp/geonet_small"), arch="small", random_init=True))

``python -m export`` only parses its flags into an :class:`ExportConfig` and calls
:func:`export_model`. The directory is written as ``DIR.tmp-XXXX`` beside DIR and
renamed when complete, so DIR is either absent or whole. Bad input raises
:class:`~geonet_infer.errors.GeoNetError` before anything is written.
"""

from __future__ import annotations

import dataclasses
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from export import manifest as mf
from export.source import Source, check_graph_size
from export.to_onnx import OPSET, ExportCheckError, export_graph
from export.wrappers import GRAPH_NAMES, RIGID_GRAPHS, build_wrapper, example_inputs, io_spec, photometric_alpha
from geonet_infer.conventions import REFERENCE_HEIGHT, REFERENCE_WIDTH
from geonet_infer.convert import manifest as cmf
from geonet_infer.convert import quantize as qz
from geonet_infer.convert.build import make_tmp_dir, publish
from geonet_infer.convert.int8 import quantize_directory
from geonet_infer.errors import GeoNetError, InputError
from geonet_infer.io import IMAGE_SUFFIXES, list_images
from geonet_infer.io.atomic import json_safe
from geonet_infer.models.manifest import PRECISIONS, load_manifest, write_manifest
from training.checkpoint import load_weights, model_from_checkpoint, trained_by
from training.config import ARCHS

DEFAULT_SEQ_LENGTH = 3


@dataclass
class ExportConfig:
    """What to export and how. Exactly one of ``checkpoint`` / ``random_init`` / ``from_tf``.

    ``height``/``width``/``seq_length`` of None mean the checkpoint's (or 128 x 416 and 3 for
    random weights). ``graphs`` and ``precisions`` may be given in any order; int8 needs
    ``calib_data`` and always comes with fp32 (its graphs are calibrated with the fp32 ones).
    """

    out: Path
    checkpoint: Path | None = None  # last.pt / best.pt of training.train
    from_tf: tuple[str, ...] = ()  # official TF checkpoints, "PREFIX" or "depth=PREFIX" (export/from_tf.py)
    scale_normalize: bool = False  # from_tf: the model_sn release (each disparity map / its mean, in the graph)
    verify: Path | None = None  # from_tf: frames folder; its first frame through the ONNX vs the checkpoint's forward
    arch: str | None = None  # random_init: one of training.config.ARCHS
    random_init: bool = False  # timing-only graphs; accuracy commands refuse them
    seed: int = 0  # torch seed of random_init weights
    height: int | None = None
    width: int | None = None
    seq_length: int | None = None
    force: bool = False  # replace an existing out directory
    graphs: tuple[str, ...] = GRAPH_NAMES
    precisions: tuple[str, ...] = ("fp32",)
    calib_data: Path | None = None  # folder of consecutive frames for INT8 calibration
    calib_frames: int = qz.QuantSettings.max_frames
    calib_method: str = qz.QuantSettings.calibrate_method
    reduce_range: bool = qz.QuantSettings.reduce_range
    per_channel: bool = qz.QuantSettings.per_channel
    int8_ops: tuple[str, ...] = qz.QuantSettings.op_types
    eval_synth_dir: Path | None = None  # held-out synthetic set for the int8 accuracy delta
    eval_prepared_dir: Path | None = None  # training.prepare folder holding heldout.txt
    eval_stride: int = 1
    quiet: bool = False  # no progress lines on stderr

    def quant_settings(self) -> qz.QuantSettings:
        return qz.QuantSettings(
            per_channel=self.per_channel,
            reduce_range=self.reduce_range,
            calibrate_method=self.calib_method,
            max_frames=self.calib_frames,
            op_types=self.int8_ops,
        )


# ------------------------------------------------------------------------------ checks
def _choose(items, allowed: tuple, what: str) -> list[str]:
    """``items`` in the canonical order of ``allowed``; GeoNetError naming unknown ones."""
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise InputError(None, f"unknown {what} {bad or list(items)!r}", f"choose from {', '.join(allowed)}")
    return [a for a in allowed if a in items]


def _check_calib_data(folder: Path) -> None:
    """Fail now, not after minutes of export, if the calibration folder holds no frames."""
    try:
        list_images(folder)
    except GeoNetError as err:
        raise InputError(
            folder,
            f"--calib-data: {err.problem}",
            f"it needs consecutive frames ({', '.join(IMAGE_SUFFIXES)}), e.g. a KITTI image_02/data folder",
        ) from None


def _check(cfg: ExportConfig) -> tuple[list[str], list[str]]:
    """Validate ``cfg``; returns (graphs, precisions) in canonical order."""
    graphs = _choose(cfg.graphs, GRAPH_NAMES, "graph")
    precisions = _choose(cfg.precisions, PRECISIONS, "precision")
    if "fp32" not in precisions:
        raise InputError(
            None,
            "--precision must include fp32",
            "int8 graphs are calibrated with the fp32 ones: use --precision fp32,int8",
        )
    if sum((bool(cfg.checkpoint), bool(cfg.random_init), bool(cfg.from_tf))) != 1:
        raise InputError(None, "pass exactly one of --checkpoint, --random-init or --from-tf")
    if cfg.verify and not cfg.from_tf:
        raise InputError(None, "--verify applies to --from-tf", "it compares the graphs with the TF checkpoint")
    if cfg.verify:
        list_images(cfg.verify)  # a missing or empty frames folder, before minutes of converting
    if cfg.scale_normalize and not cfg.from_tf:
        raise InputError(
            None, "--scale-normalize only applies to --from-tf", "our checkpoints record it in their config"
        )
    if cfg.random_init and cfg.arch not in ARCHS:
        raise InputError(None, f"unknown arch {cfg.arch!r}", f"--arch must be one of {', '.join(ARCHS)}")
    if cfg.random_init and (cfg.eval_synth_dir or cfg.eval_prepared_dir):
        raise InputError(
            None,
            "--random-init graphs have no accuracy to evaluate",
            "drop --eval-synth-dir/--eval-prepared-dir or export a trained --checkpoint",
        )
    if bool(cfg.eval_synth_dir) != bool(cfg.eval_prepared_dir):
        raise InputError(None, "--eval-synth-dir and --eval-prepared-dir go together")
    if "int8" in precisions:
        if not cfg.calib_data:
            raise InputError(
                None,
                "--precision int8 needs --calib-frames DIR (or --calib-data DIR)",
                "a folder of consecutive frames, e.g. frames of your own footage",
            )
        _check_calib_data(Path(cfg.calib_data))
        _choose([cfg.calib_method], qz.CALIBRATION_METHODS, "--calib-method")
        if cfg.int8_ops:
            _choose(list(cfg.int8_ops), qz.quantisable_op_types(), "--int8-ops")
    elif cfg.calib_data or cfg.eval_synth_dir:
        raise InputError(None, "--calib-data / --eval-* only apply to --precision fp32,int8")
    if cfg.eval_synth_dir:
        from training.evaluate import heldout_sequences

        if not Path(cfg.eval_synth_dir).is_dir():
            raise InputError(
                cfg.eval_synth_dir,
                "synthetic data folder not found",
                "pass the --out folder of `python -m training.synth`",
            )
        heldout_sequences(cfg.eval_prepared_dir)  # raises naming heldout.txt
    if cfg.seq_length is not None and (cfg.seq_length < 3 or cfg.seq_length % 2 == 0):
        raise InputError(
            None,
            f"--seq-length {cfg.seq_length}: need an odd number >= 3",
            "the target is the middle frame of the snippet",
        )
    out = Path(cfg.out)
    if out.exists() and not cfg.force:
        raise InputError(out, "output directory already exists", "pass --force to replace it, or choose another --out")
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a directory", "choose another --out")
    return graphs, precisions


def _random_source(cfg: ExportConfig, graphs: list[str]) -> Source:
    from training.model import GeoNet

    seq_length = cfg.seq_length or DEFAULT_SEQ_LENGTH
    torch.manual_seed(cfg.seed)
    model = GeoNet(cfg.arch, seq_length - 1, with_flow="resflownet" in graphs).eval()
    return Source(
        model, cfg.arch, cfg.height or REFERENCE_HEIGHT, cfg.width or REFERENCE_WIDTH, seq_length, random_init=True
    )


def _checkpoint_source(cfg: ExportConfig, graphs: list[str]) -> Source:
    path = Path(cfg.checkpoint)
    ckpt = load_weights(path)  # a training checkpoint, or a weights file of training.checkpoint (--combine, ...)
    if "source" in ckpt:  # a weights file keeps the step and command it came from under "source"
        ckpt = {**trained_by(ckpt), **ckpt}
    train_cfg = ckpt["config"]
    if "resflownet" in graphs and ckpt["stage"] != "flow":
        raise InputError(
            path,
            f"resflownet.onnx needs a stage 'flow' checkpoint, this one is stage '{ckpt['stage']}'",
            f"pass --graphs {','.join(RIGID_GRAPHS)} to export the rigid graphs only, or train stage flow first",
        )
    if cfg.arch and cfg.arch != ckpt["arch"]:
        raise InputError(
            path,
            f"checkpoint arch is '{ckpt['arch']}', --arch says '{cfg.arch}'",
            "drop --arch when exporting a checkpoint",
        )
    if cfg.seq_length and cfg.seq_length != train_cfg["seq_length"]:
        raise InputError(
            path,
            f"checkpoint was trained with seq_length {train_cfg['seq_length']}",
            "drop --seq-length; PoseNet's input width is fixed by training",
        )
    return Source(
        model_from_checkpoint(ckpt),
        ckpt["arch"],
        cfg.height or train_cfg["height"],
        cfg.width or train_cfg["width"],
        train_cfg["seq_length"],
        random_init=False,
        checkpoint=path,
        ckpt=ckpt,
    )


def load_source(cfg: ExportConfig, graphs: list[str]) -> Source:
    src = _random_source(cfg, graphs) if cfg.random_init else _checkpoint_source(cfg, graphs)
    check_graph_size(src.height, src.width)
    return src


# ------------------------------------------------------------------------------ directory
# ------------------------------------------------------------------------------ export
def _log(cfg: ExportConfig, msg: str) -> None:
    if not cfg.quiet:
        print(msg, file=sys.stderr, flush=True)


def _manifest(src: Source, graphs: dict, prov, metrics: dict, quantization) -> object:
    return cmf.build_manifest(
        height=src.height,
        width=src.width,
        seq_length=src.seq_length,
        arch=src.arch,
        random_init=src.random_init,
        graphs=graphs,
        prov=prov,
        metrics=metrics,
        quantization=quantization,
        photometric_alpha=photometric_alpha(src.model),
    )


def _interim_manifest(src: Source, graphs: dict, tmp: Path) -> None:
    """A manifest over the graphs written so far, so the runtime Predictor can run from ``tmp``."""
    write_manifest(_manifest(src, graphs, mf.provenance(src.arch, src.random_init, ""), {}, None), tmp)


def _export_fp32(cfg: ExportConfig, src: Source, graphs: list[str], tmp: Path) -> tuple[dict, str]:
    entries, exporters = {}, set()
    for graph in graphs:
        example = example_inputs(graph, src.height, src.width, src.seq_length, batch=1)
        meta = cmf.graph_metadata(
            graph,
            src.arch,
            src.height,
            src.width,
            src.seq_length,
            "fp32",
            src.random_init,
            photometric_alpha(src.model),
        )
        result = export_graph(
            build_wrapper(graph, src.model),
            example,
            io_spec(graph, src.height, src.width, src.seq_length),
            tmp / f"{graph}.onnx",
            meta,
        )
        exporters.add(result.exporter)
        _check_outputs(result.path, example, may_be_constant=_zero_when_still(graph, src.model))
        entries[graph] = mf.graph_entry(
            tmp, f"{graph}.onnx", graph, src.height, src.width, src.seq_length, OPSET, "fp32", result.exporter
        )
        size = result.path.stat().st_size / 2**20
        _log(cfg, f"  fp32 {graph}.onnx  {size:.1f} MiB  ({result.seconds:.1f} s)")
    return entries, "; ".join(sorted(exporters))


def _zero_when_still(graph: str, model) -> tuple[str, ...]:
    """Outputs that may be one value on the random example inputs: the pose vectors of a PoseNet whose hard
    motion gate (issue 53) calls those frames still, which is that gate's legitimate answer, not dead weights."""
    gate = getattr(model.pose_net, "gate", None) if graph == "posenet" else None
    return ("pose",) if gate is not None and gate.hard else ()


def _check_outputs(path: Path, example, may_be_constant: tuple[str, ...] = ()) -> None:
    """The exported graph on its (random) example inputs: every output finite and, but for ``may_be_constant``,
    not one value everywhere. NaN or all-equal weights would give a model whose every frame fails or is blank."""
    from export.verify import ort_outputs
    from geonet_infer.engines.onnxruntime import make_session, make_session_options

    # Basic optimisations suffice for this check; "all" re-lays every conv weight out (NCHWc),
    # a second copy of the weights: +0.35 GB at the peak of exporting a resnet50 graph.
    session = make_session(path, make_session_options(opt_level="basic"))
    for out, value in zip(session.get_outputs(), ort_outputs(session, [np.asarray(x) for x in example])):
        if not np.isfinite(value).all():
            raise ExportCheckError(f"{path.name}: output {out.name} holds NaN/inf on example inputs: are the weights?")
        if value.size > 1 and value.min() == value.max() and out.name not in may_be_constant:
            raise ExportCheckError(
                f"{path.name}: output {out.name} is {value.flat[0]:g} everywhere on example inputs (degenerate weights)"
            )


def _delta(results: dict, group: str, key: str) -> dict:
    fp32, int8 = results["fp32"][group][key], results["int8"][group][key]
    return {"fp32": fp32, "int8": int8, "delta": int8 - fp32}


def _accuracy_delta(cfg: ExportConfig, src: Source, graphs: dict, tmp: Path) -> tuple[dict | None, str | None]:
    if not cfg.eval_synth_dir:
        return None, "not measured: pass --eval-synth-dir and --eval-prepared-dir (held-out synthetic set)"
    from geonet_infer.core.predictor import Predictor
    from training.evaluate import evaluate_depth, evaluate_flow, heldout_sequences, onnx_depth_fn, onnx_flow_fn

    _interim_manifest(src, graphs, tmp)
    sequences = heldout_sequences(cfg.eval_prepared_dir)
    result: dict = {"synth_dir": str(cfg.eval_synth_dir), "sequences": sequences, "stride": cfg.eval_stride}
    predictors = {p: Predictor(tmp, p) for p in ("fp32", "int8")}
    depth = {
        p: evaluate_depth(onnx_depth_fn(c), cfg.eval_synth_dir, sequences, cfg.eval_stride)
        for p, c in predictors.items()
    }
    result["depth_abs_rel"] = _delta(depth, "model", "abs_rel")
    result["depth_frames"] = depth["fp32"]["frames"]
    if "resflownet" not in graphs["fp32"] or src.seq_length != 3:
        return result, "flow EPE not measured: needs resflownet (stage flow checkpoint) and seq_length 3"
    flow = {
        p: evaluate_flow(onnx_flow_fn(c), cfg.eval_synth_dir, sequences, cfg.eval_stride) for p, c in predictors.items()
    }
    result["flow_epe_noc"] = _delta(flow, "noc", "epe")
    result["flow_epe_occ"] = _delta(flow, "occ", "epe")
    result["flow_pairs"] = flow["fp32"]["pairs"]
    return result, None


def _write_graphs(cfg: ExportConfig, src: Source, graphs: list[str], precisions: list[str], tmp: Path) -> None:
    """Every graph, int8 copies and the final manifest into ``tmp``."""
    fp32, exporter = _export_fp32(cfg, src, graphs, tmp)
    all_graphs = {"fp32": fp32}
    quant = None
    if "int8" in precisions:
        int8, quant = quantize_directory(
            tmp,
            fp32,
            arch=src.arch,
            height=src.height,
            width=src.width,
            seq_length=src.seq_length,
            calib_data=Path(cfg.calib_data),  # type: ignore[arg-type]
            settings=cfg.quant_settings(),
            write_interim=lambda g: _interim_manifest(src, g, tmp),
            log=lambda msg: _log(cfg, msg),
        )
        all_graphs["int8"] = int8
        delta, reason = _accuracy_delta(cfg, src, all_graphs, tmp)
        quant = dataclasses.replace(quant, accuracy_delta=json_safe(delta), accuracy_delta_reason=reason)
    prov = mf.provenance(src.arch, src.random_init, exporter, src.checkpoint, src.ckpt)
    write_manifest(_manifest(src, all_graphs, prov, (src.ckpt or {}).get("metrics", {}), quant), tmp)
    load_manifest(tmp)  # the directory must validate before it is published


def export_model(cfg: ExportConfig) -> Path:
    """Write the model directory ``cfg.out`` and return its path.

    Raises:
        GeoNetError: bad config or input (nothing is written).
        ExportCheckError: an exported graph failed its structural check.
    """
    graphs, precisions = _check(cfg)
    if cfg.from_tf:  # the runtime's conversion, with templates for the asked size (export/from_tf.py)
        from export.from_tf import tf_export

        return tf_export(cfg, lambda msg: _log(cfg, msg))
    src = load_source(cfg, graphs)
    out = Path(cfg.out)
    tmp = make_tmp_dir(out)
    try:
        _log(
            cfg,
            f"exporting {src.arch} {src.height}x{src.width} seq {src.seq_length} "
            f"({'random init' if src.random_init else src.checkpoint or 'TensorFlow checkpoints'}) -> {out}",
        )
        _write_graphs(cfg, src, graphs, precisions, tmp)
        publish(tmp, out, cfg.force)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _log(cfg, f"done: {out}")
    return out
