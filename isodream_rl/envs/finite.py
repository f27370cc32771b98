"""NaN and inf in an env's frames or rewards stop a run where they enter it, in one line naming the env and step.

A frame that turns NaN mid-run (a renderer that divides by zero, an ``env.factory`` that normalises by a range
that collapsed) would otherwise reach the acting policy first, which fails deep inside (``normal expects all
elements of std >= 0.0``), and the world model's own input check sees it only once it is in the replay. The
runs of ``isodream-train`` append :class:`FiniteEnvData` to every env they make
(:func:`~isodream_rl.trainers.builders.checked_env_factory`), so the step that returned the frame is refused
before the policy acts on it or the replay stores it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

#: what :class:`FiniteEnvData` checks by default: what the policy acts on and the replay stores
CHECKED_KEYS = ("pixels", "reward")


class NonFiniteEnvDataError(RuntimeError):
    """An env returned NaN or inf in a checked entry; the message names the env, the entry and the env step."""


class FiniteEnvData(Transform):
    """Raise :class:`NonFiniteEnvDataError` when a step or a reset returns NaN or inf in ``keys``.

    TorchRL's ``FiniteTensorDictCheck`` checks every entry and names neither the entry nor the step; this one
    checks the floating-point entries the run uses (uint8 frames cannot hold NaN) and counts its env's steps.
    For a single (unbatched) env.

    Args:
        env: how the run's settings name the env, for the message (``"env.name=sprites"``).
        keys: the entries to check, where present. Defaults to :data:`CHECKED_KEYS`.
        first_step: the env steps taken before this env was made (a resumed run's), so that the message gives
            the run's env step.

    Examples:
        >>> from isodream_rl.envs import make_env
        >>> env = make_env("sprites").append_transform(FiniteEnvData(env="env.name=sprites"))
        >>> env.rollout(3)["next", "reward"].shape
        torch.Size([3, 1])
    """

    def __init__(self, *, env: str, keys: tuple[str, ...] = CHECKED_KEYS, first_step: int = 0) -> None:
        super().__init__(in_keys=[])
        self.env = env
        self.checked_keys = tuple(keys)
        self.steps = first_step

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.steps += 1
        self._check(next_tensordict, f"at env step {self.steps}")
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self._check(tensordict_reset, f"at the reset after env step {self.steps}")
        return tensordict_reset

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        self._check(next_tensordict, "in the data checked")
        return next_tensordict

    def _check(self, data: TensorDictBase, when: str) -> None:
        for key in self.checked_keys:
            value = data.get(key, None)
            if value is None or not value.is_floating_point() or torch.isfinite(value).all():
                continue
            found = "NaN" if torch.isnan(value).any() else "inf"
            raise NonFiniteEnvDataError(f"{self.env} gave {key!r} holding {found} {when}")
