"""The model-directory manifest (``manifest.json``): schema, writer and validating loader.

``python -m export`` writes it through these dataclasses and the runtime reads it
back with :func:`load_manifest`, so the schema lives here only. numpy/stdlib only.

Layout of a model directory::

    DIR/manifest.json
    DIR/depthnet.onnx  DIR/posenet.onnx  DIR/rigidflow.onnx  [DIR/resflownet.onnx]   fp32
    DIR/int8/depthnet.onnx  DIR/int8/posenet.onnx  [DIR/int8/resflownet.onnx]          int8 (QDQ)

``graphs[precision][name]`` lists the graph set of one precision. The int8 set's
``rigidflow`` entry points at the fp32 ``rigidflow.onnx`` (the geometric op stays
fp32), so a consumer picks a precision and gets a complete set.
"""

from __future__ import annotations

import hashlib
import json
import math
import mmap
import os
import subprocess
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path, PurePosixPath
from typing import Any

from geonet_infer import conventions
from geonet_infer.errors import ModelError
from geonet_infer.io.atomic import atomic_write

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "geonet-onnx-models"
SCHEMA_VERSION = conventions.SCHEMA_VERSION
PRECISIONS = ("fp32", "int8")
# --backend auto / --precision auto: chosen per graph at load by timing (geonet_infer.engines.pick_fastest)
AUTO = "auto"
PRECISION_CHOICES = (*PRECISIONS, AUTO)  # what load(precision=) and --precision accept
BATCH_AXIS = "B"  # symbolic batch dimension in shapes
REEXPORT_HINT = "re-export the model directory with `python -m export`"
# Limits on what a manifest may ask for: frames are resized to height x width and snippets of
# seq_length frames are stacked before any graph runs, so an absurd number here would be an
# absurd allocation at the first frame. Export writes sizes that are multiples of 8 (DepthNet and
# ResFlowNet need them, export/build.py) and odd snippets (the target is the middle frame); 2048
# is 5x KITTI's 416-pixel graph width, 32 the smallest size the tests train and export at.
SIZE_MULTIPLE = 8
MIN_SIDE, MAX_SIDE = 32, 2048
MIN_SEQ_LENGTH, MAX_SEQ_LENGTH = 3, 9
MAX_CONVENTION_MAGNITUDE = 1e4  # every number of the conventions (the largest is a reference size)
MIN_NORM_SCALE = 1e-3  # image_norm.scale: a zero scale feeds the nets a constant image
REAL_VIDEO_HINT = (
    "for real video, convert the released GeoNet checkpoints with `python -m export --from-tf` "
    "(docs/official_models.md)"
)


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _from_known_fields(cls, d: dict):
    """Build a dataclass from a dict, ignoring keys a newer writer may have added."""
    known = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in d.items() if k in known})


