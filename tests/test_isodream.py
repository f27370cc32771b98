"""``algo=isodream`` (the default): Iso-Dream's decomposition on TorchRL's DreamerV3 learner.

The decomposition's properties (masks, an action-free branch, inverse dynamics that reach the controllable branch
only, the sliding window that is the paper's ``L + tau`` chain), the TorchRL composition (losses, optimisers, keys),
the acting policy, a run that trains, evaluates and resumes exactly, and the ablations (``isodream_no_inverse``,
``isodream_no_static``, ``isodream_no_attention``): the same learner without their part."""

import json
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type
from torchrl.modules.models.model_based import _DreamerV3ChannelRMSNorm, _DreamerV3RMSNorm
from torchrl.objectives import DreamerV3ActorLoss, DreamerV3Loss, DreamerV3ModelLoss, DreamerV3ValueLoss
from torchrl.trainers.algorithms import DreamerV3Optimizer

from isodream_rl.data.sprites_episodes import collect_sprites_episodes, episode_windows
from isodream_rl.envs import make_env
from isodream_rl.evaluation import decomposition_scores
from isodream_rl.modules.composition import MaskComposition
from isodream_rl.modules.fast_paths import FastRMSNorm, FusedMaskComposition
from isodream_rl.modules.isodream.behavior import PolicyFeatures
from isodream_rl.modules.isodream.world_model import IsoDreamConfig, IsoDreamWorldModel
from isodream_rl.trainers import ConfigError, train, validate_config
from isodream_rl.trainers.isodream import IsoDreamComponents, isodream_config
from isodream_rl.trainers.learners import unread_setting_errors
from isodream_rl.trainers.openloop import open_loop_prediction
from isodream_rl.trainers.registry import components_builder, make_components
from isodream_rl.trainers.stepper import loss_sum
from isodream_rl.trainers.world_model_config import world_model_mode_errors
from tests.test_torchrl_dreamer import A, B, T, env_batch, replay_batch, tiny_config
from tests.test_torchrl_dreamer_v3 import assert_resume_is_exact, composed

ALGO = "isodream"
#: TorchRL's DreamerV3 RMS norms, the reference forms of the fused ones (``modules/fast_paths.py``)
TORCHRL_NORMS = (_DreamerV3RMSNorm, _DreamerV3ChannelRMSNorm)


def isodream_run_config(tmp_path, **train_changes):
    """The tiny run of the baselines' tests with Iso-Dream's branches and the attention policy input."""
    cfg = tiny_config(tmp_path, ALGO, **train_changes)
    cfg.algo.free_branch = cfg.algo.static_branch = cfg.algo.inverse_dynamics = True
    cfg.algo.policy_input, cfg.algo.reward_uses_free, cfg.algo.attention_window = "attention", True, 3
    cfg.model.attention_dim = 8
    return cfg


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    torch.manual_seed(0)
    cfg = isodream_run_config(tmp_path_factory.mktemp("run"))
    return IsoDreamComponents(cfg, action_dim=A, scratch_dir=tmp_path_factory.mktemp("scratch"))


def model_batch(parts, **changes) -> TensorDict:
    batch = parts.stepper.prepare(replay_batch()).reshape(B, T)
    for key, value in changes.items():
        batch.set(key, value)
    return batch


