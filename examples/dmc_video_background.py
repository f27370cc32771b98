"""Iso-Dream on DeepMind Control with moving natural backgrounds, every TorchRL piece in view (paper §4.1).

    python examples/dmc_video_background.py --smoke                      # about a minute on a 2-core CPU
    python examples/dmc_video_background.py --task walker_walk --total-steps 100000

The DMC settings of the paper: the noncontrollable branch (the video background) learns from
reconstruction only (no KL term), the reward head and the policy read the controllable branch [s, h] only.
``isodream-train env=dmc_walker_walk algo=isodream_v2`` runs the same recipe (the DreamerV2-style learner; the
default, ``algo=isodream``, is the same decomposition on DreamerV3's learner) from the Hydra configs, with
checkpoints and evaluation.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torchrl.collectors import Collector
from torchrl.data import LazyMemmapStorage, SliceSampler, TensorDictReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import get_logger
from torchrl.trainers import ReplayBufferTrainer, Trainer

from isodream_rl.envs import make_env
from isodream_rl.modules import PolicyInput
from isodream_rl.modules.isodream_v2 import (
    IsoDreamV2Actor,
    IsoDreamV2Config,
    IsoDreamV2Value,
    IsoDreamV2WorldModel,
)
from isodream_rl.modules.isodream_v2.policy import IsoDreamV2Policy
from isodream_rl.objectives.isodream_v2 import (
    IsoDreamV2ActorLoss,
    IsoDreamV2Imagination,
    IsoDreamV2ModelLoss,
    IsoDreamV2ValueLoss,
    make_target_updater,
)
from isodream_rl.trainers.builders import STREAM_KEY
from isodream_rl.trainers.hooks import ReplayPreparation, Throughput
from isodream_rl.trainers.openloop import open_loop_prediction, prediction_frames, save_gif
from isodream_rl.trainers.stepper import IsoDreamOptimizationStepper


@dataclass
class Args:
    size: str = "small"
    """World-model size preset: paper, small or tiny."""
    total_steps: int = 20_000
    """Agent steps to collect (the prefill included); each agent step is 2 simulator steps."""
    prefill_steps: int = 2500
    """Random-policy steps before the first update."""
    train_every: int = 5
    """Agent steps per update."""
    frames_per_batch: int = 100
    """Agent steps per collector batch."""
    batch_size: int = 16
    """Replay windows per update (the paper uses 50)."""
    sequence_length: int = 50
    """Steps per replay window."""
    horizon: int = 15
    """Imagination horizon L."""
    units: int = 256
    """Width of the actor and value MLPs."""
    task: str = "walker_walk"
    """DMC ``<domain>_<task>``; the paper uses walker_walk, cheetah_run, finger_spin and hopper_stand."""
    seed: int = 4
    """The authors' DMC seed."""
    threads: int = 2
    """torch threads."""
    out: str = "runs/example_dmc"
    """Where logs, the final weights and the open-loop GIF go."""
    smoke: bool = False
    """Tiny sizes and a few hundred steps: checks that everything runs (about a minute)."""


def parse_args() -> Args:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        if f.type == "bool":
            parser.add_argument(flag, action="store_true")
        else:
            parser.add_argument(flag, type=type(f.default), default=f.default)
    args = Args(**vars(parser.parse_args()))
    if args.smoke:
        args = dataclasses.replace(
            args,
            size="tiny",
            total_steps=120,
            prefill_steps=40,
            frames_per_batch=40,
            batch_size=2,
            sequence_length=10,
            horizon=5,
            units=32,
        )
    return args


