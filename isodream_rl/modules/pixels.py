"""The observation every world model of the library reads: uint8 ``[*batch, 3, 64, 64]`` RGB frames (or floats
in ``[0, 1]``), checked with one-line errors, and their float form ``[-0.5, 0.5]``."""

from __future__ import annotations

import math

import torch

IMAGE_SHAPE = (3, 64, 64)


def check_pixels(pixels: torch.Tensor, *, name: str = "pixels") -> None:
    """Raise a clear error unless ``pixels`` is ``[*batch, 3, 64, 64]``."""
    if pixels.dim() < 3 or tuple(pixels.shape[-3:]) != IMAGE_SHAPE:
        raise ValueError(
            f"{name} must have shape [*batch, 3, 64, 64] (channels first, 64x64 RGB); got {tuple(pixels.shape)}. "
            "Resize observations to 64x64 (e.g. torchrl.envs.Resize) and put channels first."
        )


def check_pixel_values(pixels: torch.Tensor, *, name: str = "pixels") -> None:
    """Raise a clear error unless ``pixels`` are uint8, or floats in ``[0, 1]`` with no NaN/inf (one min/max).

    Raises:
        TypeError: neither uint8 nor floating point.
        ValueError: NaN/inf, or floats outside ``[0, 1]``, naming the range found and the fix.
    """
    if pixels.dtype == torch.uint8:
        return
    if not pixels.is_floating_point():
        raise TypeError(f"{name} must be uint8 in [0, 255] or float in [0, 1], got {pixels.dtype}")
    low, high = (float(x) for x in torch.aminmax(pixels.detach()))
    if math.isnan(low) or math.isnan(high) or math.isinf(low) or math.isinf(high):
        raise ValueError(f"{name} hold NaN or inf values: check the env's frames or the replay data")
    if low < 0.0 or high > 1.0:
        raise ValueError(
            f"float {name} must be in [0, 1] (or uint8 in [0, 255]); got values in [{low:g}, {high:g}]: "
            "divide frames in [0, 255] by 255, add 0.5 to frames in [-0.5, 0.5], or pass the uint8 frames"
        )


def preprocess_pixels(pixels: torch.Tensor) -> torch.Tensor:
    """uint8 ``[0, 255]`` -> float ``[-0.5, 0.5]``; float input is taken to be in ``[0, 1]``."""
    if pixels.dtype == torch.uint8:
        return pixels.float().div_(255.0).sub_(0.5)
    if not pixels.is_floating_point():
        raise TypeError(f"pixels must be uint8 or floating point, got {pixels.dtype}")
    return pixels.float() - 0.5
