"""Two questions about an ONNX graph, answered from its bytes without onnx (the wire format of
:mod:`geonet_infer.io.protobuf`):

* :func:`channels_read`: which channels of an input does the graph read? (A direct ResFlowNet reads
  the two frames and the rigid flow of its 12 input channels, not the warped frame or the error.)
* :func:`keep_outputs`: the graph cut down to the nodes some of its outputs need. onnxruntime runs
  every node of a graph whatever outputs are asked for: ``rigidflow.onnx`` takes 5 ms for its three
  outputs and 0.3 ms for the rigid flow alone (128x416, one thread), with the same values.

Field numbers are those of onnx.proto (ModelProto, GraphProto, NodeProto, AttributeProto, TensorProto).
"""

from __future__ import annotations

import struct
from collections.abc import Collection
from dataclasses import dataclass

from geonet_infer.io.protobuf import encode_field, field_spans, fields, read_varint

# Field numbers of onnx.proto (stable since IR version 3), for this reader and convert/onnx_writer.py
MODEL_GRAPH, MODEL_METADATA_PROPS = 7, 14
GRAPH_NODE, GRAPH_INITIALIZER, GRAPH_OUTPUT = 1, 5, 12
NODE_INPUT, NODE_OUTPUT, NODE_OP_TYPE, NODE_ATTRIBUTE = 1, 2, 4, 5
ATTRIBUTE_NAME, ATTRIBUTE_TENSOR, ATTRIBUTE_GRAPH, ATTRIBUTE_GRAPHS = 1, 5, 6, 11
TENSOR_DIMS, TENSOR_DATA_TYPE, TENSOR_INT64_DATA, TENSOR_NAME, TENSOR_RAW_DATA = 1, 2, 7, 8, 9
VALUE_INFO_NAME = 1
ENTRY_KEY, ENTRY_VALUE = 1, 2  # StringStringEntryProto
FLOAT, INT64 = 1, 7  # TensorProto.DataType
CHANNEL_AXES = (1, -3)  # NCHW: the channel axis, counted from either end


@dataclass
class _Node:
    span: tuple[int, int]  # the whole NodeProto field within the graph
    op_type: str
    inputs: list[str]
    outputs: list[str]
    has_subgraph: bool  # If / Loop / Scan bodies may read any tensor of the outer graph
    value: list[int] | None  # a Constant node's int64 values


def _text(buf, span: tuple[int, int]) -> str:
    return bytes(buf[span[0] : span[1]]).decode()


def _int64s(buf, start: int, end: int) -> tuple[str, list[int] | None]:
    """(name, values) of a TensorProto; values None unless it is int64."""
    name, dtype, values = "", None, []
    raw: tuple[int, int] | None = None
    for number, wire, value in fields(buf, start, end):
        if isinstance(value, tuple):  # length-delimited (wire type 2)
            if number == TENSOR_NAME:
                name = _text(buf, value)
            elif number == TENSOR_INT64_DATA:  # packed
                pos, stop = value
                while pos < stop:
                    item, pos = read_varint(buf, pos)
                    values.append(_signed(item))
            elif number == TENSOR_RAW_DATA:
                raw = value  # a span: a float initializer's megabytes are not copied
        elif number == TENSOR_DATA_TYPE and wire == 0:
            dtype = value
        elif number == TENSOR_INT64_DATA and wire == 0:
            values.append(_signed(value))
    if dtype != INT64:
        return name, None
    if raw is not None:
        values = list(struct.unpack_from(f"<{(raw[1] - raw[0]) // 8}q", buf, raw[0]))
    return name, values


def _signed(varint: int) -> int:
    """An int64 from the varint protobuf writes it as (two's complement in 64 bits)."""
    return varint - (1 << 64) if varint >= 1 << 63 else varint


def _graph(buf) -> bytes:
    """The model's GraphProto. A message field may come in several pieces that a reader merges (the
    exporter appends to the graph this way): their payloads, concatenated, are the merged message."""
    pieces = [
        bytes(buf[v[0] : v[1]]) for n, _, v in fields(buf, 0, len(buf)) if n == MODEL_GRAPH and isinstance(v, tuple)
    ]
    if not pieces:
        raise ValueError("no graph in this model")
    return b"".join(pieces)


