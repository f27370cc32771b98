"""Which sprites can be read off each branch's latent state? Linear probes on a trained world model.

A missing object in a branch's mask has two possible causes: the branch's state does not carry the
object (a representation problem), or it does and the mask never lets the branch draw it (a composition
problem: a softmax mask shut at ~0 passes no gradient). This probe tells them apart. It runs a trained world
model of either Iso-Dream learner (the DreamerV2-style
:class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel`, the default's
:class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel`) over random-action sprites windows, fits a
ridge regression from each branch's posterior features (``[s, h]`` and ``[z, h']``: ``[state, belief]`` and
``[free_state, free_belief]``, or the halves of the default's packed latent) to each sprite's centre (the centroid
of its ground-truth pixels), and reports the held-out R^2 per sprite and branch: near 1, the branch knows where the
sprite is; at or below 0 (worse than the mean position), it does not.

    python -m isodream_rl.cli probe runs/world_model

With ``encoder=True`` (CLI ``--encoder``) the same read-out is also fitted one step earlier, on the
encoder: ``trunk`` (the shared trunk ``Enc_theta``'s feature map, 2x2 average-pooled and flattened),
``embed_control`` and ``embed_free`` (the branch heads' embeddings ``e^s_t``, ``e^z_t``). These are wide
(hundreds to thousands of features) and sparse (ReLU maps), so they are scaled by one common deviation
rather than each by its own, and their ridge penalty is chosen by cross-validation on the fitting half. A
sprite the trunk carries but ``embed_free`` does not is dropped by the noncontrollable head, before its RSSM. The
default's encoder has no branch heads (both branches' posteriors read one embedding): its ``trunk`` is that
embedding, the flattened final feature map, and there is no ``embed_*``.

The episodes are made like the run's (its scene, ``env.kwargs``, action hold and window, read from the
checkpoint's configuration by :func:`isodream_rl.trainers.world_model_run.probe_scene`), from seeds it never
trains on. ``isodream-train exp=world_model`` runs the same probe at the end of training (its CLI hands
:func:`probe` to the trainer) and reports it as ``probe_r2_*`` in its ``summary.json``.
"""

from __future__ import annotations

from typing import Any

import torch

from isodream_rl.data.sprites_episodes import collect_sprites_episodes, episode_windows, model_input
from isodream_rl.modules.isodream.world_model import IsoDreamWorldModel
from isodream_rl.modules.isodream_v2 import IsoDreamV2WorldModel

#: The world models the probe reads: Iso-Dream's, of either learner.
ProbedModel = IsoDreamV2WorldModel | IsoDreamWorldModel


def sprite_names(num_distractors: int, *, target: bool = False) -> list[str]:
    """The probed sprites in :func:`sprite_centres`' order: ``agent``, ``distractor_<i>``..., then ``target``."""
    return ["agent"] + [f"distractor_{i}" for i in range(num_distractors)] + (["target"] if target else [])


