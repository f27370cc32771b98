"""Mask assignment (isodream_rl/objectives/mask_assignment.py): responsibilities and their logit gradient."""

import pytest
import torch
from tensordict import TensorDict

from isodream_rl.modules import IsoDreamWorldModel, MaskComposition, WorldModelConfig
from isodream_rl.objectives import IsoDreamModelLoss, mask_assignment

NAMES = ("control", "free", "static")


def _scene(logits: torch.Tensor, colors: torch.Tensor):
    """``logits [N, 3, H, W]`` and ``colors [N, 3 branches, 3, H, W]`` -> masks and colours keyed by branch."""
    masks = dict(zip(NAMES, torch.softmax(logits, dim=1).split(1, dim=1)))
    return masks, dict(zip(NAMES, colors.unbind(1)))


def _random_scene(seed: int):
    """float64 logits (leaf, with grad) ``[2, 3, 4, 5]``, colours ``[2, 3, 3, 4, 5]``, a target, and their dicts."""
    torch.manual_seed(seed)
    logits = torch.randn(2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    colors = torch.rand(2, 3, 3, 4, 5, dtype=torch.float64) - 0.5
    target = torch.rand(2, 3, 4, 5, dtype=torch.float64) - 0.5
    return logits, colors, target, *_scene(logits, colors)


def test_logit_gradient_is_mask_minus_responsibility():
    logits, colors, target, masks, comps = _random_scene(0)
    loss, resp = mask_assignment(masks, comps, target, std=0.2)
    loss.backward()
    r = torch.cat([resp[n] for n in NAMES], dim=1)
    m = torch.softmax(logits.detach(), dim=1)
    # summed over pixels, averaged over the 2 frames
    torch.testing.assert_close(logits.grad, (m - r) / 2)
    # responsibilities by their definition: m_k N(o; c_k, std^2) normalised over branches
    likelihood = torch.exp(-0.5 * (colors - target[:, None]).pow(2).sum(2) / 0.2**2)
    expected = m * likelihood / (m * likelihood).sum(1, keepdim=True)
    torch.testing.assert_close(r, expected)
    # the value is KL(r || m) >= 0
    kl = (r * (r.log() - m.log())).sum() / 2
    torch.testing.assert_close(loss.detach(), kl)


def test_a_subset_assigns_inside_its_share_and_leaves_the_other_logits_alone():
    logits, colors, target, masks, comps = _random_scene(1)
    loss, resp = mask_assignment(masks, comps, target, std=0.2, branches=("free", "static"))
    loss.backward()
    assert set(resp) == {"free", "static"}
    m = torch.softmax(logits.detach(), dim=1)
    share = m[:, 1:].sum(1, keepdim=True)
    r = torch.cat([resp["free"], resp["static"]], dim=1)
    torch.testing.assert_close(r.sum(1), torch.ones_like(r.sum(1)))
    likelihood = torch.exp(-0.5 * (colors[:, 1:] - target[:, None]).pow(2).sum(2) / 0.2**2)
    expected = m[:, 1:] * likelihood / (m[:, 1:] * likelihood).sum(1, keepdim=True)
    torch.testing.assert_close(r, expected)
    # d/dl_k = m_k - M r_k inside the subset, nothing on the controllable logit
    torch.testing.assert_close(logits.grad[:, 1:], (m[:, 1:] - share * r) / 2)
    torch.testing.assert_close(logits.grad[:, 0], torch.zeros_like(logits.grad[:, 0]))
    with pytest.raises(ValueError, match="two or more"):
        mask_assignment(masks, comps, target, std=0.2, branches=("free",))
    with pytest.raises(ValueError, match="two or more"):
        mask_assignment(masks, comps, target, std=0.2, branches=("free", "sky"))


def test_a_shut_out_branch_that_draws_the_pixel_claims_it():
    # the free branch's mask is ~1e-4 but only its colour matches the frame: the image loss of eq. 4 gives its
    # logit a push proportional to that mask, the assignment term one of order one
    logits = torch.tensor([[-2.0], [-9.0], [3.0]]).reshape(1, 3, 1, 1).requires_grad_(True)
    target = torch.tensor([0.4, -0.4, -0.4]).reshape(1, 3, 1, 1)
    background = torch.tensor([-0.3, 0.2, 0.1]).reshape(1, 3, 1, 1)
    colors = torch.stack([background, target, background], dim=1)
    masks, comps = _scene(logits, colors)
    composite, _ = MaskComposition()(comps, {n: logits[:, i : i + 1] for i, n in enumerate(NAMES)})
    (0.5 * (composite - target).pow(2).sum()).backward()
    image_push = -logits.grad[0, 1].item()
    logits.grad = None
    masks, comps = _scene(logits, colors)
    loss, resp = mask_assignment(masks, comps, target, std=0.1)
    loss.backward()
    assignment_push = -logits.grad[0, 1].item()
    assert 0 < image_push < 1e-3
    assert resp["free"].item() > 0.99
    assert assignment_push > 0.99


def test_branches_that_explain_a_pixel_equally_are_left_alone():
    logits = torch.randn(1, 3, 6, 6, requires_grad=True)
    same = torch.rand(1, 1, 3, 6, 6) - 0.5
    masks, comps = _scene(logits, same.expand(1, 3, 3, 6, 6))
    loss, resp = mask_assignment(masks, comps, torch.rand(1, 3, 6, 6) - 0.5, std=0.1)
    loss.backward()
    assert loss.item() == pytest.approx(0.0, abs=1e-4)
    assert logits.grad.abs().max().item() < 1e-5


def test_rejects_bad_arguments():
    masks, comps = _scene(torch.zeros(1, 3, 2, 2), torch.zeros(1, 3, 3, 2, 2))
    with pytest.raises(ValueError, match="std"):
        mask_assignment(masks, comps, torch.zeros(1, 3, 2, 2), std=0.0)
    with pytest.raises(KeyError, match="same branches"):
        mask_assignment(masks, {"control": comps["control"]}, torch.zeros(1, 3, 2, 2), std=0.1)


def _batch():
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        {
            "action": torch.rand(2, 4, 2, generator=g),
            ("next", "pixels"): torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8, generator=g),
            ("next", "reward"): torch.zeros(2, 4, 1),
        },
        [2, 4],
    )


