"""The Iso-Dream world-model loss (paper eq. 5)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch.nn import functional as F
from torchrl.objectives import LossModule

from isodream_rl.modules.encoder import preprocess_pixels
from isodream_rl.modules.world_model import IsoDreamWorldModel
from isodream_rl.objectives.inverse_dynamics import InverseDynamicsLoss
from isodream_rl.objectives.kl import balanced_kl
from isodream_rl.objectives.mask_assignment import mask_assignment
from isodream_rl.objectives.pyramid import pyramid_squared_error

FREE_BRANCH_MODES = ("kl", "recon_only")
#: where each branch's component (as composed) sits in the world model's output
COMPONENT_KEYS = {"control": ("next", "reco_control"), "free": ("next", "reco_free"), "static": "background"}


class IsoDreamModelLoss(LossModule):
    """World-model loss of eq. 5 over ``[B, T]`` replay windows.

    ``L = lambda_reco * L_img + lambda_reward * L_rew + lambda_discount * L_gamma + alpha * L_inv
    + beta1 * KL_s + beta2 * KL_z`` with

    * ``L_img = -log N(o_t; o^_t, I)`` summed over pixels (``0.5 * squared error``, constants dropped),
      mean over ``B, T``; ``o^_t`` is the mask composition of eq. 4;
    * ``L_rew = -log N(r_t; r^_t, 1)`` and ``L_gamma`` a Bernoulli log-loss on "not terminated" (when the
      world model has a discount head);
    * ``L_inv`` from :class:`~isodream_rl.objectives.InverseDynamicsLoss`;
    * ``KL_s``, ``KL_z``: DreamerV2-balanced KLs with free nats on the batch mean, one per branch.

    Args:
        world_model: an :class:`~isodream_rl.modules.IsoDreamWorldModel`.
        lambda_reco: weight of the image log-loss (1).
        lambda_reward: weight of the reward log-loss (2 in the authors' DMC and CARLA configs).
        lambda_discount: weight of the discount log-loss (1; used only with a discount head).
        lambda_inverse: ``alpha``, the weight of the action loss (1).
        lambda_kl_control: ``beta1``, the weight of ``KL_s`` (1).
        lambda_kl_free: ``beta2``, the weight of ``KL_z`` (1).
        kl_balance: DreamerV2 KL balancing (0.8).
        free_nats: free nats, applied to each branch's batch-mean KL (1.0).
        free_branch: ``"kl"`` (CARLA-style: the noncontrollable branch has its KL term) or ``"recon_only"``
            (DMC-style, §3.2 last paragraph: it learns from reconstruction alone; ``KL_z`` is only logged).
        inverse_loss: ``"gaussian"`` or ``"l2"``, see :class:`~isodream_rl.objectives.InverseDynamicsLoss`.
        lambda_free_component: weight of an auxiliary term that asks the noncontrollable component alone
            (``("next", "reco_free")``, before masking) to reconstruct the whole frame, ``0.5 * squared
            error`` summed over pixels like ``L_img`` (0: off, the paper's loss). Not in the paper: it keeps
            the branch learning to draw every object it can read off the frame even where the softmax has
            shut its mask (see :mod:`isodream_rl.modules.composition`); the masks still decide the
            composite. A plain attribute, so a training loop can anneal it.
        free_component_pixels: which pixels that term covers: ``"all"`` (the whole frame) or ``"residual"``:
            each pixel weighted by ``w = e^2 / (e^2 + kappa^2)`` times ``1 - M^s``, with ``e`` the static
            background's squared error there (summed over RGB) and ``kappa = residual_scale``, both detached:
            the branch is asked to draw what the background does not explain and the controllable branch
            does not claim, not the background itself (which the whole-frame version made it take over).
        residual_scale: ``kappa`` of the residual weighting (0.1: a pixel the background misses by 0.3 weighs
            0.9, one it misses by 0.02 weighs 0.04).
        lambda_mask_assignment: weight of the mask-assignment term of
            :mod:`isodream_rl.objectives.mask_assignment` (0: off, the paper's loss): each pixel's masks are
            pulled towards the branches' responsibilities for it, so a branch whose component explains a
            region better than its owner can take it even where the softmax has shut its mask. Needs two
            or more branches.
        assignment_std: ``sigma`` of the responsibilities (0.1 on the ``[-0.5, 0.5]`` pixel range).
        assignment_branches: the branches between which the term assigns pixels (``("free", "static")``,
            the default: the split between what moves on its own and what does not; the controllable mask
            is left to the image loss and the action, see :mod:`isodream_rl.objectives.mask_assignment`);
            ``None``: every branch the model has.
        lambda_reco_pyramid: weight of a coarse-to-fine image term (0: off, the paper's loss): ``0.5 *``
            the composite's squared error on levels 1 ... ``pyramid_levels`` of a Gaussian pyramid (blurred
            and halved each level), level ``l`` weighted by ``4^l``, summed over pixels, mean over ``B, T``
            (:mod:`isodream_rl.objectives.pyramid`). Not in the paper: it gives a small object drawn off its
            place a gradient towards it.
        pyramid_levels: pyramid levels of that term (3: 32x32, 16x16 and 8x8 for 64x64 frames).

    Returns:
        ``(losses, model_output)``, like TorchRL's ``DreamerModelLoss``: ``losses`` holds
        ``loss_model_reco``, ``loss_model_reward``, ``loss_model_kl_control`` and, depending on the model
        and mode, ``loss_model_kl_free``, ``loss_model_inverse``, ``loss_model_discount``,
        ``loss_model_free_component``, ``loss_model_mask_assignment``, ``loss_model_reco_pyramid``; plus detached
        diagnostics ``kl_control``, ``kl_free``, ``mask_control``, ``mask_free``, ``mask_static`` (mean
        masks) and ``reco_mse``. ``model_output`` is the world model's output tensordict (posteriors
        under ``"next"``), the start states for imagination.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from isodream_rl.modules import IsoDreamWorldModel, WorldModelConfig
        >>> from isodream_rl.objectives import IsoDreamModelLoss
        >>> loss = IsoDreamModelLoss(IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2)))
        >>> td = TensorDict({"action": torch.zeros(2, 5, 2),
        ...                  ("next", "pixels"): torch.zeros(2, 5, 3, 64, 64, dtype=torch.uint8),
        ...                  ("next", "reward"): torch.zeros(2, 5, 1)}, [2, 5])
        >>> losses, _ = loss(td)
        >>> sorted(k for k in losses.keys() if k.startswith("loss"))[:2]
        ['loss_model_inverse', 'loss_model_kl_control']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; remap with :meth:`set_keys`.

        Attributes:
            pixels: observations o_{t+1}. Defaults to ``("next", "pixels")``.
            action: actions a_t. Defaults to ``"action"``.
            is_init: episode starts inside the window. Defaults to ``"is_init"``.
            reward: true rewards. Defaults to ``("next", "reward")``.
            terminated: true terminations (discount head only). Defaults to ``("next", "terminated")``.
        """

        pixels: NestedKey = ("next", "pixels")
        action: NestedKey = "action"
        is_init: NestedKey = "is_init"
        reward: NestedKey = ("next", "reward")
        terminated: NestedKey = ("next", "terminated")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        world_model: IsoDreamWorldModel,
        *,
        lambda_reco: float = 1.0,
        lambda_reward: float = 1.0,
        lambda_discount: float = 1.0,
        lambda_inverse: float = 1.0,
        lambda_kl_control: float = 1.0,
        lambda_kl_free: float = 1.0,
        kl_balance: float = 0.8,
        free_nats: float = 1.0,
        free_branch: str = "kl",
        inverse_loss: str = "gaussian",
        lambda_free_component: float = 0.0,
        free_component_pixels: str = "all",
        residual_scale: float = 0.1,
        lambda_mask_assignment: float = 0.0,
        assignment_std: float = 0.1,
        assignment_branches: tuple[str, ...] | None = ("free", "static"),
        lambda_reco_pyramid: float = 0.0,
        pyramid_levels: int = 3,
    ):
        super().__init__()
        if free_branch not in FREE_BRANCH_MODES:
            raise ValueError(f"unknown free_branch mode {free_branch!r}; valid: {FREE_BRANCH_MODES}")
        self.world_model = world_model
        self.inverse_loss = InverseDynamicsLoss(lambda_inverse=lambda_inverse, loss_type=inverse_loss)
        self.lambda_reco = lambda_reco
        self.lambda_reward = lambda_reward
        self.lambda_discount = lambda_discount
        self.lambda_kl_control = lambda_kl_control
        self.lambda_kl_free = lambda_kl_free
        self.kl_balance = kl_balance
        self.free_nats = free_nats
        self.free_branch = free_branch
        if lambda_free_component < 0:
            raise ValueError(f"lambda_free_component must be >= 0, got {lambda_free_component}")
        self.lambda_free_component = lambda_free_component
        if free_component_pixels not in ("all", "residual") or residual_scale <= 0:
            raise ValueError(
                f"free_component_pixels must be 'all' or 'residual' and residual_scale > 0, got "
                f"{free_component_pixels!r} and {residual_scale}"
            )
        if free_component_pixels == "residual" and not world_model.config.static_branch:
            raise ValueError("free_component_pixels='residual' needs the static branch (static_branch=True)")
        self.free_component_pixels = free_component_pixels
        self.residual_scale = residual_scale
        if lambda_mask_assignment < 0 or assignment_std <= 0:
            raise ValueError(
                f"lambda_mask_assignment must be >= 0 and assignment_std > 0, got {lambda_mask_assignment} "
                f"and {assignment_std}"
            )
        cfg = world_model.config
        present = [name for name in COMPONENT_KEYS if name == "control" or getattr(cfg, f"{name}_branch")]
        chosen = tuple(present if assignment_branches is None else assignment_branches)
        if lambda_mask_assignment and (len(chosen) < 2 or not set(chosen) <= set(present)):
            raise ValueError(
                f"lambda_mask_assignment needs two or more of the model's branches {present}, got "
                f"assignment_branches={assignment_branches}"
            )
        #: the branches the assignment term reads (its masks and components), and assigns between
        self.assignment_branches = chosen
        self.lambda_mask_assignment = lambda_mask_assignment
        self.assignment_std = assignment_std
        if lambda_reco_pyramid < 0 or not 1 <= pyramid_levels <= 6:
            raise ValueError(
                f"lambda_reco_pyramid must be >= 0 and pyramid_levels in [1, 6] (64x64 frames), got "
                f"{lambda_reco_pyramid} and {pyramid_levels}"
            )
        self.lambda_reco_pyramid = lambda_reco_pyramid
        self.pyramid_levels = pyramid_levels

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def _read(self, tensordict: TensorDictBase, key: NestedKey, *, required: bool = True):
        value = tensordict.get(key, None)
        if value is None and required:
            raise KeyError(
                f"IsoDreamModelLoss: the input has no key {key!r}; remap it with "
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
        nxt = out.get("next")

        reco = nxt.get("reco_pixels")
        target = preprocess_pixels(pixels)
        # One fused kernel forward and backward; the per-frame sum, averaged over [B, T].
        squared_sum = F.mse_loss(reco, target, reduction="sum")
        frames = reco.numel() // reco.shape[-3:].numel()
        losses = {"loss_model_reco": self.lambda_reco * 0.5 * squared_sum / frames}
        if self.lambda_reco_pyramid:
            coarse = pyramid_squared_error(reco, target, levels=self.pyramid_levels)
            losses["loss_model_reco_pyramid"] = self.lambda_reco_pyramid * 0.5 * coarse / frames
        if self.lambda_free_component:
            if not cfg.free_branch:
                raise ValueError("lambda_free_component needs the noncontrollable branch (free_branch=True)")
            component = nxt.get("reco_free")
            if self.free_component_pixels == "all":
                squared = F.mse_loss(component, target, reduction="sum")
            else:
                with torch.no_grad():
                    miss = (out.get("background") - target).pow(2).sum(-3, keepdim=True)
                    weight = miss.square() / (miss.square() + self.residual_scale**2)
                    weight = weight * (1.0 - nxt.get("mask_control"))
                squared = ((component - target).pow(2) * weight).sum()
            losses["loss_model_free_component"] = self.lambda_free_component * 0.5 * squared / frames
        if self.lambda_mask_assignment:
            names = self.assignment_branches
            colors = {name: out.get(COMPONENT_KEYS[name]) for name in names}
            masks = {name: nxt.get(f"mask_{name}") for name in names}
            assignment, _ = mask_assignment(masks, colors, target, std=self.assignment_std)
            losses["loss_model_mask_assignment"] = self.lambda_mask_assignment * assignment
        if reward.shape != nxt.get("reward_pred").shape:
            raise ValueError(f"reward must have shape [B, T, 1], got {tuple(reward.shape)}")
        losses["loss_model_reward"] = (
            self.lambda_reward * 0.5 * (nxt.get("reward_pred") - reward.float()).pow(2).mean()
        )
        if cfg.discount_head:
            not_terminated = 1.0 - self._read(tensordict, keys.terminated).float()
            losses["loss_model_discount"] = self.lambda_discount * F.binary_cross_entropy_with_logits(
                nxt.get("discount_logit"), not_terminated
            )
        if cfg.inverse_dynamics:
            losses["loss_model_inverse"] = self.inverse_loss(out)["loss_inverse"]

        kl_kwargs = {"balance": self.kl_balance, "free_nats": self.free_nats}
        kl_loss, kl_control = balanced_kl(
            nxt.get("posterior_mean"),
            nxt.get("posterior_std"),
            nxt.get("prior_mean"),
            nxt.get("prior_std"),
            **kl_kwargs,
        )
        losses["loss_model_kl_control"] = self.lambda_kl_control * kl_loss
        diagnostics = {"kl_control": kl_control, "reco_mse": squared_sum.detach() / reco.numel()}
        if cfg.free_branch:
            kl_loss, kl_free = balanced_kl(
                nxt.get("free_posterior_mean"),
                nxt.get("free_posterior_std"),
                nxt.get("free_prior_mean"),
                nxt.get("free_prior_std"),
                **kl_kwargs,
            )
            if self.free_branch == "kl":
                losses["loss_model_kl_free"] = self.lambda_kl_free * kl_loss
            diagnostics["kl_free"] = kl_free
        for name in ("control", "free", "static"):
            mask = nxt.get(f"mask_{name}", None)
            if mask is not None:
                diagnostics[f"mask_{name}"] = mask.detach().mean()
        result = TensorDict({**losses, **diagnostics}, [])
        return result, out

    @staticmethod
    def total(losses: TensorDictBase) -> torch.Tensor:
        """Sum of the ``loss_*`` entries."""
        return sum(v for k, v in losses.items() if k.startswith("loss_"))
