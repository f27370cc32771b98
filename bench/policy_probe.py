"""What a trained run's policy and world model do on fresh episodes (a diagnostic of the learning ladder).

Loads the newest readable checkpoint of an ``isodream-train`` run, plays ``--episodes`` fresh episodes of
``--steps`` steps with the deterministic policy, and reports:

- the true rewards and the world model's reward predictions while filtering those episodes (their
  correlation: does the model know what the reward depends on?);
- the policy's actions: their mean and their spread over all steps (``action_std``) and within an episode
  (``action_std_within_episode``: near 0 means the policy holds one action whatever it sees);
- the rewards the model imagines from those states under the actor (what the actor is optimising) next to
  the true mean reward;
- ``imagination_check``: from ``--starts`` fresh states (24 random steps, actions held 4 steps), 32
  imagined trajectories of the actor each, and the same action sequences replayed in copies of the real env
  (sprites only): the imagined and the real return over the horizon, and the per-step correlation of
  imagined and real rewards (near 0: the actor optimises rewards that its actions do not get). Also:

  - ``imagined_reach_rate`` / ``imagined_reaches``: the fraction / number of imagined steps whose predicted
    reward exceeds ``REACH_THRESHOLD`` (0.85: a reach earns 1 plus the progress of its step, while the
    progress term alone is at most ``10 * sqrt(2) * 3.2 / 64 = 0.71`` for a diagonal step at full speed),
    against ``real_reach_rate`` / ``real_reaches``: those of the same replayed steps where the real env
    reports ``info["reached"]``; ``reach_recall``: the fraction of the real reaches whose imagined step
    exceeded the threshold too (``None`` without a real reach). An imagined rate far above the real one: the
    actor optimises reaches that the model dreams up;
  - ``value_vs_potential``: the slow value ``v_slow(e)`` of the start states (the filtered posterior at the
    end of each context window, averaged over the imagined samples when ``e`` reads the sampled
    noncontrollable window) against the true shaping potential ``phi = -progress_reward * d / image_size``
    (``d``: the agent's distance to the target, in pixels) of the env there, over the ``--starts`` states and
    ``--value-starts`` more context windows run only for this: the least-squares ``slope`` and
    ``intercept`` of ``v_slow`` on ``phi``, ``r2``, ``correlation``, the number of ``points`` and the
    means ``v_slow_mean`` and ``phi_mean``. A value that has learned the shaping term (the return still to
    come from closing the distance, ``-phi``) has a slope near -1; near 0 it does not see the distance.
  - ``gradient_check``: what the actor's pathwise gradient says, from the same start states: a shift
    ``delta`` added to every imagined action (the model steps on ``a + delta``); the gradients of the imagined
    reward sum (``reward``) and of the mean lambda-return the actor maximises (``lambda_return``: rewards plus
    the bootstrapped slow value) with respect to ``delta``, each as its mean cosine with the direction from the
    agent to the target in action coordinates (``cosine_*``; the true reward grows along it, so a model whose
    gradients are right gives a cosine near +1) and its mean norm (``norm_*``), and the cosine of the gradient
    of the slow value of the last imagined state (``cosine_value``; negative: the value pays for moving away
    from the target).

Two learners, by the run's ``algo.name`` (:func:`probe_learner`):

- DreamerV2-style Iso-Dream components (``algo=isodream_v2``, ``isodream_paper``, ``dreamerv2``): the
  :class:`DreamerV2Learner`, everything above.
- TorchRL's DreamerV3 learner (:data:`DREAMER_V3_ALGOS`: ``algo=isodream`` and its ablations, Iso-Dream's
  decomposition on it, and ``algo=torchrl_dreamer_v3``, TorchRL's DreamerV3): :class:`DreamerV3Learner`. The same episodes, context
  windows, replays and reach counts; the world model filters from zero root ``state``/``belief`` (as the
  training stepper gives them), its filtered reward prediction is the decoded two-hot ``("next", "reward")``,
  and imagination is ``DreamerV3ActorLoss``'s (its ``DreamerEnv`` reset on the posteriors, which for
  ``isodream`` also rolls the action-free window, then the actor's rollout; ``lambda_target`` its
  continuation-weighted lambda-returns). ``value_vs_potential`` fits the critic that bootstraps those returns
  (``DreamerV3ActorLoss.value_model``, the two-hot value; the fit keeps the ``v_slow_*`` names) on the start
  states. ``gradient_check`` is ``null``, with its reason under ``gradient_check_skipped``: the actor learns by
  REINFORCE there, so the model's pathwise action gradients are not what it follows. These results also carry
  ``algo`` and ``learner`` (``"dreamer_v3"``); the DreamerV2-style results are as they were.

    python bench/policy_probe.py runs/ladder/R2_dv2 --json docs/results/archive/ladder/policy_probe_R2_dv2.json
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, git_commit  # noqa: E402

import isodream_rl.baselines  # noqa: F401  (registers algo=torchrl_dreamer and torchrl_dreamer_v3)
from isodream_rl.envs import make_env
from isodream_rl.objectives.isodream_v2 import lambda_returns
from isodream_rl.objectives.isodream_v2.imagination import policy_features
from isodream_rl.run_utils.checkpoint import CheckpointManager
from isodream_rl.run_utils.json_io import dumps_json, write_json
from isodream_rl.trainers.learners import ISODREAM_ALGOS
from isodream_rl.trainers.registry import make_components
from isodream_rl.trainers.saved_models import saved_run_config

#: an imagined step whose predicted reward exceeds this counts as a reach: a real reach step earns 1 plus its
#: progress, the progress term alone at most about 0.71 (a full-speed diagonal step), so 0.7 would count those
REACH_THRESHOLD = 0.85
#: the algorithms that learn on TorchRL's DreamerV3 learner (:class:`DreamerV3Learner`)
DREAMER_V3_ALGOS = (*ISODREAM_ALGOS, "torchrl_dreamer_v3")


class DreamerV2Learner:
    """What the probe runs of DreamerV2-style Iso-Dream components: the model loss filters a ``[B, T]`` window,
    its output is the actor loss's input (imagination from every posterior), ``("next", "reward_pred")`` the
    filtered reward prediction, and the imagination is pathwise (``gradient_check``).

    Args:
        components: the run's components (``model_loss``, ``behavior.actor_loss`` / ``value_loss`` / ``policy``).
    """

    #: the world model's reward prediction in the filtered output
    predicted_reward_key = ("next", "reward_pred")
    #: entries the probe adds to its results (what this learner reports differently)
    notes: dict = {}
    #: entries it adds to ``imagination_check``
    check_notes: dict = {}

    def __init__(self, components) -> None:
        self.components = components

    def filter(self, window: TensorDictBase) -> TensorDictBase:
        """The world model's output on a ``[B, T]`` window (``action``, ``("next", "pixels")``, ``is_init``)."""
        _, out = self.components.model_loss(window)
        return out

    def starts(self, out: TensorDictBase) -> TensorDictBase:
        """The actor loss's input that imagines from every filtered posterior of ``out``."""
        return out

    def last_starts(self, out: TensorDictBase, samples: int) -> TensorDictBase:
        """The actor loss's input that imagines ``samples`` times from the last posterior of ``out`` ``[1, T]``."""
        return out[:, -1:].expand(samples, 1).clone()

    def imagine(self, starts: TensorDictBase) -> TensorDictBase:
        """The actor's imagined trajectories ``[N, H]`` from ``starts`` (``action``, ``("next", "reward")``,
        ``lambda_target``)."""
        _, imagined = self.components.behavior.actor_loss(starts)
        return imagined

    def start_value(self, imagined: TensorDictBase) -> float:
        """The slow value of the imagined trajectories' start state ``e_0``, averaged over the samples (they
        differ only through the sampled noncontrollable window of the attention)."""
        behavior, start = self.components.behavior, imagined[:, 0]
        with behavior.actor_loss.imagination.autocast(start["state"].device.type):
            value = behavior.value_loss.target_value(policy_features(behavior.policy_input, start))
        return float(value.float().mean())

    def gradients(self, starts: TensorDictBase, env) -> dict | None:
        """``gradient_check``'s entries from ``starts`` (:meth:`last_starts`) in ``env``."""
        return action_gradients(self.components, starts, env)


