"""Policy deployment by rolling out noncontrollable dynamics (paper §3.4, Algorithm 1 lines 19-22).

:class:`IsoDreamV2Policy` acts for Iso-Dream; :class:`CarriedStatePolicy` is the base of the acting policies around a
TorchRL acting sequence (the baselines', Iso-Dream's DreamerV3 learner's): the recurrent state carried under
TorchRL's ``("next", ...)`` convention, through a primer.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.envs.utils import ExplorationType, exploration_type

from isodream_rl.modules.isodream_v2.actor import IsoDreamV2Actor
from isodream_rl.modules.attention import PolicyInput
from isodream_rl.modules.isodream_v2.encoder import IMAGE_SHAPE, check_pixel_values, check_pixels
from isodream_rl.modules.isodream_v2.rssm import filter_step
from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel

_RANDOM = (None, ExplorationType.RANDOM)


def carried_state_primer(spec: Composite) -> TensorDictPrimer:
    """A ``TensorDictPrimer`` adding the carried keys of ``spec`` (unbatched ``Composite``), zeros at reset, to
    an env or a batch of envs: what every acting policy's ``make_tensordict_primer`` returns."""
    return TensorDictPrimer(spec, random=False, default_value=0.0, expand_specs=True)


def read_acting_inputs(
    tensordict: TensorDictBase,
    *,
    owner: str,
    pixels_key: str,
    carried_keys: list[str],
    device: torch.device,
) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor | None]:
    """What a recurrent acting policy reads at one env step, flattened over the env batch ``[*B]``.

    Returns:
        ``(pixels, carried, reset)``: ``pixels`` ``[N, 3, 64, 64]`` (on their own device), each carried key
        ``[N, F]`` on ``device``, and ``is_init`` as bool ``[N, 1]`` on ``device`` (``None`` without it).

    Raises:
        KeyError: a missing observation or carried key, naming ``owner`` and the primer to add.
        ValueError: pixels that are not ``[*B, 3, 64, 64]``.
    """
    pixels = tensordict.get(pixels_key, None)
    if pixels is None:
        raise KeyError(f"{owner} needs the observation {pixels_key!r} in its input")
    check_pixels(pixels, name=repr(pixels_key))
    n = pixels[..., 0, 0, 0].numel()
    carried = {}
    for key in carried_keys:
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"{owner} carries {key!r} in the tensordict; prime the env with "
                "TransformedEnv(env, policy.make_tensordict_primer())"
            )
        carried[key] = value.to(device).reshape(n, -1)
    is_init = tensordict.get("is_init", None)
    reset = None if is_init is None else is_init.to(device).reshape(n, 1).bool()
    return pixels.reshape(n, *IMAGE_SHAPE), carried, reset


class CarriedStatePolicy(TensorDictModuleBase):
    """An acting policy around a TorchRL acting sequence ``module`` that carries its recurrent state.

    At each env step it reads ``pixels_key`` ``[*B, 3, 64, 64]`` (uint8, or floats in [0, 1] that it turns into
    uint8), ``"is_init"`` and the carried keys
    (``widths``' keys, ``[*B, width]``), flattens them over the env batch, lets :meth:`act` run ``module``, and
    writes only ``action_key`` and ``("next", key)`` for each carried key, following TorchRL's recurrent
    convention; prime the env with :meth:`make_tensordict_primer`. Runs without gradients, on the device of
    ``module``'s parameters; any batch shape (or none). Subclasses implement :meth:`act`.

    Args:
        module: the acting sequence.
        widths: the carried keys and their widths, e.g. ``{"state": S, "belief": D}``.
        pixels_key: the observation key. Defaults to ``"pixels"``.
        action_key: where the action is written. Defaults to ``"action"``.
    """

    def __init__(
        self,
        module: TensorDictModuleBase,
        *,
        widths: dict[str, int],
        pixels_key: str = "pixels",
        action_key: str = "action",
    ) -> None:
        super().__init__()
        self.module = module
        self.widths = dict(widths)
        self.pixels_key, self.action_key = pixels_key, action_key
        self.in_keys = [pixels_key, "is_init", *self.widths]
        self.out_keys = [action_key, *(("next", key) for key in self.widths)]

    def recurrent_spec(self) -> Composite:
        """Specs of the carried keys (unbatched), ``[width]`` each."""
        device = next(self.module.parameters()).device
        return Composite({key: Unbounded((width,), device=device) for key, width in self.widths.items()})

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """A ``TensorDictPrimer`` adding the carried keys (zeros at reset) to an env or a batch of envs."""
        return carried_state_primer(self.recurrent_spec())

    def act(
        self, pixels: torch.Tensor, carried: dict[str, torch.Tensor], reset: torch.Tensor | None
    ) -> dict[str, torch.Tensor]:
        """One step of the acting sequence.

        Args:
            pixels: uint8 ``[N, 3, 64, 64]`` on the module's device.
            carried: each carried key ``[N, width]``.
            reset: ``[N, 1]`` bool, ``True`` where an episode starts; ``None`` without ``"is_init"``.

        Returns:
            ``action_key`` ``[N, A]`` and the next value of each carried key ``[N, width]``.
        """
        raise NotImplementedError(f"{type(self).__name__} must define act(): each baseline's policy step")

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        device = next(self.module.parameters()).device
        pixels, carried, reset = read_acting_inputs(
            tensordict,
            owner=type(self).__name__,
            pixels_key=self.pixels_key,
            carried_keys=list(self.widths),
            device=device,
        )
        if pixels.dtype != torch.uint8:
            # Float frames in [0, 1] (checked: one min/max) become the uint8 frames the acting sequences read.
            check_pixel_values(pixels, name=repr(self.pixels_key))
            pixels = pixels.mul(255.0).round_().to(torch.uint8)
        out_device = tensordict.device if tensordict.device is not None else pixels.device
        outputs = self.act(pixels.to(device), carried, reset)
        tensordict.set(self.action_key, outputs[self.action_key].to(out_device).reshape(*batch, -1))
        for key in self.widths:
            tensordict.set(("next", key), outputs[key].to(out_device).reshape(*batch, -1))
        return tensordict


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
        world_model: the trained :class:`~isodream_rl.modules.IsoDreamV2WorldModel`.
        actor: the :class:`~isodream_rl.modules.IsoDreamV2Actor`.
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