class TestDecomposition:
    def test_masks_sum_to_one_and_mix_the_components(self, parts):
        out = parts.learner.world_model(model_batch(parts))
        masks = [out["next", f"mask_{name}"] for name in ("control", "free", "static")]
        torch.testing.assert_close(sum(masks), torch.ones_like(masks[0]))
        components = [out["next", "reco_control"], out["next", "reco_free"], out["background"]]
        mixed = sum(m * c for m, c in zip(masks, components))
        torch.testing.assert_close(out["next", "reco_pixels"], mixed)

    def test_action_free_branch_does_not_see_the_actions(self, parts):
        model = parts.learner.world_model
        batch = model_batch(parts)
        flipped = batch.clone().set("action", -batch["action"])
        torch.manual_seed(1)
        a = model(batch.clone())
        torch.manual_seed(1)
        b = model(flipped)
        width, deter = model.config.control.state_dim, model.config.control.deter
        torch.testing.assert_close(a["next", "belief"][..., deter:], b["next", "belief"][..., deter:])
        torch.testing.assert_close(a["next", "state"][..., width:], b["next", "state"][..., width:])
        assert not torch.allclose(a["next", "belief"][..., :deter], b["next", "belief"][..., :deter])

    @pytest.mark.parametrize("branch", ["control", "free"])
    @pytest.mark.parametrize("source", ["prior", "posterior"])
    def test_each_dynamic_branch_draws_its_prior_not_the_frame(self, branch, source):
        """The default's dynamic decoders draw their one-step priors (``s~_t ~ p(s_t | h_t)``, ``h_t`` from the
        previous posterior and the action; ``z~_t ~ p(z_t | h'_t)`` without the action): a frame changed at step t
        changes what they draw from step t + 1 on, never at t, so only the action can tell where the agent went
        (it lands in the controllable branch). They draw the posterior where no previous posterior exists (the
        window's first step). ``*_decoder_input="posterior"`` draws the frame it is given."""
        torch.manual_seed(0)
        config = IsoDreamConfig(
            action_dim=A, hidden=16, image_depth=2, units=16, **{f"{branch}_decoder_input": source}
        )
        model = IsoDreamWorldModel(config)
        pixels = torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8)

        def drawn(frames):
            torch.manual_seed(1)
            batch = TensorDict(
                {
                    ("next", "pixels"): frames,
                    "action": torch.ones(2, 4, A),
                    "is_init": torch.zeros(2, 4, 1, dtype=torch.bool),
                },
                [2, 4],
            )
            return model(batch)["next", f"reco_{branch}"]

        def moved(step):  # [T]: which steps' drawings change when the frame of `step` changes
            changed = pixels.clone()
            changed[:, step] = 255 - changed[:, step]
            return (drawn(pixels) - drawn(changed)).flatten(2).abs().amax(-1).amax(0) > 0

        assert moved(0).tolist() == [True, True, True, True]  # the first step draws its posterior
        sees_its_frame = source == "posterior"
        assert moved(2).tolist() == [False, False, sees_its_frame, True]

    @pytest.mark.parametrize("bias, share", [(3.0, (0.85, 0.97)), (0.0, (0.25, 0.45))])
    def test_static_mask_starts_with_most_of_every_pixel(self, bias, share):
        """``static_mask_bias=3`` (the default): an untrained model gives the static branch ~91 % of every pixel, so
        the dynamic branches must earn what moves; without it the three masks start near 1/3 each."""
        torch.manual_seed(0)
        config = IsoDreamConfig(action_dim=A, hidden=16, image_depth=2, units=16, static_mask_bias=bias)
        batch = TensorDict(
            {
                ("next", "pixels"): torch.randint(0, 256, (2, 4, 3, 64, 64), dtype=torch.uint8),
                "action": torch.zeros(2, 4, A),
                "is_init": torch.zeros(2, 4, 1, dtype=torch.bool),
            },
            [2, 4],
        )
        static = IsoDreamWorldModel(config)(batch)["next", "mask_static"]
        assert share[0] < static.mean() < share[1]

    def test_decoder_inputs_are_checked(self):
        with pytest.raises(ValueError, match="control_decoder_input must be one of"):
            IsoDreamConfig(action_dim=A, hidden=16, image_depth=2, units=16, control_decoder_input="paper")

    def test_inverse_loss_trains_the_controllable_branch_only(self, parts):
        model = parts.learner.world_model
        model.zero_grad()
        losses, _ = parts.model_loss(model_batch(parts))
        losses["loss_model_inverse"].sum().backward()
        grad = lambda module: sum(p.grad.abs().sum() for p in module.parameters() if p.grad is not None)  # noqa: E731
        assert grad(model.control_posterior) > 0 and grad(model.encoder) > 0
        assert (
            grad(model.free_prior) == 0 and grad(model.free_posterior) == 0 and grad(model.free_decoder) == 0
        )
        model.zero_grad()

    def test_inverse_prediction_is_masked_at_window_and_episode_starts(self, parts):
        batch = model_batch(parts)
        batch["is_init"][:, 5] = True
        valid = parts.learner.world_model(batch)["next", "action_pred_valid"]
        assert not valid[:, 0].any() and not valid[:, 5].any() and valid[:, 1:5].all()


