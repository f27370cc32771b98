"""What both TorchRL baselines (:mod:`~isodream_rl.baselines.torchrl_dreamer`,
:mod:`~isodream_rl.baselines.torchrl_dreamer_v3`) share around TorchRL's pieces.

- :func:`preset_widths`: the widths a baseline reads from the run's size preset, the ``model.<field>`` settings applied.
- :func:`latent_dreamer_env`: a ``DreamerEnv`` over ``state``/``belief`` with its specs set by hand.
- :class:`CarriedStatePolicy`: an acting policy that carries its recurrent state under TorchRL's ``("next", ...)``
  convention (primer, reset at ``is_init``, uint8 pixels in, only the action and the next carried state out).
- :class:`ZeroStateStepper`: a stepper that turns a flat replay sample into the loss's input, zero root
  ``state``/``belief`` added, and runs the update on it.
- :class:`BaselineComponents`: the run parts' interface with the run's replay side and a checkpoint check.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import WorldModelWrapper

from isodream_rl.modules.config import SIZE_PRESETS
from isodream_rl.modules.policy import carried_state_primer, read_acting_inputs
from isodream_rl.trainers.components import RunComponents, make_replay_parts
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper

logger = logging.getLogger(__name__)


def preset_widths(cfg: RunConfig, keys: Sequence[str], *, algo: str) -> dict[str, int]:
    """The size-preset fields ``keys`` of ``cfg`` (``SIZE_PRESETS[model.size]``, the ``model.<field>`` it sets applied).

    The other model fields it sets (``precision`` aside, which each baseline reads itself) are logged as ignored by
    ``algo``.

    Raises:
        ValueError: an unknown size preset.
    """
    if cfg.model.size not in SIZE_PRESETS:
        raise ValueError(f"unknown size preset {cfg.model.size!r}; valid: {sorted(SIZE_PRESETS)}")
    overrides = cfg.model.world_model_fields()
    ignored = sorted(set(overrides) - set(keys) - {"precision"})
    if ignored:
        logger.info("%s ignores the Iso-Dream model fields %s", algo, ignored)
    return {key: int(overrides.get(key, SIZE_PRESETS[cfg.model.size][key])) for key in keys}


def latent_dreamer_env(
    world_model: WorldModelWrapper, *, action_spec: Bounded, state_dim: int, belief_dim: int, device
) -> DreamerEnv:
    """Imagination: a ``DreamerEnv`` stepping ``world_model`` on ``state`` ``[S]`` / ``belief`` ``[D]``.

    The specs that ``set_specs_from_env`` would copy from a primed env are set by hand (the run parts know the
    action width, not the env): ``action_spec``, ``state``/``belief`` as observation and state, a ``[1]`` reward.
    """
    env = DreamerEnv(
        world_model=world_model,
        prior_shape=torch.Size([state_dim]),
        belief_shape=torch.Size([belief_dim]),
        device=device,
    )
    latent = Composite(
        state=Unbounded((state_dim,), device=device), belief=Unbounded((belief_dim,), device=device)
    )
    env.action_spec = action_spec
    env.observation_spec = latent.clone()
    env.state_spec = latent.clone()
    env.reward_spec = Unbounded((1,), device=device)
    return env


class CarriedStatePolicy(TensorDictModuleBase):
    """An acting policy around a TorchRL acting sequence ``module`` that carries its recurrent state.

    At each env step it reads uint8 ``pixels_key`` ``[*B, 3, 64, 64]``, ``"is_init"`` and the carried keys
    (``widths``' keys, ``[*B, width]``), flattens them over the env batch, lets :meth:`act` run ``module``, and
    writes only ``action_key`` and ``("next", key)`` for each carried key, following TorchRL's recurrent
    convention; prime the env with :meth:`make_tensordict_primer`. Runs without gradients, on the device of
    ``module``'s parameters; any batch shape (or none). Subclasses implement :meth:`act`.

    Args:
        module: the acting sequence.
        widths: the carried keys and their widths, e.g. ``{"state": S, "belief": D}``.
        pixels_key: the observation key. Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.
    """

    def __init__(
        self,
        module: TensorDictModuleBase,
        *,
        widths: dict[str, int],
        pixels_key: str = "pixels",
        action_key: str = "action",
    ) -> None:
        super().__init__()
        self.module = module
        self.widths = dict(widths)
        self.pixels_key, self.action_key = pixels_key, action_key
        self.in_keys = [pixels_key, "is_init", *self.widths]
        self.out_keys = [action_key, *(("next", key) for key in self.widths)]

    def recurrent_spec(self) -> Composite:
        """Specs of the carried keys (unbatched), ``[width]`` each."""
        device = next(self.module.parameters()).device
        return Composite({key: Unbounded((width,), device=device) for key, width in self.widths.items()})

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """A ``TensorDictPrimer`` adding the carried keys (zeros at reset) to an env or a batch of envs."""
        return carried_state_primer(self.recurrent_spec())

    def act(
        self, pixels: torch.Tensor, carried: dict[str, torch.Tensor], reset: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """One step of the acting sequence.

        Args:
            pixels: uint8 ``[N, 3, 64, 64]`` on the module's device.
            carried: each carried key ``[N, width]``.
            reset: ``[N, 1]`` bool, ``True`` where an episode starts; ``None`` without ``"is_init"``.

        Returns:
            ``action_key`` ``[N, A]`` and the next value of each carried key ``[N, width]``.
        """
        raise NotImplementedError(f"{type(self).__name__} must define act(): each baseline's policy step")

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        device = next(self.module.parameters()).device
        pixels, carried, reset = read_acting_inputs(
            tensordict,
            owner=type(self).__name__,
            pixels_key=self.pixels_key,
            carried_keys=list(self.widths),
            device=device,
        )
        if pixels.dtype != torch.uint8:
            raise ValueError(f"{self.pixels_key!r} must be uint8 [*B, 3, 64, 64], got {pixels.dtype}")
        out_device = tensordict.device if tensordict.device is not None else pixels.device
        outputs = self.act(pixels.to(device), carried, reset)
        tensordict.set(self.action_key, outputs[self.action_key].to(out_device).reshape(*batch, -1))
        for key in self.widths:
            tensordict.set(("next", key), outputs[key].to(out_device).reshape(*batch, -1))
        return tensordict


class ZeroStateStepper(IsoDreamOptimizationStepper):
    """An :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper` whose :meth:`step` updates on
    :meth:`prepare`'s output: the loss's input (:meth:`loss_inputs`) of the flat ``[B * T]`` replay sample, moved to
    the model's device first, with zero root ``"state"`` ``[N, S]`` / ``"belief"`` ``[N, D]`` (a rollout reads each
    window's first step, as TorchRL's examples set them).

    Args:
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        **stepper_kwargs: the arguments of :class:`~isodream_rl.trainers.stepper.IsoDreamOptimizationStepper`.
    """

    def __init__(self, *, state_dim: int, belief_dim: int, **stepper_kwargs) -> None:
        super().__init__(**stepper_kwargs)
        self.state_dim, self.belief_dim = state_dim, belief_dim

    def loss_inputs(self, sub_batch: TensorDictBase) -> TensorDictBase:
        """The entries of a flat ``[N]`` replay sample the loss reads, as it reads them (a new tensordict)."""
        raise NotImplementedError(f"{type(self).__name__} must define loss_inputs(): what its loss reads")

    def prepare(self, sample: TensorDictBase) -> TensorDictBase:
        """:meth:`loss_inputs` of a flat ``[N]`` replay sample on the model's device, zero ``"state"``/``"belief"``
        added on the same device."""
        n = sample.numel()
        batch = self.loss_inputs(sample)
        batch.set("state", torch.zeros(n, self.state_dim, device=sample.device))
        batch.set("belief", torch.zeros(n, self.belief_dim, device=sample.device))
        return batch


class BaselineComponents(RunComponents):
    """The interface of :class:`~isodream_rl.trainers.components.RunComponents` for a baseline whose
    ``__init__`` builds its own models, losses and stepper: :meth:`set_replay_parts` gives it the run's replay
    buffer, preparation and episode-return hooks, and :meth:`load_models` refuses a checkpoint of another
    algorithm in one line."""

    #: the ``algo.name`` the subclass is registered under (named by :meth:`load_models`)
    algo: ClassVar[str]

    def set_replay_parts(self, cfg: RunConfig, *, scratch_dir: Path) -> None:
        """``replay_buffer``, ``preparation``, ``returns``: the Iso-Dream run's
        (:func:`~isodream_rl.trainers.components.make_replay_parts`)."""
        self.replay_buffer, self.preparation, self.returns = make_replay_parts(cfg, scratch_dir=scratch_dir)

    def load_models(self, state: dict) -> None:
        """Load the weights saved by :meth:`state` (checkpoint key ``"models"``).

        Raises:
            KeyError: the checkpoint lacks one of :meth:`modules`' weights (another algorithm's).
        """
        missing = set(self.modules()) - set(state["models"])
        if missing:
            raise KeyError(
                f"the checkpoint has no {sorted(missing)} weights: it was not written by an "
                f"algo={self.algo} run"
            )
        super().load_models(state)
