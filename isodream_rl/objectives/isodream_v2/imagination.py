"""Behavior learning in decoupled imaginations (paper §3.3, Algorithm 1 lines 7-12).

From every start state (the detached posteriors of a replay batch, ``N = B * T`` of them) the
noncontrollable branch is rolled alone, then for ``j < L``: ``e_j = Attention(s~_j, z~_{j:j+tau})``,
``a_j ~ pi(a | e_j)`` and ``s~_{j+1}`` from the action-conditioned prior. Rewards (and continuation
probabilities) are read from the world model's heads on ``s`` or ``(s, z)``.

Why a rollout module and not a TorchRL ``DreamerEnv`` driven by ``rollout``: the state is two branches plus a
``[tau, F]`` look-ahead window that the env would have to shift at every step, and the losses need more than
``DreamerActorLoss`` reads (the log-probability of the sampled action, the window again for the value
model's attention). The noncontrollable branch does not depend on the actions, so all its steps (the
``L + tau`` chain, or the per-step windows, batched over all steps) run before the action loop, under
``no_grad``; only the controllable prior, the policy input and the actor stay in the loop, on plain tensors
(no per-step ``step_mdp`` or spec checks). The output is a TorchRL-style ``[N, L]`` tensordict (root = step
``j``, ``"next"`` = ``j + 1``), so TorchRL utilities and loggers read it as an imagined rollout.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from isodream_rl.modules.attention import PolicyInput
from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel

ATTENTION_WINDOWS = ("start", "per_step")


def policy_features(
    policy_input: PolicyInput, tensordict: TensorDictBase, *, detach_control: bool = False
) -> torch.Tensor:
    """``e`` from the standard keys of an imagined step (``state``, ``belief``, ``free_state``,
    ``free_belief``, ``free_window``); ``detach_control`` cuts the gradient into ``[s, h]``."""
    control = torch.cat([tensordict.get("state"), tensordict.get("belief")], dim=-1)
    if detach_control:
        control = control.detach()
    free = None
    if policy_input.mode == "concat":
        free = torch.cat([tensordict.get("free_state"), tensordict.get("free_belief")], dim=-1)
    window = tensordict.get("free_window") if policy_input.mode == "attention" else None
    return policy_input(control, free, window)


class IsoDreamV2Imagination(nn.Module):
    """Imagined rollouts of length ``L`` from a batch of posterior states (Algorithm 1, lines 7-12).

    Args:
        world_model: the trained :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` (its parameters are not
            trained by the behavior losses).
        policy_input: the :class:`~isodream_rl.modules.PolicyInput` giving ``e_j``; its ``window`` is ``tau``.
        horizon: ``L`` (15).
        attention_window: ``"start"`` (Iso-Dream): one noncontrollable rollout of ``L + tau`` states from the
            start, the window at step ``j`` is ``z~_{j..j+tau-1}`` of that chain, and the same chain is the
            trajectory's ``z_j``. ``"per_step"`` (Iso-Dream++): the trajectory's ``z_j`` is rolled one step at
            a time and the window at ``j`` is ``z_j`` plus ``tau - 1`` states re-rolled from it.

    Call: ``imagination(state, belief, free_state, free_belief, actor=actor)`` with start states ``[N, S]``,
    ``[N, D]`` (free ones ``None`` when unused); keyword ``actor_input_grad=True`` keeps the graph from the
    actor's input ``e_j`` to the policy input's parameters (the ``[s, h]`` it reads is always detached,
    as in the authors' code).

    Returns:
        a ``[N, L]`` tensordict with ``state``, ``belief`` (``s~_j``, ``h_j``; with the graph through the
        dynamics), ``attended_state`` (the actor input ``e_j``), ``action`` ``a_j`` (rsampled, pathwise),
        ``action_log_prob`` ``[N, L]``, and, when the policy or the reward reads the noncontrollable branch,
        ``free_state``, ``free_belief`` (``z_j``, ``h'_j``) and, for the attention, ``free_window``
        ``[N, L, tau, F]``. ``"next"`` holds the same latent keys at ``j + 1`` plus ``reward`` ``[N, L, 1]``
        (the reward head on the state reached, TorchRL's convention) and, with a discount head,
        ``continuation`` ``[N, L, 1]`` (probability that the episode goes on).
    """

    def __init__(
        self,
        world_model: IsoDreamV2WorldModel,
        policy_input: PolicyInput,
        *,
        horizon: int = 15,
        attention_window: str = "start",
    ):
        super().__init__()
        if attention_window not in ATTENTION_WINDOWS:
            raise ValueError(f"unknown attention_window {attention_window!r}; valid: {ATTENTION_WINDOWS}")
        if horizon < 1:
            raise ValueError(f"the imagination horizon must be >= 1, got {horizon}")
        cfg = world_model.config
        if policy_input.uses_free_branch and not cfg.free_branch:
            raise ValueError(
                f"policy_input={policy_input.mode!r} needs the world model's noncontrollable branch "
                "(free_branch=True)"
            )
        expected = cfg.state_dim + cfg.belief_dim
        if policy_input.feature_dim != expected:
            raise ValueError(
                f"policy_input.feature_dim is {policy_input.feature_dim}, the world model's [s, h] has {expected}"
            )
        self.world_model = world_model
        self.policy_input = policy_input
        self.horizon = horizon
        self.attention_window = attention_window

    @property
    def uses_free_branch(self) -> bool:
        """Whether the rollout needs the noncontrollable branch (policy input or reward head reads it)."""
        return self.policy_input.uses_free_branch or self.world_model.config.reward_uses_free

    def autocast(self, device_type: str):
        """The world model's precision context, used for every MLP of behavior learning."""
        return self.world_model.autocast(device_type)

    def roll_free(
        self, free_state: torch.Tensor, free_belief: torch.Tensor, steps: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The noncontrollable branch alone from ``[*N, S]``, ``[*N, D]``: ``[*N, steps + 1, S]``, ``[*N, steps + 1, D]``
        (index 0 is the input state; the others are prior samples)."""
        rssm = self.world_model.free_rssm
        states, beliefs = [free_state], [free_belief]
        for _ in range(steps):
            _, _, free_state, free_belief = rssm.imagine_step(free_state, free_belief)
            states.append(free_state)
            beliefs.append(free_belief)
        return torch.stack(states, dim=-2), torch.stack(beliefs, dim=-2)

    @torch.no_grad()
    def _free_branch(self, free_state, free_belief):
        """Trajectory features ``[N, L + 1, F]`` (with the raw states) and windows ``[N, L + 1, tau, F]`` or ``None``."""
        horizon, tau = self.horizon, self.policy_input.window
        attention = self.policy_input.mode == "attention"
        chain_steps = horizon + tau - 1 if attention and self.attention_window == "start" else horizon
        states, beliefs = self.roll_free(free_state, free_belief, chain_steps)
        features = torch.cat([states, beliefs], dim=-1)
        windows = None
        if attention and self.attention_window == "start":
            # Overlapping views of the one chain: no copy, no re-projection.
            windows = features.unfold(1, tau, 1).transpose(-1, -2)
        elif attention:
            n = states.shape[0]
            flat_s = states[:, : horizon + 1].reshape(n * (horizon + 1), -1)
            flat_h = beliefs[:, : horizon + 1].reshape(n * (horizon + 1), -1)
            ws, wh = self.roll_free(flat_s, flat_h, tau - 1)
            windows = torch.cat([ws, wh], dim=-1).reshape(n, horizon + 1, tau, -1)
        return states[:, : horizon + 1], beliefs[:, : horizon + 1], features[:, : horizon + 1], windows

    def forward(
        self,
        state: torch.Tensor,
        belief: torch.Tensor,
        free_state: torch.Tensor | None = None,
        free_belief: torch.Tensor | None = None,
        *,
        actor: IsoDreamV2Actor,
        actor_input_grad: bool = False,
    ) -> TensorDict:
        wm = self.world_model
        if state.dim() != 2 or belief.dim() != 2:
            raise ValueError(
                f"start states must be flat [N, S] and [N, D], got {tuple(state.shape)} and {tuple(belief.shape)}"
            )
        n, horizon, device_type = state.shape[0], self.horizon, state.device.type
        state, belief = state.detach(), belief.detach()
        free = None
        if self.uses_free_branch:
            if free_state is None or free_belief is None:
                raise ValueError(
                    "this imagination reads the noncontrollable branch: free_state/free_belief needed"
                )
            free = self._free_branch(free_state.detach(), free_belief.detach())
        free_states, free_beliefs, free_features, windows = free if free is not None else (None,) * 4

        input_grad = actor_input_grad and torch.is_grad_enabled()
        with torch.set_grad_enabled(input_grad):
            folded = self.policy_input.fold()  # once for all steps
        states, beliefs, inputs, actions, log_probs = [state], [belief], [], [], []
        for j in range(horizon):
            control = torch.cat([state, belief], dim=-1).detach()
            with torch.set_grad_enabled(input_grad), self.autocast(device_type):
                features = self.policy_input(
                    control,
                    None if free_features is None else free_features[:, j],
                    None if windows is None else windows[:, j],
                    folded=folded,
                ).float()
            with self.autocast(device_type):
                distribution = actor.distribution(features)
            action, log_prob = distribution.rsample_and_log_prob()
            _, _, state, belief = wm.control_rssm.imagine_step(state, belief, action)
            states.append(state)
            beliefs.append(belief)
            inputs.append(features)
            actions.append(action)
            log_probs.append(log_prob)

        states, beliefs = torch.stack(states, dim=1), torch.stack(beliefs, dim=1)
        reached = (
            states[:, 1:],
            beliefs[:, 1:],
            None if free_states is None else free_states[:, 1:],
            None if free_beliefs is None else free_beliefs[:, 1:],
        )
        with self.autocast(device_type):
            head_input = wm.reward_features(*reached)
            reward = wm.reward_head(head_input).float()
            continuation = None
            if wm.discount_head is not None:
                continuation = torch.sigmoid(wm.discount_head(head_input).float())

        root = {
            "state": states[:, :-1],
            "belief": beliefs[:, :-1],
            "attended_state": torch.stack(inputs, dim=1),
            "action": torch.stack(actions, dim=1),
            "action_log_prob": torch.stack(log_probs, dim=1),
        }
        nxt = {"state": states[:, 1:], "belief": beliefs[:, 1:], "reward": reward}
        if continuation is not None:
            nxt["continuation"] = continuation
        if free_states is not None:
            root.update(free_state=free_states[:, :-1], free_belief=free_beliefs[:, :-1])
            nxt.update(free_state=free_states[:, 1:], free_belief=free_beliefs[:, 1:])
        if windows is not None:
            root["free_window"] = windows[:, :horizon]
            nxt["free_window"] = windows[:, 1 : horizon + 1]
        root["next"] = TensorDict(nxt, batch_size=[n, horizon])
        return TensorDict(root, batch_size=[n, horizon])
