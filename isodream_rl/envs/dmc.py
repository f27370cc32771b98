"""DeepMind Control Suite from 64x64 pixels, with moving natural backgrounds (DMControl-GB style).

Iso-Dream's DMC experiments use DMControl-GB's ``video_easy``: the sky is replaced by a natural video that
moves independently of the agent, a noncontrollable distractor. This env reproduces that offline:

* ``"video_easy"``: the skybox is replaced by the video, the floor is kept;
* ``"video_hard"``: the floor (every surface drawn with the suite's ``grid`` material) is replaced too;
* ``"none"``: the plain task.

Compositing is an exact colour key. Before the GL context is created, the skybox texture is painted pure
green (0, 255, 0) and the sky haze switched off; with MSAA off (``offsamples=0``) no pixel blends the key
with a neighbour, so "pixel == key" is exactly "the skybox is visible here". For ``"video_hard"`` the floor
material is made unlit key green (emission 1, no texture, specular or reflection): the floor still
occludes whatever is below it, so the pixels outside the mask are exactly those of the ``"none"`` render.
One render per agent step, no segmentation pass.
"""

from __future__ import annotations

import os
import sys
import warnings
from typing import Any

from isodream_rl.process_settings import dm_control_gl

if "dm_control" in sys.modules and "MUJOCO_GL" not in os.environ:
    warnings.warn(
        "dm_control was imported before isodream_rl.envs.dmc with MUJOCO_GL unset, so it renders with GLFW, "
        "which fails without a display. Run with MUJOCO_GL=egl in the environment.",
        stacklevel=2,
    )
# dm_control fixes (and initialises) its GL backend at import
dm_control_gl()

import gymnasium  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from dm_control import suite  # noqa: E402
from dm_control.mujoco.engine import Camera  # noqa: E402

from isodream_rl.envs.backgrounds import SPLITS, VIDEO_SOURCES, BackgroundVideos  # noqa: E402
from isodream_rl.envs.registration import BACKGROUNDS, DMC_SUITE_TASKS  # noqa: E402

__all__ = ["BACKGROUNDS", "DMCBackgroundEnv", "dmc_tasks"]


_KEY = np.array([0, 255, 0], dtype=np.uint8)
_FLOOR_MATERIAL = "grid"


def dmc_tasks() -> list[str]:
    """Valid ``"domain-task"`` names: ``dm_control.suite.ALL_TASKS``."""
    return list(DMC_SUITE_TASKS)


def _paint_key(model: Any, background: str) -> None:
    """Recolours the parts the video replaces in key green. Must run before the first render."""
    skyboxes = [t for t in range(model.ntex) if model.tex_type[t] == mujoco.mjtTexture.mjTEXTURE_SKYBOX]
    if not skyboxes:
        raise ValueError("video backgrounds need a skybox texture, and this model has none")
    for tex in skyboxes:
        start = model.tex_adr[tex]
        channels = model.tex_nchannel[tex]
        texels = model.tex_data[start : start + model.tex_width[tex] * model.tex_height[tex] * channels]
        texels = texels.reshape(-1, channels)
        texels[:, :3] = _KEY
    # Haze blends the sky near the horizon towards the haze colour, which would break the key.
    model.vis.map.haze = 0.0
    if background == "video_hard":
        floor = mujoco.mj_name2id(model.ptr, mujoco.mjtObj.mjOBJ_MATERIAL, _FLOOR_MATERIAL)
        if floor < 0:
            raise ValueError(f"video_hard needs the suite's {_FLOOR_MATERIAL!r} floor material; none found")
        # Unlit pure green: ambient, diffuse and shadows scale the rgba, whose red and blue are 0, and the
        # emission alone saturates green, so every floor pixel is exactly the key.
        model.mat_texid[floor] = -1
        model.mat_rgba[floor] = (0.0, 1.0, 0.0, 1.0)
        model.mat_emission[floor] = 1.0
        model.mat_specular[floor] = 0.0
        model.mat_reflectance[floor] = 0.0


