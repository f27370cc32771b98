"""A fast synthetic scene with ground-truth masks: one controllable sprite, moving distractors, a static background.

The scene mirrors the three kinds of dynamics Iso-Dream separates (paper §3.1): the agent sprite moves only
through the action (controllable), the distractor sprites move with constant velocity and bounce off the
borders (noncontrollable but predictable), and the textured background never changes within an episode
(static). Every frame comes with pixel-exact masks of the agent and of the distractors, so the masks a world
model learns can be scored against the truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

SPRITES_TASKS = ("none", "reach")
TARGET_STYLES = ("disc", "ring")
#: default sprite half-width as a fraction of the frame (a 9-pixel disc at 64x64)
SPRITE_SIZE = 0.06

#: Distractor colours by name, in the default order: saturated hues, none of them close to the agent's white
#: or the target's green.
DISTRACTOR_COLOURS = {
    "red": (230, 40, 40),
    "blue": (40, 90, 240),
    "yellow": (240, 200, 20),
    "magenta": (220, 40, 220),
    "cyan": (20, 210, 230),
    "orange": (250, 130, 20),
}
AGENT_COLOURS = {"white": (255, 255, 255), **DISTRACTOR_COLOURS}
_AGENT_BORDER = np.array([0, 0, 0], dtype=np.uint8)
_TARGET_COLOUR = np.array([30, 200, 60], dtype=np.uint8)


def _disc(radius: int) -> np.ndarray:
    """Boolean stamp of a filled disc, shape [2r+1, 2r+1]."""
    y, x = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return x * x + y * y <= radius * radius + radius


def _ring(radius: int) -> np.ndarray:
    """Boolean stamp of a two-pixel-wide ring, shape [2r+1, 2r+1]."""
    y, x = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    d2 = x * x + y * y
    return (d2 <= radius * radius + radius) & (d2 > (radius - 2) ** 2 + radius - 2)


def _check_arguments(
    *,
    task: str,
    image_size: int,
    num_distractors: int,
    max_steps: int,
    speeds: tuple[float, float],
    num_backgrounds: int | None,
    sprite_size: float,
    distractor_colours: Sequence[str] | None,
    agent_colour: str,
    target_style: str,
    progress_reward: float,
    render_mode: str | None,
) -> None:
    """Refuse an argument of :class:`SpritesEnv` out of its range, in one line naming it (``speeds``: the agent's
    and the distractors')."""
    if task not in SPRITES_TASKS:
        raise ValueError(f"Unknown sprites task {task!r}; expected one of {SPRITES_TASKS}.")
    if not isinstance(image_size, int) or image_size < 16:
        raise ValueError(f"image_size must be an int >= 16, got {image_size!r}.")
    if not 0 <= num_distractors <= len(DISTRACTOR_COLOURS):
        raise ValueError(f"num_distractors must be in [0, {len(DISTRACTOR_COLOURS)}], got {num_distractors}.")
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}.")
    agent_speed, distractor_speed = speeds
    if agent_speed < 0 or distractor_speed < 0:
        raise ValueError(f"speeds must be >= 0, got agent {agent_speed} and distractor {distractor_speed}.")
    if num_backgrounds is not None and (not isinstance(num_backgrounds, int) or num_backgrounds < 1):
        raise ValueError(f"num_backgrounds must be None or an int >= 1, got {num_backgrounds!r}.")
    if not 0.0 < sprite_size <= 0.2:
        raise ValueError(f"sprite_size must be in (0, 0.2] (a fraction of image_size), got {sprite_size!r}.")
    if distractor_colours is not None:
        unknown = [c for c in distractor_colours if c not in DISTRACTOR_COLOURS]
        if unknown or len(distractor_colours) != num_distractors:
            raise ValueError(
                f"distractor_colours must name one colour of {sorted(DISTRACTOR_COLOURS)} per distractor "
                f"({num_distractors}), got {list(distractor_colours)!r}."
            )
    if agent_colour not in AGENT_COLOURS:
        raise ValueError(f"agent_colour must be one of {sorted(AGENT_COLOURS)}, got {agent_colour!r}.")
    if target_style not in TARGET_STYLES:
        raise ValueError(f"target_style must be one of {TARGET_STYLES}, got {target_style!r}.")
    if not np.isfinite(progress_reward):
        raise ValueError(f"progress_reward must be a finite float, got {progress_reward!r}.")
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}.")


