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
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path, PurePosixPath
from typing import Any

from geonet_infer import conventions
from geonet_infer.errors import GeoNetInputError
from geonet_infer.io.atomic import atomic_write

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "geonet-onnx-models"
SCHEMA_VERSION = conventions.SCHEMA_VERSION
PRECISIONS = ("fp32", "int8")
BATCH_AXIS = "B"  # symbolic batch dimension in shapes
REEXPORT_HINT = "re-export the model directory with `python -m export`"


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

    @classmethod
    def from_dict(cls, d: dict) -> Quantization:
        d = dict(d)
        d["fp32_graphs"] = tuple(d.get("fp32_graphs", ()))
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
    conventions: dict  # geonet_infer.conventions.as_dict() at export time
    provenance: Provenance
    metrics: dict  # the checkpoint's validation metrics ({} for random init)
    quantization: Quantization | None = None
    format: str = MANIFEST_FORMAT
    root: Path | None = field(default=None, compare=False, repr=False)  # directory it was loaded from

    # ------------------------------------------------------------------ access
    @property
    def num_source(self) -> int:
        return self.seq_length - 1

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
            raise GeoNetInputError(where, f"no '{name}' graph in the {precision} set", hint)
        return graphs[name]

    def path(self, name: str, precision: str = "fp32") -> Path:
        """Absolute path of a graph file (needs a manifest loaded from a directory)."""
        if self.root is None:
            raise ValueError("manifest has no root directory; load it with load_manifest()")
        return self.root / self.graph(name, precision).file

    def files_mib(self, precision: str = "fp32") -> float:
        """Size of the graph files of one precision set on disk (a file shared by two graphs counts once)."""
        files = {self.path(name, precision) for name in self._set(precision)}
        return sum(f.stat().st_size for f in files) / 2**20

    def _set(self, precision: str) -> dict:
        if precision not in self.graphs:
            where = self.root / MANIFEST_NAME if self.root else None
            raise GeoNetInputError(
                where,
                f"no {precision} graphs in this model directory",
                f"precisions present: {', '.join(self.graphs)}; export with --precision fp32,int8",
            )
        return self.graphs[precision]

    # -------------------------------------------------------------- (de)serialise
    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("root")
        # Put the identifying keys first for readers of the JSON.
        return {"format": d.pop("format"), "schema_version": d.pop("schema_version"), **d}

    @classmethod
    def from_dict(cls, d: dict, root: Path | None = None) -> Manifest:
        quant = d.get("quantization")
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
            format=str(d.get("format", "")),
            root=root,
        )


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
    package, every required key is there, conventions are present, and (with
    ``verify_files``) every graph file exists inside the directory with the
    recorded sha256. Any mismatch raises :class:`GeoNetInputError` naming the
    offending file.
    """
    directory = Path(directory)
    path = directory / MANIFEST_NAME
    if not directory.is_dir():
        raise GeoNetInputError(directory, "model directory not found", REEXPORT_HINT)
    if not path.is_file():
        raise GeoNetInputError(path, "no manifest in this model directory", REEXPORT_HINT)
    try:
        raw: Any = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GeoNetInputError(path, f"cannot parse the manifest ({exc})", REEXPORT_HINT) from None
    if not isinstance(raw, dict):
        raise GeoNetInputError(path, "the manifest is not a JSON object", REEXPORT_HINT)
    if raw.get("format") != MANIFEST_FORMAT:
        raise GeoNetInputError(
            path,
            f"not a GeoNet model manifest (format {raw.get('format')!r}, expected {MANIFEST_FORMAT!r})",
            REEXPORT_HINT,
        )
    if raw.get("schema_version") != SCHEMA_VERSION:
        raise GeoNetInputError(
            path,
            f"manifest schema_version {raw.get('schema_version')!r}, this package reads {SCHEMA_VERSION}",
            REEXPORT_HINT + " with this version of the package",
        )
    conv = raw.get("conventions")
    if not isinstance(conv, dict) or not conv:
        raise GeoNetInputError(path, "the manifest has no conventions", REEXPORT_HINT)
    missing_conv = sorted(set(conventions.as_dict()) - set(conv))
    if missing_conv:
        raise GeoNetInputError(path, f"conventions lack {missing_conv}", REEXPORT_HINT)
    try:
        manifest = Manifest.from_dict(raw, root=directory)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else f"malformed entry ({exc})"
        raise GeoNetInputError(path, f"invalid manifest: {what}", REEXPORT_HINT) from None
    if not manifest.graphs or "fp32" not in manifest.graphs:
        raise GeoNetInputError(path, "the manifest lists no fp32 graphs", REEXPORT_HINT)
    for precision, graphs in manifest.graphs.items():
        if precision not in PRECISIONS:
            raise GeoNetInputError(path, f"unknown precision {precision!r}", f"expected one of {PRECISIONS}")
        for name, entry in graphs.items():
            if not _safe_relative(entry.file):
                raise GeoNetInputError(
                    path,
                    f"graph {precision}/{name} has an unsafe file path {entry.file!r}",
                    "paths must be relative and stay inside the model directory",
                )
            if verify_files:
                _verify_file(directory / entry.file, entry.sha256)
    return manifest


def _verify_file(file: Path, expected: str) -> None:
    if not file.is_file():
        raise GeoNetInputError(file, "graph file listed in the manifest is missing", REEXPORT_HINT)
    actual = file_sha256(file)
    if actual != expected:
        raise GeoNetInputError(
            file,
            f"sha256 mismatch: manifest says {expected[:16]}..., file has {actual[:16]}...",
            "the file is corrupt or was changed after export; " + REEXPORT_HINT,
        )