@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output. ``shape`` holds ints and ``"B"`` for the batch axis."""

    name: str
    shape: tuple
    dtype: str = "float32"

    @classmethod
    def from_dict(cls, d: dict) -> TensorSpec:
        return cls(name=str(d["name"]), shape=tuple(d["shape"]), dtype=str(d["dtype"]))


@dataclass(frozen=True)
class GraphEntry:
    """One ONNX file of a graph set."""

    file: str  # POSIX path relative to the model directory
    sha256: str
    opset: int
    precision: str  # precision of this file ("fp32" also for rigidflow in the int8 set)
    inputs: tuple[TensorSpec, ...]
    outputs: tuple[TensorSpec, ...]
    exporter: str = ""  # how the file was made (torch.onnx dynamo, ORT quantize_static, ...)

    @classmethod
    def from_dict(cls, d: dict) -> GraphEntry:
        return cls(
            file=str(d["file"]),
            sha256=str(d["sha256"]),
            opset=int(d["opset"]),
            precision=str(d["precision"]),
            inputs=tuple(TensorSpec.from_dict(t) for t in d["inputs"]),
            outputs=tuple(TensorSpec.from_dict(t) for t in d["outputs"]),
            exporter=str(d.get("exporter", "")),
        )

    @property
    def input_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.inputs)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(t.name for t in self.outputs)


@dataclass(frozen=True)
class Provenance:
    """Where the graphs came from."""

    architecture: str
    random_init: bool
    export_date: str  # ISO 8601, UTC
    git_commit: str | None = None
    checkpoint: str | None = None  # path as given on the command line
    checkpoint_sha256: str | None = None
    checkpoint_stage: str | None = None
    checkpoint_step: int | None = None
    training_command: str | None = None
    data_dir: str | None = None  # prepared folder(s) trained on, joined with " + "
    exporter: str = ""
    versions: dict = field(default_factory=dict)  # torch, onnx, onnxruntime, onnxscript
    sources: list = field(default_factory=list)  # --from-tf: each TF checkpoint, its nets and files' sha256

    @classmethod
    def from_dict(cls, d: dict) -> Provenance:
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Quantization:
    """How the int8 set was made and what it costs in accuracy."""

    method: str
    activation_type: str
    weight_type: str
    per_channel: bool
    reduce_range: bool
    calibrate_method: str
    calibration_data: str
    calibration_samples: dict  # graph -> number of calibration inputs
    calibration_intrinsics: str  # where the K for the resflownet calibration inputs came from
    fp32_graphs: tuple[str, ...]  # graphs of the int8 set that stay fp32
    accuracy_delta: dict | None  # {"depth_abs_rel": {"fp32", "int8", "delta"}, "flow_epe_noc": ...}
    accuracy_delta_reason: str | None = None  # why accuracy_delta is null (or a note)
    graph_notes: dict = field(default_factory=dict)  # graph -> what stayed fp32 / was rescaled in it
    op_types: tuple[str, ...] = ()  # operator types quantised (export --int8-ops); () = every type ORT quantises
    # graph -> which x86 INT8 kernels compute it exactly (export/int8_arith.py int8_kernels); {} = not recorded
    int8_kernels: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict) -> Quantization:
        d = dict(d)
        d["fp32_graphs"] = tuple(d.get("fp32_graphs", ()))
        d["op_types"] = tuple(d.get("op_types", ()))
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Score:
    """One measured number of a model next to its baseline on the same data (written by the model card)."""

    task: str  # depth, flow, pose
    metric: str  # as the card labels it, e.g. "AbsRel"
    data: str  # what it was measured on
    value: float  # the model's FP32 number
    baseline: str  # e.g. "constant depth"
    baseline_value: float
    lower_is_better: bool = True

    @property
    def verdict(self) -> str:
        """ "better", "worse" or "no better" than the baseline."""
        ahead = self.baseline_value - self.value if self.lower_is_better else self.value - self.baseline_value
        return "better" if ahead > 0 else "worse" if ahead < 0 else "no better"

    @classmethod
    def from_dict(cls, d: dict) -> Score:
        d = dict(d)
        for key in ("value", "baseline_value"):
            d[key] = float(d[key])
            if not math.isfinite(d[key]):
                raise ValueError(f"model_card score {key} is {d[key]}")
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class ModelCard:
    """What the model was trained on and its measured scores, copied from its model card
    (``python -m benchmarks.model_card``); a model directory without one has no measured scores."""

    trained_on: str  # one line
    synthetic_only: bool  # trained on synthetic scenes only: predict/batch say so on real video
    measured_in: str  # where the measurement is written up (docs/models.md)
    generated_utc: str
    real: tuple[Score, ...] = ()
    synthetic: tuple[Score, ...] = ()

    def notice(self) -> str | None:
        """One line for users of a model that may fail them on real video (trained on synthetic
        scenes only, or no better than its baseline on real data): its real-data score and where a
        model for real video comes from; None for any other model."""
        s = self.real[0] if self.real else None
        if not self.synthetic_only and (s is None or s.verdict == "better"):
            return None
        if s is not None:
            real = (
                f"on real video it is {s.verdict} than the {s.baseline} baseline: {s.task} {s.metric} "
                f"{s.value:.3g} vs {s.baseline_value:.3g} on {s.data}, see {self.measured_in}"
            )
        else:
            real = "its real-data scores are not measured"
        trained = "trained on synthetic scenes only: " if self.synthetic_only else ""
        return f"{trained}{real}; {REAL_VIDEO_HINT}"

    @classmethod
    def from_dict(cls, d: dict) -> ModelCard:
        d = dict(d)
        d["synthetic_only"] = bool(d["synthetic_only"])
        for key in ("real", "synthetic"):
            d[key] = tuple(Score.from_dict(s) for s in d.get(key) or ())
        return _from_known_fields(cls, d)


@dataclass(frozen=True)
class Manifest:
    """Everything a consumer needs to run the graphs of one model directory."""

    schema_version: int
    height: int
    width: int
    seq_length: int
    arch: str
    random_init: bool
    precisions: tuple[str, ...]
    graphs: dict  # precision -> {graph name -> GraphEntry}
    conventions: dict  # geonet_infer.conventions.as_dict() at export time, and photometric_alpha (optional)
    provenance: Provenance
    metrics: dict  # the checkpoint's validation metrics ({} for random init)
    quantization: Quantization | None = None
    model_card: ModelCard | None = None  # optional: older manifests and fresh exports have none
    format: str = MANIFEST_FORMAT
    root: Path | None = field(default=None, compare=False, repr=False)  # directory it was loaded from

    # ------------------------------------------------------------------ access
    @property
    def num_source(self) -> int:
        return self.seq_length - 1

    @property
    def photometric_alpha(self) -> float | None:
        """α of the photometric error ``rigidflow.onnx`` computes (``α·DSSIM + (1−α)·L1``, baked in at
        export); None for a manifest written before export recorded it."""
        alpha = self.conventions.get(conventions.PHOTOMETRIC_ALPHA)
        return None if alpha is None else float(alpha)

    def graph_names(self, precision: str = "fp32") -> tuple[str, ...]:
        return tuple(self._set(precision))

    def graph(self, name: str, precision: str = "fp32") -> GraphEntry:
        graphs = self._set(precision)
        if name not in graphs:
            where = self.root / MANIFEST_NAME if self.root else None
            hint = (
                "resflownet needs a stage 'flow' checkpoint at export time"
                if name == "resflownet"
                else f"graphs present: {', '.join(graphs)}"
            )
            raise ModelError(where, f"no '{name}' graph in the {precision} set", hint)
        return graphs[name]

    def path(self, name: str, precision: str = "fp32") -> Path:
        """Absolute path of a graph file (needs a manifest loaded from a directory)."""
        if self.root is None:
            raise ValueError("manifest has no root directory; load it with load_manifest()")
        return self.root / self.graph(name, precision).file

    def files_mib(self, precision: str = "fp32") -> float:
        """Size of the graph files of one precision set on disk (a file shared by two graphs counts once)."""
        sets = [p for p in self.graphs if p in PRECISIONS] if precision == AUTO else [precision]  # auto loads all
        files = {self.path(name, p) for p in sets for name in self._set(p)}
        return sum(f.stat().st_size for f in files) / 2**20

    def _set(self, precision: str) -> dict:
        if precision == AUTO and self.graphs:  # any graph of any set: each is chosen at load
            merged: dict = {}
            for p in sorted(self.graphs, key=lambda p: PRECISIONS.index(p) if p in PRECISIONS else len(PRECISIONS)):
                for name, entry in self.graphs[p].items():
                    merged.setdefault(name, entry)
            return merged
        if precision not in self.graphs:
            where = self.root / MANIFEST_NAME if self.root else None
            raise ModelError(
                where,
                f"no {precision} graphs in this model directory",
                f"precisions present: {', '.join(self.graphs)}; export with --precision fp32,int8",
            )
        return self.graphs[precision]

    # -------------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("root")
        if d["model_card"] is None:  # written by the model card, not by export
            d.pop("model_card")
        # Put the identifying keys first for readers of the JSON.
        return {"format": d.pop("format"), "schema_version": d.pop("schema_version"), **d}

    @classmethod
    def from_dict(cls, d: dict, root: Path | None = None) -> Manifest:
        quant, card = d.get("quantization"), d.get("model_card")
        return cls(
            schema_version=int(d["schema_version"]),
            height=int(d["height"]),
            width=int(d["width"]),
            seq_length=int(d["seq_length"]),
            arch=str(d["arch"]),
            random_init=bool(d["random_init"]),
            precisions=tuple(d["precisions"]),
            graphs={p: {n: GraphEntry.from_dict(g) for n, g in gs.items()} for p, gs in d["graphs"].items()},
            conventions=dict(d["conventions"]),
            provenance=Provenance.from_dict(d["provenance"]),
            metrics=dict(d.get("metrics") or {}),
            quantization=Quantization.from_dict(quant) if quant else None,
            model_card=ModelCard.from_dict(card) if card else None,
            format=str(d.get("format", "")),
            root=root,
        )


def model_notice(manifest: Manifest) -> str | None:
    """The one-line notice ``predict`` and ``batch`` print and record for a model trained on synthetic
    scenes only (from its ``model_card``); None for any other model."""
    return manifest.model_card.notice() if manifest.model_card else None


def write_manifest(manifest: Manifest, directory: str | Path) -> Path:
    """Write ``directory/manifest.json`` atomically; returns its path."""
    path = Path(directory) / MANIFEST_NAME
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(manifest.to_dict(), indent=2, sort_keys=False) + "\n")
    return path


def _safe_relative(file: str) -> bool:
    p = PurePosixPath(file)
    return bool(file) and not p.is_absolute() and ".." not in p.parts and "\\" not in file


def load_manifest(directory: str | Path, verify_files: bool = True) -> Manifest:
    """Read and validate ``directory/manifest.json``.

    Checks: the file parses, ``format`` and ``schema_version`` match this
    package, every required key is there, conventions are present, sizes are
    within the limits (``MIN_SIDE``..``MAX_SIDE``, ``MIN_SEQ_LENGTH``..``MAX_SEQ_LENGTH``)
    and agree with the graph entries, every convention number is finite and sane,
    each listed graph's path stays inside the directory (symlinks resolved), and
    (with ``verify_files``) each listed graph file exists with the recorded sha256
    and keeps no tensor in external data (which the sha256 would not cover). Graphs
    are checked as listed; which graphs a model needs is the consumer's business.
    The graph's own inputs/outputs are compared with its entry by the engine that
    loads it (:func:`check_graph_io`). Any problem raises :class:`GeoNetError`
    naming the offending file.
    """
    directory = Path(directory)
    path = directory / MANIFEST_NAME
    if not directory.is_dir():
        raise ModelError(directory, "model directory not found", REEXPORT_HINT)
    if not path.is_file():
        raise ModelError(path, "no manifest in this model directory", REEXPORT_HINT)
    try:
        raw: Any = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:  # Recursion: nested 10^5 deep
        raise ModelError(path, f"cannot parse the manifest ({exc})", REEXPORT_HINT) from None
    if not isinstance(raw, dict):
        raise ModelError(path, "the manifest is not a JSON object", REEXPORT_HINT)
    if raw.get("format") != MANIFEST_FORMAT:
        raise ModelError(
            path,
            f"not a GeoNet model manifest (format {raw.get('format')!r}, expected {MANIFEST_FORMAT!r})",
            REEXPORT_HINT,
        )
    if raw.get("schema_version") != SCHEMA_VERSION:
        raise ModelError(
            path,
            f"manifest schema_version {raw.get('schema_version')!r}, this package reads {SCHEMA_VERSION}",
            REEXPORT_HINT + " with this version of the package",
        )
    conv = raw.get("conventions")
    if not isinstance(conv, dict) or not conv:
        raise ModelError(path, "the manifest has no conventions", REEXPORT_HINT)
    missing_conv = sorted(set(conventions.as_dict()) - set(conv))
    if missing_conv:
        raise ModelError(path, f"conventions lack {missing_conv}", REEXPORT_HINT)
    _check_sizes(raw, path)
    _check_convention_numbers(conv, path)
    try:
        manifest = Manifest.from_dict(raw, root=directory)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else f"malformed entry ({exc})"
        raise ModelError(path, f"invalid manifest: {what}", REEXPORT_HINT) from None
    if not manifest.graphs or "fp32" not in manifest.graphs:
        raise ModelError(path, "the manifest lists no fp32 graphs", REEXPORT_HINT)
    for precision, graphs in manifest.graphs.items():
        if precision not in PRECISIONS:
            raise ModelError(path, f"unknown precision {precision!r}", f"expected one of {PRECISIONS}")
        for name, entry in graphs.items():
            _check_entry_sizes(manifest, f"{precision}/{name}", entry, path)
            if name == "posenet":
                _check_snippet_length(manifest, f"{precision}/{name}", entry, path)
            file = _graph_path(directory, f"{precision}/{name}", entry.file, path)
            if verify_files:
                _verify_file(file, entry.sha256)
    return manifest


# ----------------------------------------------------------------------------- manifest checks
def _check_sizes(raw: dict, path: Path) -> None:
    """height, width and seq_length, where present, are integers within the limits above."""
    for key in ("height", "width"):
        value = raw.get(key, MIN_SIDE)  # a missing key is reported by Manifest.from_dict
        if type(value) is not int or not MIN_SIDE <= value <= MAX_SIDE or value % SIZE_MULTIPLE:
            raise ModelError(
                path,
                f"{key} {value!r} is not a multiple of {SIZE_MULTIPLE} in [{MIN_SIDE}, {MAX_SIDE}]",
                REEXPORT_HINT,
            )
    value = raw.get("seq_length", MIN_SEQ_LENGTH)
    if type(value) is not int or not MIN_SEQ_LENGTH <= value <= MAX_SEQ_LENGTH or value % 2 == 0:
        raise ModelError(
            path,
            f"seq_length {value!r} is not an odd number in [{MIN_SEQ_LENGTH}, {MAX_SEQ_LENGTH}]",
            REEXPORT_HINT,
        )


def _check_convention_numbers(conv: dict, path: Path) -> None:
    """Every number of the conventions is finite and of sane magnitude; image_norm.scale is not ~0; the
    photometric alpha, where recorded, is in [0, 1]."""

    def walk(value, where: str):
        if isinstance(value, dict):
            for key, item in value.items():
                walk(item, f"{where}.{key}")
        elif isinstance(value, list):
            for i, item in enumerate(value):
                walk(item, f"{where}[{i}]")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            if not (math.isfinite(value) and abs(value) <= MAX_CONVENTION_MAGNITUDE):
                raise ModelError(
                    path,
                    f"{where} is {value!r}: not a finite number within ±{MAX_CONVENTION_MAGNITUDE:g}",
                    REEXPORT_HINT,
                )

    walk(conv, "conventions")
    alpha = conv.get(conventions.PHOTOMETRIC_ALPHA)
    if alpha is not None and (isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0 <= alpha <= 1):
        raise ModelError(
            path, f"conventions.{conventions.PHOTOMETRIC_ALPHA} is {alpha!r}: not in [0, 1]", REEXPORT_HINT
        )
    _check_number_types(conv, conventions.as_dict(), "conventions", path)
    scale = (conv.get("image_norm") or {}).get("scale")
    if isinstance(scale, (int, float)) and abs(scale) < MIN_NORM_SCALE:
        raise ModelError(
            path, f"conventions.image_norm.scale is {scale!r}: the graphs would see a constant image", REEXPORT_HINT
        )


def _check_number_types(given: dict, defaults: dict, where: str, path: Path) -> None:
    """Where this package's conventions hold a number, the manifest holds one too: JSON ``true`` would
    be read as 1.0 (image_norm.scale true ran as scale 1)."""
    for key, default in defaults.items():
        value = given.get(key)
        if isinstance(default, dict) and isinstance(value, dict):
            _check_number_types(value, default, f"{where}.{key}", path)
        elif key in given and isinstance(default, (int, float)) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ModelError(path, f"{where}.{key} is {value!r}: not a number", REEXPORT_HINT)


def _check_entry_sizes(manifest: Manifest, graph: str, entry: GraphEntry, path: Path) -> None:
    """Image inputs (rank 4) of a graph entry are at the manifest's height x width."""
    for spec in entry.inputs:
        if len(spec.shape) == 4 and tuple(spec.shape[-2:]) != (manifest.height, manifest.width):
            raise ModelError(
                path,
                f"graph {graph} input {spec.name!r} is {spec.shape[-2]}x{spec.shape[-1]}, the manifest says "
                f"height x width {manifest.height}x{manifest.width}",
                REEXPORT_HINT,
            )


