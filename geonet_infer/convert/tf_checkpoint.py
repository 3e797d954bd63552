"""TensorFlow checkpoints (the V2 "tensor bundle" format) read and written with numpy alone.

The released GeoNet checkpoints are V2 bundles (TF >= 0.12): ``PREFIX.index`` is a LevelDB-style
SSTable whose keys are variable names and whose values are ``BundleEntryProto`` messages (dtype,
shape, shard, byte offset and size, masked crc32c); the key ``""`` holds the ``BundleHeaderProto``
(shard count, byte order). ``PREFIX.data-SSSSS-of-NNNNN`` hold the raw little-endian tensors back
to back. Formats: tensorflow/core/util/tensor_bundle/tensor_bundle.proto and
third_party/leveldb table_format.txt; TensorFlow writes the index uncompressed.

Why not TensorFlow (``tf.train.load_checkpoint``): 1.3 GB installed (tensorflow-cpu 2.21) to read a
few hundred arrays, and converting a resnet50 release with it peaked at 2.88 GB RSS (1.39 GB now,
docs/official_models.md). Searching the PyPI package list and documentation found no light,
maintained Python package that reads the format without TensorFlow (only crc32c libraries). Here
each shard is memory-mapped and a tensor is copied out only when asked for, after its crc32c is
checked as TensorFlow's reader does.

The writer (:func:`write_checkpoint`) exists for tests and ``python -m geonet_infer.convert.random_checkpoint``:
one shard, one data block; TensorFlow reads its files (tests/export/test_tf_checkpoint.py).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geonet_infer.errors import InputError
from geonet_infer.io import protobuf
from geonet_infer.io.protobuf import encode_field as _enc_field
from geonet_infer.io.protobuf import encode_varint

REDOWNLOAD = "the file is truncated or corrupt: download the checkpoint again"
_MAGIC = 0xDB4775248B80FB57  # LevelDB table magic, the last 8 bytes of every .index
_FOOTER = 48  # two block handles (varints, padded to 40 bytes) + the magic
_BLOCK_TRAILER = 5  # compression type byte + masked crc32c of block and type byte

# tensorflow/core/framework/types.proto DataType -> numpy. bfloat16, strings, complex and
# resources are not here: no GeoNet checkpoint holds them, and they are refused by name.
DTYPES: dict[int, np.dtype] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("<i4"),
    4: np.dtype("u1"),
    5: np.dtype("<i2"),
    6: np.dtype("i1"),
    9: np.dtype("<i8"),
    10: np.dtype("?"),
    17: np.dtype("<u2"),
    19: np.dtype("<f2"),
    22: np.dtype("<u4"),
    23: np.dtype("<u8"),
}
_DTYPE_ENUM = {dt: code for code, dt in DTYPES.items()}


class Unsupported(ValueError):
    """A valid checkpoint using a feature this reader leaves out (slices, bfloat16, big-endian...)."""


# ------------------------------------------------------------------------------ crc32c
_POLY = 0x82F63B78  # Castagnoli, reflected
_ROW = 256  # bytes per row of the vectorised crc: rows are run side by side, then combined


def _byte_table() -> np.ndarray:
    t = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        t = np.where(t & 1, (t >> 1) ^ np.uint32(_POLY), t >> 1).astype(np.uint32)
    return t


_TABLE = _byte_table()
_SHIFTS: list[np.ndarray] = []  # level i: the map "append ROW * 2**i zero bytes" as 4 byte tables


def _apply(tables: np.ndarray, v: np.ndarray) -> np.ndarray:
    return tables[0][v & 0xFF] ^ tables[1][(v >> 8) & 0xFF] ^ tables[2][(v >> 16) & 0xFF] ^ tables[3][v >> 24]


def _tables_of(columns: np.ndarray) -> np.ndarray:
    """Byte lookup tables of the GF(2)-linear map whose image of bit b is ``columns[b]``."""
    idx = np.arange(256, dtype=np.uint32)
    out = np.zeros((4, 256), np.uint32)
    for b in range(32):
        out[b // 8] ^= np.where((idx >> (b % 8)) & 1, columns[b], 0).astype(np.uint32)
    return out


def _shift(level: int) -> np.ndarray:
    while len(_SHIFTS) <= level:
        basis = np.uint32(1) << np.arange(32, dtype=np.uint32)
        if not _SHIFTS:
            for _ in range(_ROW):  # a raw crc (no init/xor-out) through ROW zero bytes
                basis = _TABLE[basis & 0xFF] ^ (basis >> 8)
        else:  # twice the length: the previous map applied twice
            basis = _apply(_SHIFTS[-1], _apply(_SHIFTS[-1], basis))
        _SHIFTS.append(_tables_of(basis))
    return _SHIFTS[level]


def crc32c(data) -> int:
    """CRC-32C (Castagnoli) of ``data`` (bytes or a uint8 array), as google's crc32c library.

    Pure Python would take minutes for the 230 MB of a release, so the bytes are cut into rows of
    ROW bytes whose raw crcs run side by side in numpy, then merged pairwise (crc(A+B) = crc(A)
    shifted by len(B) zero bytes, xor crc(B)). The 0xFFFFFFFF start value equals xor-ing the first
    4 bytes with 0xFF; leading zero bytes leave a raw crc unchanged, so rows are padded in front."""
    buf = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    buf = buf.reshape(-1)
    n = len(buf)
    if n < 4:
        small = 0xFFFFFFFF
        for b in buf.tolist():
            small = int(_TABLE[(small ^ b) & 0xFF]) ^ (small >> 8)
        return small ^ 0xFFFFFFFF
    rows = -(-n // _ROW)
    count = 1 << (rows - 1).bit_length()  # a power of two: the merge tree pairs every row
    start = count * _ROW - n
    padded = np.zeros(count * _ROW, np.uint8)
    padded[start:] = buf
    padded[start : start + 4] ^= 0xFF
    columns = padded.reshape(count, _ROW).T.copy()  # column j of every row, contiguous
    crc = np.zeros(count, np.uint32)
    for col in columns:
        crc = _TABLE[(crc ^ col) & 0xFF] ^ (crc >> 8)
    level = 0
    while len(crc) > 1:
        crc = _apply(_shift(level), crc[0::2]) ^ crc[1::2]
        level += 1
    return int(crc[0]) ^ 0xFFFFFFFF


def mask(crc: int) -> int:
    """LevelDB's masked crc (stored crcs are masked so crcs of data holding crcs stay well spread)."""
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


