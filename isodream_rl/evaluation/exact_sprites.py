"""The behavior learner on an exact model: sprites ``reach`` written as a differentiable simulator.

:class:`ExactSpritesModel` stands in for a trained world model in :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2Imagination`:
its latent state is the true simulator state (agent and target positions, in units of the frame side), its
controllable prior is the env's step (move by ``agent_speed * action``, clamp at the walls, the progress
reward, ``+reach_reward`` and a new target at least 6 radii away on a reach) and its reward head reads the
reward of that step. Trained on it, the actor, value and losses of :func:`~isodream_rl.trainers.isodream_v2.make_behavior`
face no model error at all, so what they learn is what the behavior learner can learn; an optional reward error
(``reward_error`` per unit action along one fixed direction, for the first ``error_updates`` updates) is the
young world model's systematic mistake, to check that the learner recovers once the model is right.

:func:`isodream_rl.trainers.exact_model.train_behavior_on_exact_model` runs that experiment with a run's
settings; :func:`reference_returns` gives the scripted controller's and the best constant action's returns on
the model's evaluation starts.
"""

from __future__ import annotations

import contextlib
import copy
import math
from types import SimpleNamespace

import torch
from torch import nn

#: The eight compass directions and zero, the candidates of the best constant action.
CONSTANT_ACTIONS = [(0.0, 0.0)] + [
    (round(math.cos(k * math.pi / 4), 6), round(math.sin(k * math.pi / 4), 6)) for k in range(8)
]


class _RewardColumn(nn.Module):
    """The reward head of the exact model: the last column of ``[s, h]`` (``h`` holds the step's reward)."""

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features[..., -1:]


