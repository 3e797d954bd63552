"""Import the released GeoNet TensorFlow checkpoints (yzcjtr/GeoNet) into our PyTorch nets.

``python -m export --from-tf CKPT [--from-tf KIND=CKPT ...] --out DIR`` (docs/official_models.md).

The reader is TensorFlow itself (``tf.train.load_checkpoint``, the optional ``[tf]`` extra): it
reads every checkpoint format TensorFlow ever wrote, including the TF 1.x files of the release,
and a hand-written reader of the tensor-bundle format would be one more thing to keep correct.
TensorFlow is imported only here, only when converting; the runtime never needs it.

Naming (``export/official_variables.json``, derived from the official code): slim names unnamed
layers ``<scope>/Conv``, ``Conv_1``, ... in creation order; each layer holds ``weights`` (HWIO) and
either ``BatchNorm/{beta,moving_mean,moving_variance}`` (no gamma: slim's scale=False, our
``BatchNormNoScale``) or ``biases`` (the prediction heads). :func:`torch_layers` lists our layers in
the official creation order, so layer i of ours is ``Conv_i`` of theirs.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from geonet_infer import conventions
from geonet_infer.core.manifest import file_sha256
from geonet_infer.errors import InputError

KINDS = ("depth", "pose", "flow")
SCOPES = {"depth": "depth_net", "pose": "pose_net", "flow": "flow_net"}
GRAPH_OF_KIND = {"depth": "depthnet", "pose": "posenet", "flow": "resflownet"}
OFFICIAL_VARIABLES = Path(__file__).with_name("official_variables.json")
OFFICIAL_CODE = "https://github.com/yzcjtr/GeoNet @ 5b17602"
INSTALL_HINT = "install the converter's extra: pip install '.[train,tf]'"
PREFIX_HINT = (
    "pass the checkpoint prefix, e.g. .../geonet_depthnet/model-250000 (the files are PREFIX.index and PREFIX.data-*)"
)
BN_VARIABLES = ("BatchNorm/beta", "BatchNorm/moving_mean", "BatchNorm/moving_variance")
_CKPT_SUFFIX = re.compile(r"\.(index|meta|data-\d{5}-of-\d{5})$")
_LAYER = re.compile(r"^Conv(?:_(\d+))?$")


# ------------------------------------------------------------------------------ our layers
def torch_layers(net: nn.Module) -> list[tuple[nn.Conv2d, nn.Module | None]]:
    """(conv, batch norm or None) of ``net`` in the official code's creation order (``Conv_i`` = item i).

    DepthNet/ResFlowNet resnet50: conv1, per bottleneck conv1, conv2, conv3, shortcut (``resconv``),
    then per decoder level upconv, iconv and (the last four levels) the prediction head. VGG: the
    7 encoder pairs, then the same decoder. PoseNet: 7 convs, then the 1x1 pose conv.
    """
    from training.networks import DepthNet, PoseNet, ResFlowNet
    from training.networks.depthnet import VGGEncoder

    def block(b) -> tuple[nn.Conv2d, nn.Module]:
        return b.conv, b.bn

    layers = []
    if isinstance(net, PoseNet):
        layers += [block(b) for b in net.convs]
        return layers + [(net.pose_pred, None)]
    if not isinstance(net, (DepthNet, ResFlowNet)):
        raise TypeError(f"not a GeoNet network: {type(net).__name__}")
    enc, dec = net.encoder, net.decoder
    if isinstance(enc, VGGEncoder):
        layers += [block(b) for pair in enc.pairs for b in pair]
    else:
        layers.append(block(enc.conv1))
        for stage in enc.stages:
            for bottleneck in stage:
                layers += [block(getattr(bottleneck, n)) for n in ("conv1", "conv2", "conv3", "shortcut")]
    first_pred_level = dec.num_levels - dec.num_preds
    for level in range(dec.num_levels):
        layers += [block(dec.upconvs[level].conv), block(dec.iconvs[level])]
        if level >= first_pred_level:
            layers.append((dec.heads[dec.num_levels - 1 - level].conv, None))
    return layers


def layer_name(index: int) -> str:
    """slim's auto-name of the ``index``-th unnamed conv of a scope."""
    return "Conv" if index == 0 else f"Conv_{index}"


