"""Evaluation episodes (mode actions) and the periodic evaluation hook with open-loop prediction GIFs."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger
from torchrl.trainers import TrainerHookBase

from isodream_rl.envs.task_metrics import TASK_METRICS
from isodream_rl.evaluation import decomposition_scores, isolation_verdict
from isodream_rl.evaluation.decomposition import PART_KEYS, TRUTH_KEYS
from isodream_rl.trainers.openloop import open_loop_prediction, prediction_frames, prediction_video, save_gif

#: Upper bound on evaluation episode length; every env here truncates well before (sprites 200, highway 250,
#: DMC 500 agent steps).
MAX_EVAL_STEPS = 10_000


@dataclass
class EpisodeResults:
    """Returns and task success counts of evaluation episodes.

    Attributes:
        returns: one return per episode.
        metrics: one dict per episode of the task's success counts (``TASK_METRICS``: ``reaches``,
            ``contacts`` on sprites; ``distance``, ``collisions`` on the highway; empty elsewhere).
        frames: the first episode's frames (uint8 ``[3, H, W]`` each) when recorded, else empty.
    """

    returns: list[float]
    metrics: list[dict[str, float]] = field(default_factory=list)
    frames: list[torch.Tensor] = field(default_factory=list)
    first_rollout: TensorDictBase | None = None
    """The first episode's ``[T]`` rollout, when kept."""

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))

    def summary(self, prefix: str = "eval_") -> dict[str, float]:
        """``{prefix}return``, ``{prefix}return_std`` and the mean of every success count ``{prefix}<name>``."""
        out = {f"{prefix}return": self.mean, f"{prefix}return_std": self.std}
        for name in self.metrics[0] if self.metrics else ():
            out[f"{prefix}{name}"] = float(np.mean([m[name] for m in self.metrics]))
        return out


@torch.no_grad()
def run_episodes(
    policy,
    env: EnvBase,
    *,
    episodes: int,
    record: bool = False,
    task: str | None = None,
    keep_rollout: bool = False,
) -> EpisodeResults:
    """Run ``episodes`` episodes with the policy's mode action.

    Args:
        policy: the acting policy; ``env`` must carry its recurrent-state primer.
        env: an unbatched env.
        episodes: how many.
        record: keep the first episode's frames (uint8 ``[3, H, W]`` each).
        task: the env's name in ``TASK_METRICS`` (``"sprites"``, ``"highway"``) to count its successes from
            the info keys ``make_env`` exports; ``None`` counts none.
        keep_rollout: keep the first episode's rollout (``EpisodeResults.first_rollout``).

    Returns:
        :class:`EpisodeResults`.
    """
    results = EpisodeResults(returns=[])
    counts = TASK_METRICS.get(task, {}) if task is not None else {}
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for episode in range(episodes):
            rollout = env.rollout(MAX_EVAL_STEPS, policy, break_when_any_done=True)
            results.returns.append(float(rollout.get(("next", "reward")).sum()))
            results.metrics.append(
                {
                    name: float(transform(rollout.get(("next", key))).sum())
                    for name, (key, transform) in counts.items()
                }
            )
            if record and episode == 0:
                results.frames = list(rollout.get(("next", "pixels")).unbind(0))
            if keep_rollout and episode == 0:
                results.first_rollout = rollout
    return results


