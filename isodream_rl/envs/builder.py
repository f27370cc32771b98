"""One builder for every isodream-rl environment, returning TorchRL envs with the keys the world model reads.

``make_env(name, **cfg)`` builds the gymnasium env, guards it against simulator faults, exposes it to TorchRL
(``GymPixelsEnv``) and appends the transforms every recipe needs:

- ``"pixels"``: uint8 ``[3, H, W]`` (CHW view of the gymnasium HWC frame, left uint8 so the replay buffer
  stores bytes and the world model normalises on the fly);
- ``"action"``: float32 in [-1, 1];
- ``"is_init"`` (``InitTracker``) and ``"step_count"`` (``StepCounter``);
- ``("next", "reward")``: float32 ``[1]``; ``done``/``terminated``/``truncated``;
- ``"sim_error"``: bool ``[]``, ``True`` on the step where the simulator raised (see ``SimulatorFaultGuard``);
- the info entries the task's success counts read (``isodream_rl.envs.task_metrics.TASK_METRICS``), float32
  ``[]``: ``"reached"`` and ``"touching"`` for sprites, ``"distance"`` and ``"collision_impulse"`` for the
  highway;
- with ``return_masks=True``, the env's ground-truth masks, bool ``[H, W]`` (:func:`ground_truth_mask_keys`).
  Every env names its controllable thing ``"mask_agent"`` and its moving noncontrollable things
  ``"mask_distractors"`` (the rest of the frame is background), the classes
  :func:`isodream_rl.evaluation.decomposition_scores` scores against; sprites adds ``"mask_target"``, DMC
  ``"mask_background"`` (the pixels showing the video, the same as its distractors), highway
  ``"mask_vehicles"`` (the other vehicles, the same as its distractors).

Any other registered gymnasium id with a ``Box`` action space works too: its ``rgb_array`` render, resized to
64x64, is the observation (``RenderedPixels``), so ``make_env("Pendulum-v1")`` trains like the built-in envs.

``GymPixelsEnv`` is a small ``EnvBase`` rather than TorchRL's ``GymWrapper``: it writes CHW pixels and the
info masks directly (the wrapper needs a ``PermuteTransform`` and an info-dict reader, which cost CPU every
step: docs/envs/index.md), and ``set_seed`` seeds the next reset exactly as ``gymnasium.Env.reset(seed=)``
does, where ``GymWrapper`` resets once at ``set_seed`` time.
"""

from __future__ import annotations

import functools
import inspect
import logging
import numbers
import os
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from PIL import Image
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, EnvCreator, InitTracker, ParallelEnv, StepCounter, TransformedEnv

from isodream_rl.envs.task_metrics import task_info_keys
from isodream_rl.process_settings import single_threaded_llvmpipe

logger = logging.getLogger(__name__)

SPRITES_MASK_KEYS = ("mask_agent", "mask_distractors", "mask_target")
DMC_MASK_KEYS = ("mask_agent", "mask_distractors", "mask_background")
HIGHWAY_MASK_KEYS = ("mask_agent", "mask_distractors", "mask_vehicles")
_DONE_KEYS = ("done", "terminated", "truncated")


