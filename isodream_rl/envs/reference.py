"""Reference policies that put a learner's return on a scale: uniform random, best constant action, scripted.

A return means little on its own: on sprites ``reach`` a policy that parks the agent in a corner already
scores far above a random one. Every task used for learning is therefore measured with three reference
policies, run on the raw gymnasium env (no TorchRL overhead) with the same episodes for each:

- ``random``: uniform actions in ``[-1, 1]``;
- ``constant``: the best of a fixed set of constant actions (:data:`CONSTANT_ACTIONS`, the 8 compass
  directions at full magnitude and zero), chosen by mean return;
- ``scripted``: a controller that reads the simulator's privileged state (:func:`scripted_action`):
  sprites steers straight at the target at full speed, ignoring the distractors; the highway keeps its lane
  at the speed limit, following a slower car ahead.

The **normalised score** of a return ``R`` is ``(R - R_constant) / (R_scripted - R_constant)``
(:func:`normalised_score`): 0 is the best constant action, 1 the scripted controller.

Each task also has its own success counts (:mod:`isodream_rl.envs.task_metrics`), reported beside the
return: reaches and contact steps per episode on sprites, metres driven and collisions on the highway.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from isodream_rl.envs.task_metrics import episode_metrics

#: The constant actions tried for the ``constant`` reference: zero and the 8 compass directions.
CONSTANT_ACTIONS: tuple[tuple[float, float], ...] = ((0.0, 0.0),) + tuple(
    (float(x), float(y)) for x, y in itertools.product((-1.0, 0.0, 1.0), repeat=2) if (x, y) != (0.0, 0.0)
)
#: The highway's scripted cruise speed (m/s): the road's speed limit.
HIGHWAY_CRUISE_SPEED = 30.0

Policy = Callable[[gym.Env, np.random.Generator], np.ndarray]


def scripted_action(env: gym.Env) -> np.ndarray:
    """The scripted controller's action in ``[-1, 1]``, from the env's privileged state.

    - sprites (``task="reach"``): ``(dx, dy)`` towards the target, each axis at full speed until it is
      aligned (ignores the distractors);
    - highway: steer back to the centre of the current lane and hold the speed limit
      (:data:`HIGHWAY_CRUISE_SPEED`) with proportional control, slowing down behind a slower car in the
      lane (about 1.5 s headway); it never changes lanes.

    Args:
        env: a ``SpritesEnv`` or ``HighwayIsoEnv`` (or a wrapper of one), after ``reset``.

    Raises:
        TypeError: for an env with no scripted controller (DMC).
    """
    from isodream_rl.envs.highway import HighwayIsoEnv
    from isodream_rl.envs.sprites import SpritesEnv

    base = env.unwrapped
    if isinstance(base, SpritesEnv):
        if base.task != "reach":
            raise TypeError(
                "the sprites scripted controller needs task='reach' (there is no target otherwise)"
            )
        step = base.agent_speed * base.image_size
        dy, dx = (base._target - base._agent) / max(step, 1e-9)
        return np.clip(np.array([dx, dy]), -1.0, 1.0).astype(np.float32)
    if isinstance(base, HighwayIsoEnv):
        ego = base.ego
        lane = ego.lane
        longitudinal, lateral = lane.local_coordinates(ego.position)
        heading_error = _wrap_angle(ego.heading - lane.heading_at(longitudinal))
        # Lateral offset is positive to the right of the lane centre; steer -1 turns left (towards -lateral).
        steer = -(0.15 * lateral + 1.5 * heading_error)
        throttle = 0.5 * (HIGHWAY_CRUISE_SPEED - ego.speed)
        leader = _leader(base)
        if leader is not None:
            gap, leader_speed = leader
            # Time-headway following: keep ~1.5 s plus 8 m behind the car ahead in the lane.
            desired = 8.0 + 1.5 * ego.speed
            throttle = min(throttle, 0.1 * (gap - desired) + 0.5 * (leader_speed - ego.speed))
        return np.clip(np.array([steer, throttle]), -1.0, 1.0).astype(np.float32)
    raise TypeError(f"no scripted controller for {type(base).__name__}")


def _leader(env) -> tuple[float, float] | None:
    """(bumper-to-bumper gap in metres, speed) of the nearest vehicle ahead in the ego's lane, if any."""
    ego = env.ego
    lane = ego.lane
    ego_s = lane.local_coordinates(ego.position)[0]
    best = None
    for vehicle in env.road.vehicles:
        if vehicle is ego or vehicle.lane_index != ego.lane_index:
            continue
        gap = lane.local_coordinates(vehicle.position)[0] - ego_s - 0.5 * (ego.LENGTH + vehicle.LENGTH)
        if gap > -0.5 * ego.LENGTH and (best is None or gap < best[0]):
            best = (float(gap), float(vehicle.speed))
    return best