# ------------------------------------------------------------------------------ protobuf wire format
def _fields(buf: bytes) -> dict[int, list]:
    """Field number -> values (ints for varint/fixed fields, bytes for length-delimited ones)."""
    out: dict[int, list] = {}
    for number, wire, value in protobuf.fields(buf, 0, len(buf)):
        out.setdefault(number, []).append(buf[value[0] : value[1]] if wire == 2 else value)  # type: ignore[index]
    return out


# ------------------------------------------------------------------------------ reader
@dataclass(frozen=True)
class Entry:
    """Where one variable lies: shard file, byte range, and the masked crc32c of its bytes."""

    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    shard: int
    offset: int
    size: int
    crc32c: int | None


MAX_RANK = 8  # the official networks' variables have at most 4 dimensions
MAX_ELEMENTS = 2**31  # values in one variable: the largest official one has 2.4 million


def _entry(name: str, value: bytes) -> Entry:
    f = _fields(value)
    code = f.get(1, [0])[0]
    if f.get(7):
        raise Unsupported(f"variable {name} is stored in slices (a partitioned variable)")
    if code not in DTYPES:
        raise Unsupported(f"variable {name} has TensorFlow dtype {code} (bfloat16, string, complex or resource)")
    shape_fields = _fields(f[2][0]) if 2 in f else {}
    dims = shape_fields.get(2, [])
    if len(dims) > MAX_RANK:  # before building anything from them (numpy stops at 64 dimensions)
        raise ValueError(f"variable {name} has {len(dims)} dimensions (at most {MAX_RANK} are read)")
    shape = tuple(_fields(d).get(1, [0])[0] for d in dims)
    dtype = DTYPES[code]
    size = f.get(5, [0])[0]
    count = math.prod(shape)  # Python integers: a crafted 2**69 does not overflow
    if any(d > MAX_ELEMENTS for d in shape) or count > MAX_ELEMENTS:
        raise ValueError(f"variable {name} claims shape {list(shape)}: over {MAX_ELEMENTS} values")
    if size != count * dtype.itemsize:
        raise ValueError(f"variable {name}: {size} bytes do not hold shape {list(shape)} {dtype.name}")
    return Entry(name, dtype, shape, f.get(3, [0])[0], f.get(4, [0])[0], size, f.get(6, [None])[0])