class TestImagination:
    def test_window_slides_along_one_action_free_chain(self, parts):
        """At imagined step j the window holds z_{j..j+tau-1} of one chain from the start: the paper's L + tau
        rollout (Algorithm 1, line 9), and the free half of the latent is the window's first entry."""
        learner, model = parts.learner, parts.learner.world_model
        posterior = model(model_batch(parts))
        start = TensorDict({k: posterior["next", k][:, -1].detach() for k in ("state", "belief")}, [B])
        env = learner.model_based_env
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            rollout = env.rollout(4, learner.actor, auto_reset=False, tensordict=env.reset(start.clone()))
        window = rollout["free_window"]  # [B, L, tau, F]
        torch.testing.assert_close(window[:, 1:, :-1], window[:, :-1, 1:])
        control, free = model.config.control, model.config.free
        torch.testing.assert_close(
            rollout["state"][..., control.state_dim :], window[..., 0, : free.state_dim]
        )
        torch.testing.assert_close(rollout["belief"][..., control.deter :], window[..., 0, free.state_dim :])
        torch.testing.assert_close(window[:, 0, 0, : free.state_dim], start["state"][:, control.state_dim :])

    def test_imagination_env_specs(self, parts):
        check_env_specs(parts.learner.model_based_env)

    @pytest.mark.parametrize("mode", ["attention", "controllable", "concat"])
    def test_policy_features_of_each_mode(self, mode):
        config = IsoDreamConfig(action_dim=A, hidden=32, free_hidden=16, image_depth=2, units=8)
        control, free = config.control, config.free
        features = PolicyFeatures(config, mode=mode, attention_dim=4)
        window = torch.randn(5, config.attention_window, free.feature_dim)
        state, belief = torch.randn(5, config.packed_state_dim), torch.randn(5, config.packed_belief_dim)
        out = features(state, belief, window) if mode == "attention" else features(state, belief)
        width = control.feature_dim + (free.feature_dim if mode == "concat" else 0)
        assert out.shape == (5, width) == (5, features.feature_dim)

    def test_attention_reads_the_windows_stochastic_states(self):
        """Eq. 6 attends over the noncontrollable states z; the beliefs h' the window carries are not read."""
        config = IsoDreamConfig(action_dim=A, hidden=32, free_hidden=16, image_depth=2, units=8)
        features = PolicyFeatures(config, mode="attention", attention_dim=4)
        window = torch.randn(5, config.attention_window, config.free.feature_dim)
        state, belief = torch.randn(5, config.packed_state_dim), torch.randn(5, config.packed_belief_dim)
        other = window.clone()
        other[..., config.free.state_dim :] = torch.randn_like(other[..., config.free.state_dim :])
        torch.testing.assert_close(features(state, belief, window), features(state, belief, other))
        other[..., : config.free.state_dim] += 1.0
        assert not torch.allclose(features(state, belief, window), features(state, belief, other))

    def test_free_branch_has_the_controllable_classes_and_fewer_categoricals(self):
        config = IsoDreamConfig(action_dim=A, hidden=80, free_hidden=40, image_depth=8, units=80)
        assert (config.control.deter, config.control.num_categoricals, config.control.classes) == (640, 32, 5)
        assert (config.free.deter, config.free.num_categoricals, config.free.classes) == (320, 16, 5)


