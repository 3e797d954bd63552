"""Write an ONNX graph from a template's head and computed initializers, without the onnx package.

ONNX files are protobuf ``ModelProto`` messages, and protobuf merges repeated records of a message
field: a head (the model without its weights and metadata) followed by records ``graph {initializer
{...}}`` and ``metadata_props {...}`` parses as one model holding them all (the exporter's
``export.to_onnx.save_streamed`` writes its files the same way). Each tensor is written as it is
computed, so memory holds one tensor at a time, and the file is hashed as it is written.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from geonet_infer.io.protobuf import encode_field, encode_varint
from geonet_infer.models.onnx_graph import (  # onnx.proto's field numbers, listed once
    ENTRY_KEY,
    ENTRY_VALUE,
    GRAPH_INITIALIZER,
    MODEL_GRAPH,
    MODEL_METADATA_PROPS,
    TENSOR_DATA_TYPE,
    TENSOR_DIMS,
    TENSOR_NAME,
    TENSOR_RAW_DATA,
)
from geonet_infer.models.onnx_graph import FLOAT as ONNX_FLOAT


def tensor_record(name: str, value: np.ndarray) -> list:
    """``graph { initializer { dims, data_type, name, raw_data } }`` as pieces (the raw bytes last, uncopied)."""
    if value.dtype != np.float32:
        raise TypeError(f"{name}: only float32 initializers are written, got {value.dtype}")
    raw = np.ascontiguousarray(value, "<f4")
    head = b"".join(encode_field(TENSOR_DIMS, int(d)) for d in value.shape)
    head += encode_field(TENSOR_DATA_TYPE, ONNX_FLOAT) + encode_field(TENSOR_NAME, name.encode())
    raw_key = encode_varint(TENSOR_RAW_DATA << 3 | 2) + encode_varint(raw.nbytes)
    tensor_len = len(head) + len(raw_key) + raw.nbytes
    init_key = encode_varint(GRAPH_INITIALIZER << 3 | 2) + encode_varint(tensor_len)
    graph_key = encode_varint(MODEL_GRAPH << 3 | 2) + encode_varint(len(init_key) + tensor_len)
    return [graph_key + init_key + head + raw_key, raw.reshape(-1).view(np.uint8)]


def metadata_record(key: str, value: str) -> bytes:
    entry = encode_field(ENTRY_KEY, key.encode()) + encode_field(ENTRY_VALUE, value.encode())
    return encode_field(MODEL_METADATA_PROPS, entry)


def write_graph(path: Path, head: bytes, metadata: dict[str, str], tensors: Iterable[tuple[str, np.ndarray]]) -> str:
    """Write the graph to ``path``; returns its sha256 (hex)."""
    digest = hashlib.sha256()
    try:
        with open(path, "wb") as f:

            def put(data) -> None:
                f.write(data)
                digest.update(data)

            put(head)
            for key in sorted(metadata):
                put(metadata_record(key, str(metadata[key])))
            for name, value in tensors:
                for piece in tensor_record(name, value):
                    put(piece)
    except OSError as exc:  # a full disk says which file it stopped
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    return digest.hexdigest()
