"""BAIR TFRecord reading without TensorFlow, on files whose framing and protobuf bytes are built here by
hand (independently of the package's own encoder)."""

import struct

import numpy as np
import pytest

from isodream_rl.data import BAIRDataset, decode_bair_example, write_bair_tfrecord
from isodream_rl.data.tfrecord import crc32c, decode_example, encode_example, iter_tfrecord, masked_crc32c


def _bitwise_crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def _masked(data: bytes) -> int:
    crc = _bitwise_crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def _varint(n: int) -> bytes:
    out = b""
    while n > 0x7F:
        out += bytes([(n & 0x7F) | 0x80])
        n >>= 7
    return out + bytes([n])


def _ld(field: int, payload: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(payload)) + payload


def _example(features: dict) -> bytes:
    """tf.train.Example bytes: Example.features(1) -> Features.feature(1) map entries {key(1), value(2)}."""
    entries = b""
    for key, value in features.items():
        if isinstance(value, bytes):
            feature = _ld(1, _ld(1, value))  # BytesList
        else:  # FloatList, unpacked: one fixed32 per value (wire type 5)
            floats = b"".join(_varint(1 << 3 | 5) + struct.pack("<f", v) for v in value)
            feature = _ld(2, floats)
        entries += _ld(1, _ld(1, key.encode()) + _ld(2, feature))
    return _ld(1, entries)


def _write_framed(path, payloads) -> None:
    with open(path, "wb") as f:
        for data in payloads:
            header = struct.pack("<Q", len(data))
            f.write(header + struct.pack("<I", _masked(header)) + data + struct.pack("<I", _masked(data)))


def _bair_sequence(rng, steps):
    frames = rng.integers(0, 256, size=(steps, 64, 64, 3), dtype=np.uint8)
    actions = rng.normal(size=(steps, 4)).astype(np.float32)
    eef = rng.normal(size=(steps, 3)).astype(np.float32)
    return frames, actions, eef


def _bair_payload(frames, actions, eef) -> bytes:
    feats = {}
    for t in range(frames.shape[0]):
        feats[f"{t}/image_aux1/encoded"] = frames[t].tobytes()
        feats[f"{t}/image_main/encoded"] = frames[t][::-1].tobytes()
        feats[f"{t}/action"] = [float(x) for x in actions[t]]
        feats[f"{t}/endeffector_pos"] = [float(x) for x in eef[t]]
    return _example(feats)


def test_crc32c_matches_standard_check_value():
    assert crc32c(b"123456789") == 0xE3069283


@pytest.mark.parametrize("size", [0, 1, 4095, 4096, 10_001, 40_000])
def test_crc32c_lane_path_matches_bitwise_reference(size):
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    assert crc32c(data) == _bitwise_crc32c(data)
    assert masked_crc32c(data) == _masked(data)


def test_bair_dataset_reads_handcrafted_tfrecord(tmp_path):
    rng = np.random.default_rng(0)
    sequences = [_bair_sequence(rng, 4) for _ in range(3)]
    path = tmp_path / "traj_0_to_2.tfrecords"
    _write_framed(path, [_bair_payload(*s) for s in sequences])

    ds = BAIRDataset(tmp_path, num_frames=4)
    assert len(ds) == 3
    for i, (frames, actions, eef) in enumerate(sequences):
        item = ds[i]
        np.testing.assert_array_equal(item["frames"], frames)
        np.testing.assert_array_equal(item["actions"], actions)
        np.testing.assert_array_equal(item["endeffector_pos"], eef)
    main = BAIRDataset(path, num_frames=4, camera="image_main")[1]["frames"]
    np.testing.assert_array_equal(main, sequences[1][0][:, ::-1])


def test_corrupt_payload_is_reported(tmp_path):
    path = tmp_path / "bad.tfrecords"
    _write_framed(path, [_example({"0/action": [1.0, 2.0]})])
    raw = bytearray(path.read_bytes())
    raw[14] ^= 0xFF  # inside the payload
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="CRC"):
        list(iter_tfrecord(path))
    assert len(list(iter_tfrecord(path, verify_crc=False))) == 1


def test_truncated_file_is_reported(tmp_path):
    path = tmp_path / "short.tfrecords"
    _write_framed(path, [_example({"0/action": [1.0]})])
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(ValueError, match="truncated"):
        list(iter_tfrecord(path))


def test_missing_step_key_raises_key_error():
    payload = _bair_payload(*_bair_sequence(np.random.default_rng(1), 2))
    with pytest.raises(KeyError, match="expected keys"):
        decode_bair_example(payload, num_frames=3)


def test_package_writer_round_trips_through_reader(tmp_path):
    rng = np.random.default_rng(2)
    frames, actions, eef = (np.stack(x) for x in zip(*[_bair_sequence(rng, 3) for _ in range(2)]))
    write_bair_tfrecord(tmp_path / "w.tfrecords", frames, actions, eef)
    ds = BAIRDataset(tmp_path / "w.tfrecords", num_frames=3)
    np.testing.assert_array_equal(ds[1]["frames"], frames[1])
    np.testing.assert_array_equal(ds[0]["actions"], actions[0])


def test_example_codec_handles_int64_and_negative_values():
    payload = encode_example({"ints": np.array([0, 5, -3, 2**40]), "b": [b"x", b"yz"]})
    decoded = decode_example(payload)
    np.testing.assert_array_equal(decoded["ints"], [0, 5, -3, 2**40])
    assert decoded["b"] == [b"x", b"yz"]