class TestComposition:
    def test_torchrls_dreamerv3_losses_and_optimisers(self, parts):
        learner = parts.learner
        assert isinstance(learner.model_loss, DreamerV3ModelLoss)
        assert isinstance(learner.actor_loss, DreamerV3ActorLoss) and learner.actor_loss.use_reinforce
        assert isinstance(learner.value_loss, DreamerV3ValueLoss)
        assert isinstance(learner.loss_module, DreamerV3Loss)
        assert all(isinstance(o, DreamerV3Optimizer) for o in parts.stepper.optimizers.values())

    def test_every_trained_parameter_is_in_one_optimiser(self, parts):
        seen = [id(p) for o in parts.stepper.optimizers.values() for g in o.param_groups for p in g["params"]]
        trained = {id(p) for m in parts.modules().values() for p in m.parameters()}
        assert len(seen) == len(set(seen)) and set(seen) == trained

    def test_one_update_returns_every_loss_term(self, parts):
        metrics = parts.stepper.step(None, replay_batch())
        for key in (
            "loss_model_reco",
            "loss_model_dynamic",
            "loss_model_inverse",
            "loss_actor",
            "loss_value",
        ):
            assert math.isfinite(float(metrics[key])), key
        assert metrics["nonfinite_skipped"] == 0

    def test_registered_and_sized_from_the_preset(self, tmp_path):
        assert components_builder(ALGO) is IsoDreamComponents
        config = isodream_config(isodream_run_config(tmp_path), action_dim=A)
        assert (config.hidden, config.free_hidden, config.control.classes, config.image_depth) == (
            16,
            8,
            2,
            2,
        )
        cfg = isodream_run_config(tmp_path)
        cfg.model.size = "bench"
        bench = isodream_config(cfg, action_dim=A)
        assert (bench.hidden, bench.free_hidden, bench.image_depth) == (80, 40, 8)

    def test_free_hidden_fraction_sets_the_action_free_width_and_is_checked(self, tmp_path):
        """``model.free_hidden_fraction`` replaces the table's 0.5 (a multiple of 8); a value outside (0, 2] is
        refused by name, and a learner without an action-free branch of its own refuses the setting."""
        cfg = isodream_run_config(tmp_path)
        cfg.model.hidden_dim = 32
        assert isodream_config(cfg, action_dim=A).free_hidden == 16  # hidden 40, 0.5 of it rounds to 16
        cfg.model.free_hidden_fraction = 0.75
        config = isodream_config(cfg, action_dim=A)
        assert (config.hidden, config.free_hidden) == (40, 32)
        assert config.free.num_categoricals % config.settings.num_blocks == 0
        for bad in (0.0, -0.5, 3.0):
            cfg.model.free_hidden_fraction = bad
            with pytest.raises(ConfigError, match="model.free_hidden_fraction"):
                isodream_config(cfg, action_dim=A)
        cfg.model.free_hidden_fraction = 0.75
        cfg.algo.name = "torchrl_dreamer_v3"
        assert any(
            "model.free_hidden_fraction=0.75 is not read" in line for line in unread_setting_errors(cfg)
        )

    def test_static_mask_bias_setting_reaches_the_static_mask(self, tmp_path):
        """``model.static_mask_bias`` replaces ``IsoDreamConfig``'s 3 (the static mask's head start), and the built
        static decoder's mask logit carries it."""
        cfg = isodream_run_config(tmp_path)
        assert isodream_config(cfg, action_dim=A).static_mask_bias == 3.0
        cfg.model.static_mask_bias = 0.5
        config = isodream_config(cfg, action_dim=A)
        assert config.static_mask_bias == 0.5
        assert not unread_setting_errors(cfg)
        torch.manual_seed(0)
        default = IsoDreamWorldModel(isodream_config(isodream_run_config(tmp_path), action_dim=A))
        torch.manual_seed(0)
        shifted = IsoDreamWorldModel(config)
        # the same initial weights but for the mask logit's bias, lower by 3 - 0.5
        default_bias = default.static_decoder.layers[-1].bias[3]
        shifted_bias = shifted.static_decoder.layers[-1].bias[3]
        assert float(default_bias - shifted_bias) == pytest.approx(2.5, abs=1e-5)

    @pytest.mark.parametrize("hidden_dim", [16, 24, 32, 40, 48, 64, 128, 200])
    def test_every_hidden_dim_builds_and_runs(self, tmp_path, hidden_dim):
        """``model.hidden_dim`` between the presets builds too: the action-free branch's categoricals are a multiple
        of the block GRU's blocks (at 32 their 13 of 3 classes made a prior input of 167, which no 8 blocks split)."""
        cfg = isodream_run_config(tmp_path)
        cfg.model.hidden_dim = hidden_dim
        config = isodream_config(cfg, action_dim=A)
        assert config.free.num_categoricals % config.settings.num_blocks == 0
        model = IsoDreamWorldModel(config)
        batch = TensorDict(
            {
                ("next", "pixels"): torch.zeros(1, 2, 3, 64, 64, dtype=torch.uint8),
                "action": torch.zeros(1, 2, A),
                "is_init": torch.zeros(1, 2, 1, dtype=torch.bool),
            },
            [1, 2],
        )
        assert model(batch)["next", "reco_pixels"].shape == (1, 2, 3, 64, 64)

    def test_bad_pixels_get_one_line(self, parts):
        with pytest.raises(ValueError, match="pixels"):
            parts.model_loss(model_batch(parts).set(("next", "pixels"), torch.full((B, T, 3, 64, 64), 2.0)))

    def test_bf16_is_refused_and_world_model_mode_is_taken(self, tmp_path):
        cfg = isodream_run_config(tmp_path)
        cfg.model.precision = "bf16"
        with pytest.raises(ConfigError, match="fp32 only"):
            isodream_config(cfg, action_dim=A)
        cfg = isodream_run_config(tmp_path)
        cfg.mode = "world_model"  # its world model alone (tests/test_world_model_mode.py trains it)
        assert not any("mode=world_model" in line for line in world_model_mode_errors(cfg))