class DreamerV3Learner(DreamerV2Learner):
    """What the probe runs of a TorchRL DreamerV3 learner (``algo=isodream``, ``torchrl_dreamer_v3``): the
    world model filters from zero root ``state``/``belief``, its decoded two-hot ``("next", "reward")`` is the
    reward prediction, ``DreamerV3ActorLoss`` imagines from flat ``state``/``belief`` starts, the critic it
    bootstraps from gives the start value, and there is no pathwise ``gradient_check`` (REINFORCE).

    Args:
        components: the run's components (``model_loss``, ``stepper.state_dim`` / ``belief_dim``,
            ``behavior.actor_loss``, ``behavior.policy``).
    """

    predicted_reward_key = ("next", "reward")
    notes = {"learner": "dreamer_v3"}
    check_notes = {
        "gradient_check_skipped": "the actor learns by REINFORCE (DreamerV3ActorLoss), not through the model's "
        "pathwise action gradients",
        "value_model": "the critic that bootstraps the actor's lambda-returns (DreamerV3ActorLoss.value_model, "
        "two-hot); the fit's v_slow_* entries name it",
    }

    def filter(self, window: TensorDictBase) -> TensorDictBase:
        stepper = self.components.stepper
        window = window.clone(False)
        window.set("state", torch.zeros(*window.batch_size, stepper.state_dim))
        window.set("belief", torch.zeros(*window.batch_size, stepper.belief_dim))
        return super().filter(window)

    def starts(self, out: TensorDictBase) -> TensorDictBase:
        state, belief = out["next", "state"], out["next", "belief"]
        return TensorDict(
            {"state": state.reshape(-1, state.shape[-1]), "belief": belief.reshape(-1, belief.shape[-1])},
            [out.numel()],
        )

    def last_starts(self, out: TensorDictBase, samples: int) -> TensorDictBase:
        return self.starts(out[:, -1:]).expand(samples).clone()

    def start_value(self, imagined: TensorDictBase) -> float:
        """The critic's value of the imagined trajectories' start state (the reset ``DreamerEnv``'s root, with
        the action-free window for ``isodream``), averaged over the samples."""
        loss = self.components.behavior.actor_loss
        start = imagined[:, 0].select(*loss.value_model.in_keys)
        return float(loss.value_model(start).get(loss.tensor_keys.value).float().mean())

    def gradients(self, starts: TensorDictBase, env) -> dict | None:
        return None


