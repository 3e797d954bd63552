"""The protobuf wire format without protobuf: enough to walk ONNX files (their external-data
fields, :mod:`geonet_infer.models.onnx_check`), to read and write TensorFlow checkpoint records
(:mod:`geonet_infer.convert.tf_checkpoint`) and to write ONNX graphs (:mod:`geonet_infer.convert.onnx_writer`)."""

from __future__ import annotations

import struct
from collections.abc import Iterator


def read_varint(buf, pos: int) -> tuple[int, int]:
    """(value, position after it) of the base-128 varint at ``pos``; IndexError past the end,
    ValueError for one longer than 10 bytes."""
    value = shift = 0
    while True:
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint longer than 10 bytes")


def fields(buf, start: int, end: int) -> Iterator[tuple[int, int, int | tuple[int, int]]]:
    """(field number, wire type, value) of one message in ``buf[start:end]``: an int for varint and
    fixed64/fixed32 fields, (start, end) of the payload for length-delimited ones. ValueError when
    the message is malformed."""
    for number, wire, value, _ in field_spans(buf, start, end):
        yield number, wire, value


def field_spans(buf, start: int, end: int) -> Iterator[tuple[int, int, int | tuple[int, int], tuple[int, int]]]:
    """As :func:`fields`, each with the (start, end) of the whole field (key included): what a writer
    copies to keep the field as it was."""
    pos = start
    while pos < end:
        field_start = pos
        key, pos = read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        value: int | tuple[int, int]
        if wire == 0:
            value, pos = read_varint(buf, pos)
        elif wire == 2:
            size, pos = read_varint(buf, pos)
            if pos + size > end:
                raise ValueError("field runs past its message")
            value = (pos, pos + size)
            pos += size
        elif wire in (1, 5):
            width = 8 if wire == 1 else 4
            if pos + width > end:
                raise ValueError("field runs past its message")
            value = struct.unpack_from("<Q" if wire == 1 else "<I", buf, pos)[0]
            pos += width
        else:
            raise ValueError(f"wire type {wire}")
        yield number, wire, value, (field_start, pos)
    if pos != end:
        raise ValueError("message runs past its end")


def encode_varint(value: int) -> bytes:
    """Protobuf's base-128 varint (``value`` >= 0)."""
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def encode_field(number: int, value: int | bytes) -> bytes:
    """One field: bytes as length-delimited (wire type 2), an int as a varint (wire type 0)."""
    if isinstance(value, bytes):
        return encode_varint(number << 3 | 2) + encode_varint(len(value)) + value
    return encode_varint(number << 3) + encode_varint(value)