class TestFastPaths:
    """``model.fast_paths`` (``IsoDreamConfig.fast_paths``): the CPU fast paths of ``modules/fast_paths.py`` (fused RMS
    norms, eq. 4 as one autograd node) or the reference forms (TorchRL's RMS norms, ``MaskComposition``); the same
    learner either way. tests/test_fast_layers.py compares each piece; this compares a whole update."""

    @staticmethod
    def build(tmp_path, fast_paths: bool | None) -> IsoDreamComponents:
        cfg = isodream_run_config(tmp_path / f"run_{fast_paths}")
        cfg.model.fast_paths = fast_paths
        validate_config(cfg)  # accepted for algo=isodream
        torch.manual_seed(0)
        return IsoDreamComponents(cfg, action_dim=A, scratch_dir=tmp_path / f"scratch_{fast_paths}")

    @staticmethod
    def update(parts: IsoDreamComponents, sample: TensorDict, *, seed: int):
        """The stepper's full update up to its optimisers (world model, imagination from every posterior, actor,
        critic, replay critic; one backward of the sum of the ``loss_*`` terms) under ``seed``: the loss terms and
        each trained parameter's gradient, by ``"<checkpoint module>.<parameter>"``."""
        stepper = parts.stepper
        batch = stepper.prepare(sample.clone()).reshape(B, T)
        params = {
            f"{group}.{name}": p
            for group, module in parts.modules().items()
            for name, p in module.named_parameters()
        }
        for p in params.values():
            p.grad = None
        torch.manual_seed(seed)
        losses = stepper._losses(batch, world_model_only=False)
        loss_sum(losses).backward()
        grads = {name: p.grad for name, p in params.items()}
        for p in params.values():
            p.grad = None
        return {key: value.detach() for key, value in losses.items()}, grads

    def test_a_whole_update_gives_the_same_losses_and_gradients_with_and_without_fast_paths(self, tmp_path):
        """Two default learners with the same weights, ``model.fast_paths`` unset (on) and ``false``: the fast and
        the reference modules under the same names and state-dict keys, and on one replayed batch (an episode start
        inside a window) under one seed, the same loss terms and the same gradient of every trained parameter."""
        fast, reference = self.build(tmp_path, None), self.build(tmp_path, False)
        assert fast.world_model.config.fast_paths and not reference.world_model.config.fast_paths
        assert type(fast.world_model.composition) is FusedMaskComposition
        assert type(reference.world_model.composition) is MaskComposition
        # each trained network (the critic's parameters live in its loss, ``value_model_params``) and the names of
        # its RMS norms' weights among the gradients below: fused ones in one, TorchRL's in the other, same places
        norm_weights = {}
        for group, network, prefix in (
            ("world_model", "world_model", "world_model."),
            ("actor", "actor", "actor."),
            ("value_loss", "value", "value_loss.value_model_params."),
        ):
            fast_net, plain_net = getattr(fast.learner, network), getattr(reference.learner, network)
            fast_norms = [n for n, m in fast_net.named_modules() if isinstance(m, FastRMSNorm)]
            plain_norms = [n for n, m in plain_net.named_modules() if isinstance(m, TORCHRL_NORMS)]
            assert fast_norms and fast_norms == plain_norms, group
            assert not any(isinstance(m, FastRMSNorm) for m in plain_net.modules()), group
            norm_weights[group] = [f"{prefix}{norm}.weight" for norm in fast_norms]
        # DreamerV3 starts the reward and critic heads' output layers at zero, which would leave no gradient through
        # the norms before them: small random weights there, so that every fast path is on the compared path
        generator = torch.Generator().manual_seed(3)
        with torch.no_grad():
            for module in fast.modules().values():
                for weight in module.parameters():
                    if weight.dim() > 1 and not weight.any():
                        weight.copy_(torch.randn(weight.shape, generator=generator) * 0.1)
        for name, module in fast.modules().items():  # world_model, actor, value_loss (critic), return_norm
            other = reference.modules()[name]
            assert module.state_dict().keys() == other.state_dict().keys(), name
            other.load_state_dict(module.state_dict())
        torch.manual_seed(1)
        sample = replay_batch(init_at=5)

        fast_losses, fast_grads = self.update(fast, sample, seed=2)
        ref_losses, ref_grads = self.update(reference, sample, seed=2)

        terms = {"loss_model_reco", "loss_model_dynamic", "loss_model_inverse", "loss_actor", "loss_value"}
        assert fast_losses.keys() == ref_losses.keys() and terms <= set(ref_losses.keys())
        # the forward passes: measured equal, or within 1.5e-7 relative (float32 rounding): 60x inside rtol
        for key, want in ref_losses.items():
            torch.testing.assert_close(fast_losses[key], want, rtol=1e-5, atol=1e-6, msg=key)
        assert fast_grads.keys() == ref_grads.keys() and len(ref_grads) > 100
        assert not any(grad is None for grads in (fast_grads, ref_grads) for grad in grads.values())
        # The comparison reaches every fast path: a gradient flows through each fused RMS norm (its weight's; but
        # the action-free prior's action projection, which sees eq. 3's constant zero action and a zero bias: an
        # input of zeros), and the decoders' outputs (the fused composition's inputs) get one.
        constant = "world_model.free_prior.rnn.action_projection.1.weight"
        for group, names in norm_weights.items():
            assert all(bool(ref_grads[name].any()) == (name != constant) for name in names), group
        for decoder in ("control_decoder", "free_decoder", "static_decoder"):
            layers = [name for name in ref_grads if name.startswith(f"world_model.{decoder}.layers.")]
            assert ref_grads[layers[-1]].abs().max() > 0, decoder
        # The backward passes differ by float32 rounding only (fused vs decomposed RMS norms, one node vs separate
        # operations for eq. 4), and the differences travel back through the RSSMs, the imagination and the
        # encoder: measured at most 2.2e-6 of a parameter's largest gradient over six batches and seeds (on this
        # one 6.6e-7 on two threads, 8.9e-7 on one), so an absolute tolerance of 2e-5 of that largest gradient
        # leaves a 9x margin. It still fails a fast path off by 1e-5 in the RMS norm's input gradient (67 of the
        # 162 parameters), by 1e-4 in its weight gradient (37) or by 1e-3 in eq. 4's gradients (92); an eps 10x
        # off fails the losses.
        for name, want in ref_grads.items():
            scale = float(want.abs().max())
            torch.testing.assert_close(fast_grads[name], want, rtol=1e-5, atol=2e-5 * scale, msg=name)


