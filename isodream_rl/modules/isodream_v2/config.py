"""The DreamerV2-style world model's configuration, :class:`IsoDreamV2Config`, built from a size preset
(:data:`~isodream_rl.modules.sizes.SIZE_PRESETS`) with :meth:`IsoDreamV2Config.from_preset`."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from isodream_rl.modules.composition import CLAMP_GRADIENTS, DECODER_STATES, MASK_MODES
from isodream_rl.modules.inverse_dynamics import INVERSE_INPUTS
from isodream_rl.modules.sizes import SIZE_PRESETS

DECODER_INPUTS = ("paper", "posterior")
#: The paper's settings of the fields whose defaults depart from it (with the loss's ``PAPER_WEIGHTS``).
PAPER_EXACT = {
    "inverse_input": "state",
    "decoder_input": "paper",
    "clamp_gradient": "zero",
    "static_mask_bias": 0.0,
}
#: The single-branch DreamerV2 baseline's switches, defined here only: ``IsoDreamV2Config.dreamerv2`` builds it
#: from this, and the trainer's ``ALGO_BRANCHES`` (``isodream_rl/trainers/config.py``) gives them to
#: ``algo=dreamerv2`` (both modes of ``isodream-train``) and to the TorchRL baselines.
DREAMERV2 = {"free_branch": False, "static_branch": False, "inverse_dynamics": False}
PRECISIONS = ("fp32", "bf16")


@dataclass
class IsoDreamV2Config:
    """Everything that shapes an :class:`~isodream_rl.modules.isodream_v2.world_model.IsoDreamV2WorldModel`."""

    action_dim: int
    """Width of the action vector."""
    depth: int = 32
    """Channels of the first convolution; encoder/decoder widths scale with it (TorchRL's ``channels``)."""
    state_dim: int = 50
    """Width of each stochastic state (s and z)."""
    belief_dim: int = 200
    """Width of each GRU state (h and h')."""
    hidden_dim: int = 200
    """Width of the RSSM's hidden layers."""
    units: int = 400
    """Width of the reward/discount/inverse MLPs."""
    min_std: float = 0.1
    """Lower bound of the latent std (``2 sigmoid(x/2) + min_std``)."""
    layer_norm_gru: bool = True
    """Layer-norm GRU cells (the authors' default) instead of ``nn.GRUCell``."""
    free_branch: bool = True
    """The action-free (noncontrollable) branch; ``False`` with no static branch and no inverse cell is DreamerV2."""
    static_branch: bool = True
    """The static background branch (Dec_phi3 on the first ``static_frames`` frames)."""
    inverse_dynamics: bool = True
    """The inverse-dynamics cell."""
    inverse_input: str = "embedding"
    """``"embedding"``: e^s_t - e^s_{t-1} (the authors' code); ``"state"``: MLP(s_{t-1}, s_t) on posterior states
    (the paper). The posterior sees ``h_t``, computed from ``a_{t-1}``, so ``"state"`` can be solved without the
    pixels; ``"embedding"`` cannot, but needs a larger ``lambda_inverse`` (the loss's default, ``LOSS_WEIGHTS``)
    to learn against the pixel-sum image loss."""
    mask_mode: str = "softmax"
    """``"softmax"`` over three logits, or the authors' ``"sigmoid"`` masks with 1 - M^s - M^z background."""
    clamp_components: bool = True
    """Clamp each branch's RGB component to the pixel range before composing (the authors' code); without it
    faint masks times out-of-range colours reproduce objects and the masks never separate the scene."""
    clamp_gradient: str = "inward"
    """Backward of that clamp: ``"inward"`` (forward unchanged; a colour beyond the range gets the gradients
    that move it back, so a branch whose colours overshoot under a shut mask can come back) or ``"zero"`` (the
    authors' plain clamp); without ``clamp_components`` it has no effect. See
    :class:`~isodream_rl.modules.composition.MaskComposition`."""
    decoder_input: str = "posterior"
    """``"posterior"``: both dynamic components from posteriors; ``"paper"``: the controllable component from
    the one-step prior s~_t, the noncontrollable one from the posterior z_t (§3.2, against collapse)."""
    free_decoder_input: str = "posterior"
    """The noncontrollable component from the posterior z_t (paper, the default) or from the action-free prior
    z~_t (``"prior"``: §3.2's guard against collapse applied to this branch too). From its one-step prior the
    branch can draw only what it predicts without actions and without the current frame: the objects that
    move on their own, not the agent, whose moves the actions decide."""
    static_frames: int = 10
    """K, the number of first frames of a window that the static branch reads (clamped to the window)."""
    static_mask_bias: float = 3.0
    """Initial bias of the static branch's mask logit, where it has one (the static branch in softmax mode;
    elsewhere the field has no effect). A positive value starts training with the background owning most of
    every pixel (3.0: 91 %), so the dynamic branches grow masks only where the background cannot explain the
    frame, instead of all three blending at 1/3 each."""
    reward_uses_free: bool = False
    """Reward head on [s, h, z, h'] (CARLA-style) instead of [s, h] (DMC-style)."""
    discount_head: bool = False
    """Predict episode continuation (Bernoulli)."""
    precision: str = "fp32"
    """``"bf16"`` runs convolutions and MLPs under bf16 autocast; GRUs and losses stay fp32."""
    channels_last: bool = True
    """Channels-last memory format for the convolutions (faster on CPU oneDNN and GPU tensor cores)."""
    fast_paths: bool = True
    """The CPU fast paths of ``modules/fast_paths.py`` (same values as the reference within float tolerance;
    ``False``: the reference forms)."""

    def __post_init__(self):
        if self.action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {self.action_dim}")
        for name, value, valid in (
            ("inverse_input", self.inverse_input, INVERSE_INPUTS),
            ("mask_mode", self.mask_mode, MASK_MODES),
            ("decoder_input", self.decoder_input, DECODER_INPUTS),
            ("free_decoder_input", self.free_decoder_input, DECODER_STATES),
            ("clamp_gradient", self.clamp_gradient, CLAMP_GRADIENTS),
            ("precision", self.precision, PRECISIONS),
        ):
            if value not in valid:
                raise ValueError(f"unknown {name} {value!r}; valid: {valid}")
        if self.reward_uses_free and not self.free_branch:
            raise ValueError("reward_uses_free=True needs the action-free branch (free_branch=True)")
        if self.mask_mode == "sigmoid" and not self.static_branch:
            raise ValueError("mask_mode='sigmoid' needs the static branch (its mask is 1 - M^s - M^z)")
        if self.static_frames < 1:
            raise ValueError(f"static_frames must be >= 1, got {self.static_frames}")

    @classmethod
    def from_preset(cls, size: str, *, action_dim: int, **overrides) -> IsoDreamV2Config:
        """A config of the named size (a key of :data:`SIZE_PRESETS`) with ``overrides`` applied."""
        if size not in SIZE_PRESETS:
            raise ValueError(f"unknown size preset {size!r}; valid: {sorted(SIZE_PRESETS)}")
        known = {f.name for f in fields(cls)}
        unknown = set(overrides) - known
        if unknown:
            raise TypeError(f"unknown IsoDreamV2Config fields {sorted(unknown)}")
        return cls(action_dim=action_dim, **{**SIZE_PRESETS[size], **overrides})

    @classmethod
    def paper_exact(cls, size: str = "paper", *, action_dim: int, **overrides) -> IsoDreamV2Config:
        """The paper's choices where the defaults depart from them (:data:`PAPER_EXACT`; docs/concepts.md,
        "Where we depart from the paper"). Train it with ``IsoDreamV2ModelLoss.paper_exact`` (``alpha = 1``)."""
        return cls.from_preset(size, action_dim=action_dim, **{**PAPER_EXACT, **overrides})

    @classmethod
    def dreamerv2(cls, size: str = "paper", *, action_dim: int, **overrides) -> IsoDreamV2Config:
        """The single-branch DreamerV2 baseline (:data:`DREAMERV2`): no action-free branch, no static
        branch, no inverse cell."""
        return cls.from_preset(size, action_dim=action_dim, **{**DREAMERV2, **overrides})

    def to_dict(self) -> dict:
        return asdict(self)
