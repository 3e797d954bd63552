"""The graph files against the manifest, without onnx: their sha256, their inputs and outputs, and a
protobuf walk that refuses external data (a graph must be one self-contained file)."""

from __future__ import annotations

import hashlib
import mmap
import os
from contextlib import nullcontext
from pathlib import Path

from geonet_infer.core.manifest_schema import BATCH_AXIS, REEXPORT_HINT, GraphEntry
from geonet_infer.errors import ModelError

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