@pytest.mark.parametrize(
    "algo, removed",
    [
        ("isodream", None),
        ("isodream_no_inverse", "inverse_dynamics"),
        ("isodream_no_static", "static_branch"),
        ("isodream_no_attention", "attention"),
    ],
)
def test_each_ablation_is_the_default_without_its_part_and_updates(tmp_path, algo, removed):
    """``isodream-train algo=<ablation> size=tiny`` builds DreamerV3's learner without the ablated part, and one
    update of it gives finite losses."""
    window = [f"train.sequence_length={T}", f"train.batch_size={B}", f"logging.video_length={T}"]
    cfg = composed(f"algo={algo}", "size=tiny", *window)
    validate_config(cfg)
    parts = make_components(cfg, action_dim=A, scratch_dir=tmp_path)
    assert isinstance(parts, IsoDreamComponents) and parts.algo == algo
    config = parts.world_model.config
    switches = ("free_branch", "static_branch", "inverse_dynamics")
    assert {name: getattr(config, name) for name in switches} == {name: name != removed for name in switches}
    modes = {m.mode for m in parts.learner.actor.modules() if isinstance(m, PolicyFeatures)}
    assert modes == {"controllable" if removed == "attention" else "attention"}
    assert ("background" in parts.world_model(model_batch(parts)).keys()) == (removed != "static_branch")
    metrics = parts.stepper.step(None, replay_batch())
    assert ("loss_model_inverse" in metrics.keys()) == (removed != "inverse_dynamics")
    losses = [key for key in metrics.keys() if key.startswith("loss_")]
    assert "loss_actor" in losses and all(math.isfinite(float(metrics[key])) for key in losses)
    assert metrics["nonfinite_skipped"] == 0