def _check_snippet_length(manifest: Manifest, graph: str, entry: GraphEntry, path: Path) -> None:
    """PoseNet takes ``seq_length`` frames stacked on channels: a seq_length the graph was not exported
    for failed only at the first snippet, inside onnxruntime (its outputs are checked against the graph
    by :func:`check_graph_io`)."""
    L = manifest.seq_length
    for spec in entry.inputs:
        if len(spec.shape) == 4 and isinstance(spec.shape[1], int) and spec.shape[1] != 3 * L:
            raise ModelError(
                path,
                f"graph {graph} input {spec.name!r} has {spec.shape[1]} channels, seq_length {L} needs {3 * L} "
                "(3 per frame)",
                "seq_length must be the snippet length the PoseNet was exported for; " + REEXPORT_HINT,
            )


# ----------------------------------------------------------------------------- graph file checks
IoSpec = tuple[str, list | None, str]  # name, shape (int = fixed, str or None = dynamic; None = unknown rank), dtype


def _dim_fits(manifest_dim, graph_dim) -> bool:
    dynamic = not isinstance(graph_dim, int)
    return dynamic if manifest_dim == BATCH_AXIS else dynamic or graph_dim == manifest_dim


def check_graph_io(entry: GraphEntry, file: Path, inputs: list[IoSpec], outputs: list[IoSpec]) -> None:
    """Compare a loaded graph's inputs and outputs (as its engine reports them) with its manifest entry.

    Names must match; per tensor the rank, the dtype and every fixed dimension. A manifest ``"B"``
    (batch) must be a dynamic dimension of the graph; a dynamic graph dimension accepts any fixed
    manifest size. Raises GeoNetError naming the graph file and the first difference.
    """
    hint = "the graph file does not match its manifest entry; " + REEXPORT_HINT
    for kind, expected, actual in (("inputs", entry.inputs, inputs), ("outputs", entry.outputs, outputs)):
        by_name = {name: (shape, dtype) for name, shape, dtype in actual}
        if set(by_name) != {t.name for t in expected}:
            raise ModelError(
                file, f"graph {kind} are {sorted(by_name)}, the manifest says {sorted(t.name for t in expected)}", hint
            )
        for spec in expected:
            shape, dtype = by_name[spec.name]
            fits = shape is not None and len(shape) == len(spec.shape) and all(map(_dim_fits, spec.shape, shape))
            if not fits or dtype != spec.dtype:
                got = "?" if shape is None else [d if isinstance(d, int) else "dynamic" for d in shape]
                raise ModelError(
                    file,
                    f"{kind[:-1]} {spec.name!r} is {dtype} {got}, the manifest says {spec.dtype} {list(spec.shape)}",
                    hint,
                )


