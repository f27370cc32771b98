"""DreamerV3's shared pieces in the lower layers: the actor on any number of inputs, imagination's extra latent
keys, one optimiser per parameter group."""

import dataclasses

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import WorldModelWrapper
from torchrl.trainers.algorithms import DreamerV3Optimizer

from isodream_rl.modules.dreamer_v3 import TORCHRL_DREAMER_V3_SETTINGS, DreamerV3ContinuousActor
from isodream_rl.objectives.imagination_env import latent_dreamer_env
from isodream_rl.trainers.dreamer_v3 import GROUPS, make_dreamer_v3_optimizers


def test_the_actor_concatenates_its_inputs_on_the_last_dim():
    torch.manual_seed(0)
    actor = DreamerV3ContinuousActor(12, 2, num_cells=8)
    belief, state, window = torch.randn(4, 6), torch.randn(4, 4), torch.randn(4, 2)
    loc, scale = actor(belief, state, window)
    loc_cat, scale_cat = actor(torch.cat([belief, state, window], dim=-1))
    assert torch.equal(loc, loc_cat) and torch.equal(scale, scale_cat)
    assert loc.shape == (4, 2) and bool(((scale >= 0.1) & (scale <= 1.0)).all())


def _env(**kwargs):
    step = TensorDictModule(nn.Identity(), in_keys=["state"], out_keys=["state"])
    reward = TensorDictModule(nn.Linear(3, 1), in_keys=["state"], out_keys=["reward"])
    return latent_dreamer_env(
        WorldModelWrapper(step, reward),
        action_spec=Bounded(-1.0, 1.0, (2,)),
        state_dim=3,
        belief_dim=5,
        device="cpu",
        **kwargs,
    )


def test_imagination_carries_extra_latent_keys_beside_state_and_belief():
    plain = _env()
    assert set(plain.observation_spec.keys()) == set(plain.state_spec.keys()) == {"state", "belief"}
    env = _env(extra_observations={"window": (4, 7)})
    for spec in (env.observation_spec, env.state_spec):
        assert set(spec.keys()) == {"state", "belief", "window"}
        assert spec["window"].shape == (4, 7) and spec["state"].shape == (3,) and spec["belief"].shape == (5,)
    with pytest.raises(ValueError, match="must not redefine"):
        _env(extra_observations={"belief": (5,)})


def test_one_optimiser_per_group_with_the_settings():
    settings = dataclasses.replace(TORCHRL_DREAMER_V3_SETTINGS, agc=0.5, optimizer_eps=1e-8, lr_warmup=10)
    groups = {name: [nn.Parameter(torch.zeros(2))] for name in GROUPS}
    rates = {"world_model": 1e-3, "actor": 2e-4, "value": 3e-4}
    optimizers = make_dreamer_v3_optimizers(groups, rates=rates, settings=settings)
    assert list(optimizers) == list(GROUPS)
    for name, optimizer in optimizers.items():
        assert isinstance(optimizer, DreamerV3Optimizer)
        (group,) = optimizer.param_groups
        assert group["params"] == groups[name] and group["lr"] == rates[name]
        assert (group["agc"], group["eps"], group["warmup_steps"]) == (0.5, 1e-8, 10)
    with pytest.raises(KeyError, match="no learning rate"):
        make_dreamer_v3_optimizers(groups, rates={"world_model": 1e-3}, settings=settings)