class SimulatorFaultGuard(gym.Wrapper):
    """Turns an exception raised by the simulator during a step into the end of that episode.

    Long training runs should not die because a physics engine or a renderer fails once in a million steps.
    When the wrapped env's ``step`` raises, the guard logs a warning naming the env, the step and the
    exception, and returns the last good observation with reward 0, ``terminated=False``,
    ``truncated=True`` and ``info["sim_error"] = True`` (``False`` on every other step and at reset). The
    next ``reset`` starts a fresh episode; an exception in ``reset`` itself is not caught, since there is no
    observation to fall back to.

    The guard also checks the action before the simulator sees it, so a wrong action shape is reported as a
    ``ValueError`` naming the expected shape instead of being mistaken for a simulator fault, and rescales
    actions from [-1, 1] to the env's own bounds when they differ.

    Args:
        env (gymnasium.Env): an env with a ``Box`` action space.
        name (str, optional): name used in the log line. Defaults to the env's class name.
    """

    def __init__(self, env: gym.Env, *, name: str | None = None) -> None:
        super().__init__(env)
        space = env.action_space
        self.name = name or getattr(env.spec, "id", None) or type(env.unwrapped).__name__
        if not isinstance(space, gym.spaces.Box):
            discrete = isinstance(
                space, (gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)
            )
            raise ValueError(
                f"{self.name} has a {'discrete' if discrete else 'non-continuous'} action space ({space}), and the "
                "agents here act with continuous "
                "actions in [-1, 1]: give an env whose action space is continuous (a gymnasium Box), such as "
                "Pendulum-v1"
            )
        self._low = space.low.astype(np.float64)
        self._high = space.high.astype(np.float64)
        self._rescale = not (np.all(self._low == -1.0) and np.all(self._high == 1.0))
        self.action_space = gym.spaces.Box(-1.0, 1.0, space.shape, dtype=np.float32)
        self._last_obs: Any = None
        self._last_info: dict[str, Any] = {}
        self._episode_steps = 0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        info = dict(info, sim_error=False)
        self._last_obs, self._last_info, self._episode_steps = obs, info, 0
        return obs, info

    def step(self, action):
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"{self.name} expects an action of shape {self.action_space.shape}, got shape {action.shape}."
            )
        if self._rescale:
            action = (self._low + (action + 1.0) * 0.5 * (self._high - self._low)).astype(np.float32)
        self._episode_steps += 1
        try:
            obs, reward, terminated, truncated, info = self.env.step(action)
        except Exception as err:  # any simulator failure ends the episode, see the docstring
            logger.warning(
                "%s: the simulator raised %s: %s at step %d of the episode; ending the episode "
                "(truncated=True, info['sim_error']=True).",
                self.name,
                type(err).__name__,
                err,
                self._episode_steps,
            )
            return self._last_obs, 0.0, False, True, dict(self._last_info, sim_error=True)
        info = dict(info, sim_error=False)
        self._last_obs, self._last_info = obs, info
        return obs, reward, terminated, truncated, info


class RenderedPixels(gym.ObservationWrapper):
    """A gymnasium env observed through its ``rgb_array`` render, resized to ``size`` x ``size`` (bilinear).

    Args:
        env (gymnasium.Env): made with ``render_mode="rgb_array"``; its own observation is dropped.
        size (int, optional): side of the square frame. Defaults to 64, the world model's input.
    """

    def __init__(self, env: gym.Env, *, size: int = 64) -> None:
        if env.render_mode != "rgb_array":
            raise ValueError(
                f"RenderedPixels needs an env made with render_mode='rgb_array', got {env.render_mode!r}."
            )
        super().__init__(gym.wrappers.AddRenderObservation(env, render_only=True))
        self.size = size
        self.observation_space = gym.spaces.Box(0, 255, (size, size, 3), dtype=np.uint8)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        frame = Image.fromarray(np.asarray(observation, dtype=np.uint8)[..., :3])
        return np.array(frame.resize((self.size, self.size), Image.BILINEAR))


