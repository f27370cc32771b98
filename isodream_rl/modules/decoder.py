"""Branch decoders ``Dec_phi1``, ``Dec_phi2`` (RGB + mask logit) and ``Dec_phi3`` (background) (§3.2).

Same layer pattern and widths as TorchRL's ``ObsDecoder`` (a linear layer to ``32*depth`` on a 1x1 map,
then transposed convolutions with kernels 5, 5, 6, 6 and stride 2 to 64x64, ReLU). It is written here
rather than reused because the static branch decodes a stack of frame embeddings, not ``(state,
belief)``, and because every call site wants the flat ``[N, C, 64, 64]`` form (channels-last friendly).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from .composition import memory_format_of


class ConvDecoder(nn.Module):
    """Latent vector -> image-sized map.

    Args:
        in_features: width of the input vector.
        out_channels: output channels (4 = RGB + mask logit for the dynamic branches).
        depth: channels of the last hidden layer (32 in the paper's setting).
        device: where to create the parameters.

    Shapes:
        ``[N, in_features]`` -> ``[N, out_channels, 64, 64]``.
    """

    def __init__(self, *, in_features: int, out_channels: int, depth: int = 32, device=None):
        super().__init__()
        self.in_features = in_features
        self.linear = nn.Linear(in_features, 32 * depth, device=device)
        # In-place ReLUs: a transposed convolution's backward needs its input, not its output, so the
        # activation can overwrite it and save one activation-sized allocation per layer.
        self.deconv = nn.Sequential(
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(32 * depth, 4 * depth, 5, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(4 * depth, 2 * depth, 5, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(2 * depth, depth, 6, stride=2, device=device),
            nn.ReLU(inplace=True),
            nn.ConvTranspose2d(depth, out_channels, 6, stride=2, device=device),
        )

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        hidden = torch.relu(self.linear(latent))
        # The first transposed convolution sees a 1x1 map: it is an outer product, computed here as one
        # matrix product. oneDNN runs it as a convolution at ~5 GFLOP/s on CPU (forward + backward),
        # 20x slower than the matmul, and it was the largest single cost of a world-model update.
        first = self.deconv[1]
        weight, (cin, cout, kh, kw) = first.weight, first.weight.shape
        if weight.is_contiguous(memory_format=torch.channels_last):
            # Stored as [Cin, kh, kw, Cout]: the product is already the channels-last [N, Cout, kh, kw]
            # map, with no copy of the weight or of the output.
            flat = weight.permute(0, 2, 3, 1).reshape(cin, -1)
            x = torch.addmm(first.bias.repeat(kh * kw), hidden, flat)
            x = x.view(-1, kh, kw, cout).permute(0, 3, 1, 2)
        else:
            x = torch.addmm(first.bias.repeat_interleave(kh * kw), hidden, weight.reshape(cin, -1))
            x = x.view(-1, cout, kh, kw)
        for layer in self.deconv[2:]:
            x = _transposed_conv(layer, x) if isinstance(layer, nn.ConvTranspose2d) else layer(x)
        return x


def _transposed_conv(layer: nn.ConvTranspose2d, x: torch.Tensor) -> torch.Tensor:
    """``layer(x)`` with the bias added outside the convolution.

    The same function, but PyTorch's CPU (oneDNN) transposed convolution computes its bias gradient far more
    slowly than a plain sum over ``grad``, a large share of an update at paper size (docs/architecture.md,
    "Speed"; updates timed by ``bench/world_model_speed.py``). The in-place add is safe: the convolution's
    backward needs its input and weight, not its output. The bias is cast to the output's dtype first (as
    autocast casts a convolution's bias): a float32 bias added in place to a bfloat16 output takes a slower
    mixed-dtype path.
    """
    out = F.conv_transpose2d(
        x,
        layer.weight,
        None,
        stride=layer.stride,
        padding=layer.padding,
        output_padding=layer.output_padding,
        groups=layer.groups,
        dilation=layer.dilation,
    )
    return out if layer.bias is None else _add_channel_bias_(out, layer.bias.to(out.dtype))


_FEW_CHANNELS = 8
_REDUCED = (torch.bfloat16, torch.float16)


def _add_channel_bias_(out: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``out += bias[:, None, None]`` in place, ``out`` ``[N, C, H, W]``, ``bias`` ``[C]`` of ``out``'s dtype.

    A channels-last bf16/fp16 map with few channels (the RGB + logit layer) gets the bias as a ``[H * W * C]``
    pattern added to its ``[N, H * W * C]`` rows: broadcasting ``[C, 1, 1]`` there runs an inner loop of C
    elements, several times slower in forward and backward. Everywhere else (float32 included, where the
    pattern is the slower way) the plain broadcast.
    """
    n, c, h, w = out.shape
    if c <= _FEW_CHANNELS and out.dtype in _REDUCED and memory_format_of(out) == torch.channels_last:
        out.permute(0, 2, 3, 1).reshape(n, h * w * c).add_(bias.repeat(h * w))
        return out
    return out.add_(bias[:, None, None])