def rollout_decomposition(
    world_model, rollout: TensorDictBase, *, window: int, max_windows: int = 4
) -> dict[str, float]:
    """:func:`~isodream_rl.evaluation.decomposition_scores` of ``world_model`` on an episode's rollout with
    ground-truth masks (``make_env(..., return_masks=True)``), cut into up to ``max_windows`` consecutive
    windows of ``window`` steps (one shorter window if the episode is shorter; nothing below 2 steps).

    Returns:
        the scores, ``{}`` when the episode is too short.
    """
    steps = rollout.shape[0]
    if steps < 2:
        return {}
    window = min(window, steps)
    count = min(max_windows, steps // window)
    keys = ["action", "is_init", ("next", "pixels"), *TRUTH_KEYS.values()]
    present = set(rollout.keys(include_nested=True))
    keys += [key for key in PART_KEYS.values() if key in present]
    windows = rollout[: count * window].select(*keys).reshape(count, window).clone()
    windows["is_init"][:, 0] = True  # each window is filtered from zero states
    return decomposition_scores(world_model, windows, device=next(world_model.parameters()).device)


#: Windows of the final evaluation's first episode that :func:`final_decomposition` scores.
FINAL_DECOMPOSITION_WINDOWS = 8


def final_decomposition(world_model, rollout: TensorDictBase, *, window: int) -> dict:
    """The decomposition scores of a run's final evaluation and where they put the agent (``summary.json``).

    Args:
        world_model: the run's Iso-Dream world model.
        rollout: the first evaluation episode, ``[T]``, with the ground-truth masks.
        window: the replay window length (the model filters each window from zero states, as in training).

    Returns:
        ``decomposition``: :func:`rollout_decomposition` over up to :data:`FINAL_DECOMPOSITION_WINDOWS` windows;
        ``isolation``: :func:`~isodream_rl.evaluation.isolation_verdict` of those scores.
    """
    scores = rollout_decomposition(
        world_model, rollout, window=window, max_windows=FINAL_DECOMPOSITION_WINDOWS
    )
    return {"decomposition": scores, "isolation": isolation_verdict(scores) if scores else None}


def log_prediction(logger: Logger, name: str, video: torch.Tensor, *, step: int) -> None:
    """Log an open-loop prediction: as a video when moviepy is installed, else as one image, frames top to bottom.

    TorchRL's TensorBoard and W&B loggers encode videos with moviepy, which is not a dependency of this package.

    Args:
        logger: a TorchRL logger (TensorBoard or W&B; any other gets ``log_video``).
        name: the logged key.
        video: uint8 ``[1, T, 3, H, W]`` (:func:`~isodream_rl.trainers.openloop.prediction_video`).
        step: agent steps.
    """
    kind = type(logger).__name__
    if importlib.util.find_spec("moviepy") is not None or kind not in ("TensorboardLogger", "WandbLogger"):
        logger.log_video(name, video, step=step)
        return
    strip = torch.cat(list(video[0]), dim=-2)  # [3, T * H, W]
    if kind == "TensorboardLogger":
        logger.experiment.add_image(name, strip, global_step=step)
    else:
        import wandb

        # log_scalar hands the value to wandb as it is, with the logger's step bookkeeping.
        logger.log_scalar(name, wandb.Image(strip.permute(1, 2, 0).numpy()), step=step)


def save_episode_gif(frames: list[torch.Tensor], path: str | Path, *, fps: int = 15, scale: int = 2) -> Path:
    """Write uint8 ``[3, H, W]`` frames as a GIF (atomically)."""
    images = [
        Image.fromarray(np.ascontiguousarray(f.permute(1, 2, 0).cpu().numpy())).resize(
            (f.shape[-1] * scale, f.shape[-2] * scale), Image.NEAREST
        )
        for f in frames
    ]
    return save_gif(images, path, fps=fps)


class Evaluation(TrainerHookBase):
    """``post_steps_log`` hook: every ``every`` agent steps, evaluation episodes and an open-loop prediction.

    Logs ``eval_return``, ``eval_return_std``, the task's success counts (``eval_reaches``, ...) and, with a
    ``clock``, ``eval_wall_s`` (the training time when the evaluation started); writes ``<pictures>/openloop_<steps>.gif`` (ground truth,
    prediction, each branch's component and mask; ``context`` frames observed, then imagined) and logs the
    same frames with :func:`log_prediction`.

    Args:
        policy: the acting policy.
        env_factory: ``() -> EnvBase`` (with the policy's primer) for evaluation episodes; built on first use.
        world_model: the world model to predict with, or ``None`` for no open-loop prediction (a model
            without the :func:`~isodream_rl.trainers.openloop.open_loop_prediction` interface).
        replay_buffer: source of the prediction windows.
        sequence_length: replay window length T.
        pictures: folder of the GIFs.
        every: agent steps between evaluations.
        episodes: episodes per evaluation.
        task: the env's name in ``TASK_METRICS``, to log its success counts (``None``: none).
        clock: ``() -> seconds`` of the run's training wall-clock, logged as ``eval_wall_s`` (``None``: not
            logged).
        context: observed frames of the open-loop prediction.
        length: frames of the open-loop prediction.
        logger: TorchRL logger for the video (TensorBoard, W&B), or ``None`` (the GIF is written either way).
        decomposition: score ``world_model``'s branches against the ground truth on the first evaluation
            episode (:func:`rollout_decomposition`, up to 4 windows of ``sequence_length``), logged as
            ``eval/decomposition/<score>``; ``env_factory``'s env must then return the masks
            (``make_env(..., return_masks=True)``).
    """

    def __init__(
        self,
        *,
        policy,
        env_factory,
        world_model,
        replay_buffer,
        sequence_length: int,
        pictures: Path,
        every: int,
        episodes: int,
        task: str | None = None,
        clock=None,
        context: int,
        length: int,
        logger=None,
        decomposition: bool = False,
    ) -> None:
        self.policy, self.env_factory, self.env = policy, env_factory, None
        self.world_model, self.replay_buffer = world_model, replay_buffer
        self.sequence_length, self.pictures = sequence_length, Path(pictures)
        self.every, self.episodes, self.task, self.clock = every, episodes, task, clock
        self.context, self.length, self.logger = context, length, logger
        self.decomposition = decomposition and world_model is not None
        self.last = 0
        self.last_gif: Path | None = None
        self._trainer = None

    def evaluate(self, step: int) -> dict:
        """Run the evaluation now; returns the logged scalars."""
        wall_s = None if self.clock is None else self.clock()
        if self.env is None:
            self.env = self.env_factory()
        results = run_episodes(
            self.policy, self.env, episodes=self.episodes, task=self.task, keep_rollout=self.decomposition
        )
        if self.world_model is not None:
            window = self.replay_buffer.sample().reshape(-1, self.sequence_length)[:1, : self.length]
            prediction = open_loop_prediction(self.world_model, window, context=self.context)
            self.last_gif = save_gif(
                prediction_frames(prediction), self.pictures / f"openloop_{step:08d}.gif"
            )
            if self.logger is not None:
                log_prediction(self.logger, "openloop_prediction", prediction_video(prediction), step=step)
        out = results.summary()
        if self.decomposition:
            scores = rollout_decomposition(
                self.world_model, results.first_rollout, window=self.sequence_length
            )
            out.update({f"eval/decomposition/{key}": value for key, value in scores.items()})
        if wall_s is not None:
            out["eval_wall_s"] = wall_s
        return out

    def __call__(self, batch) -> dict | None:
        step = self._trainer.collected_frames
        if step // self.every <= self.last // self.every or len(self.replay_buffer) < self.sequence_length:
            return None
        self.last = step
        return self.evaluate(step)

    def state_dict(self) -> dict:
        return {"last": self.last}

    def load_state_dict(self, state_dict: dict) -> None:
        self.last = state_dict["last"]

    def register(self, trainer, name: str = "evaluation") -> None:
        self._trainer = trainer
        trainer.register_op("post_steps_log", self)


def learning_summary(
    results: EpisodeResults,
    *,
    env_name: str,
    env_kwargs: dict,
    env_steps: int,
    wall_s: float,
    seed: int = 10_000,
) -> dict:
    """The agent's evaluation next to the task's reference policies (``isodream_rl.envs.reference``).

    Args:
        results: the agent's evaluation episodes (mode actions).
        env_name, env_kwargs: the env as ``make_env`` builds it; the references run on the same env.
        env_steps: agent steps the run collected.
        wall_s: the run's training wall-clock time in seconds.
        seed: first episode seed of the reference policies.

    Returns:
        ``eval_return``, ``eval_return_std``, the success counts (``eval_reaches``, ...), ``random_return``,
        ``constant_return``, ``scripted_return``, ``normalised_score`` (``None`` where the env has no scripted
        controller), ``env_steps``, ``wall_s``, ``eval_episodes`` and ``references`` (each reference policy's
        returns and success counts).
    """
    from isodream_rl.envs.reference import has_reference_policies, normalised_score, reference_returns

    summary: dict = {**results.summary(), "eval_episodes": len(results.returns)}
    refs = None
    if has_reference_policies(env_name, **env_kwargs):
        refs = reference_returns(env_name, episodes=len(results.returns), seed=seed, **env_kwargs)
    for name in ("random", "constant", "scripted"):
        summary[f"{name}_return"] = None if refs is None else refs[name]["return"]
    summary["normalised_score"] = (
        None
        if refs is None
        else normalised_score(
            results.mean, constant=refs["constant"]["return"], scripted=refs["scripted"]["return"]
        )
    )
    summary.update(env_steps=int(env_steps), wall_s=float(wall_s), references=refs)
    return summary
