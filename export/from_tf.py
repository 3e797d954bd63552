"""Import the released GeoNet TensorFlow checkpoints (yzcjtr/GeoNet) into our PyTorch nets.

``python -m export --from-tf CKPT [--from-tf KIND=CKPT ...] --out DIR`` (docs/official_models.md).

The reader is :mod:`export.tf_checkpoint` (numpy only: the ``.index`` table and memory-mapped
``.data-*`` shards, each tensor's crc32c checked), so converting needs the ``[train]`` extra alone.
TensorFlow (``[tf]``) is used only by ``--verify`` when installed (the official forward pass) and
by the equality tests; the runtime never needs either.

Naming (``export/official_variables.json``, derived from the official code): slim names unnamed
layers ``<scope>/Conv``, ``Conv_1``, ... in creation order; each layer holds ``weights`` (HWIO) and
either ``BatchNorm/{beta,moving_mean,moving_variance}`` (no gamma: slim's scale=False, our
``BatchNormNoScale``) or ``biases`` (the prediction heads). :func:`torch_layers` lists our layers in
the official creation order, so layer i of ours is ``Conv_i`` of theirs.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from export.official_tf import OfficialNet, layer_name
from export.tf_checkpoint import BundleReader
from geonet_infer import conventions
from geonet_infer.core.manifest import file_sha256
from geonet_infer.errors import InputError

KINDS = ("depth", "pose", "flow")
SCOPES = {"depth": "depth_net", "pose": "pose_net", "flow": "flow_net"}
GRAPH_OF_KIND = {"depth": "depthnet", "pose": "posenet", "flow": "resflownet"}
OFFICIAL_VARIABLES = Path(__file__).with_name("official_variables.json")
OFFICIAL_CODE = "https://github.com/yzcjtr/GeoNet @ 5b17602"
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
    reader: BundleReader = field(repr=False)

    @classmethod
    def open(cls, path: str | Path) -> TFCheckpoint:
        reader = BundleReader(resolve_prefix(path))
        shapes = {n: list(e.shape) for n, e in reader.entries.items()}
        return cls(reader.prefix, shapes, {n: e.dtype.name for n, e in reader.entries.items()}, reader)

    def files(self) -> dict[str, str]:
        """File name -> sha256 of the .index and .data-* files (a missing shard whose variables were not
        read is left out, as it was not needed)."""
        files = [self.reader.index_path, *(f for f in self.reader.shard_paths() if f.is_file())]
        return {f.name: file_sha256(f) for f in files}

    def tensor(self, name: str) -> np.ndarray:
        value = self.reader.tensor(name)
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


def convert_network(ckpt: TFCheckpoint, spec: NetSpec, net: nn.Module | None = None) -> nn.Module:
    """Our network (``net``, or a new one for ``spec``) with every parameter and BN statistic set from ``ckpt``.

    Every ``<scope>/`` variable is consumed exactly once; a missing, left-over or misshapen
    variable is a GeoNetError naming it. HWIO weights become OIHW. (``num_batches_tracked``,
    a PyTorch training counter unused in eval mode, stays 0.)
    """
    net = net.eval() if net is not None else build_network(spec.kind, spec.arch, spec.num_source)
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
    checkpoints: dict = field(default_factory=dict)  # kind -> the TFCheckpoint it came from (for --verify)


def convert_checkpoints(specs: tuple[str, ...] | list[str], log=print, targets=None) -> Conversion:
    """Open every ``--from-tf`` checkpoint, decide which net comes from which, and convert them.

    Explicit ``kind=PFX`` assignments win; a plain ``PFX`` gives every net it holds that no
    explicit assignment names. A net given twice is an error. ``targets(chosen)``, if given, returns
    the nets (kind -> module) to fill for the chosen NetSpecs; else new ones are built.
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
    chosen = {kind: detect(ckpts[owner[kind]], kind) for kind in KINDS if kind in owner}
    into = targets(chosen) if targets is not None else {}
    nets = {kind: convert_network(ckpts[owner[kind]], spec, into.get(kind)) for kind, spec in chosen.items()}
    sources, notes = [], []
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
    return Conversion(nets, chosen, sources, notes, {kind: ckpts[owner[kind]] for kind in chosen})


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
    built: dict = {}

    def geonet_for(chosen: dict) -> dict:
        """Check the request against the chosen nets, then build the GeoNet whose nets are filled:
        converting into new nets and swapping them in would hold a third resnet50 (0.2 GB) at the peak."""
        available = {GRAPH_OF_KIND[k] for k in chosen} | {"rigidflow"}
        if tuple(requested) == GRAPH_NAMES:  # the default: everything the checkpoints give
            built["graphs"] = [g for g in GRAPH_NAMES if g in available]
        else:
            lacking = [g for g in requested if g not in available]
            if lacking:
                raise InputError(
                    None,
                    f"--graphs {','.join(lacking)}: the --from-tf checkpoints hold no network for it",
                    f"they give {', '.join(g for g in GRAPH_NAMES if g in available)}",
                )
            built["graphs"] = list(requested)
        if "resflownet" in built["graphs"] and not {"depthnet", "posenet"} <= set(built["graphs"]):
            raise InputError(
                None,
                "resflownet.onnx needs depthnet and posenet too (its input is their rigid flow)",
                "the released flow checkpoint holds all three: --from-tf PREFIX converts them together",
            )
        if cfg.scale_normalize and "depth" not in chosen:
            raise InputError(None, "--scale-normalize applies to a depth_net, and none is converted")
        arch = chosen["depth"].arch if "depth" in chosen else "resnet50"
        if cfg.arch and cfg.arch != arch:
            raise InputError(None, f"the checkpoint's depth_net is {arch}, --arch says {cfg.arch}", "drop --arch")
        seq_length = chosen["pose"].num_source + 1 if "pose" in chosen else (cfg.seq_length or 3)
        if cfg.seq_length and cfg.seq_length != seq_length:
            raise InputError(
                None,
                f"the checkpoint's pose_net takes {seq_length}-frame snippets, --seq-length says {cfg.seq_length}",
            )
        built.update(arch=arch, seq_length=seq_length)
        built["model"] = GeoNet(arch, seq_length - 1, with_flow="flow" in chosen, scale_normalize=cfg.scale_normalize)
        attrs = {"depth": "depth_net", "pose": "pose_net", "flow": "flow_net"}
        return {kind: getattr(built["model"], attrs[kind]) for kind in chosen}

    conv = convert_checkpoints(cfg.from_tf, log, targets=geonet_for)
    model, arch, seq_length, graphs = built["model"], built["arch"], built["seq_length"], built["graphs"]
    official = official_conventions(conv.specs, cfg.scale_normalize)
    if conv.notes:
        official["notes"] = conv.notes
    for ckpt in conv.checkpoints.values():
        ckpt.reader.close()  # unmap the shards for the export; --verify maps them again
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
        verify=(lambda model_dir: verify_conversion(conv, model, height, width, seq_length, cfg, model_dir))
        if cfg.verify
        else None,
    )