class DMCBackgroundEnv(gymnasium.Env):
    """A DeepMind Control Suite task seen in 64x64 RGB, optionally behind a moving natural background.

    Rewards are summed over the action repeat, as in DMControl-GB and Iso-Dream. The episode is truncated
    after ``max_sim_steps`` simulator steps (1000, i.e. 500 agent steps at action repeat 2) or when the
    suite's own time limit ends it first; a task that ends with discount 0 is terminated.

    Args:
        domain (str): suite domain, e.g. ``"walker"``.
        task (str): suite task, e.g. ``"walk"``; see :func:`dmc_tasks`.
        background (str): one of :data:`BACKGROUNDS`. Defaults to ``"video_easy"``.
        action_repeat (int): simulator steps per agent step. Defaults to 2.
        image_size (int): side of the square observation, rendered natively. Defaults to 64.
        camera_id (int, optional): suite camera; ``None`` picks 2 for quadruped and 0 otherwise.
        video_split (str): ``"train"`` or ``"eval"``, disjoint sets of background videos.
        render_mode (str, optional): ``None`` or ``"rgb_array"`` (returns the last observation).
        video_source (str): ``"natural"`` (photos and clips shipped in installed packages) or
            ``"procedural"`` (noise pictures that need nothing). Defaults to ``"natural"``.
        max_sim_steps (int): simulator steps before truncation. Defaults to 1000.
        shadows (bool): cast shadows. Defaults to ``True`` (the suite's look). ``False`` cuts the step time by
            a third to a half on llvmpipe (the shadow pass is about half of a render), but changes the picture.
        masks (bool): add the robot's mask and the distractors' to ``info`` (below; a segmentation pass per
            agent step). Defaults to ``True`` (``make_env`` and ``make_gym_env``: off unless
            ``return_masks=True``).

    Observations are uint8 [image_size, image_size, 3] (HWC, RGB); actions are float32 in [-1, 1]^A,
    rescaled to the task's bounds (values outside are clipped). ``info["mask_background"]`` is a bool
    [image_size, image_size] array marking the pixels that show the video. With ``masks=True``, also bool
    [image_size, image_size], exact to the pixel:

    * ``info["mask_agent"]``: the robot, every geom of a body other than the world body, from MuJoCo's
      segmentation pass of the same frame (not the complement of ``mask_background``: with ``"video_easy"``
      the floor stays, and it is neither robot nor video);
    * ``info["mask_distractors"]``: the moving noncontrollable pixels, ``mask_background`` under the name
      every env uses (:func:`isodream_rl.evaluation.decomposition_scores`); all ``False`` for ``"none"``.

    Examples:
        >>> env = DMCBackgroundEnv(domain="walker", task="walk", video_source="procedural")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, info["mask_background"].shape
        ((64, 64, 3), (64, 64))
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> env.close()
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        *,
        domain: str,
        task: str,
        background: str = "video_easy",
        action_repeat: int = 2,
        image_size: int = 64,
        camera_id: int | None = None,
        video_split: str = "train",
        render_mode: str | None = None,
        video_source: str = "natural",
        max_sim_steps: int = 1000,
        shadows: bool = True,
        masks: bool = True,
    ) -> None:
        if (domain, task) not in suite.ALL_TASKS:
            raise ValueError(f"unknown DMC task {domain}-{task}; valid tasks: {', '.join(dmc_tasks())}")
        if background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS}, got {background!r}")
        if video_split not in SPLITS:
            raise ValueError(f"video_split must be one of {SPLITS}, got {video_split!r}")
        if video_source not in VIDEO_SOURCES:
            raise ValueError(f"video_source must be one of {VIDEO_SOURCES}, got {video_source!r}")
        if action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        if image_size < 1:
            raise ValueError(f"image_size must be >= 1, got {image_size}")
        if max_sim_steps < 1:
            raise ValueError(f"max_sim_steps must be >= 1, got {max_sim_steps}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.domain, self.task, self.background = domain, task, background
        self.action_repeat = action_repeat
        self.max_sim_steps = max_sim_steps
        self.render_mode = render_mode
        self.masks = bool(masks)

        self._env = suite.load(domain, task, task_kwargs={"random": 0})
        physics = self._env.physics
        model = physics.model
        camera_id = (2 if domain == "quadruped" else 0) if camera_id is None else camera_id
        if not 0 <= camera_id < model.ncam:
            raise ValueError(f"camera_id must be in [0, {model.ncam}) for {domain}, got {camera_id}")
        self.camera_id = camera_id
        # Fast llvmpipe settings, the same picture within 1/255 (docs/envs/dmc.md): no MSAA, a 256 px shadow map,
        # capsules and spheres of 12 x 6 facets instead of 28 x 16 (at 64x64, llvmpipe spends most of a frame
        # transforming vertices) and an offscreen buffer of the image size instead of 640x480. The GL context
        # reads them, and the skybox texture, when the first Camera creates it.
        quality = model.vis.quality
        quality.offsamples = 0
        quality.shadowsize = 256
        quality.numslices = min(quality.numslices, 12)
        quality.numstacks = min(quality.numstacks, 6)
        model.vis.global_.offwidth = model.vis.global_.offheight = image_size
        if not shadows:
            model.light_castshadow[:] = 0
        if background != "none":
            _paint_key(model, background)
        self.image_size = image_size
        # One Camera reused for the whole life of the env (physics.render() would rebuild it every frame), made
        # with its GL context at the first render: a ParallelEnv builds an env in the parent only to read specs.
        self._camera: Camera | None = None

        self._videos = (
            BackgroundVideos(split=video_split, size=image_size, video_source=video_source)
            if background != "none"
            else None
        )
        self.video_split = video_split
        self.video_sources = self._videos.sources if self._videos is not None else ()
        self.current_video: str | None = None

        spec = self._env.action_spec()
        self._action_low = spec.minimum.astype(np.float64)
        self._action_high = spec.maximum.astype(np.float64)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, shape=spec.shape, dtype=np.float32)
        self.observation_space = gymnasium.spaces.Box(
            0, 255, shape=(image_size, image_size, 3), dtype=np.uint8
        )
        self.metadata = {
            **self.metadata,
            "render_fps": round(1.0 / (self._env.control_timestep() * action_repeat)),
        }
        self._video = None
        self._agent_steps = 0
        self._sim_steps = 0
        self._needs_reset = True
        self._seeded = False
        self._last_obs = np.zeros(self.observation_space.shape, np.uint8)

    def _observe(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        if self._camera is None:
            self._camera = Camera(
                self._env.physics, height=self.image_size, width=self.image_size, camera_id=self.camera_id
            )
        # Camera.render returns a view of its internal buffer, which the next render overwrites.
        obs = self._camera.render().copy()
        if self._video is None:
            mask = np.zeros(obs.shape[:2], dtype=bool)
        else:
            mask = (obs == _KEY).all(axis=-1)
            obs[mask] = self._video.frame(self._agent_steps)[mask]
        self._last_obs = obs
        info = {"mask_background": mask}
        if self.masks:
            segmentation = self._camera.render(segmentation=True)  # [H, W, (object id, object type)]
            model = self._env.physics.model
            is_geom = segmentation[..., 1] == mujoco.mjtObj.mjOBJ_GEOM
            body = model.geom_bodyid[np.where(is_geom, segmentation[..., 0], 0)]
            info["mask_agent"] = is_geom & (body != 0)
            info["mask_distractors"] = mask.copy()
        return obs, info

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Starts an episode with the next background video.

        Args:
            seed (int, optional): reseeds the task's initial-state sampler and the video stream, so the
                same seed gives the same episode (physics and background) under the same actions.
            options (dict, optional): unused, accepted for the gymnasium API.

        Returns:
            ``(obs, info)``: uint8 [H, W, 3] and the masks of the class docstring, bool [H, W] each.
        """
        super().reset(seed=seed)
        if seed is not None or not self._seeded:
            task_seed, video_seed = (int(s) for s in self.np_random.integers(0, 2**31 - 1, size=2))
            # dm_control draws initial states from task.random, fixed at load time: swap in a seeded one.
            self._env.task._random = np.random.RandomState(task_seed)
            if self._videos is not None:
                self._videos.seed(video_seed)
            self._seeded = True
        self._env.reset()
        if self._videos is not None:
            self._video = self._videos.next_video()
            self.current_video = self._videos.current_source
        self._agent_steps = 0
        self._sim_steps = 0
        self._needs_reset = False
        return self._observe()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, np.ndarray]]:
        """Applies ``action`` for ``action_repeat`` simulator steps, then renders once.

        Args:
            action (np.ndarray): [A] in [-1, 1].

        Returns:
            ``(obs, reward, terminated, truncated, info)``; ``reward`` is the sum over the repeats.
        """
        if self._needs_reset:
            raise RuntimeError("call reset() before step(): the episode has ended or not started")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"action must have shape {self.action_space.shape} for {self.domain}-{self.task}, "
                f"got {action.shape}"
            )
        scaled = self._action_low + (np.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (
            self._action_high - self._action_low
        )
        reward = 0.0
        for _ in range(self.action_repeat):
            time_step = self._env.step(scaled)
            self._sim_steps += 1
            reward += time_step.reward or 0.0
            if time_step.last() or self._sim_steps >= self.max_sim_steps:
                break
        self._agent_steps += 1
        terminated = bool(time_step.last() and time_step.discount == 0.0)
        truncated = not terminated and (time_step.last() or self._sim_steps >= self.max_sim_steps)
        self._needs_reset = terminated or truncated
        obs, info = self._observe()
        return obs, float(reward), terminated, truncated, info

    def render(self) -> np.ndarray | None:
        """The last observation (uint8 [H, W, 3]) in ``"rgb_array"`` mode, else ``None``."""
        return self._last_obs.copy() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        """Frees the GL context; the env cannot be used afterwards."""
        physics = getattr(getattr(self, "_env", None), "physics", None)
        if physics is not None:
            physics.free()
            self._env = None
