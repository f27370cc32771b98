"""Terms added to eq. 5 (``IsoDreamV2ModelLoss(extra_terms=...)``): their place in the loss and their checks."""

import pytest
import torch

from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel
from isodream_rl.objectives.isodream_v2 import IsoDreamV2ModelLoss
from tests.test_world_model import make_batch


class _SquaredError(torch.nn.Module):
    """An extra term: ``0.5 * ||o^ - o||^2`` per frame, under a ``loss_`` name of its own."""

    def forward(self, reco: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"loss_model_extra": 0.5 * (reco - target).pow(2).sum() / reco.shape[:2].numel()}


def test_model_loss_adds_the_term_on_the_composite():
    torch.manual_seed(0)
    loss = IsoDreamV2ModelLoss(
        IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2)),
        extra_terms=[_SquaredError()],
    )
    td = make_batch()
    losses, out = loss(td)
    target = td["next", "pixels"].float() / 255 - 0.5
    reco = out["next", "reco_pixels"]
    expected = 0.5 * (reco - target).pow(2).sum() / reco.shape[:2].numel()
    torch.testing.assert_close(losses["loss_model_extra"], expected)
    loss.total(losses).backward()
    assert all(p.grad is not None for p in loss.world_model.static_decoder.parameters())


def test_extra_terms_must_add_new_loss_entries():
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
    for bad in ({"pyramid": torch.zeros(())}, {"loss_model_reco": torch.zeros(())}):
        loss = IsoDreamV2ModelLoss(model, extra_terms=[lambda reco, target, bad=bad: bad])
        with pytest.raises(ValueError, match="new loss_"):
            loss(make_batch())
