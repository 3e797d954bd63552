"""The released GeoNet TensorFlow checkpoints (yzcjtr/GeoNet): what they hold and which network is which.

numpy only (no torch, no TensorFlow): the checkpoint is read by :mod:`.tf_checkpoint`; the official
variable list of each network (names, TF shapes, dtypes) is ``official_variables.json`` beside this
file, derived by building the official graphs (``scripts/derive_official_variables.py``).

Naming: slim names unnamed layers ``<scope>/Conv``, ``Conv_1``, ... in creation order; each layer
holds ``weights`` (HWIO) and either ``BatchNorm/{beta,moving_mean,moving_variance}`` (no gamma:
slim's scale=False) or ``biases`` (the prediction heads).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geonet_infer import conventions
from geonet_infer.convert.tf_checkpoint import BundleReader
from geonet_infer.errors import InputError
from geonet_infer.models.manifest import file_sha256

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
MAX_GLOBAL_STEP = 2**63 - 1


def layer_name(index: int) -> str:
    """slim's auto-name of the ``index``-th unnamed conv of a scope."""
    return "Conv" if index == 0 else f"Conv_{index}"


def official_variables() -> dict:
    """``official_variables.json``: network key (``depth_resnet50``, ``pose_seq3``...) -> [name, shape, dtype]."""
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
        """``global_step`` as an int; a step stored as anything but one integer is refused by name."""
        if "global_step" not in self.shapes:
            return None
        value = self.tensor("global_step")
        if value.size != 1 or not np.issubdtype(value.dtype, np.integer):
            raise InputError(
                f"{self.prefix}.index",
                f"global_step is a {value.dtype.name} tensor of shape {list(value.shape)}, not one integer",
                "this is not a checkpoint of the official GeoNet code",
            )
        return int(value.reshape(()))


# ------------------------------------------------------------------------------ which network
@dataclass(frozen=True)
class NetSpec:
    kind: str
    arch: str | None = None  # depth: resnet50 | vgg; flow: resnet50
    num_source: int | None = None  # pose

    def describe(self) -> str:
        if self.kind == "pose":
            return f"pose_net (PoseNet, seq {self.num_source + 1})"  # type: ignore[operator]
        return f"{SCOPES[self.kind]} ({'DepthNet' if self.kind == 'depth' else 'ResFlowNet'} {self.arch})"

    @property
    def key(self) -> str:
        """The network's key in ``official_variables.json`` (``depth_resnet50``, ``pose_seq5``...)."""
        if self.kind == "pose":
            return f"pose_seq{self.num_source + 1}"  # type: ignore[operator]
        return f"{self.kind}_{self.arch}"


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
        if len(shape) != 4 or shape[3] not in (12, 24):  # the official PoseNet: seq 3 or seq 5
            raise InputError(
                ckpt.prefix, f"variable {last} has shape {shape}: expected 1x1x256x12 (seq 3) or 1x1x256x24 (seq 5)"
            )
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


def check_variables(ckpt: TFCheckpoint, spec: NetSpec) -> None:
    """Every official variable of ``spec`` present with its shape and dtype, none left over (InputError)."""
    expected = official_variables()[spec.key]
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
class Selection:
    """Which network comes from which checkpoint, and where each checkpoint came from."""

    specs: dict  # kind -> NetSpec
    checkpoints: dict  # kind -> TFCheckpoint
    sources: list  # manifest provenance records, one per checkpoint
    notes: list  # human-readable remarks (also in the manifest)

    @property
    def arch(self) -> str:
        """The DepthNet's arch; resnet50 (the ResFlowNet's) when no depth_net is converted."""
        return self.specs["depth"].arch if "depth" in self.specs else "resnet50"

    def seq_length(self, default: int = 3) -> int:
        """Frames of a PoseNet snippet; ``default`` when no pose_net is converted."""
        return self.specs["pose"].num_source + 1 if "pose" in self.specs else default


def select_networks(specs: tuple[str, ...] | list[str], log=print) -> Selection:
    """Open every checkpoint, decide which net comes from which, and check their variables.

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
    chosen = {kind: detect(ckpts[owner[kind]], kind) for kind in KINDS if kind in owner}
    for kind, spec in chosen.items():
        check_variables(ckpts[owner[kind]], spec)
    sources, notes = [], []
    for i, ckpt in enumerate(ckpts):
        used = [k for k in KINDS if owner.get(k) == i]
        unused = [f"{SCOPES[k]} ({len(ckpt.scope_variables(k))} variables)" for k in ckpt.kinds() if k not in used]
        other = sorted(
            n for n in ckpt.shapes if n != "global_step" and not any(n in ckpt.scope_variables(k) for k in KINDS)
        )
        record: dict = {
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
    return Selection(chosen, {kind: ckpts[owner[kind]] for kind in chosen}, sources, notes)


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