def sprite_centres(truth, num_distractors: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres ``[N, S, 2]`` (row, column in [0, 1]) of the agent, each distractor, then the target where ``truth``
    has one (:func:`sprite_names`), and ``[N, S]`` visibility.

    ``truth``: a flat tensordict with ``"mask_agent"`` and ``"distractor_ids"`` ``[N, 64, 64]``, and
    ``"mask_target"`` (sprites ``reach``: the still target the agent is rewarded for reaching) if any.
    """
    masks = [truth["mask_agent"].bool()] + [truth["distractor_ids"] == i + 1 for i in range(num_distractors)]
    if "mask_target" in truth.keys():
        masks.append(truth["mask_target"].bool())
    masks = torch.stack(masks, dim=1).float()  # [N, S, 64, 64]
    size = masks.shape[-1]
    grid = torch.arange(size, dtype=torch.float32) / (size - 1)
    count = masks.sum((-2, -1))
    rows = (masks.sum(-1) * grid).sum(-1) / count.clamp(min=1)
    cols = (masks.sum(-2) * grid).sum(-1) / count.clamp(min=1)
    return torch.stack([rows, cols], dim=-1), count > 0


def ridge_r2(
    x_train: torch.Tensor,
    y_train: torch.Tensor,
    x_test: torch.Tensor,
    y_test: torch.Tensor,
    *,
    ridge: float,
    per_feature: bool = True,
) -> float:
    """Held-out R^2 of a ridge regression ``y ~ x``, averaged over the columns of ``y``.

    Features are centred on the training set and scaled by their standard deviation there: each its own
    (``per_feature``, for dense features such as latent states), or all by one common scale (for sparse
    ReLU features: a unit active in a handful of training frames would otherwise be blown up by its tiny
    training deviation wherever it fires on the test set)."""
    mean = x_train.mean(0)
    std = (
        x_train.std(0).clamp(min=1e-6) if per_feature else x_train.std(0).pow(2).mean().sqrt().clamp(min=1e-6)
    )
    a = torch.cat([(x_train - mean) / std, torch.ones(len(x_train), 1)], dim=1).double()
    b = torch.cat([(x_test - mean) / std, torch.ones(len(x_test), 1)], dim=1).double()
    eye = torch.eye(a.shape[1], dtype=torch.float64)
    eye[-1, -1] = 0.0  # the intercept is not shrunk
    weights = torch.linalg.solve(a.T @ a + ridge * eye, a.T @ y_train.double())
    residual = (b @ weights - y_test.double()).pow(2).sum(0)
    total = (y_test.double() - y_test.double().mean(0)).pow(2).sum(0).clamp(min=1e-12)
    return float((1.0 - residual / total).mean())


@torch.no_grad()
def branch_features(model: ProbedModel, data, *, window: int) -> dict[str, torch.Tensor]:
    """Posterior features ``[N, D]`` of each dynamic branch over flat episode data cut into windows: ``control``,
    ``[s, h]``, and, with the noncontrollable branch, ``free``, ``[z, h']``.

    The first ``window // 4`` steps of each window are dropped (the filter is still settling there)."""
    out = model(model_input(episode_windows(data, window=window)))["next"]
    keep = slice(window // 4, None)
    if isinstance(model, IsoDreamWorldModel):  # one packed latent, [s, z] and [h, h']
        (s, z), (h, h_free) = model.split_state(out["state"]), model.split_belief(out["belief"])
    else:
        s, h = out["state"], out["belief"]
        z, h_free = (out["free_state"], out["free_belief"]) if "free_state" in out.keys() else (None, None)
    feats = {"control": torch.cat([s, h], dim=-1)[:, keep]}
    if z is not None:
        feats["free"] = torch.cat([z, h_free], dim=-1)[:, keep]
    return {name: f.reshape(-1, f.shape[-1]).float() for name, f in feats.items()}


#: ridge penalties tried by :func:`ridge_cv` (standardised features)
RIDGES = (1.0, 10.0, 100.0, 1e3, 1e4, 1e5)


def ridge_cv(
    x: torch.Tensor, y: torch.Tensor, *, ridges=RIDGES, folds: int = 2, per_feature: bool = True
) -> float:
    """The ridge penalty of ``ridges`` with the best ``folds``-fold cross-validated R^2 of ``y ~ x``
    (``per_feature``: as :func:`ridge_r2`).

    Folds are contiguous blocks (consecutive frames are correlated; shuffled folds would leak)."""
    bounds = torch.linspace(0, len(x), folds + 1).long().tolist()

    def score(ridge: float) -> float:
        total = 0.0
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            held = torch.zeros(len(x), dtype=torch.bool)
            held[lo:hi] = True
            total += ridge_r2(x[~held], y[~held], x[held], y[held], ridge=ridge, per_feature=per_feature)
        return total

    return max(ridges, key=score)


@torch.no_grad()
def encoder_features(model: ProbedModel, data, *, window: int) -> dict[str, torch.Tensor]:
    """Encoder features ``[N, D]`` of the same frames as :func:`branch_features` (the same steps dropped):
    ``trunk`` (2x2-pooled shared trunk map), ``embed_control`` and, with the noncontrollable branch,
    ``embed_free``; of the default's world model, whose encoder has no branch heads, ``trunk`` only (its
    embedding, the flattened final feature map that both branches' posteriors read)."""
    pixels = episode_windows(data, window=window).get(("next", "pixels"))[:, window // 4 :]
    device = next(model.parameters()).device
    pixels = pixels.reshape(-1, *pixels.shape[-3:]).to(device)
    if isinstance(model, IsoDreamWorldModel):
        return {"trunk": model.encoder(pixels).float()}
    trunk = model.encoder.trunk_features(pixels)
    feats = {"trunk": torch.nn.functional.avg_pool2d(trunk, 2).flatten(1)}
    feats["embed_control"] = model.encoder.head("control", trunk)
    if "free" in model.encoder.heads:
        feats["embed_free"] = model.encoder.head("free", trunk)
    return {name: f.float() for name, f in feats.items()}


def probe(
    model: ProbedModel,
    *,
    window: int = 16,
    episodes: int = 32,
    episode_length: int = 96,
    action_hold: int = 8,
    num_distractors: int = 3,
    seed: int = 1000,
    ridge: float = 10.0,
    encoder: bool = False,
    **scene: Any,
) -> dict[str, float]:
    """``r2_{branch}_{sprite}`` for each dynamic branch and sprite (``agent``, ``distractor_0`` ..., and ``target``
    with ``task="reach"`` in ``scene``: whether a branch's state knows where the reward is).

    Half of the episodes fit the probes, the other half score them. ``ridge`` is the penalty of the
    branches' posterior features; with ``encoder=True`` the encoder's features (see :func:`encoder_features`)
    are probed too, as ``r2_trunk_*``, ``r2_embed_control_*``, ``r2_embed_free_*``, each sprite with the
    penalty :func:`ridge_cv` picks on the fitting half. ``seed`` makes the episodes and the
    model's latent samples; the scores of one checkpoint are the same on every call. ``action_hold``,
    ``num_distractors`` and ``scene`` (``SpritesEnv`` keywords: ``num_backgrounds``, ``background_seed``,
    ``sprite_size``, ``distractor_colours``...) make the episodes, as
    :func:`~isodream_rl.data.sprites_episodes.collect_sprites_episodes` does."""
    if episode_length % window:
        raise ValueError(f"episode_length ({episode_length}) must be a multiple of window ({window})")
    data = collect_sprites_episodes(
        episodes=episodes,
        steps=episode_length,
        seed=seed,
        action_hold=action_hold,
        num_distractors=num_distractors,
        **scene,
    )
    training = model.training
    model.eval()
    device = next(model.parameters()).device
    # the posterior states are samples: seeded here (without touching the caller's generator), so a probe
    # of one checkpoint gives the same scores every time
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(seed)
        feats = branch_features(model, data.to(device), window=window)
    wide = encoder_features(model, data, window=window) if encoder else {}
    feats.update(wide)
    model.train(training)
    truth = data["next"].reshape(-1, window)[:, window // 4 :].reshape(-1)
    centres, visible = sprite_centres(truth, num_distractors)
    half = len(centres) // 2
    names = sprite_names(num_distractors, target="mask_target" in truth.keys())
    scores = {}
    for branch, x in feats.items():
        x = x.cpu()
        for s, name in enumerate(names):
            train = visible[:half, s]
            test = visible[half:, s]
            x_fit, y_fit = x[:half][train], centres[:half, s][train]
            dense = branch not in wide  # the posteriors; the encoder's ReLU maps are sparse
            penalty = ridge if dense else ridge_cv(x_fit, y_fit, per_feature=False)
            scores[f"r2_{branch}_{name}"] = ridge_r2(
                x_fit, y_fit, x[half:][test], centres[half:, s][test], ridge=penalty, per_feature=dense
            )
    return scores