def expected_variables(kind: str, net: nn.Module) -> list[tuple[str, list[int], str]]:
    """(name, TF shape, dtype) of every checkpoint variable ``net`` needs, in creation order."""
    scope = SCOPES[kind]
    out = []
    for i, (conv, bn) in enumerate(torch_layers(net)):
        o, c, kh, kw = conv.weight.shape
        prefix = f"{scope}/{layer_name(i)}"
        out.append((f"{prefix}/weights", [kh, kw, c, o], "float32"))
        tails = BN_VARIABLES if bn is not None else ("biases",)
        out += [(f"{prefix}/{tail}", [o], "float32") for tail in tails]
    return out


def build_network(kind: str, arch: str | None = None, num_source: int | None = None) -> nn.Module:
    """Our (eval-mode) network for an official one: DepthNet resnet50/vgg, PoseNet, ResFlowNet."""
    from training.networks import DepthNet, PoseNet, ResFlowNet

    if kind == "depth":
        return DepthNet(arch).eval()
    if kind == "pose":
        return PoseNet(num_source, arch="standard").eval()
    return ResFlowNet("resnet50").eval()


def official_variables() -> dict:
    """``export/official_variables.json``: network key -> list of [name, shape, dtype]."""
    data = json.loads(OFFICIAL_VARIABLES.read_text())
    return {key: net["variables"] for key, net in data["networks"].items()}


# ------------------------------------------------------------------------------ reading
def _tf():
    # TensorFlow's C++ start-up notices (CPU features, oneDNN, no CUDA) are not the user's business here.
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    try:
        import tensorflow as tf
    except ImportError:
        raise InputError(None, "--from-tf needs TensorFlow to read the checkpoint", INSTALL_HINT) from None
    return tf


def resolve_prefix(path: str | Path) -> Path:
    """The checkpoint prefix for what the user passed.

    Accepted: the prefix itself (``.../model-250000``, as the official ``--init_ckpt_file``); a file
    of the checkpoint (``.index``, ``.meta``, ``.data-*``: the suffix is stripped); a folder holding
    one checkpoint (the one its ``checkpoint`` file names, else its single ``*.index``).
    """
    path = Path(path)
    if path.is_dir():
        index = None
        state = path / "checkpoint"
        if state.is_file():
            # The released 'checkpoint' files hold the authors' absolute paths: keep the file name only.
            m = re.search(r'^model_checkpoint_path:\s*"(.+)"', state.read_text(errors="replace"), re.M)
            if m:
                index = path / (Path(m.group(1)).name + ".index")
        if index is None or not index.is_file():
            found = sorted(path.glob("*.index"))
            if len(found) != 1:
                problem = (
                    "no TensorFlow checkpoint (*.index) in this folder"
                    if not found
                    else (f"{len(found)} checkpoints in this folder ({', '.join(f.stem for f in found[:4])}...)")
                )
                raise InputError(path, problem, PREFIX_HINT)
            index = found[0]
        return index.with_suffix("")
    prefix = path.with_name(_CKPT_SUFFIX.sub("", path.name))
    if not Path(f"{prefix}.index").is_file():
        raise InputError(path, "no TensorFlow checkpoint here (PREFIX.index not found)", PREFIX_HINT)
    return prefix