# ------------------------------------------------------------------------------ --verify
VERIFY_TOLERANCE = 1e-3  # of the output's range: a swapped or untransposed tensor is off by the whole range
VERIFY_OUTPUTS = {
    "depthnet": ("depth", "disparity"),
    "posenet": ("pose", "pose"),
    "resflownet": ("flow", "residual_flow"),
}


def _verify_feeds(frames: list, spec, seq_length: int) -> dict:
    """One input per converted graph: the first frame; the first snippet; frame 0 -> 1 for the flow net
    (its 12 channels: target, source, the source as its own warp, zero rigid flow and error)."""
    from export.quantize import depth_feeds, pose_feeds

    feeds = {"depthnet": depth_feeds(frames[:1], spec)[0]}
    if len(frames) >= seq_length:
        feeds["posenet"] = pose_feeds(frames[:seq_length], spec)[0]
    if len(frames) >= 2:
        tgt, src = (spec.to_network(f) for f in frames[:2])
        zeros = np.zeros((3, *tgt.shape[1:]), np.float32)
        feeds["resflownet"] = {"flow_input": np.concatenate([tgt, src, src, zeros])[None]}
    return feeds


def _official_outputs(conv: Conversion, graph: str, feed: np.ndarray, scale_normalize: bool):
    """The official TensorFlow forward pass from the checkpoint's own tensors; None where
    TensorFlow is missing or the net has no TF re-statement here (vgg DepthNet)."""
    kind = VERIFY_OUTPUTS[graph][0]
    spec = conv.specs[kind]
    if kind != "pose" and spec.arch != "resnet50":
        return None

    try:
        net = OfficialNet(SCOPES[kind])  # imports TensorFlow
    except ImportError:
        return None
    ckpt = conv.checkpoints[kind]
    net.values = {name: ckpt.tensor(name) for name in ckpt.scope_variables(kind)}
    x = np.ascontiguousarray(np.transpose(feed, (0, 2, 3, 1)))
    if kind == "depth":
        disp = net.disp_resnet50(x)[0].numpy()
        if scale_normalize:  # the official spatial_normalize: each map over its mean
            disp = disp / disp.mean(axis=(1, 2, 3), keepdims=True)
        return np.transpose(disp, (0, 3, 1, 2))
    if kind == "pose":
        return net.pose(x, spec.num_source).numpy()
    h, w = x.shape[1:3]
    return np.transpose(net.flow(x)[0].numpy() * np.array([w, h], np.float32), (0, 3, 1, 2))  # pixels