def _block(index: bytes, offset: int, size: int) -> list[tuple[bytes, bytes]]:
    """The (key, value) entries of the SSTable block at ``offset`` (prefix-compressed keys)."""
    end = offset + size
    if end + _BLOCK_TRAILER > len(index):
        raise ValueError(f"block at byte {offset} runs past the end of the file")
    kind, stored = index[end], struct.unpack_from("<I", index, end + 1)[0]
    if mask(crc32c(index[offset : end + 1])) != stored:
        raise ValueError(f"block at byte {offset} fails its crc32c checksum")
    if kind != 0:
        raise Unsupported(f"block at byte {offset} is compressed (type {kind}); TensorFlow writes bundles uncompressed")
    block = index[offset:end]
    restarts = struct.unpack_from("<I", block, len(block) - 4)[0]
    limit = len(block) - 4 * (restarts + 1)
    if limit < 0:
        raise ValueError(f"block at byte {offset} has a bad restart array")
    entries, key, pos = [], b"", 0
    while pos < limit:
        shared, pos = protobuf.read_varint(block, pos)
        own, pos = protobuf.read_varint(block, pos)
        length, pos = protobuf.read_varint(block, pos)
        key = key[:shared] + block[pos : pos + own]
        pos += own
        entries.append((key, block[pos : pos + length]))
        pos += length
    if pos != limit:
        raise ValueError(f"block at byte {offset} has entries running into its restart array")
    return entries


def _parse_index(index: bytes) -> tuple[int, dict[str, Entry]]:
    """(number of shards, name -> Entry) of a whole .index file."""
    if len(index) < _FOOTER or struct.unpack_from("<Q", index, len(index) - 8)[0] != _MAGIC:
        raise ValueError("not a TensorFlow V2 checkpoint index (no table footer: truncated, or another format)")
    pos = len(index) - _FOOTER
    _, pos = protobuf.read_varint(index, pos)  # metaindex block: unused by TensorFlow bundles
    _, pos = protobuf.read_varint(index, pos)
    offset, pos = protobuf.read_varint(index, pos)
    size, pos = protobuf.read_varint(index, pos)
    shards, entries = None, {}
    for _, handle in _block(index, offset, size):
        block_offset, p = protobuf.read_varint(handle, 0)
        block_size, _ = protobuf.read_varint(handle, p)
        for key, value in _block(index, block_offset, block_size):
            if key == b"":
                header = _fields(value)
                shards = header.get(1, [0])[0]
                if header.get(2, [0])[0] != 0:
                    raise Unsupported("a big-endian checkpoint")
                continue
            name = key.decode("utf-8", "replace")
            entries[name] = _entry(name, value)
    if not shards:
        raise ValueError("no bundle header (the entry with the empty key)")
    return shards, entries