@dataclass
class TFCheckpoint:
    """One opened checkpoint: its variables (name -> shape, dtype) and its files' sha256."""

    prefix: Path
    shapes: dict
    dtypes: dict
    reader: object = field(repr=False)

    @classmethod
    def open(cls, path: str | Path) -> TFCheckpoint:
        prefix = resolve_prefix(path)
        if any(c in str(prefix) for c in "[]*?"):  # TensorFlow globs the prefix: it would find nothing
            raise InputError(
                prefix,
                "TensorFlow reads checkpoint paths as glob patterns and cannot open one holding [ ] * or ?",
                "rename the folder, or link the checkpoint files from a path without those characters",
            )
        tf = _tf()
        try:
            reader = tf.train.load_checkpoint(str(prefix))
            shapes = reader.get_variable_to_shape_map()
            dtypes = {k: v.name for k, v in reader.get_variable_to_dtype_map().items()}
        except (tf.errors.OpError, ValueError, OSError) as exc:
            raise InputError(
                f"{prefix}.index", f"unreadable TensorFlow checkpoint ({_first_line(exc)})", PREFIX_HINT
            ) from None
        return cls(prefix, {k: list(v) for k, v in shapes.items()}, dtypes, reader)

    def files(self) -> dict[str, str]:
        """File name -> sha256 of the .index and .data-* files."""
        names = [Path(f"{self.prefix}.index"), *sorted(self.prefix.parent.glob(f"{self.prefix.name}.data-*"))]
        return {f.name: file_sha256(f) for f in names}

    def tensor(self, name: str) -> np.ndarray:
        try:
            value = np.asarray(self.reader.get_tensor(name))
        except Exception as exc:  # TF raises DataLossError / OpError subclasses from C++; all mean unreadable
            raise InputError(
                self.prefix,
                f"cannot read variable {name} ({_first_line(exc)}): the checkpoint is truncated or corrupt",
                "download it again",
            ) from None
        if np.issubdtype(value.dtype, np.floating) and not np.isfinite(value).all():  # every frame would fail
            raise InputError(
                self.prefix,
                f"variable {name} holds NaN/inf values ({np.count_nonzero(~np.isfinite(value))} of {value.size})",
                "the checkpoint is corrupt or its training diverged: use another checkpoint",
            )
        return value

    def scope_variables(self, kind: str) -> set[str]:
        return {n for n in self.shapes if n.startswith(SCOPES[kind] + "/")}

    def kinds(self) -> list[str]:
        return [k for k in KINDS if self.scope_variables(k)]

    def step(self) -> int | None:
        return int(self.tensor("global_step")) if "global_step" in self.shapes else None


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]


# ------------------------------------------------------------------------------ detection + mapping
@dataclass(frozen=True)
class NetSpec:
    kind: str
    arch: str | None = None  # depth: resnet50 | vgg; flow: resnet50
    num_source: int | None = None  # pose

    def describe(self) -> str:
        if self.kind == "pose":
            return f"pose_net (PoseNet, seq {self.num_source + 1})"
        return f"{SCOPES[self.kind]} ({'DepthNet' if self.kind == 'depth' else 'ResFlowNet'} {self.arch})"


def _shape(ckpt: TFCheckpoint, name: str, kind: str) -> list[int]:
    if name not in ckpt.shapes:
        raise InputError(
            ckpt.prefix,
            f"variable {name} missing: not an official GeoNet {SCOPES[kind]}",
            "the converter reads the checkpoints of yzcjtr/GeoNet (docs/official_models.md)",
        )
    return ckpt.shapes[name]