class GymPixelsEnv(EnvBase):
    """A gymnasium env with HxWx3 uint8 frames and a [-1, 1] ``Box`` action, as a TorchRL ``EnvBase``.

    Output keys: ``"pixels"`` uint8 ``[3, H, W]``, ``"sim_error"`` bool ``[]`` (from ``SimulatorFaultGuard``,
    ``False`` when the env has no such info), the ``mask_keys`` info entries as bool ``[H, W]``, the
    ``info_keys`` entries as float32 ``[]`` (0 at reset), and
    ``reward`` float32 ``[1]``, ``done``/``terminated``/``truncated`` bool ``[1]``. ``set_seed(s)`` makes the
    next reset ``env.reset(seed=s)``; later resets continue the env's own generator.

    Args:
        env (gymnasium.Env): observation ``Box(0, 255, (H, W, 3), uint8)``, action ``Box(-1, 1, (A,))``.
        device (torch.device or str, optional): device of the output tensors. Defaults to ``"cpu"``.
        mask_keys (tuple of str, optional): bool ``[H, W]`` info entries copied into the output.
        info_keys (tuple of str, optional): scalar info entries copied into the output as float32 ``[]``.
    """

    def __init__(
        self,
        env: gym.Env,
        *,
        device: torch.device | str = "cpu",
        mask_keys: tuple[str, ...] = (),
        info_keys: tuple[str, ...] = (),
    ) -> None:
        obs_space, act_space = env.observation_space, env.action_space
        if not (
            isinstance(obs_space, gym.spaces.Box)
            and obs_space.dtype == np.uint8
            and obs_space.shape[2:] == (3,)
        ):
            raise ValueError(f"GymPixelsEnv needs an HxWx3 uint8 Box observation, got {obs_space}.")
        if not (
            isinstance(act_space, gym.spaces.Box)
            and len(act_space.shape) == 1
            and (act_space.low == -1).all()
            and (act_space.high == 1).all()
        ):
            raise ValueError(
                f"GymPixelsEnv needs a Box(-1, 1, (A,)) action space, got {act_space}; "
                "SimulatorFaultGuard rescales other bounds."
            )
        super().__init__(device=device, batch_size=())
        self.env = env
        self.mask_keys = tuple(mask_keys)
        self.info_keys = tuple(info_keys)
        height, width = obs_space.shape[:2]
        observations = {
            "pixels": Bounded(0, 255, (3, height, width), dtype=torch.uint8, device=device),
            "sim_error": Categorical(2, shape=(), dtype=torch.bool, device=device),
        }
        for key in self.mask_keys:
            observations[key] = Binary(shape=(height, width), dtype=torch.bool, device=device)
        for key in self.info_keys:
            observations[key] = Unbounded(shape=(), dtype=torch.float32, device=device)
        self.observation_spec = Composite(observations)
        self.action_spec = Bounded(-1.0, 1.0, act_space.shape, dtype=torch.float32, device=device)
        self.reward_spec = Unbounded((1,), dtype=torch.float32, device=device)
        self.full_done_spec = Composite(
            {key: Categorical(2, shape=(1,), dtype=torch.bool, device=device) for key in _DONE_KEYS}
        )
        self._next_seed: int | None = None

    def _observation(self, obs: np.ndarray, info: dict[str, Any]) -> dict[str, torch.Tensor]:
        out = {
            # A copy, not a view: a renderer may hand out the same buffer again at the next step.
            "pixels": torch.from_numpy(obs).permute(2, 0, 1).contiguous(),
            "sim_error": torch.tensor(bool(info.get("sim_error", False))),
        }
        for key in self.mask_keys:
            out[key] = torch.from_numpy(np.asarray(info[key], dtype=bool))
        for key in self.info_keys:
            # Reset infos carry no step outcome (e.g. no reach yet): 0.
            out[key] = torch.tensor(float(info.get(key, 0.0)), dtype=torch.float32)
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        obs, info = self.env.reset(seed=self._next_seed)
        self._next_seed = None
        out = self._observation(obs, info)
        for key in _DONE_KEYS:
            out[key] = torch.zeros(1, dtype=torch.bool)
        return TensorDict(out, batch_size=(), device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy()
        obs, reward, terminated, truncated, info = self.env.step(action)
        out = self._observation(obs, info)
        out["reward"] = torch.tensor([float(reward)], dtype=torch.float32)
        out["terminated"] = torch.tensor([bool(terminated)])
        out["truncated"] = torch.tensor([bool(truncated)])
        out["done"] = torch.tensor([bool(terminated or truncated)])
        return TensorDict(out, batch_size=(), device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._next_seed = seed

    def close(self, *, raise_if_closed: bool = True) -> None:
        self.env.close()
        super().close(raise_if_closed=raise_if_closed)


def wrap_gym_env(
    env: gym.Env,
    *,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    mask_keys: tuple[str, ...] = (),
    info_keys: tuple[str, ...] = (),
    name: str | None = None,
) -> TransformedEnv:
    """Wraps a gymnasium env with an HxWx3 uint8 observation into the TorchRL env ``make_env`` returns.

    Args:
        env (gymnasium.Env): observation ``Box(0, 255, (H, W, 3), uint8)``, ``Box`` action.
        seed (int, optional): the first reset is ``env.reset(seed=seed)``; later resets continue the env's
            generator, so the sequence of episodes is reproducible. Defaults to ``None`` (unseeded).
        device (torch.device or str, optional): device of the output tensors. Defaults to ``"cpu"``.
        mask_keys (tuple of str, optional): bool ``[H, W]`` info entries copied into the step output.
            Defaults to none.
        info_keys (tuple of str, optional): scalar info entries copied into the step output as float32 ``[]``.
            Defaults to none.
        name (str, optional): name used in fault log lines.

    Returns:
        TransformedEnv: ``GymPixelsEnv(SimulatorFaultGuard(env))`` with ``InitTracker`` and ``StepCounter``.
    """
    base = GymPixelsEnv(
        SimulatorFaultGuard(env, name=name), device=device, mask_keys=mask_keys, info_keys=info_keys
    )
    transformed = TransformedEnv(base, Compose(InitTracker(), StepCounter()))
    if seed is not None:
        transformed.set_seed(seed)
    return transformed


@functools.cache
def dmc_env_names() -> dict[str, tuple[str, str]]:
    """Maps every ``"dmc_<domain>_<task>"`` name to its ``(domain, task)``, for all dm_control suite tasks."""
    from isodream_rl.envs.registration import DMC_SUITE_TASKS

    pairs = (name.split("-") for name in DMC_SUITE_TASKS)
    return {f"dmc_{domain}_{task}": (domain, task) for domain, task in pairs}


def env_names() -> list[str]:
    """The built-in names ``make_env`` accepts: ``"sprites"``, ``"highway"`` and ``"dmc_<domain>_<task>"`` (any
    registered gymnasium id works as well)."""
    return ["sprites", "highway", *dmc_env_names()]


def ground_truth_mask_keys(name: str) -> tuple[str, ...]:
    """The ground-truth masks ``make_env(name, return_masks=True)`` adds to every step (bool ``[H, W]``), or
    ``()`` for an env without them (a gymnasium id): always ``"mask_agent"`` and ``"mask_distractors"``
    first, then the env's own."""
    if name == "sprites":
        return SPRITES_MASK_KEYS
    if name == "highway":
        return HIGHWAY_MASK_KEYS
    return DMC_MASK_KEYS if name in dmc_env_names() else ()


def _check_name(name: str) -> None:
    if name not in ("sprites", "highway") and name not in dmc_env_names() and name not in gym.registry:
        raise ValueError(
            f"Unknown env name {name!r}. Valid names: 'sprites', 'highway', 'dmc_<domain>_<task>' (one of: "
            f"{', '.join(dmc_env_names())}) or a registered gymnasium id."
        )


def make_gym_env(name: str, **cfg: Any) -> gym.Env:
    """Builds the raw gymnasium env behind ``make_env(name, **cfg)`` (HWC uint8 frames, no guard). As there,
    highway and DMC compute their ground-truth masks only when ``cfg`` asks (``masks=True``).

    Args:
        name (str): see ``env_names()``, or a registered gymnasium id (seen through ``RenderedPixels``).
        **cfg: constructor arguments of ``SpritesEnv``, ``HighwayIsoEnv`` or ``DMCBackgroundEnv``, or
            ``gymnasium.make`` keywords.

    Raises:
        ValueError: for an unknown name, listing the valid ones.
        TypeError: a keyword of the wrong type for the built-in envs (e.g. ``vehicles_count='many'``), naming it.
    """
    _check_name(name)
    if name == "highway" or name in dmc_env_names():
        cfg = {"masks": False, **cfg}  # a render pass per step: only when asked for
    if name == "sprites":
        from isodream_rl.envs.sprites import SpritesEnv

        return SpritesEnv(**_checked_kwargs(SpritesEnv, name, cfg))
    if name == "highway":
        from isodream_rl.envs.highway import HighwayIsoEnv

        return HighwayIsoEnv(**_checked_kwargs(HighwayIsoEnv, name, cfg))
    if name not in dmc_env_names():
        return RenderedPixels(gym.make(name, render_mode="rgb_array", **cfg))
    from isodream_rl.envs.dmc import DMCBackgroundEnv

    domain, task = dmc_env_names()[name]
    return DMCBackgroundEnv(domain=domain, task=task, **_checked_kwargs(DMCBackgroundEnv, name, cfg))


def _checked_kwargs(env_class: type, name: str, cfg: dict[str, Any]) -> dict[str, Any]:
    """``cfg``, once every keyword whose default is a number, a bool or a string is found to have that kind
    of value; an env's own checks would otherwise fail inside numpy without naming the keyword.

    Raises:
        TypeError: naming the keyword, its value and the expected kind.
    """
    parameters = inspect.signature(env_class.__init__).parameters
    for key, value in cfg.items():
        parameter = parameters.get(key)
        default = None if parameter is None else parameter.default
        if isinstance(default, bool):
            expected, ok = "a bool", isinstance(value, bool)
        elif isinstance(default, numbers.Real):
            expected = "a number"
            ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
        elif isinstance(default, str):
            expected, ok = "a string", isinstance(value, str)
        else:
            continue
        if not ok:
            raise TypeError(f"make_env({name!r}): {key}={value!r} must be {expected} (default {default!r})")
    return cfg


def make_env(
    name: str,
    *,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    return_masks: bool = False,
    any_image_size: bool = False,
    **cfg: Any,
) -> TransformedEnv:
    """Builds a TorchRL env by name, with uint8 ``"pixels"`` ``[3, H, W]`` and float32 actions in [-1, 1].

    Args:
        name (str): ``"sprites"``, ``"highway"``, ``"dmc_<domain>_<task>"`` (e.g. ``"dmc_walker_walk"``) or a
            registered gymnasium id with a ``Box`` action space (observed through its render, 64x64).
        seed (int, optional): seeds the env; the same seed gives the same episodes under the same actions.
        device (torch.device or str, optional): device of the output tensors. Defaults to ``"cpu"``.
        return_masks (bool, optional): add the ground-truth masks (bool ``[H, W]``) to every step:
            :func:`ground_truth_mask_keys` (``"mask_agent"``, ``"mask_distractors"`` and the env's own).
            Highway and DMC compute their masks only then (their ``masks`` keyword). Gymnasium ids have
            none. Defaults to ``False``.
        any_image_size (bool, optional): allow an ``image_size`` other than 64. The world model reads
            ``[3, 64, 64]`` frames, so other sizes are refused unless set (for models of your own).
            Defaults to ``False``.
        **cfg: passed to the env class, e.g. ``task="reach"`` (sprites), ``view="top_down"``,
            ``vehicles_count=20`` (highway), ``background="video_hard"`` (dmc).

    Returns:
        TransformedEnv: keys listed in this module's docstring.

    Raises:
        ValueError: unknown name (the message lists the valid ones), ``return_masks`` on an env without
            ground-truth masks, or an ``image_size`` other than 64 without ``any_image_size``.
        TypeError: ``seed`` not an int, or a keyword of the wrong type (named).

    Examples:
        >>> env = make_env("sprites", seed=0, task="reach", return_masks=True)
        >>> td = env.rollout(3)
        >>> td["next", "pixels"].shape, td["next", "mask_agent"].shape
        (torch.Size([3, 3, 64, 64]), torch.Size([3, 64, 64]))
    """
    _check_name(name)
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, numbers.Integral)):
        raise TypeError(f"make_env({name!r}): seed={seed!r} must be an int or None")
    image_size = cfg.get("image_size", 64)
    if image_size != 64 and not any_image_size:
        raise ValueError(
            f"make_env({name!r}): image_size={image_size!r}, but the world model reads [3, 64, 64] frames; "
            "leave image_size at 64, or pass any_image_size=True for a model of your own"
        )
    mask_keys = ground_truth_mask_keys(name)
    if return_masks and not mask_keys:
        raise ValueError(
            f"return_masks=True needs ground-truth masks: 'sprites', 'highway' and 'dmc_*' have them, "
            f"{name!r} not."
        )
    if return_masks and (name == "highway" or name in dmc_env_names()):
        cfg.setdefault("masks", True)
    env = make_gym_env(name, **cfg)
    return wrap_gym_env(
        env,
        seed=seed,
        device=device,
        mask_keys=mask_keys if return_masks else (),
        info_keys=task_info_keys(name),
        name=name,
    )


