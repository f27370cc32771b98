"""The agent learns to act: Algorithm 1 end to end on a task whose first reach needs no perception.

With ``fixed_start=True`` every sprites episode starts with the agent and the target at the same places, so
moving diagonally down-right earns the progress reward and a reach within the 20 steps of an episode. A tiny
world model learns that from its own data in a few hundred updates; the behavior side (imagination, the
lambda-returns, the actor and value losses, the acting policy) must then turn it into a policy that beats a
random one. A wrong actor-loss sign, misaligned rewards or returns, or an acting policy that ignores the
actor all end below that. The learning aims on the real task live in ``bench/learning.py``.
"""

import pytest

from isodream_rl.trainers import RunConfig
from isodream_rl.trainers.run import train


def trivial_task_config(tmp_path, algo: str) -> RunConfig:
    cfg = RunConfig(run_dir=str(tmp_path), size_name="tiny")
    cfg.algo.name = algo
    cfg.env.kwargs = {"task": "reach", "num_distractors": 0, "max_steps": 20, "fixed_start": True}
    cfg.model.size, cfg.model.actor_units, cfg.model.value_units, cfg.model.attention_dim = "tiny", 32, 32, 8
    cfg.train.batch_size, cfg.train.sequence_length, cfg.train.buffer_size = 4, 8, 2000
    cfg.train.prefill_steps, cfg.train.total_steps = 100, 400
    cfg.train.train_every, cfg.train.frames_per_batch = 1, 10
    cfg.train.world_model_lr, cfg.train.actor_lr, cfg.train.value_lr = 1e-3, 3e-4, 3e-4
    cfg.train.threads = 1
    cfg.algo.horizon, cfg.algo.attention_window = 5, 2
    if algo == "isodream":
        # DreamerV3's optimiser would warm its learning rate up over 1000 updates; 500 updates at full rate
        # (measured: evaluation returns 4.5 and 4.8 on seeds 0 and 1, one reach each; 300 gave 2.9 and 4.1)
        cfg.train.lr_warmup, cfg.train.total_steps = 0, 600
    if algo == "dreamerv2":
        cfg.algo.free_branch = cfg.algo.static_branch = cfg.algo.inverse_dynamics = False
        cfg.algo.reward_uses_free, cfg.algo.policy_input = False, "controllable"
    cfg.logging.eval_every, cfg.logging.final_eval_episodes, cfg.logging.progress_bar = 0, 3, False
    cfg.logging.video_length, cfg.logging.video_context = 6, 3
    return cfg


@pytest.mark.parametrize("algo", ["isodream_v2", "isodream"])
def test_agent_learns_to_beat_a_random_policy_on_a_reach_that_needs_no_perception(tmp_path, algo):
    result = train(trivial_task_config(tmp_path, algo))
    summary = result.summary
    assert result.updates >= 300
    # A random policy earns about nothing here; heading for the target earns ~0.5 per step and a reach.
    assert abs(summary["random_return"]) < 1.5
    assert summary["eval_return"] > summary["random_return"] + 3.0, summary