def detect(ckpt: TFCheckpoint, kind: str) -> NetSpec:
    """Which variant of ``kind`` the checkpoint holds, from the shape of one telling variable."""
    scope = SCOPES[kind]
    if kind == "depth":
        first = f"{scope}/Conv/weights"
        widths = {64: "resnet50", 32: "vgg"}  # conv1: 7x7x3x64 (resnet50) or 7x7x3x32 (vgg)
        shape = _shape(ckpt, first, kind)
        if len(shape) != 4 or shape[3] not in widths:
            raise InputError(ckpt.prefix, f"variable {first} has shape {shape}: neither resnet50 nor vgg")
        return NetSpec(kind, arch=widths[shape[3]])
    if kind == "pose":
        last = f"{scope}/Conv_7/weights"
        shape = _shape(ckpt, last, kind)
        if len(shape) != 4 or shape[3] % 6 or shape[3] < 6:
            raise InputError(ckpt.prefix, f"variable {last} has shape {shape}: expected 1x1x256x(6*num_source)")
        return NetSpec(kind, num_source=shape[3] // 6)
    first = f"{scope}/Conv/weights"
    shape = _shape(ckpt, first, kind)
    if len(shape) == 4 and shape[2] == 6:
        raise InputError(
            ckpt.prefix,
            f"variable {first} takes 6 channels: this is the 'direct' flow net (geonet_dirflownet)",
            "only the residual ResFlowNet (geonet_resflownet, 12 input channels) is supported",
        )
    return NetSpec(kind, arch="resnet50")


def convert_network(ckpt: TFCheckpoint, spec: NetSpec) -> nn.Module:
    """Our network with every parameter and BN statistic set from ``ckpt``.

    Every ``<scope>/`` variable is consumed exactly once; a missing, left-over or misshapen
    variable is a GeoNetError naming it. HWIO weights become OIHW. (``num_batches_tracked``,
    a PyTorch training counter unused in eval mode, stays 0.)
    """
    net = build_network(spec.kind, spec.arch, spec.num_source)
    expected = expected_variables(spec.kind, net)
    present = ckpt.scope_variables(spec.kind)
    what = f"{spec.describe()}; the official one has {len(expected)} variables"
    missing = [n for n, _, _ in expected if n not in present]
    if missing:
        raise InputError(
            ckpt.prefix, f"variable {missing[0]} missing ({len(missing)} missing in all) for {what}", PREFIX_HINT
        )
    extra = sorted(present - {n for n, _, _ in expected})
    if extra:
        raise InputError(
            ckpt.prefix,
            f"unexpected variable {extra[0]} ({len(extra)} left over in all) for {what}",
            "this is not a checkpoint of the official GeoNet code; nothing was converted",
        )
    for name, shape, dtype in expected:
        if ckpt.shapes[name] != shape or ckpt.dtypes[name] != dtype:
            raise InputError(
                ckpt.prefix,
                f"variable {name} has shape {ckpt.shapes[name]} {ckpt.dtypes[name]}, "
                f"the official {SCOPES[spec.kind]} has {shape} {dtype}",
                "this is not a checkpoint of the official GeoNet code; nothing was converted",
            )
    assigned = set()
    with torch.no_grad():
        for i, (conv, bn) in enumerate(torch_layers(net)):
            prefix = f"{SCOPES[spec.kind]}/{layer_name(i)}"
            conv.weight.copy_(torch.from_numpy(ckpt.tensor(f"{prefix}/weights").transpose(3, 2, 0, 1).copy()))
            assigned.add(id(conv.weight))
            if bn is None:
                targets = {"biases": conv.bias}
            else:
                targets = dict(zip(BN_VARIABLES, (bn.bias, bn.running_mean, bn.running_var)))
            for tail, target in targets.items():
                target.copy_(torch.from_numpy(ckpt.tensor(f"{prefix}/{tail}")))
                assigned.add(id(target))
    unset = [n for n, t in (*net.named_parameters(), *net.named_buffers()) if id(t) not in assigned]
    unset = [n for n in unset if not n.endswith("num_batches_tracked")]
    if unset:  # a mapping bug, not a user error: torch_layers missed a layer
        raise AssertionError(f"parameters not set by the checkpoint: {unset[:5]}")
    return net


# ------------------------------------------------------------------------------ sources
def parse_spec(text: str) -> tuple[tuple[str, ...], str]:
    """``PFX`` -> ((), PFX): every network it holds; ``depth=PFX`` / ``depth,pose=PFX`` -> those only."""
    head, sep, tail = text.partition("=")
    kinds = tuple(k.strip() for k in head.split(","))
    if sep and tail and all(k in KINDS for k in kinds):
        return kinds, tail
    if sep and re.fullmatch(r"[a-z_,]+", head):
        raise InputError(None, f"--from-tf {text}: unknown network {head!r}", f"use {'|'.join(KINDS)}=PREFIX")
    return (), text


@dataclass
class Conversion:
    """What ``--from-tf`` produced: the converted nets and where each came from."""

    nets: dict  # kind -> nn.Module
    specs: dict  # kind -> NetSpec
    sources: list  # manifest provenance records, one per checkpoint
    notes: list  # human-readable remarks (also in the manifest)


def convert_checkpoints(specs: tuple[str, ...] | list[str], log=print) -> Conversion:
    """Open every ``--from-tf`` checkpoint, decide which net comes from which, and convert them.

    Explicit ``kind=PFX`` assignments win; a plain ``PFX`` gives every net it holds that no
    explicit assignment names. A net given twice is an error.
    """
    parsed = [parse_spec(s) for s in specs]
    ckpts = [TFCheckpoint.open(path) for _, path in parsed]
    for ckpt in ckpts:
        if not ckpt.kinds():
            raise InputError(
                f"{ckpt.prefix}.index",
                "not a GeoNet checkpoint: no depth_net/, pose_net/ or flow_net/ variables",
                "pass a checkpoint of the official GeoNet code (docs/official_models.md)",
            )
    explicit = {k for kinds, _ in parsed for k in kinds}
    owner: dict[str, int] = {}
    for i, ((kinds, _), ckpt) in enumerate(zip(parsed, ckpts)):
        for kind in kinds:
            if kind not in ckpt.kinds():
                raise InputError(
                    ckpt.prefix,
                    f"holds no {SCOPES[kind]}/ variables (it holds {', '.join(SCOPES[k] for k in ckpt.kinds())})",
                    "pick the release that contains it (docs/official_models.md)",
                )
        for kind in kinds or [k for k in ckpt.kinds() if k not in explicit]:
            if kind in owner:
                raise InputError(
                    None,
                    f"{SCOPES[kind]} is given twice ({ckpts[owner[kind]].prefix} and {ckpt.prefix})",
                    f"choose one with --from-tf {kind}=PREFIX",
                )
            owner[kind] = i
    nets, chosen, sources, notes = {}, {}, [], []
    for kind in KINDS:
        if kind in owner:
            ckpt = ckpts[owner[kind]]
            chosen[kind] = detect(ckpt, kind)
            nets[kind] = convert_network(ckpt, chosen[kind])
    for i, ckpt in enumerate(ckpts):
        used = [k for k in KINDS if owner.get(k) == i]
        unused = [f"{SCOPES[k]} ({len(ckpt.scope_variables(k))} variables)" for k in ckpt.kinds() if k not in used]
        other = sorted(
            n for n in ckpt.shapes if n != "global_step" and not any(n in ckpt.scope_variables(k) for k in KINDS)
        )
        record = {
            "checkpoint": ckpt.prefix.name,
            "path": str(ckpt.prefix),
            "networks": [chosen[k].describe() for k in used],
            "global_step": ckpt.step(),
            "not_converted": unused + ([f"{len(other)} other variables"] if other else []),
            "sha256": ckpt.files(),
        }
        sources.append(record)
        log(
            f"  {ckpt.prefix}: converted {', '.join(record['networks']) or 'nothing'}"
            + (f"; not converted: {', '.join(record['not_converted'])}" if record["not_converted"] else "")
            + (f"; global_step {record['global_step']}" if record["global_step"] is not None else "")
        )
    if "flow" in owner and any(owner.get(k, owner["flow"]) != owner["flow"] for k in ("depth", "pose")):
        notes.append(
            f"ResFlowNet comes from {ckpts[owner['flow']].prefix.name}, which was trained on the rigid flow of that "
            "checkpoint's own depth_net and pose_net; here depth/pose come from another checkpoint, so the flow "
            "is not the released cascade (convert the flow checkpoint alone for that)"
        )
    for note in notes:
        log(f"  note: {note}")
    return Conversion(nets, chosen, sources, notes)


def official_conventions(chosen: dict, scale_normalize: bool) -> dict:
    """The official code's conventions for the manifest (``conventions.official_tf``).

    They are the project's own conventions (``geonet_infer.conventions``), which the runtime
    applies from the manifest; this block states them as the official code has them.
    """
    out: dict = {
        "code": OFFICIAL_CODE,
        "input": "uint8 RGB, tf.image.convert_image_dtype (x/255) then x*2-1; NHWC in TF, NCHW in the graphs",
        "reference_size": [conventions.REFERENCE_HEIGHT, conventions.REFERENCE_WIDTH],
    }
    if "depth" in chosen:
        head = conventions.DISP_HEADS[chosen["depth"].arch]
        out["depth"] = {
            "arch": chosen["depth"].arch,
            "disparity": f"{head.scale:g}*sigmoid+{head.offset:g} (minimum {head.offset:g}); depth = 1/disparity",
            "scale_normalize": scale_normalize,
            "scale_normalize_note": "each disparity map divided by its spatial mean (model_sn), inside depthnet.onnx"
            if scale_normalize
            else "off (pass --scale-normalize for the model_sn release)",
        }
    if "pose" in chosen:
        n = chosen["pose"].num_source
        k = n // 2
        order = ["t"] + [f"t{o:+d}" for o in range(-k, k + 1) if o]
        out["pose"] = {
            "snippet_order": order,
            "vector": list(conventions.POSE.vector),
            "units": "translation in the depth's units, Euler angles in radians",
            "output_scale": conventions.POSE.output_scale,
            "direction": conventions.POSE.direction,
        }
    if "flow" in chosen:
        out["flow"] = {
            "flow_scaling": conventions.FLOW_SCALING,
            "output": "residual flow = 0.1*conv, normalised by image size, times (W, H) = pixels; "
            "full flow = residual + rigid flow",
        }
    return out


def tf_source(cfg, requested: list[str], log=print):
    """``export.source.Source`` for ``cfg.from_tf`` (called by :func:`export.build.export_model`).

    Graphs: those the checkpoints' nets give (depthnet, posenet, resflownet) plus the weightless
    rigidflow.onnx; ``--graphs`` narrows that set and must not ask for a net the checkpoints lack.
    """
    from export.source import Source, check_graph_size
    from export.wrappers import GRAPH_NAMES
    from training.model import GeoNet

    height = cfg.height or conventions.REFERENCE_HEIGHT
    width = cfg.width or conventions.REFERENCE_WIDTH
    check_graph_size(height, width)  # before minutes of reading checkpoints
    conv = convert_checkpoints(cfg.from_tf, log)
    available = {GRAPH_OF_KIND[k] for k in conv.nets} | {"rigidflow"}
    if tuple(requested) == GRAPH_NAMES:  # the default: everything the checkpoints give
        graphs = [g for g in GRAPH_NAMES if g in available]
    else:
        lacking = [g for g in requested if g not in available]
        if lacking:
            raise InputError(
                None,
                f"--graphs {','.join(lacking)}: the --from-tf checkpoints hold no network for it",
                f"they give {', '.join(g for g in GRAPH_NAMES if g in available)}",
            )
        graphs = list(requested)
    if "resflownet" in graphs and not {"depthnet", "posenet"} <= set(graphs):
        raise InputError(
            None,
            "resflownet.onnx needs depthnet and posenet too (its input is their rigid flow)",
            "the released flow checkpoint holds all three: --from-tf PREFIX converts them together",
        )
    if cfg.scale_normalize and "depth" not in conv.nets:
        raise InputError(None, "--scale-normalize applies to a depth_net, and none is converted")
    arch = conv.specs["depth"].arch if "depth" in conv.specs else "resnet50"
    if cfg.arch and cfg.arch != arch:
        raise InputError(None, f"the checkpoint's depth_net is {arch}, --arch says {cfg.arch}", "drop --arch")
    seq_length = conv.specs["pose"].num_source + 1 if "pose" in conv.specs else (cfg.seq_length or 3)
    if cfg.seq_length and cfg.seq_length != seq_length:
        raise InputError(
            None, f"the checkpoint's pose_net takes {seq_length}-frame snippets, --seq-length says {cfg.seq_length}"
        )
    model = GeoNet(arch, seq_length - 1, with_flow="flow" in conv.nets, scale_normalize=cfg.scale_normalize)
    for kind, attr in (("depth", "depth_net"), ("pose", "pose_net"), ("flow", "flow_net")):
        if kind in conv.nets:
            setattr(model, attr, conv.nets[kind])
    official = official_conventions(conv.specs, cfg.scale_normalize)
    if conv.notes:
        official["notes"] = conv.notes
    return Source(
        model.eval(),
        arch,
        height,
        width,
        seq_length,
        random_init=False,
        graphs=graphs,
        sources=conv.sources,
        official=official,
    )
