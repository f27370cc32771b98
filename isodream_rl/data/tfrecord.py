"""TFRecord framing and ``tf.train.Example`` protobuf coding without TensorFlow.

A TFRecord file is a sequence of records, each framed as::

    uint64 length | uint32 masked_crc32c(length) | bytes data[length] | uint32 masked_crc32c(data)

(little endian). The payload of BAIR's ``softmotion30_44k`` records is a serialised ``tf.train.Example``:
``Example{features: Features{feature: map<string, Feature>}}`` where a ``Feature`` holds one of
``BytesList`` (field 1), ``FloatList`` (field 2) or ``Int64List`` (field 3). Only that subset of the
protobuf wire format is implemented here; the ``tfrecord`` package would add protobuf and crc32c
dependencies for ~150 lines of code.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator, Mapping, Sequence
from functools import cache

import numpy as np

__all__ = [
    "crc32c",
    "masked_crc32c",
    "encode_example",
    "decode_example",
    "write_tfrecord",
    "iter_tfrecord",
    "index_tfrecord",
    "read_record_at",
]

FeatureValue = bytes | Sequence[bytes] | np.ndarray | Sequence[float] | Sequence[int]

_CRC32C_POLY = 0x82F63B78  # Castagnoli, reflected
_MASK_DELTA = 0xA282EAD8
# Buffers shorter than this use the byte loop; longer ones the lane-parallel numpy path.
_LANE_THRESHOLD = 4096


def _make_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ _CRC32C_POLY if crc & 1 else crc >> 1
        table[byte] = crc
    return table


_TABLE = _make_table()
_TABLE_LIST = [int(v) for v in _TABLE]


def _apply(matrix: np.ndarray, value: int) -> int:
    """Apply a GF(2) 32x32 matrix (given as its 32 column words) to a 32-bit word."""
    out = 0
    bit = 0
    while value:
        if value & 1:
            out ^= int(matrix[bit])
        value >>= 1
        bit += 1
    return out


def _apply_vec(matrix: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros_like(values)
    for bit in range(32):
        out ^= np.where((values >> np.uint32(bit)) & np.uint32(1), matrix[bit], np.uint32(0))
    return out


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Matrix of ``x -> a(b(x))``."""
    return np.array([_apply(a, int(col)) for col in b], dtype=np.uint32)


@cache
def _zero_shift(log2_bytes: int) -> np.ndarray:
    """Matrix advancing a raw (uninverted) CRC register over ``2**log2_bytes`` zero bytes."""
    if log2_bytes == 0:
        cols = []
        for bit in range(32):
            crc = 1 << bit
            cols.append(_TABLE_LIST[crc & 0xFF] ^ (crc >> 8))
        return np.array(cols, dtype=np.uint32)
    half = _zero_shift(log2_bytes - 1)
    return _compose(half, half)


def _shift_zeros(value: int, n_bytes: int) -> int:
    k = 0
    while n_bytes:
        if n_bytes & 1:
            value = _apply(_zero_shift(k), value)
        n_bytes >>= 1
        k += 1
    return value