def main() -> None:
    args = parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    out = Path(args.out)

    # 1. Environment: 64x64 frames (uint8 "pixels") whose sky/floor show a moving natural video; the
    #    evaluation env uses the held-out videos (video_split="eval").
    def env_fn(split: str = "train"):
        return make_env(f"dmc_{args.task}", background="video_easy", action_repeat=2, video_split=split)

    probe = env_fn()
    action_dim = probe.action_spec.shape[-1]
    probe.close()

    # 2. World model (eq. 2-4) and its loss (eq. 5): in DMC the noncontrollable branch learns from
    #    reconstruction alone (paper §3.2) and the reward comes from [s, h].
    world_model = IsoDreamV2WorldModel(
        IsoDreamV2Config.from_preset(args.size, action_dim=action_dim, reward_uses_free=False)
    )
    model_loss = IsoDreamV2ModelLoss(world_model, lambda_reward=2.0, free_branch_loss="recon_only")

    # 3. Behavior (eq. 7): actor and value on the controllable state [s, h], trained in imagination.
    policy_input = PolicyInput.for_world_model(world_model, mode="controllable")
    imagination = IsoDreamV2Imagination(world_model, policy_input, horizon=args.horizon)
    value_loss = IsoDreamV2ValueLoss(
        IsoDreamV2Value(in_features=policy_input.out_features, num_cells=args.units), imagination
    )
    actor = IsoDreamV2Actor(
        in_features=policy_input.out_features, action_dim=action_dim, num_cells=args.units
    )
    actor_loss = IsoDreamV2ActorLoss(actor, imagination, value_loss)

    # 4. Acting: filter o_t with both branches, act on [s, h]. The primer carries the recurrent states.
    policy = IsoDreamV2Policy(world_model, actor, policy_input)

    # 5. Collector: random prefill, then the policy; a TensorDictPrimer adds the recurrent keys to the env.
    def primed_env(split: str = "train"):
        env = env_fn(split)
        env.append_transform(policy.make_tensordict_primer())
        return env

    collector = Collector(
        primed_env,
        policy,
        frames_per_batch=args.frames_per_batch,
        total_frames=args.total_steps,
        init_random_frames=args.prefill_steps,
    )
    collector.set_seed(args.seed)

    # 6. Replay: uint8 frames on disk, windows of T steps cut by SliceSampler; windows may cross episode
    #    starts (is_init resets the world model there), never the buffer's write cursor (STREAM_KEY).
    replay = TensorDictReplayBuffer(
        storage=LazyMemmapStorage(100_000, scratch_dir=str(out / "replay")),
        sampler=SliceSampler(slice_len=args.sequence_length, traj_key=STREAM_KEY, strict_length=True),
        batch_size=args.batch_size * args.sequence_length,
    )

    # 7. Three Adam optimisers (world model 3e-4; actor 8e-5; value + attention 8e-5; eps 1e-5; clip 100)
    #    and the slow value target (hard copy every 100 updates) inside one TorchRL OptimizationStepper.
    groups = actor_loss.parameter_groups()
    stepper = IsoDreamOptimizationStepper(
        model_loss=model_loss,
        world_model_optimizer=torch.optim.Adam(groups["world_model"], lr=3e-4, eps=1e-5),
        actor_loss=actor_loss,
        value_loss=value_loss,
        actor_optimizer=torch.optim.Adam(groups["actor"], lr=8e-5, eps=1e-5),
        value_optimizer=torch.optim.Adam(groups["value"], lr=8e-5, eps=1e-5),
        target_updater=make_target_updater(value_loss, period=100),
        sequence_length=args.sequence_length,
        grad_clip=100.0,
    )

    # 8. TorchRL Trainer: collect a batch -> store it -> (frames_per_batch / train_every) updates -> log.
    logger = get_logger("csv", logger_name=str(out / "logs"), experiment_name="dmc")
    trainer = Trainer(
        collector=collector,
        total_frames=args.total_steps,
        frame_skip=1,
        optim_steps_per_batch=args.frames_per_batch // args.train_every,
        loss_module=model_loss,
        optimization_stepper=stepper,
        logger=logger,
        log_interval=args.frames_per_batch,
    )
    ReplayPreparation(num_envs=1, capacity_per_env=100_000).register(trainer)
    replay_hook = ReplayBufferTrainer(replay, flatten_tensordicts=False)
    trainer.register_op("batch_process", replay_hook.extend)
    trainer.register_op("process_optim_batch", replay_hook.sample)
    Throughput(stepper).register(trainer)

    start = time.perf_counter()
    trainer.train()
    minutes = (time.perf_counter() - start) / 60

    # 9. One evaluation episode with the mode action, and an open-loop prediction GIF (5 frames observed,
    #    then imagined: truth, prediction, each branch's component and mask).
    eval_env = primed_env("eval")
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        episode = eval_env.rollout(1000, policy, break_when_any_done=True)
    eval_env.close()
    window = replay.sample().reshape(-1, args.sequence_length)[:1]
    gif = save_gif(
        prediction_frames(open_loop_prediction(world_model, window, context=5)), out / "openloop.gif"
    )
    torch.save({"world_model": world_model.state_dict(), "actor": actor.state_dict()}, out / "weights.pt")
    print(f"{args.total_steps} env steps, {stepper.updates} updates in {minutes:.1f} min")
    print(f"evaluation return {float(episode['next', 'reward'].sum()):.2f} over {episode.shape[0]} steps")
    print(f"logs: {out / 'logs'}  weights: {out / 'weights.pt'}  open-loop prediction: {gif}")


if __name__ == "__main__":
    main()