def probe_learner(components, algo: str) -> DreamerV2Learner:
    """The probe's view of a run's ``components`` by its ``algo.name``: :class:`DreamerV3Learner` for
    :data:`DREAMER_V3_ALGOS`, :class:`DreamerV2Learner` otherwise."""
    return (DreamerV3Learner if algo in DREAMER_V3_ALGOS else DreamerV2Learner)(components)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--starts", type=int, default=8)
    parser.add_argument(
        "--value-starts",
        type=int,
        default=32,
        help="context windows run only for the slow value against the potential (on top of --starts)",
    )
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    state, path = CheckpointManager(args.run_dir / "checkpoints", keep=2).load_latest()
    # a run of algo=isodream when it was the DreamerV2-style learner is read as algo=isodream_v2
    cfg = saved_run_config(state)
    components = make_components(
        cfg, action_dim=2, scratch_dir=Path("/tmp") / f"policy_probe_{args.run_dir.name}"
    )
    components.load_models(state, checkpoint=path)
    learner = probe_learner(components, cfg.algo.name)
    batch = play_episodes(
        components.behavior.policy, cfg, episodes=args.episodes, steps=args.steps, seed=args.seed
    )
    with torch.no_grad():
        out = learner.filter(batch)
        imagined = learner.imagine(learner.starts(out))
    true = batch["next", "reward"][:, 2:].flatten().numpy()
    predicted = out[learner.predicted_reward_key][:, 2:].flatten().numpy()
    actions = batch["action"].reshape(-1, 2).numpy()
    notes = {"algo": cfg.algo.name, **learner.notes} if learner.notes else {}
    result = {
        "run": str(args.run_dir),
        **notes,
        "checkpoint": str(path),
        "updates": int(state["stepper"]["updates"]),
        "true_reward_mean": float(true.mean()),
        "true_reward_std": float(true.std()),
        "predicted_reward_mean": float(predicted.mean()),
        "predicted_reward_std": float(predicted.std()),
        "reward_correlation": float(np.corrcoef(true, predicted)[0, 1]) if true.std() > 0 else None,
        "action_mean": actions.mean(0).round(3).tolist(),
        "action_std": actions.std(0).round(3).tolist(),
        "action_std_within_episode": batch["action"].std(1).mean(0).numpy().round(3).tolist(),
        "imagined_reward_mean": float(imagined["next", "reward"].mean()),
        "lambda_target_mean": float(imagined["lambda_target"].mean()),
        "imagination_check": imagination_check(
            learner, cfg, starts=args.starts, value_starts=args.value_starts
        )
        if cfg.env.name == "sprites"
        else None,
        "commit": git_commit(),
        "cpu": cpu_name(),
        "command": "python bench/policy_probe.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, result, indent=1)
    print(dumps_json({k: v for k, v in result.items() if k not in ("commit", "cpu", "command")}, indent=1))
    return result


def play_episodes(policy, cfg, *, episodes: int, steps: int, seed: int) -> TensorDict:
    """``episodes`` fresh episodes of ``steps`` steps of the run's env under the deterministic ``policy``: a
    ``[episodes, steps]`` window (``action``, ``("next", "pixels")``, ``("next", "reward")``, ``is_init`` at the
    first step)."""
    env = make_env(cfg.env.name, seed=seed, **dict(cfg.env.kwargs))
    env.append_transform(policy.make_tensordict_primer())
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollouts = [env.rollout(steps, policy, break_when_any_done=False) for _ in range(episodes)]
    batch = TensorDict(
        {
            "action": torch.stack([r["action"] for r in rollouts]),
            ("next", "pixels"): torch.stack([r["next", "pixels"] for r in rollouts]),
            ("next", "reward"): torch.stack([r["next", "reward"] for r in rollouts]),
            "is_init": torch.zeros(episodes, steps, 1, dtype=torch.bool),
        },
        [episodes, steps],
    )
    batch["is_init"][:, 0] = True
    return batch


def context_window(learner: DreamerV2Learner, env, rng: np.random.Generator, context: int) -> TensorDict:
    """Steps ``env`` ``context`` times with random actions held 4 steps and filters them with the world model:
    the model output ``[1, context]`` (its last posterior is the state of ``env`` now)."""
    actions, pixels, rewards = [], [], []
    for t in range(context):
        if t % 4 == 0:
            action = rng.uniform(-1, 1, 2)
        obs, reward, *_ = env.step(action)
        actions.append(action.copy())
        pixels.append(obs.transpose(2, 0, 1))
        rewards.append(reward)
    window = TensorDict(
        {
            "action": torch.tensor(np.array(actions), dtype=torch.float32)[None],
            ("next", "pixels"): torch.from_numpy(np.array(pixels))[None],
            ("next", "reward"): torch.tensor(rewards, dtype=torch.float32)[None, :, None],
            "is_init": torch.zeros(1, context, 1, dtype=torch.bool),
        },
        [1, context],
    )
    window["is_init"][:, 0] = True
    return learner.filter(window)


def potential(env) -> float:
    """The true shaping potential ``-progress_reward * d / image_size`` of the sprites env's current state."""
    distance = float(np.sqrt(((env._agent - env._target) ** 2).sum()))
    return -env.progress_reward * distance / env.image_size


def reach_rates(imagined_reward: np.ndarray, reached: np.ndarray) -> dict:
    """Imagined reaches (predicted reward above ``REACH_THRESHOLD``) against the real env's reaches, step by
    step of the same plans."""
    dreamt = imagined_reward > REACH_THRESHOLD
    return {
        "reach_threshold": REACH_THRESHOLD,
        "imagined_reach_rate": float(dreamt.mean()),
        "real_reach_rate": float(reached.mean()),
        "imagined_reaches": int(dreamt.sum()),
        "real_reaches": int(reached.sum()),
        "reach_recall": float(dreamt[reached].mean()) if reached.any() else None,
    }


def linear_fit(x: np.ndarray, y: np.ndarray) -> dict:
    """Least-squares ``y = slope * x + intercept`` with ``r2`` and the correlation (``None`` where undefined)."""
    fit = {"slope": None, "intercept": None, "r2": None, "correlation": None, "points": len(x)}
    if len(x) >= 2 and x.std() > 0:
        slope, intercept = np.polyfit(x, y, 1)
        residual = ((y - (slope * x + intercept)) ** 2).sum()
        total = ((y - y.mean()) ** 2).sum()
        fit.update(slope=float(slope), intercept=float(intercept))
        if total > 0:
            fit.update(r2=float(1 - residual / total), correlation=float(np.corrcoef(x, y)[0, 1]))
    fit.update(v_slow_mean=float(y.mean()) if len(y) else None, phi_mean=float(x.mean()) if len(x) else None)
    return fit


def replay_plans(env, plan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each imagined action sequence ``plan[k]`` (``[samples, H, 2]``) replayed in its own copy of the sprites
    ``env``: the real rewards and ``info["reached"]`` flags, ``[samples, H]`` each."""
    real = np.zeros(plan.shape[:2], dtype=np.float32)
    reached = np.zeros(plan.shape[:2], dtype=bool)
    for k in range(plan.shape[0]):
        replay = copy.deepcopy(env)
        for j in range(plan.shape[1]):
            _, real[k, j], _, _, info = replay.step(plan[k, j])
            reached[k, j] = info["reached"]
    return real, reached


@torch.no_grad()
def imagination_check(
    learner: DreamerV2Learner,
    cfg,
    *,
    starts: int,
    value_starts: int = 0,
    samples: int = 32,
    context: int = 24,
) -> dict:
    """Imagined against real rewards and reaches of the actor's own imagined action sequences, and the start
    value against the true potential (see the module doc)."""
    from isodream_rl.envs.sprites import SpritesEnv

    kwargs = {"task": "reach", **dict(cfg.env.kwargs)}
    rng = np.random.default_rng(1)
    imagined_sums, real_sums, imagined_all, real_all, reached_all = [], [], [], [], []
    values, potentials, gradients = [], [], []

    def imagine_from(seed: int, generator: np.random.Generator):
        """A fresh env after a context window from ``seed``, the actor's imagined plans from its state, and the
        (start value, potential) pair of that state."""
        env = SpritesEnv(**kwargs)
        env.reset(seed=seed)
        out = context_window(learner, env, generator, context)
        imagined = learner.imagine(learner.last_starts(out, samples))
        values.append(learner.start_value(imagined))
        potentials.append(potential(env))
        grads = learner.gradients(learner.last_starts(out, samples), env)
        if grads is not None:
            gradients.append(grads)
        return env, imagined

    for start in range(starts):
        env, imagined = imagine_from(20_000 + start, rng)
        dreamt = imagined["next", "reward"].squeeze(-1).numpy()
        real, reached = replay_plans(env, imagined["action"].numpy())
        imagined_sums.append(dreamt.sum(1).mean())
        real_sums.append(real.sum(1).mean())
        imagined_all.append(dreamt.ravel())
        real_all.append(real.ravel())
        reached_all.append(reached.ravel())
    # More start states for the value alone, from their own seeds and action draws (the check above unchanged).
    value_rng = np.random.default_rng(2)
    for start in range(value_starts):
        imagine_from(30_000 + start, value_rng)
    dreamt, real = np.concatenate(imagined_all), np.concatenate(real_all)
    return {
        "starts": starts,
        "samples": samples,
        "imagined_return": float(np.mean(imagined_sums)),
        "real_return": float(np.mean(real_sums)),
        "reward_correlation": float(np.corrcoef(dreamt, real)[0, 1]),
        **reach_rates(dreamt, np.concatenate(reached_all)),
        "value_starts": value_starts,
        "value_vs_potential": linear_fit(np.array(potentials), np.array(values)),
        "gradient_check": {key: float(np.mean([g[key] for g in gradients])) for key in gradients[0]}
        if gradients
        else None,
        **learner.check_notes,
    }


def action_gradients(components, start: TensorDict, env) -> dict:
    """The gradients of the imagined reward sum and of the lambda-return with respect to a shift of every
    imagined action, against the direction to the target (see ``gradient_check`` in the module doc)."""
    loss = components.behavior.actor_loss
    imagination, rssm = loss.imagination, loss.imagination.world_model.control_rssm
    delta = torch.zeros(2, requires_grad=True)
    step = rssm.imagine_step
    rssm.imagine_step = lambda state, belief, action: step(state, belief, action + delta)
    try:
        with torch.enable_grad():
            imagined = imagination(*loss._start(start), actor=loss.actor)
            with imagination.autocast("cpu"):
                next_value = loss.value_loss.target_value(
                    policy_features(imagination.policy_input, imagined["next"])
                )
            reward = imagined["next", "reward"]
            target = lambda_returns(reward, next_value.float(), loss.gamma, loss.lmbda)
            (grad_reward,) = torch.autograd.grad(reward.sum(1).mean(), delta, retain_graph=True)
            (grad_return,) = torch.autograd.grad(target.mean(), delta, retain_graph=True)
            (grad_value,) = torch.autograd.grad(next_value[:, -1].float().mean(), delta)
    finally:
        del rssm.imagine_step
    direction = torch.as_tensor((env._target - env._agent)[::-1].copy(), dtype=torch.float32)

    def cosine(g: torch.Tensor) -> float:
        return float(torch.nn.functional.cosine_similarity(g, direction, dim=0, eps=1e-12))

    return {
        "cosine_reward": cosine(grad_reward),
        "cosine_lambda_return": cosine(grad_return),
        "cosine_value": cosine(grad_value),
        "norm_reward": float(grad_reward.norm()),
        "norm_lambda_return": float(grad_return.norm()),
    }


if __name__ == "__main__":
    main()