def _node(buf, span: tuple[int, int], payload: tuple[int, int]) -> _Node:
    op_type, inputs, outputs, has_subgraph, value = "", [], [], False, None
    for number, _, field in fields(buf, *payload):
        if not isinstance(field, tuple):
            continue
        if number == NODE_INPUT:
            inputs.append(_text(buf, field))
        elif number == NODE_OUTPUT:
            outputs.append(_text(buf, field))
        elif number == NODE_OP_TYPE:
            op_type = _text(buf, field)
        elif number == NODE_ATTRIBUTE:
            for a_number, _, a_field in fields(buf, *field):
                if a_number in (ATTRIBUTE_GRAPH, ATTRIBUTE_GRAPHS):
                    has_subgraph = True
                elif a_number == ATTRIBUTE_TENSOR and isinstance(a_field, tuple):
                    value = _int64s(buf, *a_field)[1]
    return _Node(span, op_type, inputs, outputs, has_subgraph, value if op_type == "Constant" else None)


def _parts(buf) -> tuple[bytes, list, list[_Node], dict[str, list[int]]]:
    """(the GraphProto, its fields with their spans in it, its nodes, its int64 constants by name)."""
    graph = _graph(buf)
    spans = list(field_spans(graph, 0, len(graph)))
    nodes, constants = [], {}
    for number, _, value, span in spans:
        if not isinstance(value, tuple):
            continue
        if number == GRAPH_NODE:
            node = _node(graph, span, value)
            nodes.append(node)
            if node.value is not None:
                constants[node.outputs[0]] = node.value
        elif number == GRAPH_INITIALIZER:
            name, values = _int64s(graph, *value)
            if values is not None:
                constants[name] = values
    return graph, spans, nodes, constants


def channels_read(buf, input_name: str) -> frozenset[int] | None:
    """The channels (axis 1) of graph input ``input_name`` that the graph reads, when every node that
    takes the input is a Slice of constant, step-1 channel ranges; None when any node reads it
    otherwise (a convolution reads every channel), or the ranges are not plain."""
    _, _, nodes, constants = _parts(buf)
    read: set[int] = set()
    for node in nodes:
        if input_name not in node.inputs:
            continue
        if node.op_type != "Slice" or node.inputs.index(input_name) != 0 or node.inputs.count(input_name) != 1:
            return None
        starts, ends, axes, steps = (
            constants.get(name) if name else None for name in (node.inputs[1:] + ["", "", ""])[:4]
        )
        if starts is None or ends is None or len(starts) != 1 or len(ends) != 1:
            return None
        if (axes is None or axes[0] not in CHANNEL_AXES) or (steps is not None and steps != [1]):
            return None
        if not 0 <= starts[0] <= ends[0] < 1 << 16:  # counted from the end, or "to the end": not plain
            return None
        read.update(range(starts[0], ends[0]))
    return frozenset(read)


def keep_outputs(buf, outputs: Collection[str]) -> bytes | None:
    """The model with only the graph outputs named in ``outputs`` and the nodes and initializers they
    need (every other field as it was); None when a needed node holds a subgraph (it may read any tensor)
    or ``outputs`` names no output of the graph."""
    outputs = set(outputs)
    graph, spans, nodes, _ = _parts(buf)
    graph_outputs = {_name(graph, v, VALUE_INFO_NAME) for n, _, v, _ in spans if n == GRAPH_OUTPUT}
    if not outputs & graph_outputs:
        return None
    needed = set(outputs)
    kept: set[tuple[int, int]] = set()
    for node in reversed(nodes):  # ONNX nodes are topologically sorted
        if needed.intersection(node.outputs):
            if node.has_subgraph:
                return None
            kept.add(node.span)
            needed.update(name for name in node.inputs if name)
    body = bytearray()
    for number, _, value, span in spans:
        if number == GRAPH_NODE and span not in kept:
            continue
        if number == GRAPH_OUTPUT and _name(graph, value, VALUE_INFO_NAME) not in outputs:
            continue
        if number == GRAPH_INITIALIZER and _name(graph, value, TENSOR_NAME) not in needed:
            continue  # onnxruntime warns of an initializer no node uses
        body += graph[span[0] : span[1]]
    model, placed = bytearray(), False
    for number, _, _, span in field_spans(buf, 0, len(buf)):
        if number != MODEL_GRAPH:
            model += buf[span[0] : span[1]]
        elif not placed:  # the graph once, merged, where its first piece was
            model += encode_field(MODEL_GRAPH, bytes(body))
            placed = True
    return bytes(model)


def _name(buf, payload: int | tuple[int, int], field: int) -> str:
    """The string field ``field`` (a name) of the message at ``payload``; "" when there is none."""
    if not isinstance(payload, tuple):
        return ""
    return next((_text(buf, v) for n, _, v in fields(buf, *payload) if n == field and isinstance(v, tuple)), "")
