"""The coarse-to-fine image term (isodream_rl/objectives/pyramid.py) and its place in IsoDreamModelLoss."""

import pytest
import torch
from torch.nn import functional as F

from isodream_rl.modules import IsoDreamWorldModel, WorldModelConfig
from isodream_rl.objectives import IsoDreamModelLoss, PyramidImageTerm, pyramid_squared_error
from tests.test_world_model import make_batch


def _disc(centre: float, size: int = 32, radius: float = 2.5) -> torch.Tensor:
    """``[1, 1, size, size]``: a soft disc at ``(centre, size / 2)``, as a float the gradient can move."""
    rows = torch.arange(size, dtype=torch.float64)[:, None]
    cols = torch.arange(size, dtype=torch.float64)[None, :]
    dist2 = (rows - centre) ** 2 + (cols - size / 2) ** 2
    return torch.sigmoid(4 * (radius**2 - dist2) / radius)[None, None]


def _reference_down(images: torch.Tensor) -> torch.Tensor:
    """The pyramid step written out: 5x5 binomial weights, edge pixels repeated, even pixels kept."""
    w = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=images.dtype) / 16
    padded = F.pad(images, (2, 2, 2, 2), mode="replicate")
    height, width = images.shape[-2:]
    out = torch.zeros(*images.shape[:-2], height // 2, width // 2, dtype=images.dtype)
    for i in range(height // 2):
        for j in range(width // 2):
            patch = padded[..., 2 * i : 2 * i + 5, 2 * j : 2 * j + 5]
            out[..., i, j] = (patch * w[:, None] * w[None, :]).sum((-2, -1))
    return out


def test_levels_are_binomial_pyramid_errors_weighted_by_the_area():
    torch.manual_seed(0)
    reco, target = torch.rand(2, 5, 3, 16, 16), torch.rand(2, 5, 3, 16, 16)
    expected, r, t = 0.0, reco.flatten(0, 1), target.flatten(0, 1)
    for level in (1, 2, 3):
        r, t = _reference_down(r), _reference_down(t)
        expected = expected + 4**level * (r - t).pow(2).sum()
    torch.testing.assert_close(pyramid_squared_error(reco, target, levels=3), expected)
    # an error spread evenly over the frame weighs the same at every level as at full resolution
    flat = pyramid_squared_error(torch.full((1, 3, 16, 16), 0.1), torch.zeros(1, 3, 16, 16), levels=2)
    torch.testing.assert_close(flat, torch.tensor(2 * 3 * 256 * 0.01))


def test_a_disc_drawn_off_its_place_is_pulled_towards_it_only_by_the_coarse_levels():
    target = _disc(10.0)
    centre = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)
    # ten pixels apart, the two discs do not overlap: the full-resolution error has no gradient on the position
    full = F.mse_loss(_disc(centre), target, reduction="sum")
    (grad_full,) = torch.autograd.grad(full, centre)
    assert abs(grad_full.item()) < 1e-3
    coarse = pyramid_squared_error(_disc(centre), target, levels=3)
    (grad_coarse,) = torch.autograd.grad(coarse, centre)
    assert grad_coarse.item() > 0.05  # descending it moves the disc from row 20 towards row 10


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="levels"):
        pyramid_squared_error(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), levels=0)
    with pytest.raises(ValueError, match="divisible"):
        pyramid_squared_error(torch.zeros(1, 3, 12, 12), torch.zeros(1, 3, 12, 12), levels=3)
    with pytest.raises(ValueError, match="shape"):
        pyramid_squared_error(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 4), levels=1)
    with pytest.raises(ValueError, match="levels"):
        PyramidImageTerm(levels=7)
    with pytest.raises(ValueError, match="lambda_reco_pyramid"):
        PyramidImageTerm(lambda_reco_pyramid=-1.0)


def test_model_loss_adds_the_term_on_the_composite():
    torch.manual_seed(0)
    loss = IsoDreamModelLoss(
        IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2)),
        extra_terms=[PyramidImageTerm(lambda_reco_pyramid=0.5)],
    )
    td = make_batch()
    losses, out = loss(td)
    target = td["next", "pixels"].float() / 255 - 0.5
    reco = out["next", "reco_pixels"]
    expected = 0.5 * 0.5 * pyramid_squared_error(reco, target, levels=3) / reco.shape[:2].numel()
    torch.testing.assert_close(losses["loss_model_reco_pyramid"], expected)
    loss.total(losses).backward()
    assert all(p.grad is not None for p in loss.world_model.static_decoder.parameters())


def test_extra_terms_must_add_new_loss_entries():
    model = IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2))
    for bad in ({"pyramid": torch.zeros(())}, {"loss_model_reco": torch.zeros(())}):
        loss = IsoDreamModelLoss(model, extra_terms=[lambda reco, target, bad=bad: bad])
        with pytest.raises(ValueError, match="new loss_"):
            loss(make_batch())