class TestPolicy:
    def test_acts_with_the_window_and_carries_the_packed_latent(self, parts):
        policy = parts.behavior.policy
        out = policy(env_batch(policy))
        config = parts.learner.world_model.config
        assert out["action"].shape == (3, A) and out["action"].abs().max() <= 1
        assert out["next", "state"].shape == (3, config.packed_state_dim)
        assert out["next", "belief"].shape == (3, config.packed_belief_dim)
        assert "free_window" not in out.keys()

    def test_evaluation_takes_the_actors_mean(self, parts):
        """Same seed (the posterior's categorical draws): the deterministic action repeats, a sampled one differs."""
        policy = parts.behavior.policy
        td = env_batch(policy)

        def act(kind):
            torch.manual_seed(0)
            with set_exploration_type(kind):
                return policy(td.clone())["action"]

        mean = act(ExplorationType.DETERMINISTIC)
        torch.testing.assert_close(mean, act(ExplorationType.DETERMINISTIC))
        assert not torch.allclose(mean, act(ExplorationType.RANDOM))

    def test_runs_in_a_primed_env(self, parts):
        policy = parts.behavior.policy
        env = make_env("sprites", task="reach", max_steps=20)
        env.append_transform(policy.make_tensordict_primer())
        rollout = env.rollout(4, policy)
        torch.testing.assert_close(rollout["previous_action"][1:], rollout["action"][:-1])
        torch.testing.assert_close(rollout["belief"][1:], rollout["next", "belief"][:-1])


def test_train_writes_a_summary_and_resumes(tmp_path):
    cfg = isodream_run_config(tmp_path)
    result = train(cfg)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["algo"] == ALGO and math.isfinite(summary["eval_return"])
    # sprites renders the ground truth: the final decomposition and where it put the agent
    assert 0.0 <= summary["decomposition"]["iou_control_vs_agent"] <= 1.0
    assert summary["isolation"]["agent_branch"] in ("control", "free", "static")
    assert math.isfinite(result.metrics["loss_model_inverse"]) and math.isfinite(result.metrics["loss_actor"])
    cfg.resume, cfg.train.total_steps = True, 80
    resumed = train(cfg)
    assert resumed.resumed_from == result.checkpoint and resumed.env_steps == 80


def test_resume_is_exact(tmp_path):
    assert_resume_is_exact(IsoDreamComponents, isodream_run_config(tmp_path / "run"), tmp_path)


class TestPictures:
    def test_open_loop_prediction_draws_every_branch(self, parts):
        window = parts.stepper.prepare(replay_batch()).reshape(B, T)
        prediction = open_loop_prediction(parts.world_model, window, context=3)
        for key in ("reco_pixels", "reco_control", "reco_free", "background"):
            assert prediction[key].shape == (B, T, 3, 64, 64), key
            assert prediction[key].min() >= -0.5 - 1e-6 and prediction[key].max() <= 0.5 + 1e-6, key
        masks = sum(prediction[f"mask_{name}"] for name in ("control", "free", "static"))
        torch.testing.assert_close(masks, torch.ones_like(masks))
        assert prediction["imagined"][:, 3:].all() and not prediction["imagined"][:, :3].any()

    def test_decomposition_scores_read_the_composite_in_the_ground_truths_units(self, parts):
        windows = episode_windows(collect_sprites_episodes(episodes=1, steps=8), window=8)
        scores = decomposition_scores(parts.world_model, windows)
        output = parts.world_model(windows.select("action", "is_init", ("next", "pixels")))
        truth = windows["next", "pixels"].float() / 255
        expected = (output["next", "reco_pixels"] - truth).pow(2).mean()
        assert scores["reco_mse"] == pytest.approx(float(expected.detach()), rel=0.05)


def test_the_readme_example_trains_the_default_world_model():
    """The "Use the modules" snippet of README.md runs: the default's world model and loss, exported by the
    packages, on a [B, T] window."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    (block,) = re.findall(r"## Use the modules\n\n```python\n(.*?)```", readme, flags=re.S)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert {"loss_model_reco", "loss_model_inverse", "loss_model_dynamic"} <= set(scope["losses"].keys())
    assert scope["output"]["next", "mask_control"].shape == (4, 16, 1, 64, 64)
