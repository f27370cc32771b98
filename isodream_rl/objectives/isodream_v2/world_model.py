"""The Iso-Dream world-model loss (paper eq. 5)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F
from torchrl.objectives import LossModule

from isodream_rl.modules.isodream_v2.world_model import IsoDreamV2WorldModel
from isodream_rl.modules.pixels import preprocess_pixels
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.isodream_v2.kl import balanced_kl

FREE_BRANCH_MODES = ("kl", "recon_only")
#: The weights of eq. 5's terms: the one table of their defaults (as DreamerV3's ``loss_scales``), read by
#: :class:`IsoDreamV2ModelLoss` and by the training config (``AlgoConfig``). ``lambda_inverse`` (``alpha``) departs
#: from eq. 5's 1: with the default ``inverse_input="embedding"`` the embedding differences are small and at 1
#: the inverse cell does not learn against the pixel-sum image loss (:data:`PAPER_WEIGHTS` has the paper's).
LOSS_WEIGHTS = {
    "lambda_reco": 1.0,
    "lambda_reward": 1.0,
    "lambda_discount": 1.0,
    "lambda_inverse": 30.0,
    "lambda_kl_control": 1.0,
    "lambda_kl_free": 1.0,
}
#: eq. 5's weights where :data:`LOSS_WEIGHTS` departs from them (:meth:`IsoDreamV2ModelLoss.paper_exact`,
#: ``algo=isodream_paper``).
PAPER_WEIGHTS = {"lambda_inverse": 1.0}


class IsoDreamV2ModelLoss(LossModule):
    """World-model loss of eq. 5 over ``[B, T]`` replay windows.

    ``L = lambda_reco * L_img + lambda_reward * L_rew + lambda_discount * L_gamma + alpha * L_inv
    + beta1 * KL_s + beta2 * KL_z`` with

    * ``L_img = -log N(o_t; o^_t, I)`` summed over pixels (``0.5 * squared error``, constants dropped),
      mean over ``B, T``; ``o^_t`` is the mask composition of eq. 4;
    * ``L_rew = -log N(r_t; r^_t, 1)`` and ``L_gamma`` a Bernoulli log-loss on "not terminated" (when the
      world model has a discount head);
    * ``L_inv`` from :class:`~isodream_rl.objectives.InverseDynamicsLoss`;
    * ``KL_s``, ``KL_z``: DreamerV2-balanced KLs with free nats on the batch mean, one per branch.

    The ``lambda_*`` weights default to :data:`LOSS_WEIGHTS`.

    Args:
        world_model: an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`.
        lambda_reco: weight of the image log-loss.
        lambda_reward: weight of the reward log-loss (2 in the authors' DMC and CARLA configs).
        lambda_discount: weight of the discount log-loss (used only with a discount head).
        lambda_inverse: ``alpha``, the weight of the action loss (see :data:`LOSS_WEIGHTS` for its default;
            :meth:`paper_exact` gives eq. 5's 1).
        lambda_kl_control: ``beta1``, the weight of ``KL_s``.
        lambda_kl_free: ``beta2``, the weight of ``KL_z``.
        kl_balance: DreamerV2 KL balancing (0.8).
        free_nats: free nats, applied to each branch's batch-mean KL (1.0).
        free_branch_loss: ``"kl"`` (CARLA-style: the noncontrollable branch has its KL term) or
            ``"recon_only"`` (DMC-style, §3.2 last paragraph: it learns from reconstruction alone; ``KL_z`` is
            only logged).
        inverse_loss: ``"gaussian"`` or ``"l2"``, see :class:`~isodream_rl.objectives.InverseDynamicsLoss`.
        extra_terms: terms added to eq. 5 (none by default, the paper's loss), each a callable (an
            ``nn.Module`` to have its parameters and device follow the loss) taking the composite ``o^``
            and the target ``o``, both ``[B, T, 3, 64, 64]`` in the ``[-0.5, 0.5]`` range, and returning a
            mapping of ``loss_*`` scalars.

    Inputs are checked at the world model's boundary (:class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`,
    ``check_inputs``): float pixels outside ``[0, 1]``, NaN/inf pixels or actions, a missing ``is_init`` and
    windows shorter than 2 steps raise a ``ValueError``; ``IsoDreamV2WorldModel(..., check_inputs=False)`` skips
    these checks.

    Returns:
        ``(losses, model_output)``, like TorchRL's ``DreamerModelLoss``: ``losses`` holds
        ``loss_model_reco``, ``loss_model_reward``, ``loss_model_kl_control`` and, depending on the model
        and mode, ``loss_model_kl_free``, ``loss_model_inverse``, ``loss_model_discount`` and the extra
        terms' entries; plus detached
        diagnostics ``kl_control``, ``kl_free``, ``mask_control``, ``mask_free``, ``mask_static`` (mean
        masks) and ``reco_mse``. ``model_output`` is the world model's output tensordict (posteriors
        under ``"next"``), the start states for imagination.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from isodream_rl.modules import IsoDreamV2WorldModel, IsoDreamV2Config
        >>> from isodream_rl.objectives import IsoDreamV2ModelLoss
        >>> loss = IsoDreamV2ModelLoss(IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2)))
        >>> td = TensorDict({"action": torch.zeros(2, 5, 2), "is_init": torch.zeros(2, 5, 1, dtype=torch.bool),
        ...                  ("next", "pixels"): torch.zeros(2, 5, 3, 64, 64, dtype=torch.uint8),
        ...                  ("next", "reward"): torch.zeros(2, 5, 1)}, [2, 5])
        >>> losses, _ = loss(td)
        >>> sorted(k for k in losses.keys() if k.startswith("loss"))[:2]
        ['loss_model_inverse', 'loss_model_kl_control']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; remap with :meth:`set_keys`.

        The first five are read from the input; the others from the world model's output (remap them for a
        world model that writes its predictions elsewhere, as TorchRL's ``DreamerModelLoss`` does).

        Attributes:
            pixels: observations o_{t+1}. Defaults to ``("next", "pixels")``.
            action: actions a_t. Defaults to ``"action"``.
            is_init: episode starts inside the window. Defaults to ``"is_init"``.
            reward: true rewards. Defaults to ``("next", "reward")``.
            terminated: true terminations (discount head only). Defaults to ``("next", "terminated")``.
            reco_pixels: the composite o^_{t+1} (eq. 4). Defaults to ``("next", "reco_pixels")``.
            reward_pred: predicted rewards. Defaults to ``("next", "reward_pred")``.
            discount_logit: predicted continuation logits. Defaults to ``("next", "discount_logit")``.
            prior_mean, prior_std, posterior_mean, posterior_std: the controllable branch's prior and posterior
                statistics. Default to ``("next", "prior_mean")`` and so on.
            free_prior_mean, free_prior_std, free_posterior_mean, free_posterior_std: the same for the
                noncontrollable branch. Default to ``("next", "free_prior_mean")`` and so on.
            mask_control, mask_free, mask_static: the masks of eq. 4 (logged as means). Default to
                ``("next", "mask_control")`` and so on.
            action_pred, action_pred_valid: the inverse cell's prediction and where it exists (see
                :class:`~isodream_rl.objectives.InverseDynamicsLoss`). Default to ``("next", "action_pred")``
                and ``("next", "action_pred_valid")``.
        """

        pixels: NestedKey = ("next", "pixels")
        action: NestedKey = "action"
        is_init: NestedKey = "is_init"
        reward: NestedKey = ("next", "reward")
        terminated: NestedKey = ("next", "terminated")
        reco_pixels: NestedKey = ("next", "reco_pixels")
        reward_pred: NestedKey = ("next", "reward_pred")
        discount_logit: NestedKey = ("next", "discount_logit")
        prior_mean: NestedKey = ("next", "prior_mean")
        prior_std: NestedKey = ("next", "prior_std")
        posterior_mean: NestedKey = ("next", "posterior_mean")
        posterior_std: NestedKey = ("next", "posterior_std")
        free_prior_mean: NestedKey = ("next", "free_prior_mean")
        free_prior_std: NestedKey = ("next", "free_prior_std")
        free_posterior_mean: NestedKey = ("next", "free_posterior_mean")
        free_posterior_std: NestedKey = ("next", "free_posterior_std")
        mask_control: NestedKey = ("next", "mask_control")
        mask_free: NestedKey = ("next", "mask_free")
        mask_static: NestedKey = ("next", "mask_static")
        action_pred: NestedKey = ("next", "action_pred")
        action_pred_valid: NestedKey = ("next", "action_pred_valid")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        world_model: IsoDreamV2WorldModel,
        *,
        lambda_reco: float = LOSS_WEIGHTS["lambda_reco"],
        lambda_reward: float = LOSS_WEIGHTS["lambda_reward"],
        lambda_discount: float = LOSS_WEIGHTS["lambda_discount"],
        lambda_inverse: float = LOSS_WEIGHTS["lambda_inverse"],
        lambda_kl_control: float = LOSS_WEIGHTS["lambda_kl_control"],
        lambda_kl_free: float = LOSS_WEIGHTS["lambda_kl_free"],
        kl_balance: float = 0.8,
        free_nats: float = 1.0,
        free_branch_loss: str = "kl",
        inverse_loss: str = "gaussian",
        extra_terms: Iterable[Callable[[torch.Tensor, torch.Tensor], Mapping[str, torch.Tensor]]] = (),
    ):
        super().__init__()
        if free_branch_loss not in FREE_BRANCH_MODES:
            raise ValueError(f"unknown free_branch_loss {free_branch_loss!r}; valid: {FREE_BRANCH_MODES}")
        self.world_model = world_model
        self.inverse_loss = InverseDynamicsLoss(lambda_inverse=lambda_inverse, loss_type=inverse_loss)
        self.lambda_reco = lambda_reco
        self.lambda_reward = lambda_reward
        self.lambda_discount = lambda_discount
        self.lambda_kl_control = lambda_kl_control
        self.lambda_kl_free = lambda_kl_free
        self.kl_balance = kl_balance
        self.free_nats = free_nats
        self.free_branch_loss = free_branch_loss
        modules = [term for term in extra_terms if isinstance(term, nn.Module)]
        #: the extra terms that are modules (registered, so they follow ``.to()`` and ``state_dict``)
        self.extra_modules = nn.ModuleList(modules)
        self.extra_terms = tuple(extra_terms)

    @classmethod
    def paper_exact(cls, world_model: IsoDreamV2WorldModel, **overrides) -> IsoDreamV2ModelLoss:
        """The loss with eq. 5's weights (``alpha = 1``), the partner of
        :meth:`IsoDreamV2Config.paper_exact <isodream_rl.modules.isodream_v2.config.IsoDreamV2Config.paper_exact>`."""
        return cls(world_model, **{**PAPER_WEIGHTS, **overrides})

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def _read(self, tensordict: TensorDictBase, key: NestedKey, *, required: bool = True):
        value = tensordict.get(key, None)
        if value is None and required:
            raise KeyError(
                f"IsoDreamV2ModelLoss: no key {key!r} in the input or the world model's output; remap it with "
                f"loss.set_keys(...) (accepted keys: {self.tensor_keys})"
            )
        return value

    def forward(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        keys = self.tensor_keys
        cfg = self.world_model.config
        pixels = self._read(tensordict, keys.pixels)
        reward = self._read(tensordict, keys.reward)
        model_in = TensorDict(
            {("next", "pixels"): pixels, "action": self._read(tensordict, keys.action)},
            batch_size=tensordict.batch_size,
            device=tensordict.device,
        )
        is_init = self._read(tensordict, keys.is_init, required=False)
        if is_init is not None:
            model_in.set("is_init", is_init)
        out = self.world_model(model_in)

        reco = self._read(out, keys.reco_pixels)
        target = preprocess_pixels(pixels)
        # One fused kernel forward and backward; the per-frame sum, averaged over [B, T].
        squared_sum = F.mse_loss(reco, target, reduction="sum")
        frames = reco.numel() // reco.shape[-3:].numel()
        losses = {"loss_model_reco": self.lambda_reco * 0.5 * squared_sum / frames}
        for term in self.extra_terms:
            entries = dict(term(reco, target))
            if not all(name.startswith("loss_") for name in entries) or set(entries) & set(losses):
                raise ValueError(f"extra term {term!r} must return new loss_* entries, got {sorted(entries)}")
            losses.update(entries)
        reward_pred = self._read(out, keys.reward_pred)
        if reward.shape != reward_pred.shape:
            raise ValueError(f"reward must have shape [B, T, 1], got {tuple(reward.shape)}")
        losses["loss_model_reward"] = self.lambda_reward * 0.5 * (reward_pred - reward.float()).pow(2).mean()
        if cfg.discount_head:
            not_terminated = 1.0 - self._read(tensordict, keys.terminated).float()
            losses["loss_model_discount"] = self.lambda_discount * F.binary_cross_entropy_with_logits(
                self._read(out, keys.discount_logit), not_terminated
            )
        if cfg.inverse_dynamics:
            # under the inverse loss's own default keys, whatever this loss's keys are remapped to
            inverse_in = TensorDict(
                {
                    "action": model_in.get("action"),
                    ("next", "action_pred"): self._read(out, keys.action_pred),
                    ("next", "action_pred_valid"): self._read(out, keys.action_pred_valid),
                },
                batch_size=out.batch_size,
            )
            losses["loss_model_inverse"] = self.inverse_loss(inverse_in)["loss_inverse"]

        kl_kwargs = {"balance": self.kl_balance, "free_nats": self.free_nats}
        kl_loss, kl_control = balanced_kl(
            self._read(out, keys.posterior_mean),
            self._read(out, keys.posterior_std),
            self._read(out, keys.prior_mean),
            self._read(out, keys.prior_std),
            **kl_kwargs,
        )
        losses["loss_model_kl_control"] = self.lambda_kl_control * kl_loss
        diagnostics = {"kl_control": kl_control, "reco_mse": squared_sum.detach() / reco.numel()}
        if cfg.free_branch:
            kl_loss, kl_free = balanced_kl(
                self._read(out, keys.free_posterior_mean),
                self._read(out, keys.free_posterior_std),
                self._read(out, keys.free_prior_mean),
                self._read(out, keys.free_prior_std),
                **kl_kwargs,
            )
            if self.free_branch_loss == "kl":
                losses["loss_model_kl_free"] = self.lambda_kl_free * kl_loss
            diagnostics["kl_free"] = kl_free
        for name, key in (
            ("mask_control", keys.mask_control),
            ("mask_free", keys.mask_free),
            ("mask_static", keys.mask_static),
        ):
            mask = out.get(key, None)
            if mask is not None:
                diagnostics[name] = mask.detach().mean()
        result = TensorDict({**losses, **diagnostics}, [])
        return result, out

    @staticmethod
    def total(losses: TensorDictBase) -> torch.Tensor:
        """Sum of the ``loss_*`` entries."""
        return sum(v for k, v in losses.items() if k.startswith("loss_"))
