"""Whether a torch device can be used on this machine, said in one line naming the setting that gave it."""

from __future__ import annotations


def device_error(device: str, *, setting: str = "train.device") -> str | None:
    """Why ``device`` cannot be used on this machine, or ``None``; the message names it as ``setting`` (the
    config field or command-line flag the user gave it with) and says what to set instead."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, TypeError) as err:
        return f"{setting}={device!r} is not a torch device ({err})"
    if kind == "cuda" and not torch.cuda.is_available():
        return f"{setting}={device!r} but this machine has no usable CUDA GPU: set {setting}=cpu"
    if kind == "mps" and not torch.backends.mps.is_available():
        return f"{setting}={device!r} but MPS is not available here: set {setting}=cpu"
    return None
