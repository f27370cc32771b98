"""The acting policies' common part: a recurrent state carried from step to step under TorchRL's
``("next", ...)`` convention, through a primer (:class:`CarriedStatePolicy`, the base of the baselines' and the
default learner's acting policies; :func:`read_acting_inputs`, what any of them reads at one env step)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer

from isodream_rl.modules.pixels import IMAGE_SHAPE, check_pixel_values, check_pixels


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