def _graph_path(directory: Path, graph: str, file: str, path: Path) -> Path:
    """The graph's file, refused if its path (or a symlink on the way) leads out of the model directory."""
    if not _safe_relative(file):
        raise ModelError(
            path,
            f"graph {graph} has an unsafe file path {file!r}",
            "paths must be relative and stay inside the model directory",
        )
    full = directory / file
    if not full.resolve().is_relative_to(directory.resolve()):
        raise ModelError(
            full,
            f"graph file resolves to {full.resolve()}, outside the model directory",
            "the manifest's sha256 vouches for files inside the model directory only: copy the file in",
        )
    return full


def _verify_file(file: Path, expected: str) -> None:
    """The file has the recorded sha256 and loads nothing the sha256 does not cover (external data)."""
    if not file.is_file():
        raise ModelError(file, "graph file listed in the manifest is missing", REEXPORT_HINT)
    with open(file, "rb") as f:
        empty = os.fstat(f.fileno()).st_size == 0  # mmap refuses an empty file
        with nullcontext(b"") if empty else mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            actual = hashlib.sha256(data).hexdigest()
            if actual != expected:
                raise ModelError(
                    file,
                    f"sha256 mismatch: manifest says {expected[:16]}..., file has {actual[:16]}...",
                    "the file is corrupt or was changed after export; " + REEXPORT_HINT,
                )
            try:
                location = external_data_location(data)
            except (IndexError, ValueError):
                raise ModelError(file, "not a valid ONNX file (cannot parse its protobuf)", REEXPORT_HINT) from None
    if location is not None:
        raise ModelError(
            file,
            f"the graph keeps tensors in external data ({location or 'no location given'}), which the manifest's "
            "sha256 does not cover",
            "export with the weights inside the .onnx file (`python -m export` does)",
        )


