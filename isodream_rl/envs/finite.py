"""NaN and inf in an env's frames or rewards stop a run where they enter it, in one line naming the env and step.

A frame that turns NaN mid-run (a renderer that divides by zero, an ``env.factory`` that normalises by a range
that collapsed) would otherwise reach the acting policy first, which fails deep inside (``normal expects all
elements of std >= 0.0``), and the world model's own input check sees it only once it is in the replay. The
runs of ``isodream-train`` append :class:`FiniteEnvData` to every env they make
(:func:`~isodream_rl.trainers.builders.checked_env_factory`), so the step that returned the frame is refused
before the policy acts on it or the replay stores it.

An env in a collector worker process (``env.num_envs > 1``, Ray, ``torch.distributed``) cannot raise into the run:
the worker would die with a traceback on its own stderr and the run would only learn that "a process failed".
There :class:`FiniteEnvData` runs with ``on_fault="mark"``: it writes what it found into :data:`FAULT_KEY`,
zeroes the bad values (so the worker's policy can act) and ends the episode; the run's process reads the mark in
the collected batch (:func:`raise_marked_fault`) and refuses it, before the replay stores it, in the same one line.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Unbounded
from torchrl.envs.transforms import Transform

#: what :class:`FiniteEnvData` checks by default: what the policy acts on and the replay stores
CHECKED_KEYS = ("pixels", "reward")
#: the mark ``on_fault="mark"`` writes: int64 ``[5]`` = (found, env step, index into the checked keys, 1 for inf
#: else 0, 1 at a reset else 0); ``found`` is 0 on every clean step
FAULT_KEY = "nonfinite_env_data"
ON_FAULT = ("raise", "mark")


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
        on_fault: ``"raise"`` (default) or ``"mark"``: for an env in a collector worker, write the finding into
            :data:`FAULT_KEY` (int64 ``[5]``, added to the observation spec), zero the non-finite values and set
            ``truncated``/``done`` on that step, for :func:`raise_marked_fault` in the run's process.

    Examples:
        >>> from isodream_rl.envs import make_env
        >>> env = make_env("sprites").append_transform(FiniteEnvData(env="env.name=sprites"))
        >>> env.rollout(3)["next", "reward"].shape
        torch.Size([3, 1])
    """

    def __init__(
        self, *, env: str, keys: tuple[str, ...] = CHECKED_KEYS, first_step: int = 0, on_fault: str = "raise"
    ) -> None:
        if on_fault not in ON_FAULT:
            raise ValueError(f"on_fault must be one of {ON_FAULT}, got {on_fault!r}")
        super().__init__(in_keys=[])
        self.env = env
        self.checked_keys = tuple(keys)
        self.steps = first_step
        self.on_fault = on_fault

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.steps += 1
        return self._check(next_tensordict, at_reset=False)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._check(tensordict_reset, at_reset=True)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._check(next_tensordict, at_reset=False)

    def transform_observation_spec(self, observation_spec):
        if self.on_fault == "mark":
            observation_spec[FAULT_KEY] = Unbounded(
                shape=(*observation_spec.shape, 5), dtype=torch.int64, device=observation_spec.device
            )
        return observation_spec

    def _check(self, data: TensorDictBase, *, at_reset: bool) -> TensorDictBase:
        mark = torch.zeros(5, dtype=torch.int64, device=data.device)
        for index, key in enumerate(self.checked_keys):
            value = data.get(key, None)
            if value is None or not value.is_floating_point() or torch.isfinite(value).all():
                continue
            inf = not torch.isnan(value).any()
            if self.on_fault == "raise":
                raise NonFiniteEnvDataError(
                    fault_message(self.env, key, inf=inf, step=self.steps, at_reset=at_reset)
                )
            if not mark[0]:
                mark = torch.tensor([1, self.steps, index, int(inf), int(at_reset)], device=data.device)
            data.set(key, torch.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0))
        if mark[0] and not at_reset:  # end the episode there
            for flag in ("truncated", "done"):
                if data.get(flag, None) is not None:
                    data.set(flag, torch.ones_like(data.get(flag)))
        if self.on_fault == "mark":
            data.set(FAULT_KEY, mark)
        return data


def fault_message(env: str, key: str, *, inf: bool, step: int, at_reset: bool) -> str:
    """The one line that names the env, the entry and the env step of a NaN/inf (:class:`FiniteEnvData`)."""
    when = f"at the reset after env step {step}" if at_reset else f"at env step {step}"
    return f"{env} gave {key!r} holding {'inf' if inf else 'NaN'} {when}"


def raise_marked_fault(
    batch: TensorDictBase, envs: tuple[str, ...], keys: tuple[str, ...] = CHECKED_KEYS
) -> None:
    """Raise :class:`NonFiniteEnvDataError` for the first mark of ``FiniteEnvData(on_fault="mark")`` in a
    collected batch; nothing when the batch has no mark or none is set.

    Args:
        batch: a collector batch, ``[num_envs, T]`` (env ``i`` in row ``i``) or ``[T]`` for one env; the mark is
            read at the root (resets) and under ``"next"`` (steps).
        envs: how each env is named in the message, one per row (``"env.name=sprites (collector env 1 of 2)"``).
        keys: the entries the envs check, in the order of their :class:`FiniteEnvData`.
    """
    for where in (("next", FAULT_KEY), FAULT_KEY):
        marks = batch.get(where, None)
        if marks is None:
            continue
        marks = marks.reshape(len(envs), -1, 5) if marks.ndim != 3 else marks
        found = marks[..., 0].nonzero()
        if len(found):
            row, col = (int(i) for i in found[0])
            _, step, index, inf, at_reset = (int(v) for v in marks[row, col])
            raise NonFiniteEnvDataError(
                fault_message(envs[row], keys[index], inf=bool(inf), step=step, at_reset=bool(at_reset))
            )
