"""Imagination as a TorchRL env: a ``DreamerEnv`` over a latent state whose specs are set by hand.

:func:`latent_dreamer_env` is the imagination env of ``algo=torchrl_dreamer``, ``algo=torchrl_dreamer_v3``
(:mod:`isodream_rl.baselines`) and Iso-Dream's DreamerV3 learner, which carries more than ``state`` and
``belief`` (``extra_observations``, e.g. a window ``[tau, F]`` of the free branch).
"""

from __future__ import annotations

import torch
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.model_based.dreamer import DreamerEnv
from torchrl.modules import WorldModelWrapper


def latent_dreamer_env(
    world_model: WorldModelWrapper,
    *,
    action_spec: Bounded,
    state_dim: int,
    belief_dim: int,
    device,
    extra_observations: dict[str, tuple[int, ...]] | None = None,
    env_class: type[DreamerEnv] = DreamerEnv,
    env_kwargs: dict | None = None,
) -> DreamerEnv:
    """Imagination: a ``DreamerEnv`` stepping ``world_model`` on ``state`` ``[S]`` / ``belief`` ``[D]``.

    The specs that ``set_specs_from_env`` would copy from a primed env are set by hand (the run parts know the
    action width, not the env): ``action_spec``, ``state``/``belief`` (and each of ``extra_observations``) as
    observation and state, a ``[1]`` reward.

    Args:
        world_model: the imagination step (reads the latent keys and ``"action"``, writes the next latent keys and
            ``"reward"``).
        action_spec: the action's spec.
        state_dim: width of ``"state"``.
        belief_dim: width of ``"belief"``.
        device: where the env lives.
        extra_observations: more latent keys beside ``state`` and ``belief``, each with its unbatched shape
            (e.g. ``{"window": (tau, F)}``); observation and state too. Defaults to none.
        env_class: ``DreamerEnv`` or a subclass of it (e.g. one whose reset adds the extra keys).
        env_kwargs: more keyword arguments of ``env_class``.

    Raises:
        ValueError: an extra observation named ``state`` or ``belief``.
    """
    extra = dict(extra_observations or {})
    clashes = sorted({"state", "belief"} & set(extra))
    if clashes:
        raise ValueError(f"extra_observations must not redefine {clashes}: state and belief are always there")
    env = env_class(
        world_model=world_model,
        prior_shape=torch.Size([state_dim]),
        belief_shape=torch.Size([belief_dim]),
        device=device,
        **(env_kwargs or {}),
    )
    shapes = {
        "state": (state_dim,),
        "belief": (belief_dim,),
        **{key: tuple(shape) for key, shape in extra.items()},
    }
    latent = Composite({key: Unbounded(shape, device=device) for key, shape in shapes.items()})
    env.action_spec = action_spec
    env.observation_spec = latent.clone()
    env.state_spec = latent.clone()
    env.reward_spec = Unbounded((1,), device=device)
    return env
