"""Object slots of the noncontrollable decoder (WorldModelConfig.free_slots, isodream_rl.modules.slots)."""

import pytest
import torch

from isodream_rl.modules import IsoDreamWorldModel, MaskComposition, WorldModelConfig
from isodream_rl.modules.slots import SlotDecoder
from isodream_rl.recipes.visualize import branch_grid
from tests.test_world_model import make_batch, tiny


def test_slots_are_a_softmax_over_all_logits():
    """Composing the combined slot output equals one softmax over control, K slot and background logits."""
    torch.manual_seed(0)
    slots = SlotDecoder(in_features=12, num_slots=3, depth=4, clamp=(-0.5, 0.5))
    latent = torch.randn(5, 12)
    combined, weights = slots.decompose(latent)
    raw = slots.decoder(slots.project(latent).reshape(15, 12)).reshape(5, 3, 4, 64, 64)
    control, static = torch.randn(5, 4, 64, 64), torch.randn(5, 4, 64, 64)
    composite, masks = MaskComposition()(
        {"control": control[:, :3], "free": combined[:, :3], "static": static[:, :3]},
        {"control": control[:, 3:], "free": combined[:, 3:], "static": static[:, 3:]},
    )
    logits = torch.cat([control[:, None, 3:], raw[:, :, 3:], static[:, None, 3:]], dim=1)
    colors = torch.cat([control[:, None, :3], raw[:, :, :3], static[:, None, :3]], dim=1).clamp(-0.5, 0.5)
    expected = (torch.softmax(logits, dim=1) * colors).sum(1)
    torch.testing.assert_close(composite, expected, atol=1e-5, rtol=1e-5)
    slot_masks = masks["free"][:, None] * weights
    torch.testing.assert_close(slot_masks, torch.softmax(logits, dim=1)[:, 1:4], atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("mask_mode", ["softmax", "sigmoid"])
def test_world_model_writes_slot_masks_that_sum_to_the_branch_mask(mask_mode):
    wm = IsoDreamWorldModel(tiny(free_slots=3, mask_mode=mask_mode))
    out = wm(make_batch())["next"]
    assert out["mask_free_slots"].shape == (2, 6, 3, 1, 64, 64)
    assert (out["mask_free_slots"] >= 0).all()
    torch.testing.assert_close(out["mask_free_slots"].sum(2), out["mask_free"], atol=1e-6, rtol=1e-5)
    assert ("next", "mask_free_slots") in wm.out_keys


def test_every_slot_gets_gradient():
    torch.manual_seed(0)
    wm = IsoDreamWorldModel(tiny(free_slots=3))
    out = wm(make_batch())
    out["next", "reco_pixels"].pow(2).sum().backward()
    grad = wm.free_decoder.project.weight.grad.reshape(3, -1, wm.free_decoder.in_features)
    assert (grad.abs().sum((1, 2)) > 0).all()


def test_picture_has_one_row_per_slot():
    out = IsoDreamWorldModel(tiny(free_slots=2))(make_batch())
    plain = IsoDreamWorldModel(tiny())(make_batch())
    assert branch_grid(out, scale=1).height == branch_grid(plain, scale=1).height + 2 * 64


def test_bad_slot_settings_are_refused():
    with pytest.raises(ValueError, match="free_slots must be >= 1"):
        tiny(free_slots=0)
    with pytest.raises(ValueError, match="free_slots > 1 needs the action-free branch"):
        WorldModelConfig.dreamerv2("tiny", action_dim=2, free_slots=2)
    with pytest.raises(ValueError, match="num_slots >= 2"):
        SlotDecoder(in_features=4, num_slots=1, depth=4)
    with pytest.raises(ValueError, match=r"expects features \[N, 12\]"):
        SlotDecoder(in_features=12, num_slots=2, depth=4)(torch.zeros(3, 10))