def make_parallel_env(
    name: str,
    *,
    num_workers: int,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    mp_start_method: str | None = None,
    **cfg: Any,
) -> ParallelEnv:
    """Runs ``num_workers`` copies of ``make_env(name, **cfg)`` in worker processes (TorchRL ``ParallelEnv``).

    Args:
        name (str): see ``make_env``.
        num_workers (int): number of worker processes, >= 1.
        seed (int, optional): worker 0 is seeded with ``seed``, each next worker with the seed TorchRL's
            ``set_seed`` chain derives from the previous one (distinct and deterministic).
        device (torch.device or str, optional): device of the output tensors. Defaults to ``"cpu"``.
        mp_start_method (str, optional): ``"fork"`` starts workers in about a second; TorchRL's default
            (``"spawn"``) re-imports torch in each worker, which takes 10+ s on a busy 2-core machine. Envs
            rendered with OpenGL (DMC, highway first-person) can fork only with ``LP_NUM_THREADS=0``, the default
            ``isodream_rl.envs`` sets.
        **cfg: passed to ``make_env``.

    Returns:
        ParallelEnv: batch size ``[num_workers]``, same keys as ``make_env``.

    Raises:
        ValueError: for ``num_workers < 1``, an unknown name, or ``"fork"`` with an OpenGL env while llvmpipe
            runs worker threads (a forked worker would hang at its first render).
    """
    if num_workers < 1:
        raise ValueError(f"num_workers must be >= 1, got {num_workers}.")
    _check_name(name)  # here, with the list of valid names, rather than inside a worker
    uses_gl = name.startswith("dmc_") or (
        name == "highway" and cfg.get("view", "first_person") == "first_person"
    )
    if mp_start_method == "fork" and uses_gl:
        single_threaded_llvmpipe()
    llvmpipe_threads = os.environ.get("LP_NUM_THREADS", "")
    if mp_start_method == "fork" and uses_gl and llvmpipe_threads != "0":
        raise ValueError(
            f"mp_start_method='fork' with {name!r}, which renders with OpenGL, needs LP_NUM_THREADS=0 (got "
            f"{llvmpipe_threads or 'unset'}): Mesa's llvmpipe worker threads do not survive fork and a forked "
            "worker hangs at its first render. Set LP_NUM_THREADS=0 (or leave it unset) before the process makes "
            "its first GL context, or use mp_start_method='spawn'."
        )
    env = ParallelEnv(
        num_workers,
        EnvCreator(functools.partial(make_env, name, device=device, **cfg)),
        mp_start_method=mp_start_method,
    )
    if seed is not None:
        env.set_seed(seed)
    return env


__all__ = [
    "DMC_MASK_KEYS",
    "GymPixelsEnv",
    "RenderedPixels",
    "SPRITES_MASK_KEYS",
    "SimulatorFaultGuard",
    "HIGHWAY_MASK_KEYS",
    "env_names",
    "ground_truth_mask_keys",
    "make_env",
    "make_gym_env",
    "make_parallel_env",
    "wrap_gym_env",
]