class SpritesEnv(gym.Env):
    """Agent sprite, bouncing distractor sprites and a static textured background, rendered with numpy.

    Scene (``S = image_size``):

    - **agent** (controllable): a white square with a black border, half-width
      ``radius = max(2, round(sprite_size * S))`` pixels.
      Its centre moves by ``agent_speed * S * action`` pixels per step and is clamped inside the frame.
    - **distractors** (noncontrollable): ``num_distractors`` coloured discs of the same radius, each moving
      with a constant speed ``distractor_speed * S`` pixels per step in a random direction, reflected by the
      borders.
    - **background** (static): a smooth random colour field plus a faint oriented stripe texture, fixed for
      the whole episode. By default every episode draws a new one from its random generator at reset; with
      ``num_backgrounds=N`` the episodes pick one of ``N`` backgrounds made once from ``background_seed``
      (a scene family whose backgrounds a world model can learn, like a DMC floor).
    - **target** (``task="reach"`` only): a green disc (``target_style="disc"``, the default) or a two-pixel
      ring (``"ring"``) that the agent has to reach; it respawns elsewhere when reached.

    Occlusion order, back to front: background, target, distractors (in index order), agent. The masks in
    ``info`` are the pixels where each sprite is visible in the final frame, so they never overlap:

    - ``info["mask_agent"]``: bool ``[S, S]``, the agent's pixels;
    - ``info["mask_distractors"]``: bool ``[S, S]``, the visible pixels of any distractor (agent pixels
      excluded);
    - ``info["mask_target"]``: bool ``[S, S]``, the visible pixels of the target (all ``False`` for
      ``task="none"``). The target is part of neither other mask: it is static between respawns and only
      moves when the agent reaches it;
    - ``info["distractor_ids"]``: uint8 ``[S, S]``, ``i + 1`` where distractor ``i`` is visible, else 0
      (``distractor_ids > 0`` is ``mask_distractors``).

    Tasks:

    - ``"none"``: reward 0; world-model data with random actions.
    - ``"reach"``: ``+reach_reward`` each time the agent's centre comes within ``2 * radius`` pixels of the
      target's centre (the target then respawns), ``-contact_penalty`` on every step the agent touches a
      distractor (centres closer than ``2 * radius``), and ``progress_reward * (d_{t-1} - d_t) / S`` where
      ``d`` is the agent's distance to the target it was heading for (measured before a respawn, so
      reaching never costs shaping reward). The shaping term is potential-based: it sums to
      ``progress_reward * d_spawn / S`` per target reached and to about zero for a policy that wanders or
      parks, so it does not change which policies are best; it gives a learner a signal on every step
      instead of on the few random reaches (0.2 per episode). The distractors cross the way to the target,
      so a policy that anticipates their motion scores higher than one that only reacts.

    ``info`` also carries ``"reached"`` and ``"touching"`` (bool). Episodes never terminate; they are
    truncated after ``max_steps`` steps.

    Args:
        image_size (int, optional): frame height and width ``S``, at least 16. Defaults to 64.
        num_distractors (int, optional): number of distractor sprites, 0 to 6. Defaults to 3.
        task (str, optional): ``"none"`` or ``"reach"``. Defaults to ``"none"``.
        max_steps (int, optional): steps before truncation. Defaults to 200.
        agent_speed (float, optional): agent displacement per step at ``|action| = 1``, as a fraction of
            ``S``. Defaults to 0.05.
        distractor_speed (float, optional): distractor speed per step, as a fraction of ``S``. Defaults
            to 0.03.
        reach_reward (float, optional): reward for reaching the target. Defaults to 1.0.
        contact_penalty (float, optional): penalty per step touching a distractor. Defaults to 0.5.
        progress_reward (float, optional): weight of the dense progress term (distance to the target gained
            this step, as a fraction of ``S``); 0 gives the sparse task. Defaults to 10.0 (about 0.5 per step
            at full speed straight at the target).
        target_style (str, optional): ``"disc"`` (filled, the default) or ``"ring"`` (two pixels wide).
        fixed_start (bool, optional): every episode starts with the agent a quarter of the frame from the
            top-left corner and the first target a quarter from the bottom-right one (later targets respawn
            at random): a task whose first reach needs no perception, to check that behavior learning works.
            Defaults to ``False`` (random positions).
        render_mode (str, optional): ``None`` or ``"rgb_array"``. Defaults to ``None``.
        num_backgrounds (int, optional): size of a fixed pool of backgrounds that episodes draw from;
            ``None`` draws a new background every episode. Defaults to ``None``.
        background_seed (int, optional): seed of the background pool (ignored without
            ``num_backgrounds``). Defaults to 0.
        sprite_size (float, optional): half-width of every sprite (agent, distractors, target) as a fraction
            of ``S``, in ``(0, 0.2]``. Defaults to 0.06 (a 9-pixel disc at ``S = 64``).
        distractor_colours (sequence of str, optional): the distractors' colours by name (keys of
            ``DISTRACTOR_COLOURS``), one per distractor, drawn in this order (later ones on top). Defaults to
            ``None``: the first ``num_distractors`` of red, blue, yellow, magenta, cyan, orange.
        agent_colour (str, optional): the agent's fill colour by name (keys of ``AGENT_COLOURS``: ``"white"``
            or a distractor colour; its border stays black). Defaults to ``"white"``.

    Observation: ``Box(0, 255, (S, S, 3), uint8)``, HWC. Action: ``Box(-1, 1, (2,), float32)``, ``(dx, dy)``.

    Examples:
        >>> env = SpritesEnv(task="reach")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, info["mask_agent"].shape
        ((64, 64, 3), (64, 64))
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        *,
        image_size: int = 64,
        num_distractors: int = 3,
        task: str = "none",
        max_steps: int = 200,
        agent_speed: float = 0.05,
        distractor_speed: float = 0.03,
        reach_reward: float = 1.0,
        contact_penalty: float = 0.5,
        progress_reward: float = 10.0,
        target_style: str = "disc",
        fixed_start: bool = False,
        render_mode: str | None = None,
        num_backgrounds: int | None = None,
        background_seed: int = 0,
        sprite_size: float = SPRITE_SIZE,
        distractor_colours: Sequence[str] | None = None,
        agent_colour: str = "white",
    ) -> None:
        _check_arguments(
            task=task,
            image_size=image_size,
            num_distractors=num_distractors,
            max_steps=max_steps,
            speeds=(agent_speed, distractor_speed),
            num_backgrounds=num_backgrounds,
            sprite_size=sprite_size,
            distractor_colours=distractor_colours,
            agent_colour=agent_colour,
            target_style=target_style,
            progress_reward=progress_reward,
            render_mode=render_mode,
        )
        self.image_size = image_size
        self.num_distractors = num_distractors
        self.task = task
        self.max_steps = max_steps
        self.agent_speed = agent_speed
        self.distractor_speed = distractor_speed
        self.reach_reward = reach_reward
        self.contact_penalty = contact_penalty
        self.progress_reward = float(progress_reward)
        self.target_style = target_style
        self.fixed_start = bool(fixed_start)
        self.render_mode = render_mode

        self.sprite_size = sprite_size
        self.distractor_colours = (
            tuple(distractor_colours)
            if distractor_colours is not None
            else tuple(DISTRACTOR_COLOURS)[:num_distractors]
        )
        self._colours = np.array([DISTRACTOR_COLOURS[c] for c in self.distractor_colours], dtype=np.uint8)
        self.agent_colour = agent_colour
        self._agent_rgb = np.array(AGENT_COLOURS[agent_colour], dtype=np.uint8)
        self.radius = max(2, round(sprite_size * image_size))
        side = 2 * self.radius + 1
        self._agent_fill = np.zeros((side, side), dtype=bool)
        self._agent_fill[1:-1, 1:-1] = True
        self._disc = _disc(self.radius)
        self._target_stamp = _disc(self.radius) if target_style == "disc" else _ring(self.radius)
        # Sprite centres stay in [lo, hi] so every stamp lies fully inside the frame: no clipping per step.
        self._lo = float(self.radius)
        self._hi = float(image_size - 1 - self.radius)

        self.observation_space = gym.spaces.Box(0, 255, (image_size, image_size, 3), dtype=np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)

        self.num_backgrounds = num_backgrounds
        self._background_pool = None
        if num_backgrounds is not None:
            pool_rng = np.random.default_rng(background_seed)
            self._background_pool = np.stack(
                [self._make_background(pool_rng) for _ in range(num_backgrounds)]
            )
        self._background = np.zeros((image_size, image_size, 3), dtype=np.uint8)
        self._frame = self._background
        self._agent = np.zeros(2)
        self._distractors = np.zeros((num_distractors, 2))
        self._velocities = np.zeros((num_distractors, 2))
        self._target = np.zeros(2)
        self._steps = -1  # -1 until the first reset

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Starts an episode: background, sprite positions, distractor velocities and target.

        Args:
            seed (int, optional): seeds the episode generator; the same seed gives the same episode under
                the same actions.
            options (dict, optional): unused.

        Returns:
            ``(obs, info)``: obs uint8 ``[S, S, 3]``; info with the masks described in the class docstring.
        """
        super().reset(seed=seed)
        rng = self.np_random
        if self._background_pool is None:
            self._background = self._make_background(rng)
        else:
            self._background = self._background_pool[rng.integers(len(self._background_pool))]
        self._agent = rng.uniform(self._lo, self._hi, size=2)
        self._distractors = rng.uniform(self._lo, self._hi, size=(self.num_distractors, 2))
        angles = rng.uniform(0.0, 2.0 * np.pi, size=self.num_distractors)
        speed = self.distractor_speed * self.image_size
        self._velocities = speed * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
        self._target = self._spawn_target(rng)
        if self.fixed_start:
            quarter = 0.25 * (self.image_size - 1)
            self._agent = np.full(2, quarter)
            self._target = np.full(2, self.image_size - 1 - quarter)
        self._steps = 0
        obs, info = self._render_with_masks()
        info["reached"] = False
        info["touching"] = self._touching()
        return obs, info

    def step(self, action):
        """Moves the agent by the action and the distractors by their velocities, then renders.

        Args:
            action (array-like): shape ``[2]``, ``(dx, dy)``, clipped to [-1, 1].

        Returns:
            ``(obs, reward, terminated, truncated, info)``; ``terminated`` is always ``False``.
        """
        if self._steps < 0:
            raise RuntimeError("SpritesEnv.step() called before reset().")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,):
            raise ValueError(f"SpritesEnv expects an action of shape (2,), got shape {action.shape}.")
        if not np.isfinite(action).all():
            raise ValueError(f"SpritesEnv got a non-finite action {action}.")
        step = self.agent_speed * self.image_size
        distance_before = float(np.sqrt(((self._agent - self._target) ** 2).sum()))
        # Action (dx, dy) is in image coordinates; positions are stored as (row, col) = (y, x).
        self._agent[0] += step * min(max(action[1], -1.0), 1.0)
        self._agent[1] += step * min(max(action[0], -1.0), 1.0)
        np.clip(self._agent, self._lo, self._hi, out=self._agent)
        self._move_distractors()
        self._steps += 1

        reward = 0.0
        reached = False
        touching = self._touching()
        if self.task == "reach":
            distance = float(np.sqrt(((self._agent - self._target) ** 2).sum()))
            reached = distance <= 2 * self.radius
            progress = (distance_before - distance) / self.image_size
            if reached:
                self._target = self._spawn_target(self.np_random)
            reward = (
                self.reach_reward * reached
                - self.contact_penalty * touching
                + self.progress_reward * progress
            )
        obs, info = self._render_with_masks()
        info["reached"] = reached
        info["touching"] = touching
        truncated = self._steps >= self.max_steps
        return obs, float(reward), False, truncated, info

    def render(self) -> np.ndarray | None:
        """Returns the last frame, uint8 ``[S, S, 3]``, when ``render_mode="rgb_array"``."""
        if self.render_mode == "rgb_array":
            return self._frame.copy()
        return None

    def _move_distractors(self) -> None:
        pos = self._distractors + self._velocities
        # Reflect at the borders: a centre that overshoots by d ends d inside, and its velocity flips.
        low = pos < self._lo
        high = pos > self._hi
        pos = np.where(low, 2 * self._lo - pos, pos)
        pos = np.where(high, 2 * self._hi - pos, pos)
        self._velocities = np.where(low | high, -self._velocities, self._velocities)
        self._distractors = np.clip(pos, self._lo, self._hi)

    def _touching(self) -> bool:
        if self.num_distractors == 0:
            return False
        d2 = ((self._distractors - self._agent) ** 2).sum(axis=-1)
        return bool((d2 < (2 * self.radius) ** 2).any())

    def _spawn_target(self, rng: np.random.Generator) -> np.ndarray:
        # Away from the agent, so a reach is never free; a bounded number of draws keeps reset fast.
        for _ in range(32):
            target = rng.uniform(self._lo, self._hi, size=2)
            if ((target - self._agent) ** 2).sum() > (6 * self.radius) ** 2:
                break
        return target

    def _make_background(self, rng: np.random.Generator) -> np.ndarray:
        """Smooth colour field (bilinear 5x5 grid) plus a faint oriented stripe texture, uint8 ``[S, S, 3]``."""
        size = self.image_size
        grid = rng.uniform(50.0, 170.0, size=(5, 5, 3))
        coords = np.linspace(0.0, 4.0, size)
        i0 = np.minimum(coords.astype(int), 3)
        w = coords - i0
        interp = np.zeros((size, 5))
        interp[np.arange(size), i0] = 1.0 - w
        interp[np.arange(size), i0 + 1] = w
        field = np.einsum("yi,ijc->yjc", interp, grid)
        field = np.einsum("yjc,xj->yxc", field, interp)
        angle = rng.uniform(0.0, np.pi)
        period = rng.uniform(4.0, 10.0)
        y, x = np.mgrid[0:size, 0:size]
        stripes = 12.0 * np.sin(2.0 * np.pi * (x * np.cos(angle) + y * np.sin(angle)) / period)
        return np.clip(field + stripes[..., None], 0, 255).astype(np.uint8)

    def _render_with_masks(self) -> tuple[np.ndarray, dict[str, Any]]:
        size, r = self.image_size, self.radius
        frame = self._background.copy()
        mask_target = np.zeros((size, size), dtype=bool)
        mask_distractors = np.zeros((size, size), dtype=bool)
        mask_agent = np.zeros((size, size), dtype=bool)
        ids = np.zeros((size, size), dtype=np.uint8)
        if self.task == "reach":
            y, x = np.rint(self._target).astype(int)
            mask_target[y - r : y + r + 1, x - r : x + r + 1] = self._target_stamp
            frame[mask_target] = _TARGET_COLOUR
        for i, (y, x) in enumerate(np.rint(self._distractors).astype(int)):
            sl = (slice(y - r, y + r + 1), slice(x - r, x + r + 1))
            frame[sl][self._disc] = self._colours[i]
            mask_distractors[sl] |= self._disc
            ids[sl][self._disc] = i + 1
        y, x = np.rint(self._agent).astype(int)
        sl = (slice(y - r, y + r + 1), slice(x - r, x + r + 1))
        frame[sl] = _AGENT_BORDER
        frame[sl][self._agent_fill] = self._agent_rgb
        mask_agent[sl] = True
        mask_distractors &= ~mask_agent
        ids[mask_agent] = 0
        mask_target &= ~(mask_agent | mask_distractors)
        self._frame = frame
        info = {
            "mask_agent": mask_agent,
            "mask_distractors": mask_distractors,
            "mask_target": mask_target,
            "distractor_ids": ids,
        }
        return frame, info