def _raw_crc_small(data: bytes, crc: int) -> int:
    for byte in data:
        crc = _TABLE_LIST[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc


def _raw_crc_lanes(data: bytes) -> int:
    """Raw CRC (initial register 0, no final xor) of a long buffer.

    The buffer is left-padded with zeros (which leaves a zero-initialised CRC unchanged) and cut into
    ``2**k`` equal lanes whose CRCs are computed in parallel; lanes are then merged pairwise using the
    linearity of the CRC: ``crc(A || B) = shift_{|B|}(crc(A)) ^ crc(B)``.
    """
    n = len(data)
    lane_len_log2 = max(1, int(np.ceil(np.log2(np.sqrt(n)))) - 2)
    lane_len = 1 << lane_len_log2
    lanes = 1 << int(np.ceil(np.log2(-(-n // lane_len))))
    buf = np.zeros(lanes * lane_len, dtype=np.uint8)
    buf[lanes * lane_len - n :] = np.frombuffer(data, dtype=np.uint8)
    grid = buf.reshape(lanes, lane_len).astype(np.uint32)
    state = np.zeros(lanes, dtype=np.uint32)
    mask = np.uint32(0xFF)
    eight = np.uint32(8)
    for j in range(lane_len):
        state = _TABLE[(state ^ grid[:, j]) & mask] ^ (state >> eight)
    level = lane_len_log2
    while state.shape[0] > 1:
        state = _apply_vec(_zero_shift(level), state[0::2]) ^ state[1::2]
        level += 1
    return int(state[0])


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) checksum of ``data``, as used by TFRecord framing."""
    if len(data) < _LANE_THRESHOLD:
        return _raw_crc_small(data, 0xFFFFFFFF) ^ 0xFFFFFFFF
    raw = _raw_crc_lanes(data) ^ _shift_zeros(0xFFFFFFFF, len(data))
    return raw ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC: rotate right by 15 bits and add a constant."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


# ---------------------------------------------------------------- protobuf wire format (subset)


def _varint(value: int) -> bytes:
    if value < 0:
        value += 1 << 64  # int64 negatives are encoded as 10-byte two's complement
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _read_varint(buf: memoryview, pos: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated protobuf varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def _field(number: int, payload: bytes) -> bytes:
    """Length-delimited field (wire type 2)."""
    return _varint(number << 3 | 2) + _varint(len(payload)) + payload


def _iter_fields(buf: memoryview) -> Iterator[tuple[int, int, object]]:
    pos = 0
    while pos < len(buf):
        key, pos = _read_varint(buf, pos)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _read_varint(buf, pos)
        elif wire == 1:
            value, pos = buf[pos : pos + 8], pos + 8
        elif wire == 2:
            size, pos = _read_varint(buf, pos)
            value, pos = buf[pos : pos + size], pos + size
        elif wire == 5:
            value, pos = buf[pos : pos + 4], pos + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire} in field {number}")
        if pos > len(buf):
            raise ValueError(f"truncated protobuf field {number}")
        yield number, wire, value


def _encode_feature(value: FeatureValue) -> bytes:
    if isinstance(value, bytes | bytearray):
        return _field(1, _field(1, bytes(value)))
    if isinstance(value, list | tuple) and value and all(isinstance(v, bytes | bytearray) for v in value):
        return _field(1, b"".join(_field(1, bytes(v)) for v in value))
    array = np.asarray(value)
    if array.dtype.kind == "f":
        return _field(2, _field(1, array.astype("<f4").reshape(-1).tobytes()))
    if array.dtype.kind in "iub":
        return _field(3, _field(1, b"".join(_varint(int(v)) for v in array.reshape(-1))))
    raise ValueError(f"cannot encode a feature of dtype {array.dtype}; expected bytes, floats or ints")


def encode_example(features: Mapping[str, FeatureValue]) -> bytes:
    """Serialise a ``tf.train.Example``.

    Args:
        features: maps a key to ``bytes`` (or a list of ``bytes``), a float array (stored as a packed
            ``FloatList`` of float32) or an integer array (packed ``Int64List``).

    Returns:
        The protobuf bytes.
    """
    entries = b"".join(
        _field(1, _field(1, key.encode()) + _field(2, _encode_feature(value)))
        for key, value in features.items()
    )
    return _field(1, entries)


def _decode_feature(buf: memoryview) -> list[bytes] | np.ndarray:
    for number, _, payload in _iter_fields(buf):
        if number == 1:
            return [bytes(v) for n, _, v in _iter_fields(payload) if n == 1]
        if number == 2:
            chunks = []
            for n, _wire, v in _iter_fields(payload):
                if n == 1:  # packed (wire 2) or one float per field (wire 5)
                    chunks.append(bytes(v))
            return np.frombuffer(b"".join(chunks), dtype="<f4").astype(np.float32)
        if number == 3:
            values = []
            for n, wire, v in _iter_fields(payload):
                if n != 1:
                    continue
                if wire == 0:
                    values.append(v)
                else:
                    pos = 0
                    while pos < len(v):
                        item, pos = _read_varint(v, pos)
                        values.append(item)
            signed = [x - (1 << 64) if x >= 1 << 63 else x for x in values]
            return np.asarray(signed, dtype=np.int64)
    return []


def decode_example(data: bytes, keys: Sequence[str] | None = None) -> dict[str, list[bytes] | np.ndarray]:
    """Parse a serialised ``tf.train.Example``.

    Args:
        data: the protobuf bytes.
        keys: if given, only these features are decoded (others are skipped without parsing).

    Returns:
        Maps each key to a list of ``bytes`` (BytesList), a float32 array (FloatList) or an int64 array
        (Int64List).
    """
    wanted = None if keys is None else set(keys)
    out: dict[str, list[bytes] | np.ndarray] = {}
    for number, _, features in _iter_fields(memoryview(data)):
        if number != 1:
            continue
        for fnum, _, entry in _iter_fields(features):
            if fnum != 1:
                continue
            key, value = None, None
            for enum, _, v in _iter_fields(entry):
                if enum == 1:
                    key = bytes(v).decode()
                elif enum == 2:
                    value = v
            if key is None or (wanted is not None and key not in wanted):
                continue
            out[key] = _decode_feature(value) if value is not None else []
    return out


# ---------------------------------------------------------------- TFRecord framing


def write_tfrecord(path: str | os.PathLike, records: Iterator[bytes] | Sequence[bytes]) -> None:
    """Write ``records`` (payload bytes) to ``path`` with TFRecord framing."""
    with open(path, "wb") as f:
        for data in records:
            header = struct.pack("<Q", len(data))
            f.write(header)
            f.write(struct.pack("<I", masked_crc32c(header)))
            f.write(data)
            f.write(struct.pack("<I", masked_crc32c(data)))


def _read_header(f, path) -> int | None:
    header = f.read(12)
    if not header:
        return None
    if len(header) < 12:
        raise ValueError(f"{path}: truncated TFRecord header at byte {f.tell() - len(header)}")
    (length,) = struct.unpack("<Q", header[:8])
    (crc,) = struct.unpack("<I", header[8:])
    if crc != masked_crc32c(header[:8]):
        raise ValueError(f"{path}: corrupt TFRecord length CRC at byte {f.tell() - 12}")
    return length


def _read_payload(f, path, length: int, verify: bool) -> bytes:
    data = f.read(length)
    footer = f.read(4)
    if len(data) < length or len(footer) < 4:
        raise ValueError(f"{path}: truncated TFRecord payload (expected {length} bytes)")
    if verify and struct.unpack("<I", footer)[0] != masked_crc32c(data):
        raise ValueError(f"{path}: corrupt TFRecord data CRC (record of {length} bytes)")
    return data


def iter_tfrecord(path: str | os.PathLike, *, verify_crc: bool = True) -> Iterator[bytes]:
    """Yield the payload of every record in a TFRecord file.

    Args:
        path: the file (uncompressed TFRecords only).
        verify_crc: also check each payload's CRC (the length CRC is always checked).

    Raises:
        ValueError: on a truncated file or a CRC mismatch.
    """
    with open(path, "rb") as f:
        while (length := _read_header(f, path)) is not None:
            yield _read_payload(f, path, length, verify_crc)


def index_tfrecord(path: str | os.PathLike) -> list[int]:
    """Byte offsets of every record in a TFRecord file, reading only the 12-byte headers."""
    offsets = []
    with open(path, "rb") as f:
        while True:
            offset = f.tell()
            length = _read_header(f, path)
            if length is None:
                return offsets
            offsets.append(offset)
            f.seek(length + 4, os.SEEK_CUR)


def read_record_at(path: str | os.PathLike, offset: int, *, verify_crc: bool = True) -> bytes:
    """Read the record starting at byte ``offset`` (from :func:`index_tfrecord`)."""
    with open(path, "rb") as f:
        f.seek(offset)
        length = _read_header(f, path)
        if length is None:
            raise ValueError(f"{path}: no record at byte offset {offset}")
        return _read_payload(f, path, length, verify_crc)
