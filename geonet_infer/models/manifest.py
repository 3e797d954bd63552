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

import json
import math
from pathlib import Path, PurePosixPath
from typing import Any

from geonet_infer import conventions
from geonet_infer.errors import ModelError
from geonet_infer.io.atomic import atomic_write
from geonet_infer.models.manifest_schema import (  # noqa: F401  (re-exported: this module's names before the split)
    AUTO,
    BATCH_AXIS,
    MANIFEST_FORMAT,
    MANIFEST_NAME,
    MAX_CONVENTION_MAGNITUDE,
    MAX_SEQ_LENGTH,
    MAX_SIDE,
    MIN_NORM_SCALE,
    MIN_SEQ_LENGTH,
    MIN_SIDE,
    PRECISION_CHOICES,
    PRECISIONS,
    REAL_VIDEO_HINT,
    REEXPORT_HINT,
    SCHEMA_VERSION,
    SIZE_MULTIPLE,
    GraphEntry,
    Manifest,
    ModelCard,
    Provenance,
    Quantization,
    Score,
    TensorSpec,
    _from_known_fields,
    file_sha256,
    model_notice,
)
from geonet_infer.models.onnx_check import (  # noqa: F401  (re-exported: this module's names before the split)
    _EXTERNAL,
    _ONNX_CHILDREN,
    _TENSOR_DATA_LOCATION,
    _TENSOR_EXTERNAL_DATA,
    IoSpec,
    _dim_fits,
    _fields,
    _tensor_location,
    _verify_file,
    check_graph_io,
    external_data_location,
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
    # ValueError: JSONDecodeError, and a number of more digits than Python's int-string limit (4300)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # Recursion: nested 10^5 deep
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
        if isinstance(default, dict) and key in given and not isinstance(value, dict):
            raise ModelError(path, f"{where}.{key} is {type(value).__name__}: expected an object", REEXPORT_HINT)
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