class ExactSpritesModel(nn.Module):
    """Sprites ``reach`` without distractors as an exact, differentiable world model.

    The state ``s = (agent_x, agent_y, target_x, target_y)`` is in units of the frame side ``S`` (the env's
    pixels divided by ``S``), so the sprite centres stay in ``[radius / S, (S - 1 - radius) / S]``; the belief
    ``h`` is the reward of the step that reached ``s`` (``[*N, 1]``, 0 at a start). One step
    (:meth:`imagine_step`) is :class:`~isodream_rl.envs.SpritesEnv`'s: the agent moves by
    ``agent_speed * clamp(action, -1, 1)`` and is clamped inside the frame; the reward is
    ``progress_reward * (d_{t-1} - d_t) + reach_reward * [d_t <= 2 radius / S]`` with ``d`` the distance to
    the target the agent was heading for, and a reached target respawns uniformly at least ``6 radius / S``
    away from the agent. Gradients flow from the reward to the action through the move and the clamp (not
    through the reach indicator or the respawn, which are events).

    With ``reward_error != 0`` the reward gains ``reward_error * <action, error_direction>``: a model that
    believes one direction pays, whatever the state. With ``imagine_reaches=False`` imagination
    (:meth:`imagine_step`) has no reach event: no ``reach_reward`` and no respawn, only the progress term, as a
    young world model that has not yet learnt the rare reaches; :meth:`step` (the evaluation) keeps them.

    It duck-types the parts of :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` that behavior learning reads
    (``config``, ``control_rssm.imagine_step``, ``reward_features``, ``reward_head``, ``discount_head``,
    ``autocast``); it has no parameters.

    Args:
        image_size: ``S`` (64).
        sprite_size: the sprite radius as a fraction of ``S`` (0.1: radius 6, the learning bench's sprites).
        agent_speed: displacement per step at ``|action| = 1``, a fraction of ``S`` (0.05).
        progress_reward: weight of the progress term (10).
        reach_reward: reward of a reach (1).
        reward_error: the fixed-direction reward error per unit action (0: exact).
        error_direction: its direction in action space (normalised).
        seed: seeds the respawns.
        imagine_reaches: whether :meth:`imagine_step` imagines the reach and the respawn (True: exact).
    """

    def __init__(
        self,
        *,
        image_size: int = 64,
        sprite_size: float = 0.1,
        agent_speed: float = 0.05,
        progress_reward: float = 10.0,
        reach_reward: float = 1.0,
        reward_error: float = 0.0,
        error_direction: tuple[float, float] = (1.0, 0.0),
        seed: int = 0,
        imagine_reaches: bool = True,
    ):
        super().__init__()
        self.imagine_reaches = imagine_reaches
        radius = max(2, round(sprite_size * image_size))
        self.lo, self.hi = radius / image_size, (image_size - 1 - radius) / image_size
        self.reach_distance = 2 * radius / image_size
        self.respawn_distance = 6 * radius / image_size
        self.agent_speed = agent_speed
        self.progress_reward, self.reach_reward = progress_reward, reach_reward
        self.reward_error = reward_error
        direction = torch.tensor(error_direction, dtype=torch.float32)
        self.register_buffer(
            "error_direction", direction / direction.norm().clamp_min(1e-12), persistent=False
        )
        self.generator = torch.Generator().manual_seed(seed)
        self.config = SimpleNamespace(
            state_dim=4, belief_dim=1, action_dim=2, free_branch=False, reward_uses_free=False
        )
        self.reward_head = _RewardColumn()
        self.discount_head = None

    @property
    def control_rssm(self) -> ExactSpritesModel:
        """The controllable prior: this model's own :meth:`imagine_step`."""
        return self

    def autocast(self, device_type: str):
        return contextlib.nullcontext()

    def reward_features(self, state, belief, free_state=None, free_belief=None) -> torch.Tensor:
        return torch.cat([state, belief], dim=-1)

    def _positions(self, n: int, device: torch.device | str) -> torch.Tensor:
        return torch.empty(n, 2).uniform_(self.lo, self.hi, generator=self.generator).to(device)

    def respawn(self, agent: torch.Tensor) -> torch.Tensor:
        """New targets ``[N, 2]`` at least ``6 radius / S`` from ``agent`` (32 draws, as the env)."""
        target = self._positions(agent.shape[0], agent.device)
        for _ in range(31):
            near = (target - agent).norm(dim=-1) <= self.respawn_distance
            if not near.any():
                break
            target = torch.where(near.unsqueeze(-1), self._positions(agent.shape[0], agent.device), target)
        return target

    def initial_state(self, n: int, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """``n`` random starts: ``state [n, 4]`` (a target away from the agent, as the env's reset) and ``belief [n, 1]``."""
        agent = self._positions(n, device)
        state = torch.cat([agent, self.respawn(agent)], dim=-1)
        return state, torch.zeros(n, 1, device=device)

    def step(
        self, state: torch.Tensor, action: torch.Tensor, *, reaches: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One env step from ``state [N, 4]`` under ``action [N, 2]``: ``(next_state, reward [N], reached [N])``.
        With ``reaches=False`` a reach earns nothing and the target stays (``reached`` still reports it)."""
        if action.shape[-1] != 2 or state.shape[-1] != 4:
            raise ValueError(
                f"ExactSpritesModel steps states [N, 4] with actions [N, 2], got {tuple(state.shape)} and "
                f"{tuple(action.shape)}"
            )
        agent, target = state[..., :2], state[..., 2:]
        before = (agent - target).pow(2).sum(-1).add(1e-12).sqrt()
        agent = (agent + self.agent_speed * action.clamp(-1, 1)).clamp(self.lo, self.hi)
        after = (agent - target).pow(2).sum(-1).add(1e-12).sqrt()
        reached = (after <= self.reach_distance).detach()
        reward = self.progress_reward * (before - after)
        if reaches:
            reward = reward + self.reach_reward * reached.float()
            target = torch.where(reached.unsqueeze(-1), self.respawn(agent.detach()), target)
        if self.reward_error:
            reward = reward + self.reward_error * (action * self.error_direction.to(action)).sum(-1)
        return torch.cat([agent, target], dim=-1), reward, reached

    def imagine_step(self, state: torch.Tensor, belief: torch.Tensor, action: torch.Tensor):
        """The controllable prior's interface: ``(None, None, next_state [N, 4], reward [N, 1])`` (see :meth:`step`)."""
        next_state, reward, _ = self.step(state, action, reaches=self.imagine_reaches)
        return None, None, next_state, reward.unsqueeze(-1)

    @torch.no_grad()
    def episode_returns(
        self, policy, *, episodes: int = 16, steps: int = 200, seed: int = 1234
    ) -> dict[str, float]:
        """Mean return, reaches and action-target cosine of ``policy(state, belief) -> action [N, 2]`` over
        ``episodes`` episodes of ``steps`` steps from seeded starts, with the exact reward (no error)."""
        model = copy.copy(self)
        model.reward_error, model.generator = 0.0, torch.Generator().manual_seed(seed)
        state, belief = model.initial_state(episodes, self.error_direction.device)
        total = torch.zeros(episodes)
        reaches = torch.zeros(episodes)
        cosine = []
        for _ in range(steps):
            action = policy(state, belief)
            direction = state[:, 2:] - state[:, :2]
            cosine.append(nn.functional.cosine_similarity(action, direction, dim=-1, eps=1e-8))
            state, reward, reached = model.step(state, action)
            belief = reward.unsqueeze(-1)
            total += reward.cpu()
            reaches += reached.float().cpu()
        return {
            "return": float(total.mean()),
            "reaches": float(reaches.mean()),
            "cosine": float(torch.stack(cosine).mean()),
        }

    def scripted_action(self, state: torch.Tensor, belief: torch.Tensor | None = None) -> torch.Tensor:
        """The env's scripted controller: each axis at full speed towards the target until aligned."""
        return ((state[..., 2:] - state[..., :2]) / self.agent_speed).clamp(-1, 1)


def reference_returns(model: ExactSpritesModel, **kwargs) -> tuple[float, float]:
    """The scripted controller's and the best constant action's returns on ``model``'s evaluation starts."""
    scripted = model.episode_returns(model.scripted_action, **kwargs)["return"]
    constant = max(
        model.episode_returns(lambda s, h, a=a: torch.tensor(a).expand(s.shape[0], 2), **kwargs)["return"]
        for a in CONSTANT_ACTIONS
    )
    return scripted, constant