def _wrap_angle(angle: float) -> float:
    return float((angle + np.pi) % (2 * np.pi) - np.pi)


def has_reference_policies(name: str, **env_kwargs: Any) -> bool:
    """Whether env ``name`` built with ``env_kwargs`` has a scripted controller (sprites ``reach``, highway)."""
    if name == "sprites":
        return env_kwargs.get("task", "none") == "reach"
    return name == "highway"


def run_reference_episodes(
    name: str, env: gym.Env, policy: Policy, *, episodes: int, seed: int
) -> tuple[list[float], list[dict[str, float]]]:
    """Run ``episodes`` episodes of ``policy(env, rng) -> action`` on the gymnasium env ``env`` (named ``name``).

    Episode ``k`` starts with ``env.reset(seed=seed + k)``, so every policy meets the same episodes.

    Returns:
        ``(returns, metrics)``: one float and one
        :func:`~isodream_rl.envs.task_metrics.episode_metrics` dict per episode.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    rng = np.random.default_rng(seed)
    returns, metrics = [], []
    for k in range(episodes):
        env.reset(seed=seed + k)
        total, infos, done = 0.0, [], False
        while not done:
            _, reward, terminated, truncated, info = env.step(policy(env, rng))
            total += float(reward)
            infos.append(info)
            done = terminated or truncated
        returns.append(total)
        metrics.append(episode_metrics(name, infos))
    return returns, metrics


def _summary(returns: list[float], metrics: list[dict[str, float]], **extra) -> dict[str, Any]:
    out = {"return": float(np.mean(returns)), "return_std": float(np.std(returns)), "returns": returns}
    for key in metrics[0] if metrics else ():
        out[key] = float(np.mean([m[key] for m in metrics]))
    out.update(extra)
    return out


def reference_returns(
    name: str,
    *,
    episodes: int = 20,
    seed: int = 0,
    constant_actions: Sequence[Sequence[float]] | None = None,
    **env_kwargs: Any,
) -> dict[str, dict[str, Any]]:
    """The three reference policies on env ``name`` (built with ``make_gym_env(name, **env_kwargs)``).

    Args:
        name: ``"sprites"`` or ``"highway"`` (the envs with a scripted controller).
        episodes: episodes per policy (and per candidate constant action).
        seed: episode ``k`` of every policy is ``reset(seed=seed + k)``.
        constant_actions: candidates of the constant reference; defaults to :data:`CONSTANT_ACTIONS` for a
            2-d action.
        **env_kwargs: the env's constructor arguments (e.g. ``task="reach"``).

    Returns:
        ``{"random": ..., "constant": ..., "scripted": ...}``, each with ``return`` (mean), ``return_std``,
        ``returns`` and the mean of each :func:`~isodream_rl.envs.task_metrics.episode_metrics` key;
        ``constant`` also has ``action``.
    """
    # the TorchRL builders load on first use (isodream_rl/envs/__init__.py)
    from isodream_rl.envs.builder import make_gym_env

    env = make_gym_env(name, **env_kwargs)
    try:
        low, high = env.action_space.low, env.action_space.high
        shape = env.action_space.shape

        def uniform(_env, rng):
            return rng.uniform(low, high, size=shape).astype(np.float32)

        out = {"random": _summary(*run_reference_episodes(name, env, uniform, episodes=episodes, seed=seed))}
        candidates = constant_actions if constant_actions is not None else CONSTANT_ACTIONS
        best = None
        for action in candidates:
            value = np.asarray(action, dtype=np.float32)
            if value.shape != shape:
                raise ValueError(
                    f"constant action {list(action)} does not have the env's action shape {shape}"
                )
            result = _summary(
                *run_reference_episodes(name, env, lambda _e, _r, v=value: v, episodes=episodes, seed=seed),
                action=[float(x) for x in value],
            )
            if best is None or result["return"] > best["return"]:
                best = result
        out["constant"] = best
        out["scripted"] = _summary(
            *run_reference_episodes(name, env, lambda e, _r: scripted_action(e), episodes=episodes, seed=seed)
        )
    finally:
        env.close()
    return out


def normalised_score(value: float, *, constant: float, scripted: float) -> float:
    """``(value - constant) / (scripted - constant)``: 0 is the best constant action, 1 the scripted policy.

    Raises:
        ValueError: when the scripted return does not exceed the constant one (the scale is undefined).
    """
    if not scripted > constant:
        raise ValueError(
            f"the scripted return {scripted} must exceed the constant-action return {constant} for a "
            "normalised score"
        )
    return (value - constant) / (scripted - constant)


__all__ = [
    "CONSTANT_ACTIONS",
    "has_reference_policies",
    "normalised_score",
    "reference_returns",
    "run_reference_episodes",
    "scripted_action",
]
