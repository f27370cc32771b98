"""The actor loss of eq. 7: DreamerV2 lambda-returns over an Iso-Dream imagination."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule
from torchrl.objectives.utils import hold_out_net
from torchrl.objectives.value.functional import td_lambda_return_estimate, vec_td_lambda_return_estimate

from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.objectives.isodream_v2.imagination import IsoDreamV2Imagination, policy_features
from isodream_rl.objectives.isodream_v2.value import IsoDreamV2ValueLoss

ACTOR_GRADIENTS = ("dynamics", "reinforce")


def lambda_returns(
    reward: torch.Tensor, next_value: torch.Tensor, gamma: float | torch.Tensor, lmbda: float
) -> torch.Tensor:
    """DreamerV2 lambda-returns with TorchRL's value functional, time on dim ``-2``.

    ``G_j = r_j + gamma_j ((1 - lambda) v_{j+1} + lambda G_{j+1})`` and ``G_{L-1} = r_{L-1} + gamma_{L-1} v_L``,
    where ``r_j``, ``gamma_j`` and ``v_{j+1}`` (``next_value``) belong to the transition ``j -> j + 1``.

    Args:
        reward: ``[N, L, 1]``.
        next_value: ``[N, L, 1]``, the value of the state reached at each step.
        gamma: a float, or ``[N, L, 1]`` (``gamma * continuation``).
        lmbda: the lambda of TD(lambda).
    """
    never = torch.zeros(reward.shape, dtype=torch.bool, device=reward.device)
    if isinstance(gamma, torch.Tensor):
        # The loop form takes a per-step gamma exactly; L is ~15, so the loop costs nothing.
        return td_lambda_return_estimate(gamma, lmbda, next_value, reward, never, never, rolling_gamma=True)
    return vec_td_lambda_return_estimate(gamma, lmbda, next_value, reward, never, never)


class IsoDreamV2ActorLoss(LossModule):
    """Imagines from the batch's posteriors and maximises the lambda-returns (eq. 7, DreamerV2).

    ``L_actor = -mean_{N, j} w_j * (G^lambda_j + eta * H_j)`` by dynamics backpropagation (pathwise through
    the rsampled actions, the controllable prior, the reward head and the slow value), or with
    ``gradient="reinforce"``: ``-mean w_j * (log pi(a_j | e_j) * sg(G_j - v_slow(e_j)) + eta * H_j)``.
    ``H_j = -log pi(a_j | e_j)`` of a sample (``TanhNormal`` has no closed-form entropy).

    ``loss_actor_loc = rho * mean_{N, j, k} mu_{j,k}^2`` (``loc_penalty``) keeps the actor's pre-tanh mean ``mu``
    (the network's raw output, before ``TanhNormal``'s ``upscale * tanh(mu / upscale)``) near zero. It is not in
    the paper: without it, an early model error that pays one direction in every state drives ``mu`` to the
    bound, where neither the squashed action's gradient nor, against a wall, the dynamics' gradient is left to
    bring it back, and the policy stays there after the model is right (``tests/test_exact_model.py``). With
    it, a mean that no return gradient holds decays back to where samples explore again. ``loc_penalty=0`` is
    the paper's loss.
    ``w_j = prod_{k<j} gamma * c_{k+1}`` (detached), ``c`` the world model's continuation probability (1 without a
    discount head). Returns are computed with the slow value target of ``value_loss``.

    The world model's parameters are held out (``requires_grad=False`` during the forward, as in the authors'
    code), so no gradient reaches them; neither does any reach the value network or, unless
    ``attention_through_actor=True``, the policy input (attention). ``actor_loss.parameters()`` is the actor's
    parameter group; :meth:`parameter_groups` gives all three.

    Args:
        actor: an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2Actor`.
        imagination: an :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2Imagination`.
        value_loss: the :class:`~isodream_rl.objectives.isodream_v2.IsoDreamV2ValueLoss` owning the slow value target.
        gamma: discount (0.99).
        lmbda: TD(lambda) parameter (0.95).
        entropy_bonus: ``eta`` (1e-4).
        gradient: ``"dynamics"`` (the authors' setting) or ``"reinforce"``.
        attention_through_actor: let the actor loss's gradient reach the policy input's parameters too (they
            stay in the value group; backpropagate both losses before stepping, e.g. their sum).
        loc_penalty: ``rho``, the weight of the squared pre-tanh mean (0.1; 0: the paper's loss).

    Reads (``_AcceptedKeys``): the start states, by default the posteriors ``("next", "state" | "belief" |
    "free_state" | "free_belief")`` of the world-model output (any batch shape; flattened and detached).

    Returns:
        ``(losses, imagined)``: ``losses`` holds ``loss_actor``, ``loss_actor_loc`` (with ``loc_penalty > 0``)
        and detached diagnostics ``actor_entropy``, ``actor_loc_abs`` (mean ``|mu|``), ``lambda_target_mean``,
        ``imagined_reward_mean``; ``imagined`` is the detached ``[N, L]`` rollout with
        ``lambda_target`` and ``discount_weight`` added, the input of the value loss.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from isodream_rl.modules import (IsoDreamV2Actor, IsoDreamV2Value, IsoDreamV2WorldModel, PolicyInput,
        ...                                  IsoDreamV2Config)
        >>> from isodream_rl.objectives import IsoDreamV2ActorLoss, IsoDreamV2Imagination, IsoDreamV2ValueLoss
        >>> wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
        >>> pin = PolicyInput.for_world_model(wm, mode="attention", window=3, width=8)
        >>> imagination = IsoDreamV2Imagination(wm, pin, horizon=4)
        >>> value_loss = IsoDreamV2ValueLoss(IsoDreamV2Value(in_features=pin.out_features, num_cells=8), imagination)
        >>> actor = IsoDreamV2Actor(in_features=pin.out_features, action_dim=2, num_cells=8)
        >>> actor_loss = IsoDreamV2ActorLoss(actor, imagination, value_loss)
        >>> start = wm.initial_state((6,))
        >>> losses, imagined = actor_loss(TensorDict({("next", k): v for k, v in start.items()}, [6]))
        >>> imagined.batch_size, value_loss(imagined)[0]["loss_value"].shape
        (torch.Size([6, 4]), torch.Size([]))
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; remap with :meth:`set_keys`.

        Attributes:
            state: start states s. Defaults to ``("next", "state")``.
            belief: start beliefs h. Defaults to ``("next", "belief")``.
            free_state: start states z. Defaults to ``("next", "free_state")``.
            free_belief: start beliefs h'. Defaults to ``("next", "free_belief")``.
            lambda_target: where the returns are written. Defaults to ``"lambda_target"``.
            discount_weight: where the weights ``w`` are written. Defaults to ``"discount_weight"``.
        """

        state: NestedKey = ("next", "state")
        belief: NestedKey = ("next", "belief")
        free_state: NestedKey = ("next", "free_state")
        free_belief: NestedKey = ("next", "free_belief")
        lambda_target: NestedKey = "lambda_target"
        discount_weight: NestedKey = "discount_weight"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        actor: IsoDreamV2Actor,
        imagination: IsoDreamV2Imagination,
        value_loss: IsoDreamV2ValueLoss,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        entropy_bonus: float = 1e-4,
        gradient: str = "dynamics",
        attention_through_actor: bool = False,
        loc_penalty: float = 0.1,
    ):
        super().__init__()
        if gradient not in ACTOR_GRADIENTS:
            raise ValueError(f"unknown actor gradient {gradient!r}; valid: {ACTOR_GRADIENTS}")
        if not loc_penalty >= 0:
            raise ValueError(f"loc_penalty must be >= 0, got {loc_penalty}")
        if actor.in_features != imagination.policy_input.out_features:
            raise ValueError(
                f"the actor reads {actor.in_features} features, the policy input gives "
                f"{imagination.policy_input.out_features}"
            )
        if imagination.world_model.config.action_dim != actor.action_dim:
            raise ValueError(
                f"the actor has {actor.action_dim} action dims, the world model {imagination.world_model.config.action_dim}"
            )
        self.actor = actor
        # Kept out of the module tree so that ``parameters()`` is the actor's group only.
        self.__dict__["imagination"] = imagination
        self.__dict__["value_loss"] = value_loss
        self.gamma, self.lmbda, self.entropy_bonus = gamma, lmbda, entropy_bonus
        self.gradient = gradient
        self.attention_through_actor = attention_through_actor
        self.loc_penalty = loc_penalty

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """``{"world_model", "actor", "value"}`` parameter lists, one per optimiser; ``"value"`` holds the value
        network and the policy input (attention)."""
        return {
            "world_model": list(self.imagination.world_model.parameters()),
            "actor": list(self.actor.parameters()),
            "value": list(self.value_loss.parameters()),
        }

    def _start(self, tensordict: TensorDictBase) -> list[torch.Tensor | None]:
        keys = self.tensor_keys
        names = ["state", "belief"] + (
            ["free_state", "free_belief"] if self.imagination.uses_free_branch else []
        )
        out: list[torch.Tensor | None] = [None] * 4
        for i, name in enumerate(names):
            key = getattr(keys, name)
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(
                    f"IsoDreamV2ActorLoss needs the start {name} at key {key!r} (remap with set_keys); found "
                    f"{sorted(map(str, tensordict.keys(True, True)))}"
                )
            out[i] = value.detach().reshape(-1, value.shape[-1])
        return out

    def forward(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        imagination, value_loss, actor = self.imagination, self.value_loss, self.actor
        start = self._start(tensordict)
        reinforce = self.gradient == "reinforce"
        device_type = start[0].device.type
        with hold_out_net(imagination.world_model):
            with torch.no_grad() if reinforce else contextlib.nullcontext():
                imagined = imagination(*start, actor=actor, actor_input_grad=self.attention_through_actor)
                with hold_out_net(imagination.policy_input), imagination.autocast(device_type):
                    next_value = value_loss.target_value(
                        policy_features(imagination.policy_input, imagined["next"])
                    )
        reward = imagined.get(("next", "reward"))
        continuation = imagined.get(("next", "continuation"), None)
        gamma = self.gamma if continuation is None else self.gamma * continuation
        target = lambda_returns(reward, next_value.float(), gamma, self.lmbda)
        step_discount = torch.as_tensor(gamma, device=reward.device).expand_as(reward)
        weight = torch.cat([torch.ones_like(reward[:, :1]), step_discount[:, :-1]], dim=1).cumprod(1).detach()

        if reinforce:
            features = imagined.get("attended_state")
            with imagination.autocast(device_type):
                if self.attention_through_actor:
                    features = policy_features(
                        imagination.policy_input, imagined, detach_control=True
                    ).float()
                distribution = actor.distribution(features)
                with torch.no_grad():
                    baseline = value_loss.target_value(features)
            log_prob = distribution.log_prob(imagined.get("action")).unsqueeze(-1)
            objective = log_prob * (target - baseline.float()).detach()
            entropy = -distribution.rsample_and_log_prob()[1].unsqueeze(-1)
        else:
            objective = target
            entropy = -imagined.get("action_log_prob").unsqueeze(-1)
        loss = -(weight * (objective + self.entropy_bonus * entropy)).mean()
        with (
            torch.set_grad_enabled(torch.is_grad_enabled() and self.loc_penalty > 0),
            imagination.autocast(device_type),
        ):
            loc = actor(imagined.get("attended_state").detach())[0].float()

        imagined = imagined.detach()
        imagined.set(self.tensor_keys.lambda_target, target.detach())
        imagined.set(self.tensor_keys.discount_weight, weight)
        terms = {"loss_actor": loss}
        if self.loc_penalty:
            terms["loss_actor_loc"] = self.loc_penalty * loc.pow(2).mean()
        losses = TensorDict(
            {
                **terms,
                "actor_entropy": entropy.detach().mean(),
                "actor_loc_abs": loc.detach().abs().mean(),
                "lambda_target_mean": target.detach().mean(),
                "imagined_reward_mean": reward.detach().mean(),
            },
            [],
        )
        return losses, imagined
