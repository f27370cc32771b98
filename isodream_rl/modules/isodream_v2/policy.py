"""The DreamerV2-style learner's acting policy: policy deployment by rolling out noncontrollable dynamics (paper
§3.4, Algorithm 1 lines 19-22), :class:`IsoDreamV2Policy`."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.envs.utils import ExplorationType, exploration_type

from isodream_rl.modules.attention import PolicyInput
from isodream_rl.modules.carried_state import carried_state_primer, read_acting_inputs
from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.modules.isodream_v2.rssm import filter_step
from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel

_RANDOM = (None, ExplorationType.RANDOM)


class IsoDreamV2Policy(TensorDictModuleBase):
    """Acting policy: filter the new observation, roll ``z`` ``tau - 1`` steps ahead, attend, act.

    At each environment step ``t``: both branches' posteriors ``(s_t, h_t)``, ``(z_t, h'_t)`` from the
    previous posteriors, the previous action and ``o_t`` (:func:`~isodream_rl.modules.isodream_v2.rssm.filter_step`, the same filter as
    in training, zeroing the carried state where ``is_init``); the window ``[z_t, z~_{t+1..t+tau-1}]`` from the
    action-free prior; ``e_t`` from the policy input; ``a_t`` sampled from the actor (exploration type
    ``RANDOM`` or unset, plus optional Gaussian ``exploration_noise``, clamped to [-1, 1]) or its mode
    (``DETERMINISTIC``/``MODE``/``MEAN``, e.g. under ``set_exploration_type`` for evaluation).

    The recurrent state follows TorchRL's recurrent-module convention: the root holds what the previous step
    left (``state``, ``belief``, ``free_state``, ``free_belief``, ``previous_action``) and the policy writes
    the new values under ``"next"``, which ``step_mdp`` moves to the root for the next step. Prime the env
    with :meth:`make_tensordict_primer` (``TensorDictPrimer``; also found by TorchRL's
    ``get_primers_from_module``) so the keys exist at reset and travel through the collector.

    Runs without gradients; works for an unbatched env or any batch of envs.

    Args:
        world_model: the trained :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`.
        actor: the :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2Actor`.
        policy_input: the :class:`~isodream_rl.modules.PolicyInput` (its ``window`` is ``tau``).
        exploration_noise: std of Gaussian noise added to sampled actions (0, as the authors).
        pixels_key: observation key (uint8 ``[*B, 3, 64, 64]``). Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from isodream_rl.modules import IsoDreamV2Actor, IsoDreamV2WorldModel, PolicyInput, IsoDreamV2Config
        >>> wm = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
        >>> pin = PolicyInput.for_world_model(wm, mode="attention", window=3, width=8)
        >>> policy = IsoDreamV2Policy(wm, IsoDreamV2Actor(in_features=pin.out_features, action_dim=2, num_cells=8), pin)
        >>> td = policy.make_tensordict_primer().primers.zero().expand(4).clone()
        >>> td.update({"pixels": torch.zeros(4, 3, 64, 64, dtype=torch.uint8), "is_init": torch.ones(4, 1, dtype=torch.bool)})
        TensorDict(...)
        >>> policy(td)["action"].shape
        torch.Size([4, 2])
    """

    def __init__(
        self,
        world_model: IsoDreamV2WorldModel,
        actor: IsoDreamV2Actor,
        policy_input: PolicyInput,
        *,
        exploration_noise: float = 0.0,
        pixels_key: str = "pixels",
        action_key: str = "action",
    ):
        super().__init__()
        cfg = world_model.config
        if policy_input.uses_free_branch and not cfg.free_branch:
            raise ValueError(f"policy_input={policy_input.mode!r} needs the world model's free branch")
        if actor.in_features != policy_input.out_features or actor.action_dim != cfg.action_dim:
            raise ValueError(
                f"actor ({actor.in_features} -> {actor.action_dim}) does not fit the policy input "
                f"({policy_input.out_features} features) and world model ({cfg.action_dim} action dims)"
            )
        if exploration_noise < 0:
            raise ValueError(f"exploration_noise must be >= 0, got {exploration_noise}")
        self.world_model, self.actor, self.policy_input = world_model, actor, policy_input
        self.exploration_noise = exploration_noise
        self.pixels_key, self.action_key = pixels_key, action_key
        self.recurrent_keys = ["state", "belief"] + (["free_state", "free_belief"] if cfg.free_branch else [])
        self.in_keys = [pixels_key, "is_init", *self.recurrent_keys, "previous_action"]
        self.out_keys = [action_key] + [("next", k) for k in [*self.recurrent_keys, "previous_action"]]

    def recurrent_spec(self) -> Composite:
        """Specs of the carried keys (unbatched): ``state``/``free_state`` ``[S]``, ``belief``/``free_belief``
        ``[D]``, ``previous_action`` ``[A]``."""
        cfg = self.world_model.config
        device = next(self.world_model.parameters()).device
        sizes = {"state": cfg.state_dim, "belief": cfg.belief_dim, "previous_action": cfg.action_dim}
        sizes.update(free_state=cfg.state_dim, free_belief=cfg.belief_dim)
        keys = [*self.recurrent_keys, "previous_action"]
        return Composite({k: Unbounded(shape=(sizes[k],), device=device) for k in keys})

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """A ``TensorDictPrimer`` adding the carried keys (zeros at reset) to an env or a batch of envs."""
        return carried_state_primer(self.recurrent_spec())

    def _window(self, free_state: torch.Tensor, free_belief: torch.Tensor) -> torch.Tensor:
        tau = self.policy_input.window
        states, beliefs = [free_state], [free_belief]
        for _ in range(tau - 1):
            _, _, free_state, free_belief = self.world_model.free_rssm.imagine_step(free_state, free_belief)
            states.append(free_state)
            beliefs.append(free_belief)
        return torch.cat([torch.stack(states, dim=-2), torch.stack(beliefs, dim=-2)], dim=-1)

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        wm = self.world_model
        batch = tensordict.batch_size
        device = next(wm.parameters()).device
        pixels, previous, reset = read_acting_inputs(
            tensordict,
            owner="IsoDreamV2Policy",
            pixels_key=self.pixels_key,
            carried_keys=[*self.recurrent_keys, "previous_action"],
            device=device,
        )

        with wm.autocast(device.type):
            control_embed, free_embed = wm.encode(pixels.to(device))
            control_proj = wm.control_rssm.project_embedding(control_embed).float()
            free_proj = None if free_embed is None else wm.free_rssm.project_embedding(free_embed).float()
        post = filter_step(
            wm.control_rssm,
            wm.free_rssm,
            previous,
            previous["previous_action"],
            control_proj,
            free_proj,
            reset,
        )

        control = torch.cat([post["state"], post["belief"]], dim=-1)
        free = window = None
        if self.policy_input.mode == "concat":
            free = torch.cat([post["free_state"], post["free_belief"]], dim=-1)
        elif self.policy_input.mode == "attention":
            window = self._window(post["free_state"], post["free_belief"])
        with wm.autocast(device.type):
            features = self.policy_input(control, free, window).float()
            if exploration_type() in _RANDOM:
                action = self.actor.distribution(features).sample()
                if self.exploration_noise:
                    action = (action + self.exploration_noise * torch.randn_like(action)).clamp(-1.0, 1.0)
            else:
                action = self.actor.mode(features)

        out_device = tensordict.device if tensordict.device is not None else pixels.device
        action = action.to(out_device)
        tensordict.set(self.action_key, action.reshape(*batch, -1))
        for key in self.recurrent_keys:
            tensordict.set(("next", key), post[key].to(out_device).reshape(*batch, -1))
        tensordict.set(("next", "previous_action"), action.reshape(*batch, -1))
        return tensordict
