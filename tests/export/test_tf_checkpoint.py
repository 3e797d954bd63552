"""geonet_infer/convert/tf_checkpoint.py: TensorFlow V2 checkpoints read with numpy alone (issue 43, point 7).

Golden values: files TensorFlow wrote (tests/export/fixtures/tf_bundle, made by its write_fixture.py) read
back against the values it was given; crc32c against RFC 3720's test vectors and a bit-by-bit
implementation here. Needs no TensorFlow except the test that TensorFlow reads our writer's files.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")  # the export package imports torch
from geonet_infer.convert.tf_checkpoint import BundleReader, crc32c, write_checkpoint  # noqa: E402
from geonet_infer.errors import GeoNetError  # noqa: E402

FIXTURE = Path(__file__).parent / "fixtures" / "tf_bundle"
sys.path.insert(0, str(FIXTURE))
from write_fixture import values  # noqa: E402

sys.path.pop(0)


def bitwise_crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def test_crc32c_rfc3720_vectors_and_lengths():
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA
    assert crc32c(b"\xff" * 32) == 0x62A8AB43
    assert crc32c(bytes(range(32))) == 0x46DD794E
    assert crc32c(bytes(range(31, -1, -1))) == 0x113FDB5C
    data = np.random.default_rng(0).integers(0, 256, 5000, np.uint8).tobytes()
    for n in (0, 1, 3, 4, 5, 255, 256, 257, 511, 1000, 5000):  # 1 row, a partial row, a merge tree of 2..32
        assert crc32c(data[:n]) == bitwise_crc32c(data[:n]), n


def _copy(tmp_path: Path) -> Path:
    for f in FIXTURE.glob("tf_written.*"):
        shutil.copy(f, tmp_path / f.name)
    return tmp_path / "tf_written"


def test_reads_what_tensorflow_wrote():
    """Two shards, a two-block index, float32/float64/int32/int64, scalars to 4-D, an empty tensor."""
    reader = BundleReader(FIXTURE / "tf_written")
    expected = {**values()[0], **values()[1]}
    assert reader.num_shards == 2
    assert set(reader.entries) == set(expected)
    assert {reader.entries[n].shard for n in expected} == {0, 1}
    for name, value in expected.items():
        got = reader.tensor(name)
        assert got.dtype == np.asarray(value).dtype and got.shape == np.shape(value), name
        np.testing.assert_array_equal(got, value, err_msg=name)


def test_fixture_index_has_two_data_blocks():
    """The fixture exercises the index block's walk: its 300 long names fill two table blocks."""
    from geonet_infer.convert.tf_checkpoint import _block
    from geonet_infer.io.protobuf import read_varint as _varint

    index = (FIXTURE / "tf_written.index").read_bytes()
    pos = len(index) - 48
    for _ in range(2):
        _, pos = _varint(index, pos)
    offset, pos = _varint(index, pos)
    size, _ = _varint(index, pos)
    assert len(_block(index, offset, size)) == 2


def test_writer_round_trip(tmp_path):
    values_ = {**values()[0], "bool/v": np.array([True, False]), "half/v": np.float16([1.5, -2])}
    prefix = write_checkpoint(tmp_path / "ckpt" / "model-1", values_)
    reader = BundleReader(prefix)
    assert reader.num_shards == 1 and set(reader.entries) == set(values_)
    for name, value in values_.items():
        got = reader.tensor(name)
        assert got.dtype == np.asarray(value).dtype, name
        np.testing.assert_array_equal(got, value, err_msg=name)


def test_tensorflow_reads_our_writer(tmp_path):
    tf = pytest.importorskip("tensorflow")
    prefix = write_checkpoint(tmp_path / "model-1", values()[0])
    reader = tf.train.load_checkpoint(str(prefix))
    for name, value in values()[0].items():
        np.testing.assert_array_equal(reader.get_tensor(name), value, err_msg=name)


def _one_line_error(fn) -> str:
    with pytest.raises(GeoNetError) as exc:
        fn()
    text = str(exc.value)
    assert "\n" not in text, text
    return text


def test_truncated_index_is_named(tmp_path):
    prefix = _copy(tmp_path)
    index = Path(f"{prefix}.index")
    index.write_bytes(index.read_bytes()[:-20])
    err = _one_line_error(lambda: BundleReader(prefix))
    assert err.startswith(f"{index}: unreadable TensorFlow checkpoint index") and "truncated or corrupt" in err


