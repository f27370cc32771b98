"""Configuration of the video predictor and the named variants of Iso-Dream's Table 3."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

__all__ = ["PredictorConfig", "VARIANTS", "variant_config"]


@dataclass(frozen=True)
class PredictorConfig:
    """Sizes and switches of :class:`~isodream_rl.video_prediction.predictor.ThreeBranchPredictor`.

    The paper's BAIR/RoboNet model (Appendix D, Table 5) is the default: encoder ``conv3-64`` (two
    stride-2 convolutions, 64x64 -> 16x16), two ST-LSTM layers of 64 channels per branch, kernel 5.
    """

    action_dim: int = 4
    """Size of the action vector (BAIR: 4, Iso-Dream's RoboNet: 5)."""
    image_channels: int = 3
    """Channels of the frames."""
    encoder_channels: tuple[int, int] = (32, 64)
    """Widths of the two stride-2 convolutions of the shared encoder."""
    hidden_channels: int = 64
    """Channels of every ST-LSTM layer (paper: 64)."""
    num_layers: int = 2
    """ST-LSTM layers per branch (paper: 2)."""
    kernel_size: int = 5
    """Kernel of the ST-LSTM convolutions and branch heads (paper: 5)."""
    action_embedding: int = 64
    """Width of the action embedding fed to the action-conditioned cells."""
    action_free_branch: bool = True
    """Whether the noncontrollable (action-free) branch exists."""
    inverse_dynamics: bool = True
    """Whether the inverse-dynamics cell is trained (its loss is the action reconstruction term)."""
    mask_composition: bool = True
    """Compose branch outputs with masks and the static branch (eq. 4); ``False`` decodes the frame
    directly from the single branch (PredRNN)."""
    action_conditioning: str = "modulate"
    """``"modulate"``: the action gates the hidden-state term of the cells (Iso-Dream);
    ``"concat"``: the action embedding is added to the cell input (PredRNN's action-conditioned mode)."""
    forget_bias: float = 1.0
    """Added to the forget gates' pre-activations."""
    rgb_activation: str = "sigmoid"
    """What bounds the RGB each branch decodes (PredRNN's frame too): ``"sigmoid"`` keeps it in ``[0, 1]``, so
    every composed frame is a convex combination of values in ``[0, 1]`` and a rollout past the training horizon
    cannot drift out of range; ``"linear"`` is the authors' unbounded output (they clip only for the metrics).
    See ``docs/recipes/video_prediction.md`` for the measured difference."""
    channels_last: bool = True
    """Run the convolutions on channels-last tensors (oneDNN's native layout on CPU). The outputs equal
    the contiguous-layout path within float tolerance; ``False`` is that plain path, kept as the reference."""
    precision: str = "fp32"
    """``"bf16"`` runs the convolutions and linear layers under bf16 autocast (faster where the CPU has
    native bf16, e.g. ``avx512_bf16``, and on GPUs); the ST-LSTM memories, the mask composition and the
    losses stay fp32."""

    def __post_init__(self) -> None:
        if self.action_conditioning not in ("modulate", "concat"):
            raise ValueError(
                f"action_conditioning must be 'modulate' or 'concat', got {self.action_conditioning!r}"
            )
        if self.precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {self.precision!r}")
        if self.rgb_activation not in ("sigmoid", "linear"):
            raise ValueError(f"rgb_activation must be 'sigmoid' or 'linear', got {self.rgb_activation!r}")
        if self.action_free_branch and not self.mask_composition:
            raise ValueError("the action-free branch needs mask_composition=True (eq. 4 merges the branches)")
        if self.num_layers < 1 or self.hidden_channels < 1:
            raise ValueError(
                f"need num_layers >= 1 and hidden_channels >= 1, got {self.num_layers}, {self.hidden_channels}"
            )

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, values: dict) -> PredictorConfig:
        """Inverse of :meth:`to_dict` (accepts lists where tuples are expected, e.g. from JSON). A config saved
        before ``rgb_activation`` existed had linear outputs."""
        values = {"rgb_activation": "linear", **values}
        return cls(**{**values, "encoder_channels": tuple(values["encoder_channels"])})


VARIANTS: dict[str, dict] = {
    "isodream": {},
    "no_action_free": {"action_free_branch": False},
    "no_inverse": {"inverse_dynamics": False},
    "predrnn": {
        "action_free_branch": False,
        "inverse_dynamics": False,
        "mask_composition": False,
        "action_conditioning": "concat",
    },
}
"""Named variants: the full model, the two ablations of Table 3, and a single-branch PredRNN baseline."""


def variant_config(name: str, **overrides) -> PredictorConfig:
    """The configuration of a named variant, with size overrides.

    Args:
        name: one of :data:`VARIANTS`.
        **overrides: :class:`PredictorConfig` fields (e.g. ``hidden_channels=32``).

    Examples:
        >>> variant_config("no_action_free", hidden_channels=16).action_free_branch
        False
    """
    if name not in VARIANTS:
        raise KeyError(f"unknown variant {name!r}; expected one of {sorted(VARIANTS)}")
    return replace(PredictorConfig(**overrides), **VARIANTS[name])