class BundleReader:
    """An opened checkpoint: ``entries`` parsed at once; the shards memory-mapped when first read."""

    def __init__(self, prefix: str | Path):
        self.prefix = Path(prefix)
        self.index_path = Path(f"{self.prefix}.index")
        try:
            index = self.index_path.read_bytes()
        except OSError as exc:
            raise InputError(self.index_path, f"cannot read ({exc.strerror or exc})") from None
        try:
            self.num_shards, self.entries = _parse_index(index)
        except Unsupported as exc:
            raise InputError(
                self.index_path,
                f"unsupported TensorFlow checkpoint: {exc}",
                "this reader reads the unpartitioned numeric tensors of the official GeoNet checkpoints",
            ) from None
        except (ValueError, IndexError, struct.error) as exc:
            problem = str(exc) if isinstance(exc, ValueError) else "the table ends inside an entry"
            raise InputError(
                self.index_path, f"unreadable TensorFlow checkpoint index: {problem}", REDOWNLOAD
            ) from None
        for entry in self.entries.values():
            if entry.shard >= self.num_shards:
                raise InputError(
                    self.index_path, f"variable {entry.name} names shard {entry.shard} of {self.num_shards}", REDOWNLOAD
                )
        self._maps: dict[int, np.ndarray] = {}

    def shard_path(self, shard: int) -> Path:
        return Path(f"{self.prefix}.data-{shard:05d}-of-{self.num_shards:05d}")

    def shard_paths(self) -> list[Path]:
        return [self.shard_path(i) for i in range(self.num_shards)]

    def _map(self, shard: int) -> np.ndarray:
        if shard not in self._maps:
            path = self.shard_path(shard)
            try:
                size = path.stat().st_size
                self._maps[shard] = np.memmap(path, np.uint8, "r") if size else np.zeros(0, np.uint8)
            except OSError as exc:
                raise InputError(
                    path, f"cannot read this checkpoint shard ({exc.strerror or exc})", "it must lie beside the .index"
                ) from None
        return self._maps[shard]

    def close(self) -> None:
        """Unmap the shards (they are mapped again if a tensor is read after)."""
        self._maps.clear()

    def tensor(self, name: str) -> np.ndarray:
        """A copy of variable ``name``, after checking its bytes against the index's crc32c."""
        entry = self.entries[name]
        data = self._map(entry.shard)
        path = self.shard_path(entry.shard)
        if entry.offset + entry.size > len(data):
            raise InputError(
                path,
                f"truncated: variable {name} needs bytes {entry.offset}-{entry.offset + entry.size}, "
                f"the file has {len(data)}",
                REDOWNLOAD,
            )
        raw = data[entry.offset : entry.offset + entry.size]
        if entry.crc32c is not None and mask(crc32c(raw)) != entry.crc32c:
            raise InputError(path, f"variable {name} fails its crc32c checksum", REDOWNLOAD)
        return np.array(raw).view(entry.dtype).reshape(entry.shape)


# ------------------------------------------------------------------------------ writer
def _table_block(entries: list[tuple[bytes, bytes]]) -> bytes:
    """An SSTable block without key compression (every entry a restart point: valid, simple)."""
    body, restarts = bytearray(), []
    for key, value in entries:
        restarts.append(len(body))
        body += encode_varint(0) + encode_varint(len(key)) + encode_varint(len(value)) + key + value
    body += b"".join(struct.pack("<I", r) for r in restarts) + struct.pack("<I", len(restarts))
    return bytes(body)


def write_checkpoint(prefix: str | Path, values: dict[str, np.ndarray]) -> Path:
    """Write ``values`` as a one-shard V2 checkpoint ``PREFIX.index`` + ``PREFIX.data-00000-of-00001``."""
    prefix = Path(prefix)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    header = _enc_field(1, 1) + _enc_field(3, _enc_field(1, 1))  # num_shards 1, little-endian, version 1
    entries, offset = [(b"", header)], 0
    with open(f"{prefix}.data-00000-of-00001", "wb") as data:
        for name in sorted(values):
            array = np.asarray(values[name])
            dtype = array.dtype.newbyteorder("<") if array.dtype.itemsize > 1 else array.dtype
            raw = np.ascontiguousarray(array, dtype).tobytes()
            data.write(raw)
            shape = b"".join(_enc_field(2, _enc_field(1, d) if d else b"") for d in array.shape)
            entry = _enc_field(1, _DTYPE_ENUM[dtype]) + _enc_field(2, shape)
            entry += _enc_field(4, offset) if offset else b""
            entry += _enc_field(5, len(raw)) + encode_varint(6 << 3 | 5) + struct.pack("<I", mask(crc32c(raw)))
            entries.append((name.encode(), entry))
            offset += len(raw)
    out, handles = bytearray(), []
    for block in (_table_block(entries), _table_block([])):  # the data block, the (empty) metaindex
        handles.append(encode_varint(len(out)) + encode_varint(len(block)))
        out += block + b"\0" + struct.pack("<I", mask(crc32c(block + b"\0")))
    index_block = _table_block([(entries[-1][0], handles[0])])  # key: the data block's last
    index_handle = encode_varint(len(out)) + encode_varint(len(index_block))
    out += index_block + b"\0" + struct.pack("<I", mask(crc32c(index_block + b"\0")))
    footer = (handles[1] + index_handle).ljust(_FOOTER - 8, b"\0")
    Path(f"{prefix}.index").write_bytes(bytes(out) + footer + struct.pack("<Q", _MAGIC))
    return prefix
