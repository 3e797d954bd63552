"""The graph files against the manifest, without onnx: their sha256, their inputs and outputs, and a
protobuf walk that refuses external data (a graph must be one self-contained file)."""

from __future__ import annotations

import hashlib
import mmap
import os
from contextlib import nullcontext
from pathlib import Path

from geonet_infer.errors import ModelError
from geonet_infer.io.protobuf import fields as _fields
from geonet_infer.models.manifest_schema import BATCH_AXIS, REEXPORT_HINT, GraphEntry

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


def external_data_location(buf, kind: str = "model", start: int = 0, end: int | None = None) -> str | None:
    """The ``location`` of the first tensor an ONNX model keeps in external data ("" if it names none),
    or None when every tensor is inside the file. Walks the protobuf structure only (weights are
    skipped, not decoded), so the runtime needs no ``onnx`` package; raises ValueError or IndexError
    on a malformed file."""
    end = len(buf) if end is None else end
    if kind == "tensor":
        return _tensor_location(buf, start, end)
    for field_number, _, value in _fields(buf, start, end):
        child = _ONNX_CHILDREN[kind].get(field_number)
        if child and isinstance(value, tuple):
            location = external_data_location(buf, child, *value)
            if location is not None:
                return location
    return None


def _tensor_location(buf, start: int, end: int) -> str | None:
    external = None
    for field_number, wire, value in _fields(buf, start, end):
        if field_number == _TENSOR_EXTERNAL_DATA and isinstance(value, tuple):
            entry = {k: bytes(buf[v[0] : v[1]]) for k, _, v in _fields(buf, *value) if isinstance(v, tuple)}
            if entry.get(1) == b"location":  # StringStringEntryProto: key = 1, value = 2
                return entry.get(2, b"").decode("utf-8", "replace")
            external = ""
        elif field_number == _TENSOR_DATA_LOCATION and wire == 0 and value == _EXTERNAL:
            external = ""
    return external