def test_model_loss_term_reaches_only_the_mask_logits_and_what_feeds_them():
    torch.manual_seed(0)
    config = WorldModelConfig.from_preset("tiny", action_dim=2)
    loss = IsoDreamModelLoss(IsoDreamWorldModel(config), lambda_mask_assignment=2.0)
    assert loss.assignment_branches == ("free", "static")
    losses, out = loss(_batch())
    nxt = out["next"]
    expected, _ = mask_assignment(
        {n: nxt[f"mask_{n}"] for n in ("control", "free")} | {"static": nxt["mask_static"]},
        {"control": nxt["reco_control"], "free": nxt["reco_free"], "static": out["background"]},
        _batch()["next", "pixels"].float() / 255 - 0.5,
        std=0.1,
        branches=("free", "static"),
    )
    torch.testing.assert_close(losses["loss_model_mask_assignment"], 2.0 * expected)
    loss.world_model.zero_grad()
    losses["loss_model_mask_assignment"].backward()
    # the colours are detached in the responsibilities: the decoders' RGB output channels get nothing,
    # their mask-logit channel does
    last = loss.world_model.free_decoder.deconv[-1]
    assert last.weight.grad[:, :3].abs().max() == 0 and last.bias.grad[:3].abs().max() == 0
    assert last.weight.grad[:, 3].abs().max() > 0
    # the default subset (free, static) leaves the controllable decoder alone (up to rounding)
    control = loss.world_model.control_decoder.deconv[-1].weight.grad
    assert control is None or control.abs().max() < 1e-5 * last.weight.grad[:, 3].abs().max()


def test_model_loss_with_every_branch_reaches_the_controllable_logit():
    torch.manual_seed(0)
    config = WorldModelConfig.from_preset("tiny", action_dim=2)
    loss = IsoDreamModelLoss(IsoDreamWorldModel(config), lambda_mask_assignment=1.0, assignment_branches=None)
    losses, _ = loss(_batch())
    losses["loss_model_mask_assignment"].backward()
    last = loss.world_model.control_decoder.deconv[-1]
    assert last.weight.grad[:, 3].abs().max() > 0 and last.weight.grad[:, :3].abs().max() == 0


def test_model_loss_rejects_the_term_without_masks():
    config = WorldModelConfig.dreamerv2("tiny", action_dim=2)
    with pytest.raises(ValueError, match="two or more of the model's branches"):
        IsoDreamModelLoss(IsoDreamWorldModel(config), lambda_mask_assignment=1.0)
    no_static = WorldModelConfig.from_preset("tiny", action_dim=2, static_branch=False)
    with pytest.raises(ValueError, match="two or more of the model's branches"):
        IsoDreamModelLoss(IsoDreamWorldModel(no_static), lambda_mask_assignment=1.0)
    # every branch of a model without the static branch: control and free
    IsoDreamModelLoss(IsoDreamWorldModel(no_static), lambda_mask_assignment=1.0, assignment_branches=None)
    with pytest.raises(ValueError, match="assignment_std"):
        IsoDreamModelLoss(
            IsoDreamWorldModel(WorldModelConfig.from_preset("tiny", action_dim=2)), assignment_std=0
        )