@pytest.mark.parametrize("where", ["start", "middle"])
def test_corrupt_index_block_is_named(tmp_path, where):
    prefix = _copy(tmp_path)
    index = Path(f"{prefix}.index")
    data = bytearray(index.read_bytes())
    data[10 if where == "start" else len(data) // 2] ^= 0x01
    index.write_bytes(bytes(data))
    err = _one_line_error(lambda: BundleReader(prefix))
    assert err.startswith(f"{index}: unreadable TensorFlow checkpoint index") and "crc32c" in err


def test_index_of_another_format_is_named(tmp_path):
    index = tmp_path / "model-1.index"
    index.write_bytes(b"not a table" * 10)
    err = _one_line_error(lambda: BundleReader(tmp_path / "model-1"))
    assert err.startswith(f"{index}: unreadable TensorFlow checkpoint index: not a TensorFlow V2 checkpoint index")


def test_truncated_shard_is_named(tmp_path):
    prefix = _copy(tmp_path)
    shard = Path(f"{prefix}.data-00000-of-00002")
    reader = BundleReader(prefix)  # the index is whole: shards are read per tensor
    cut = reader.entries["float/vec"].offset + 8
    shard.write_bytes(shard.read_bytes()[:cut])
    np.testing.assert_array_equal(reader.tensor("float/big"), values()[0]["float/big"])  # before the cut
    err = _one_line_error(lambda: reader.tensor("float/vec"))
    assert err.startswith(f"{shard}: truncated: variable float/vec needs bytes") and f"the file has {cut}" in err


def test_corrupt_shard_fails_its_checksum(tmp_path):
    prefix = _copy(tmp_path)
    shard = Path(f"{prefix}.data-00000-of-00002")
    entry = BundleReader(prefix).entries["float/big"]
    data = bytearray(shard.read_bytes())
    data[entry.offset + 12345] ^= 0x10
    shard.write_bytes(bytes(data))
    err = _one_line_error(lambda: BundleReader(prefix).tensor("float/big"))
    assert err.startswith(f"{shard}: variable float/big fails its crc32c checksum")


def test_missing_shard_is_named(tmp_path):
    prefix = _copy(tmp_path)
    shard = Path(f"{prefix}.data-00001-of-00002")
    shard.unlink()
    reader = BundleReader(prefix)
    np.testing.assert_array_equal(reader.tensor("float/vec"), np.arange(7) - 3)  # shard 0 still reads
    err = _one_line_error(lambda: reader.tensor(f"pad/007/{'x' * 1000}"))
    assert err.startswith(f"{shard}: cannot read this checkpoint shard")


def test_size_that_does_not_fit_the_shape_is_refused():
    """An entry whose byte size contradicts dtype x shape (a corrupt entry with a valid block crc)."""
    from geonet_infer.convert import tf_checkpoint as tc

    bad = tc._enc_field(1, 1) + tc._enc_field(2, tc._enc_field(2, tc._enc_field(1, 3))) + tc._enc_field(5, 8)
    with pytest.raises(ValueError, match="8 bytes do not hold shape \\[3\\] float32"):
        tc._entry("v", bad)


def test_partitioned_variable_is_named_as_unsupported(tmp_path, monkeypatch):
    """A slices field (a partitioned variable) is a valid checkpoint this reader leaves out: said so,
    not called corrupt."""
    from geonet_infer.convert import tf_checkpoint as tc

    sliced = tc._enc_field(1, 1) + tc._enc_field(2, tc._enc_field(2, tc._enc_field(1, 3))) + tc._enc_field(7, b"")
    with pytest.raises(tc.Unsupported, match="variable v is stored in slices"):
        tc._entry("v", sliced + tc._enc_field(5, 12))
    prefix = write_checkpoint(tmp_path / "model-1", {"v": np.zeros(3, np.float32)})
    original = tc._entry
    monkeypatch.setattr(tc, "_entry", lambda name, value: original(name, sliced))  # every entry written sliced
    err = _one_line_error(lambda: BundleReader(prefix))
    assert err.startswith(f"{prefix}.index: unsupported TensorFlow checkpoint: variable v is stored in slices")
    assert "corrupt" not in err
