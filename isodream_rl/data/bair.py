"""BAIR robot pushing (``softmotion30_44k``) TFRecords, read and written without TensorFlow.

Each record is a ``tf.train.Example`` with one key per time step ``t``:
``'{t}/image_aux1/encoded'`` (raw 64x64x3 RGB bytes, not PNG), ``'{t}/image_main/encoded'``,
``'{t}/action'`` (4 floats) and ``'{t}/endeffector_pos'`` (3 floats). Iso-Dream uses ``image_aux1``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from isodream_rl.data.tfrecord import (
    decode_example,
    encode_example,
    index_tfrecord,
    read_record_at,
    write_tfrecord,
)

__all__ = [
    "decode_bair_example",
    "encode_bair_example",
    "write_bair_tfrecord",
    "write_tiny_bair",
    "BAIRDataset",
]


def decode_bair_example(
    payload: bytes, *, num_frames: int = 30, camera: str = "image_aux1", image_size: int = 64
) -> dict[str, np.ndarray]:
    """Decode one BAIR record.

    Args:
        payload: serialised ``tf.train.Example``.
        num_frames: number of leading time steps to decode (BAIR has 30).
        camera: ``"image_aux1"`` (Iso-Dream's choice) or ``"image_main"``.
        image_size: side of the raw square RGB images.

    Returns:
        ``{"frames": uint8 [T, H, W, 3], "actions": float32 [T, 4], "endeffector_pos": float32 [T, 3]}``.

    Raises:
        KeyError: if a time step's image, action or end-effector key is missing.
    """
    keys = [
        f"{t}/{name}"
        for t in range(num_frames)
        for name in (f"{camera}/encoded", "action", "endeffector_pos")
    ]
    feats = decode_example(payload, keys)
    missing = [k for k in keys if k not in feats]
    if missing:
        raise KeyError(
            f"BAIR record lacks {len(missing)} expected keys, e.g. {missing[:3]}; found {sorted(feats)[:6]}"
        )
    frames = np.empty((num_frames, image_size, image_size, 3), dtype=np.uint8)
    for t in range(num_frames):
        (raw,) = feats[f"{t}/{camera}/encoded"]
        if len(raw) != image_size * image_size * 3:
            raise ValueError(
                f"{t}/{camera}/encoded holds {len(raw)} bytes; expected raw {image_size}x{image_size}x3 RGB"
            )
        frames[t] = np.frombuffer(raw, dtype=np.uint8).reshape(image_size, image_size, 3)
    actions = np.stack([feats[f"{t}/action"] for t in range(num_frames)]).astype(np.float32)
    eef = np.stack([feats[f"{t}/endeffector_pos"] for t in range(num_frames)]).astype(np.float32)
    return {"frames": frames, "actions": actions, "endeffector_pos": eef}


def encode_bair_example(
    frames: np.ndarray, actions: np.ndarray, endeffector_pos: np.ndarray, *, camera: str = "image_aux1"
) -> bytes:
    """Serialise one sequence as a BAIR ``tf.train.Example`` (frames ``[T, H, W, 3]`` uint8).

    The other camera key (``image_main``) is written with the same frames, as both exist in BAIR.
    """
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be uint8 [T, H, W, 3], got {frames.dtype} {frames.shape}")
    features = {}
    for t in range(frames.shape[0]):
        raw = np.ascontiguousarray(frames[t]).tobytes()
        features[f"{t}/{camera}/encoded"] = raw
        other = "image_main" if camera == "image_aux1" else "image_aux1"
        features[f"{t}/{other}/encoded"] = raw
        features[f"{t}/action"] = np.asarray(actions[t], dtype=np.float32)
        features[f"{t}/endeffector_pos"] = np.asarray(endeffector_pos[t], dtype=np.float32)
    return encode_example(features)


def write_bair_tfrecord(
    path: str | os.PathLike, frames: np.ndarray, actions: np.ndarray, endeffector_pos: np.ndarray
) -> None:
    """Write sequences (``[N, T, H, W, 3]`` uint8, ``[N, T, 4]``, ``[N, T, 3]``) as a BAIR TFRecord file."""
    write_tfrecord(path, (encode_bair_example(f, a, e) for f, a, e in zip(frames, actions, endeffector_pos)))


def write_tiny_bair(root: str | os.PathLike) -> Path:
    """A BAIR-format set of random clips under ``root``: ``train/`` 3 clips and ``test/`` 2, of 5 frames, in the
    layout :class:`BAIRDataset` reads (for a check that needs a data set, not its content); ``root``."""
    root = Path(root)
    rng = np.random.default_rng(0)
    for split, clips in (("train", 3), ("test", 2)):
        (root / split).mkdir(parents=True, exist_ok=True)
        write_bair_tfrecord(
            root / split / "traj.tfrecords",
            rng.integers(0, 256, (clips, 5, 64, 64, 3), dtype=np.uint8),
            rng.normal(size=(clips, 5, 4)).astype(np.float32),
            rng.normal(size=(clips, 5, 3)).astype(np.float32),
        )
    return root


class BAIRDataset(Dataset):
    """Random access to BAIR sequences stored in TFRecord files.

    Only the 12-byte record headers are read at construction (to index record offsets); each item is
    read and decoded on access, so the 44k-sequence training set needs no extra memory.

    Args:
        paths: a ``.tfrecords`` file, a directory of them (e.g. ``softmotion30_44k/test``) or a list of
            files.
        num_frames: time steps per sequence to decode (BAIR: 30).
        camera: ``"image_aux1"`` or ``"image_main"``.
        image_size: side of the raw square images (BAIR: 64).
        verify_crc: check every payload's CRC (slow in numpy; docs/recipes/video_prediction.md gives the cost).

    Examples:
        >>> ds = BAIRDataset("softmotion30_44k/test")  # doctest: +SKIP
        >>> ds[0]["frames"].shape  # doctest: +SKIP
        (30, 64, 64, 3)
    """

    def __init__(
        self,
        paths: str | os.PathLike | Iterable[str | os.PathLike],
        *,
        num_frames: int = 30,
        camera: str = "image_aux1",
        image_size: int = 64,
        verify_crc: bool = True,
    ) -> None:
        if isinstance(paths, str | os.PathLike):
            root = Path(paths)
            files = sorted(root.glob("*.tfrecord*")) if root.is_dir() else [root]
        else:
            files = [Path(p) for p in paths]
        if not files:
            raise FileNotFoundError(f"no TFRecord files found at {paths}")
        self.num_frames = num_frames
        self.camera = camera
        self.image_size = image_size
        self.verify_crc = verify_crc
        self._index = [(f, off) for f in files for off in index_tfrecord(f)]

    def __len__(self) -> int:
        return len(self._index)

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        path, offset = self._index[index]
        payload = read_record_at(path, offset, verify_crc=self.verify_crc)
        return decode_bair_example(
            payload, num_frames=self.num_frames, camera=self.camera, image_size=self.image_size
        )