# ONNX protobuf field numbers (onnx/onnx.proto) of the messages on the way to a TensorProto:
# message kind -> {field number: kind of the sub-message}.
_ONNX_CHILDREN = {
    "model": {7: "graph", 25: "function"},  # ModelProto.graph, .functions
    "graph": {1: "node", 5: "tensor", 15: "sparse"},  # GraphProto.node, .initializer, .sparse_initializer
    "function": {7: "node"},  # FunctionProto.node
    "node": {5: "attribute"},  # NodeProto.attribute
    "attribute": {5: "tensor", 6: "graph", 10: "tensor", 11: "graph", 22: "sparse", 23: "sparse"},  # t g tensors ...
    "sparse": {1: "tensor", 2: "tensor"},  # SparseTensorProto.values, .indices
}
_TENSOR_EXTERNAL_DATA, _TENSOR_DATA_LOCATION, _EXTERNAL = 13, 14, 1  # TensorProto fields, DataLocation.EXTERNAL


def _varint(buf, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def _fields(buf, start: int, end: int):
    """(field number, wire type, value) of one protobuf message; value = (start, end) for wire type 2."""
    pos = start
    while pos < end:
        key, pos = _varint(buf, pos)
        field_number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
            yield field_number, wire, value
        elif wire == 2:
            size, pos = _varint(buf, pos)
            if pos + size > end:
                raise ValueError("field runs past its message")
            yield field_number, wire, (pos, pos + size)
            pos += size
        elif wire in (1, 5):
            pos += 8 if wire == 1 else 4
        else:
            raise ValueError(f"wire type {wire}")
    if pos != end:
        raise ValueError("message runs past its end")


def external_data_location(buf, kind: str = "model", start: int = 0, end: int | None = None) -> str | None:
    """The ``location`` of the first tensor an ONNX model keeps in external data ("" if it names none),
    or None when every tensor is inside the file. Walks the protobuf structure only (weights are
    skipped, not decoded), so the runtime needs no ``onnx`` package; raises ValueError or IndexError
    on a malformed file."""
    end = len(buf) if end is None else end
    if kind == "tensor":
        return _tensor_location(buf, start, end)
    for field_number, wire, value in _fields(buf, start, end):
        child = _ONNX_CHILDREN[kind].get(field_number)
        if child and wire == 2:
            location = external_data_location(buf, child, *value)
            if location is not None:
                return location
    return None


def _tensor_location(buf, start: int, end: int) -> str | None:
    external = None
    for field_number, wire, value in _fields(buf, start, end):
        if field_number == _TENSOR_EXTERNAL_DATA and wire == 2:
            entry = {k: bytes(buf[v[0] : v[1]]) for k, w, v in _fields(buf, *value) if w == 2}
            if entry.get(1) == b"location":  # StringStringEntryProto: key = 1, value = 2
                return entry.get(2, b"").decode("utf-8", "replace")
            external = ""
        elif field_number == _TENSOR_DATA_LOCATION and wire == 0 and value == _EXTERNAL:
            external = ""
    return external


SOURCE_ROOT = Path(__file__).resolve().parents[1]  # the checkout holding this package, when run from one


def git_commit(root: Path | None = None, short: bool = False) -> str | None:
    """``git rev-parse [--short] HEAD`` in ``root`` (default: the checkout holding this package),
    or None where there is no git or no checkout (an installed wheel). Provenance of manifests,
    bench reports, the model card and the results report."""
    root = SOURCE_ROOT if root is None else Path(root)
    if not (root / ".git").exists():
        return None
    cmd = ["git", "-C", str(root), "rev-parse", *(["--short"] if short else []), "HEAD"]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip() or None