def verify_conversion(conv: Conversion, model, height: int, width: int, seq_length: int, cfg, model_dir) -> str:
    """``--verify``: the converted fp32 graphs in ``model_dir`` on one frame (snippet, frame pair) of
    ``cfg.verify`` against the checkpoint's own forward pass, as one line.

    The reference is the official graph in TensorFlow from the checkpoint's tensors when TensorFlow
    is installed (independent of our mapping), else our PyTorch nets holding the converted tensors
    (checks the ONNX export, not the mapping). ExportCheckError beyond VERIFY_TOLERANCE of the range.
    """
    from export.quantize import load_frames
    from export.to_onnx import ExportCheckError
    from export.verify import ort_outputs, torch_outputs
    from export.wrappers import build_wrapper
    from geonet_infer.core.spec import InputSpec
    from geonet_infer.engines.onnxruntime import make_session

    frames, _ = load_frames(cfg.verify, height, width, max_frames=max(seq_length, 2))
    feeds = _verify_feeds(frames, InputSpec.from_conventions(height, width, seq_length), seq_length)
    parts, failed, references = [], [], set()
    for graph, (kind, output) in VERIFY_OUTPUTS.items():
        if kind not in conv.nets or graph not in feeds or not (Path(model_dir) / f"{graph}.onnx").is_file():
            continue
        ((_, value),) = feeds[graph].items()
        session = make_session(Path(model_dir) / f"{graph}.onnx")
        names = [o.name for o in session.get_outputs()]
        got = dict(zip(names, ort_outputs(session, [value])))[output]
        ref = _official_outputs(conv, graph, value, cfg.scale_normalize)
        references.add(
            "the official TensorFlow graph with the checkpoint's tensors"
            if ref is not None
            else "our PyTorch nets with the checkpoint's tensors (checks the export, not the mapping)"
        )
        if ref is None:
            ref = dict(zip(names, torch_outputs(build_wrapper(graph, model), [value])))[output]
        err = np.abs(got.astype(np.float64) - ref)
        span = float(ref.max() - ref.min()) or 1.0
        parts.append(f"{graph} {output} max {err.max():.2e} mean {err.mean():.2e} (range {span:.3g})")
        if err.max() > VERIFY_TOLERANCE * span:
            failed.append(graph)
    if not parts:
        raise InputError(
            cfg.verify,
            f"{len(frames)} frame(s): too few to verify the converted graphs",
            f"pass a folder of at least {seq_length} consecutive frames",
        )
    what = " and ".join(sorted(references))
    errors = "; ".join(parts)
    line = f"verify: first frames of {cfg.verify} at {height}x{width}, converted ONNX vs {what}, |error|: {errors}"
    if failed:
        raise ExportCheckError(f"{line}: {', '.join(failed)} beyond {VERIFY_TOLERANCE:g} of the range")
    return line
