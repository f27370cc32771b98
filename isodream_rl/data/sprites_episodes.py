"""Random-action episodes of the sprites scene, in TorchRL's replay layout, with ground-truth masks."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, SliceSampler, TensorDictReplayBuffer

from isodream_rl.envs.sprites import SpritesEnv


def collect_sprites_episodes(
    *,
    episodes: int,
    steps: int,
    seed: int = 0,
    action_hold: int = 1,
    num_distractors: int = 3,
    **scene: Any,
) -> TensorDict:
    """Roll out uniform random actions in :class:`~isodream_rl.envs.sprites.SpritesEnv`.

    ``action_hold``: each random action is kept for this many steps. With a new action every step (``1``)
    the agent jitters in place (its centre moves about 5 pixels in 15 steps, 20 with ``8``), so a window's
    first frames, which the static branch reads, already show it almost where it stays; held actions make it
    travel as far as the distractors do.

    ``num_distractors`` and ``scene`` (``num_backgrounds``, ``background_seed``, ``sprite_size``,
    ``distractor_colours``, ``agent_colour``, ``task``...) are :class:`~isodream_rl.envs.sprites.SpritesEnv`'s
    keywords (``num_backgrounds``: a fixed background pool; ``None``, the default, a new background per
    episode). The gymnasium env is stepped directly (cheaper per step than through a TorchRL wrapper;
    ``bench/env_speed.py`` measures both, docs/results/env_speed.json) and the result is laid out as TorchRL's
    collectors do it.

    Returns:
        a flat ``[episodes * steps]`` tensordict with ``"action"``, ``"is_init"``, ``"episode"`` and under
        ``"next"``: ``"pixels"`` uint8 ``[3, 64, 64]``, ``"reward"``, ``"terminated"``, ``"truncated"``,
        ``"done"``, and the ground-truth masks ``"mask_agent"``, ``"mask_distractors"`` bool ``[64, 64]`` and
        ``"distractor_ids"`` uint8 ``[64, 64]`` (``i + 1`` on distractor ``i``); with ``task="reach"`` also
        ``"mask_target"`` bool ``[64, 64]`` (the target's visible pixels).
    """
    env = SpritesEnv(num_distractors=num_distractors, max_steps=steps, **scene)
    n = episodes * steps
    pixels = np.empty((n, 64, 64, 3), np.uint8)
    agent = np.empty((n, 64, 64), bool)
    distractors = np.empty((n, 64, 64), bool)
    ids = np.empty((n, 64, 64), np.uint8)
    target = np.empty((n, 64, 64), bool) if env.task == "reach" else None
    actions = held_random_actions(seed, episodes=episodes, steps=steps, hold=action_hold, dim=2).numpy()
    rewards = np.empty((n, 1), np.float32)
    for episode in range(episodes):
        env.reset(seed=seed * 100_003 + episode)
        for t in range(steps):
            i = episode * steps + t
            obs, reward, _, _, info = env.step(actions[i])
            pixels[i], rewards[i] = obs, reward
            agent[i], distractors[i] = info["mask_agent"], info["mask_distractors"]
            ids[i] = info["distractor_ids"]
            if target is not None:
                target[i] = info["mask_target"]
    is_init = np.zeros((n, 1), bool)
    is_init[::steps] = True
    done = np.zeros((n, 1), bool)
    done[steps - 1 :: steps] = True
    truth = {} if target is None else {"mask_target": torch.from_numpy(target)}
    return TensorDict(
        {
            "action": torch.from_numpy(actions),
            "is_init": torch.from_numpy(is_init),
            "episode": torch.arange(episodes).repeat_interleave(steps),
            "next": {
                "pixels": torch.from_numpy(pixels).permute(0, 3, 1, 2).contiguous(),
                "reward": torch.from_numpy(rewards),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "truncated": torch.from_numpy(done),
                "done": torch.from_numpy(done),
                "mask_agent": torch.from_numpy(agent),
                "mask_distractors": torch.from_numpy(distractors),
                "distractor_ids": torch.from_numpy(ids),
                **truth,
            },
        },
        [n],
    )


def held_random_actions(seed: int, *, episodes: int, steps: int, hold: int, dim: int) -> torch.Tensor:
    """Uniform random actions in ``[-1, 1]``, each kept for ``hold`` steps: float32 ``[episodes * steps, dim]``
    (the draws of ``numpy.random.default_rng(seed)``)."""
    if hold < 1:
        raise ValueError(f"action_hold must be >= 1, got {hold}")
    draws = np.random.default_rng(seed).uniform(-1, 1, (episodes, -(-steps // hold), dim)).astype(np.float32)
    return torch.from_numpy(np.repeat(draws, hold, axis=1)[:, :steps].reshape(episodes * steps, dim))


def episode_windows(data: TensorDict, *, window: int) -> TensorDict:
    """Flat episode data ``[episodes * steps]`` cut into consecutive windows ``[episodes * steps / window, window]``.

    ``steps`` must be a multiple of ``window``. Each window starts with ``is_init=True`` (a copy: ``data`` is
    not changed), so a world model filters it from zero states.
    """
    windows = data.reshape(-1, window)
    is_init = windows["is_init"].clone()
    is_init[:, 0] = True
    windows.set("is_init", is_init)
    return windows


def model_input(windows: TensorDict) -> TensorDict:
    """The keys a world model reads from a window: ``"action"``, ``"is_init"``, ``("next", "pixels")``."""
    return windows.select("action", "is_init", ("next", "pixels"))


def make_window_buffer(data: TensorDict, *, batch_size: int, window: int) -> TensorDictReplayBuffer:
    """A TorchRL replay buffer sampling ``batch_size`` windows of ``window`` steps inside episodes.

    ``SliceSampler`` marks the first step of every sampled window with ``is_init=True`` by default
    (each window then starts from zero states, as the world model does anyway).
    """
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(data.shape[0]),
        sampler=SliceSampler(slice_len=window, traj_key="episode", strict_length=True),
        batch_size=batch_size * window,
    )
    buffer.extend(data)
    return buffer
