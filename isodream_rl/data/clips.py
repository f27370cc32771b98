"""Fixed-length training / test clips cut from sequence datasets, with optional bouncing balls.

A *sequence source* is anything indexable returning ``{"frames": uint8 [T, H, W, 3], "actions": [T, A]}``
(:class:`~isodream_rl.data.bair.BAIRDataset`, :class:`~isodream_rl.data.robonet.RoboNetDataset`, or
:class:`ArraySequences` over in-memory arrays such as the local pusher set).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

__all__ = ["ArraySequences", "VideoClips"]


class ArraySequences(Dataset):
    """Sequence source over arrays ``frames [N, T, H, W, 3]`` uint8 and ``actions [N, T, A]``."""

    def __init__(self, arrays: Mapping[str, np.ndarray]) -> None:
        for key in ("frames", "actions"):
            if key not in arrays:
                raise KeyError(f"arrays must contain '{key}', got keys {sorted(arrays)}")
        if arrays["frames"].shape[:2] != arrays["actions"].shape[:2]:
            raise ValueError(
                f"frames {arrays['frames'].shape} and actions {arrays['actions'].shape} disagree on [N, T]"
            )
        self.arrays = arrays

    def __len__(self) -> int:
        return self.arrays["frames"].shape[0]

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        return {k: v[index] for k, v in self.arrays.items()}


class VideoClips(Dataset):
    """Clips of ``clip_length`` frames from every sequence, as ``float`` tensors.

    Args:
        source: a sequence source (see module docstring); all sequences must have ``sequence_length``
            frames or more.
        clip_length: frames per clip (training: 2 context + 10 predicted = 12; BAIR test: 30).
        sequence_length: frames per source sequence used for windowing.
        stride: step between clip starts; ``stride >= sequence_length`` gives one clip per sequence.
        distractor: optional transform ``(frames [L, H, W, 3] uint8, clip_index) -> frames`` applied at
            load time, e.g. :class:`~isodream_rl.data.bouncing_balls.BouncingBalls`.

    Items are ``{"frames": float32 [L, 3, H, W] in [0, 1], "actions": float32 [L, A]}``.
    """

    def __init__(
        self,
        source: Sequence | Dataset,
        *,
        clip_length: int,
        sequence_length: int,
        stride: int = 1,
        distractor: Callable[[np.ndarray, int], np.ndarray] | None = None,
    ) -> None:
        if clip_length > sequence_length:
            raise ValueError(f"clip_length={clip_length} exceeds sequence_length={sequence_length}")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        self.source = source
        self.clip_length = clip_length
        self.distractor = distractor
        self._starts = list(range(0, sequence_length - clip_length + 1, stride))

    def __len__(self) -> int:
        return len(self.source) * len(self._starts)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not 0 <= index < len(self):
            raise IndexError(f"clip index {index} out of range [0, {len(self)})")
        seq, start = divmod(index, len(self._starts))
        item = self.source[seq]
        stop = self._starts[start] + self.clip_length
        frames = item["frames"][self._starts[start] : stop]
        if frames.shape[0] < self.clip_length:
            raise ValueError(f"sequence {seq} has {item['frames'].shape[0]} frames; need at least {stop}")
        if self.distractor is not None:
            frames = self.distractor(frames, index)
        return {
            "frames": torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float().div_(255.0),
            "actions": torch.as_tensor(item["actions"][self._starts[start] : stop], dtype=torch.float32),
        }
