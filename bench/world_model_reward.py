"""How fast the world model learns the sprites ``reach`` reward, measured on held-out episodes.

A diagnostic of the learning ladder (docs/results/learning.md): before an agent can learn to act, its world
model must predict the reward from the latent state. This script collects ``--episodes`` training episodes
of sprites ``reach`` (no distractors; even episodes random actions held ``--hold`` steps, odd ones 70 %
scripted steps towards the target), trains the world model alone (no behavior) on windows of ``B x T``,
and every 100 updates scores it on 24 windows of 6 held-out episodes: the correlation between predicted
and true rewards (after the first two steps of each window), the same correlation when the model imagines the
last 24 steps of each window from 8 observed ones with the window's actions (``open_loop_corr``: what the
actor's imagination relies on; ``--algo dreamerv2`` only), the reconstruction loss and the KL. At the end
it writes an open-loop prediction GIF and the JSON ``--out`` (with the CPU, commit and command).

    python bench/world_model_reward.py --name bg8 --backgrounds 8 --updates 600
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_name, git_commit  # noqa: E402  (bench/common.py, on the path above)

from isodream_rl.envs.builder import make_gym_env
from isodream_rl.envs.reference import scripted_action
from isodream_rl.run_utils.json_io import write_json
from isodream_rl.trainers.config import RunConfig
from isodream_rl.trainers.isodream_v2 import IsoDreamV2Components
from isodream_rl.trainers.openloop import open_loop_prediction, prediction_frames, save_gif

p = argparse.ArgumentParser()
p.add_argument("--name", required=True)
p.add_argument("--out", default=None)
p.add_argument("--updates", type=int, default=600)
p.add_argument("--episodes", type=int, default=30)
p.add_argument("--depth", type=int, default=8)
p.add_argument("--belief", type=int, default=64)
p.add_argument("--state", type=int, default=32)
p.add_argument("--lambda-reward", type=float, default=1.0)
p.add_argument("--backgrounds", type=int, default=0)
p.add_argument("--sprite-size", type=float, default=0.06)
p.add_argument("--lr", type=float, default=1e-3)
p.add_argument("--B", type=int, default=16)
p.add_argument("--T", type=int, default=32)
p.add_argument("--hold", type=int, default=1)
p.add_argument("--algo", default="dreamerv2")
p.add_argument("--kl-scale", type=float, default=1.0)
p.add_argument("--free-nats", type=float, default=1.0)
p.add_argument("--action-repeat", type=int, default=1)
a = p.parse_args()
torch.set_num_threads(1)
torch.manual_seed(0)
kw = dict(task="reach", num_distractors=0, sprite_size=a.sprite_size)
if a.backgrounds:
    kw["num_backgrounds"] = a.backgrounds
env = make_gym_env("sprites", **kw)
rng = np.random.default_rng(0)


def collect(n, seed0, scripted_frac=0.5):
    eps = []
    for k in range(n):
        obs, _ = env.reset(seed=seed0 + k)
        A, P, R = [], [], []
        act = rng.uniform(-1, 1, 2)
        for t in range(200 // a.action_repeat):
            if k % 2 == 1 and rng.random() < 0.7:
                act = scripted_action(env)
            elif t % a.hold == 0:
                act = rng.uniform(-1, 1, 2)
            r = 0.0
            for _ in range(a.action_repeat):
                obs, r_step, *_ = env.step(act)
                r += r_step
            A.append(np.asarray(act, np.float32))
            P.append(obs.transpose(2, 0, 1))
            R.append(r)
        eps.append((np.stack(A), np.stack(P), np.array(R, np.float32)))
    return eps


train, test = collect(a.episodes, 0), collect(6, 10_000)


def window(eps, B, T):
    A, P, R = [], [], []
    for _ in range(B):
        e = eps[rng.integers(len(eps))]
        s = rng.integers(0, len(e[0]) - T + 1)
        A.append(e[0][s : s + T])
        P.append(e[1][s : s + T])
        R.append(e[2][s : s + T])
    td = TensorDict(
        {
            "action": torch.from_numpy(np.stack(A)),
            ("next", "pixels"): torch.from_numpy(np.stack(P)),
            ("next", "reward"): torch.from_numpy(np.stack(R))[..., None],
            "is_init": torch.zeros(B, T, 1, dtype=torch.bool),
        },
        [B, T],
    )
    td["is_init"][:, 0] = True
    return td


cfg = RunConfig()
cfg.model.size = "small"
cfg.model.depth, cfg.model.state_dim = a.depth, a.state
cfg.model.belief_dim = cfg.model.hidden_dim = a.belief
cfg.algo.lambda_reward = a.lambda_reward
cfg.algo.free_nats = a.free_nats
if a.algo == "dreamerv2":
    cfg.algo.free_branch = cfg.algo.static_branch = cfg.algo.inverse_dynamics = False
    cfg.algo.reward_uses_free = False
    cfg.algo.policy_input = "controllable"
else:
    cfg.algo.reward_uses_free = True
    cfg.algo.policy_input = "attention"
comp = IsoDreamV2Components(cfg, action_dim=2, scratch_dir=Path("/tmp/world_model_reward_" + a.name))
comp.model_loss.lambda_kl_control = a.kl_scale
opt = torch.optim.Adam(comp.world_model.parameters(), lr=a.lr, eps=1e-5)
test_batch = window(test, 24, a.T)


@torch.no_grad()
def open_loop_rewards(batch, context):
    """Rewards the model predicts when it imagines the rest of each window with its actions (no images)."""
    wm = comp.world_model
    filtered = wm(batch[:, :context].select("action", ("next", "pixels"), "is_init").clone()).get("next")
    state, belief = filtered["state"][:, -1], filtered["belief"][:, -1]
    predicted = []
    for t in range(context, batch.shape[1]):
        _, _, state, belief = wm.control_rssm.imagine_step(state, belief, batch["action"][:, t].float())
        predicted.append(wm.reward_head(wm.reward_features(state, belief)).float())
    predicted = torch.stack(predicted, 1)
    return predicted.flatten().numpy(), batch["next", "reward"][:, context:].flatten().numpy()


res = []
t0 = time.perf_counter()
for u in range(1, a.updates + 1):
    losses, _ = comp.model_loss(window(train, a.B, a.T))
    opt.zero_grad()
    sum(v for k, v in losses.items() if k.startswith("loss")).backward()
    torch.nn.utils.clip_grad_norm_(comp.world_model.parameters(), 100)
    opt.step()
    if u % 100 == 0:
        with torch.no_grad():
            tl, out = comp.model_loss(test_batch)
        pr, tr = (
            out["next", "reward_pred"][:, 2:].flatten().numpy(),
            test_batch["next", "reward"][:, 2:].flatten().numpy(),
        )
        # the action-free branch's own rollout is not part of this check: the single-branch model only
        open_pred, open_true = (
            open_loop_rewards(test_batch, context=8) if a.algo == "dreamerv2" else (None, None)
        )
        row = dict(
            u=u,
            open_loop_corr=None
            if open_pred is None
            else round(float(np.corrcoef(open_pred, open_true)[0, 1]), 3),
            s=round(time.perf_counter() - t0),
            corr=round(float(np.corrcoef(pr, tr)[0, 1]), 3),
            test_reco=round(float(tl["loss_model_reco"]), 1),
            test_kl=round(float(tl["kl_control"]), 2),
            train_rew=round(float(losses["loss_model_reward"]), 4),
        )
        res.append(row)
        print(a.name, row, flush=True)
out_path = Path(a.out or f"runs/world_model_reward_{a.name}.json")
out_path.parent.mkdir(parents=True, exist_ok=True)
write_json(
    out_path,
    {
        "args": vars(a),
        "curve": res,
        "cpu": cpu_name(),
        "commit": git_commit(),
        "command": "python bench/world_model_reward.py " + " ".join(sys.argv[1:]),
    },
    indent=1,
)

tb = test_batch[:1, :16]
pred = open_loop_prediction(comp.world_model, tb, context=8)
save_gif(prediction_frames(pred), out_path.with_suffix(".gif"))
