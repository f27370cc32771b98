"""What a trained run's policy and world model do on fresh episodes (a diagnostic of the learning ladder).

Loads the newest readable checkpoint of an ``isodream-train`` run, plays ``--episodes`` fresh episodes of
``--steps`` steps with the deterministic policy, and reports:

- the true rewards and the world model's reward predictions while filtering those episodes (their
  correlation: does the model know what the reward depends on?);
- the policy's actions: their mean and their spread over all steps (``action_std``) and within an episode
  (``action_std_within_episode``: near 0 means the policy holds one action whatever it sees);
- the rewards the model imagines from those states under the actor (what the actor is optimising) next to
  the true mean reward.

    python bench/policy_probe.py runs/ladder/R2_dv2 --json docs/results/ladder/policy_probe_R2_dv2.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_name, git_commit  # noqa: E402

from isodream_rl.envs import make_env
from isodream_rl.trainers.checkpoint import CheckpointManager
from isodream_rl.trainers.run import config_from_dict, make_components


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    state, path = CheckpointManager(args.run_dir / "checkpoints", keep=2).load_latest()
    cfg = config_from_dict(state["config"])
    components = make_components(
        cfg, action_dim=2, scratch_dir=Path("/tmp") / f"policy_probe_{args.run_dir.name}"
    )
    components.load_models(state)
    policy = components.behavior.policy
    env = make_env(cfg.env.name, seed=args.seed, **dict(cfg.env.kwargs))
    env.append_transform(policy.make_tensordict_primer())
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        rollouts = [env.rollout(args.steps, policy, break_when_any_done=False) for _ in range(args.episodes)]
    batch = TensorDict(
        {
            "action": torch.stack([r["action"] for r in rollouts]),
            ("next", "pixels"): torch.stack([r["next", "pixels"] for r in rollouts]),
            ("next", "reward"): torch.stack([r["next", "reward"] for r in rollouts]),
            "is_init": torch.zeros(args.episodes, args.steps, 1, dtype=torch.bool),
        },
        [args.episodes, args.steps],
    )
    batch["is_init"][:, 0] = True
    with torch.no_grad():
        _, out = components.model_loss(batch)
        _, imagined = components.behavior.actor_loss(out)
    true = batch["next", "reward"][:, 2:].flatten().numpy()
    predicted = out["next", "reward_pred"][:, 2:].flatten().numpy()
    actions = batch["action"].reshape(-1, 2).numpy()
    result = {
        "run": str(args.run_dir),
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
        "commit": git_commit(),
        "cpu": cpu_name(),
        "command": "python bench/policy_probe.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k not in ("commit", "cpu", "command")}, indent=1))
    return result


if __name__ == "__main__":
    main()
