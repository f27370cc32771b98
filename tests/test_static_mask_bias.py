import pytest
import torch
from tensordict import TensorDict

from isodream_rl.modules.isodream_v2 import IsoDreamV2Config, IsoDreamV2WorldModel


def _masks(bias: float) -> dict[str, float]:
    torch.manual_seed(0)
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, static_mask_bias=bias))
    td = TensorDict(
        {
            "action": torch.zeros(2, 4, 2),
            "is_init": torch.zeros(2, 4, 1, dtype=torch.bool),
            ("next", "pixels"): torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8),
        },
        [2, 4],
    )
    with torch.no_grad():
        out = model(td)["next"]
    return {name: out[f"mask_{name}"].mean().item() for name in ("control", "free", "static")}


def test_static_mask_bias_gives_the_background_most_of_the_image_at_init():
    plain, biased = _masks(0.0), _masks(3.0)
    assert 0.2 < plain["static"] < 0.5
    # softmax with logits (b, 0, 0) and small decoder outputs: about e^3 / (e^3 + 2) = 0.91.
    assert biased["static"] > 0.85
    assert biased["control"] < 0.1 and biased["free"] < 0.1


def test_static_mask_bias_is_the_default_prior_and_leaves_models_without_a_background_logit_alone():
    assert IsoDreamV2Config(action_dim=2).static_mask_bias == 3.0
    for options in ({"mask_mode": "sigmoid"}, {"static_branch": False}):
        torch.manual_seed(0)
        biased = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, **options))
        torch.manual_seed(0)
        plain = IsoDreamV2WorldModel(
            IsoDreamV2Config.from_preset("tiny", action_dim=2, static_mask_bias=0.0, **options)
        )
        for (name, a), b in zip(biased.state_dict().items(), plain.state_dict().values()):
            assert torch.equal(a, b), name


def test_shift_static_mask_bias_moves_the_background_logit_only_and_needs_it():
    torch.manual_seed(0)
    model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, static_mask_bias=1.0))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.shift_static_mask_bias(2.5)
    changed = {k for k, v in model.state_dict().items() if not torch.equal(v, before[k])}
    (key,) = changed
    assert key.startswith("static_decoder.") and key.endswith(".bias")
    assert torch.allclose(model.state_dict()[key] - before[key], torch.tensor([0.0, 0.0, 0.0, 2.5]))
    for options in ({"mask_mode": "sigmoid"}, {"static_branch": False}):
        other = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2, **options))
        with pytest.raises(ValueError, match="static branch in softmax mode"):
            other.shift_static_mask_bias(1.0)
