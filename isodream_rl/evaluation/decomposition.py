"""Decomposition scores: each branch's mask against the ground-truth classes of the scene.

Iso-Dream composes every frame from three branches (eq. 4): the controllable one (``mask_control``), the
noncontrollable one (``mask_free``) and the static background (``mask_static``). Every env of
``isodream_rl.envs`` renders the matching ground truth (``make_env(..., return_masks=True)``) with one
vocabulary:

* ``agent`` (``"mask_agent"``): what the action moves (the sprites agent, the DMC robot, the highway ego);
* ``distractors`` (``"mask_distractors"``): what moves without it (the sprites discs, the DMC background
  video, the other vehicles);
* ``background``: every other pixel (the sprites background and target, the DMC floor, the road).

A perfect Iso-Dream model gives ``control`` the agent, ``free`` the distractors and ``static`` the
background. Where the windows also hold a task object's mask (:data:`PART_KEYS`: the sprites target, part of
the background above), the scores say which branch draws it: the target is still between respawns, so the
static branch can draw it, and then neither state the actor reads needs to know where it is.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torch import nn

from isodream_rl.modules.isodream.world_model import IsoDreamWorldModel
from isodream_rl.run_utils.json_io import nan_if_none

#: The world model's branches, in the order their masks are stacked.
BRANCHES = ("control", "free", "static")
#: The ground-truth classes; ``background`` is every pixel of neither of the other two.
CLASSES = ("agent", "distractors", "background")
#: Where the windows hold the ground truth of the classes with a mask of their own.
TRUTH_KEYS = {"agent": ("next", "mask_agent"), "distractors": ("next", "mask_distractors")}
#: Optional ground truth of objects inside the classes above, scored when the windows hold it.
PART_KEYS = {"target": ("next", "mask_target")}
_MODEL_KEYS = ("action", "is_init", ("next", "pixels"))
#: The images of a world model's output (each branch's drawn where it has one): the composite, the controllable and
#: noncontrollable components and the background.
IMAGE_KEYS = (("next", "reco_pixels"), ("next", "reco_control"), ("next", "reco_free"), "background")


def centred_images(world_model: nn.Module, output: TensorDictBase) -> TensorDictBase:
    """``output``, the output of ``world_model``, with its images (:data:`IMAGE_KEYS`) in the pixel range the scores
    and pictures read, ``[-0.5, 0.5]`` (``preprocess_pixels``'): an
    :class:`~isodream_rl.modules.isodream.world_model.IsoDreamWorldModel` draws in its loss's units, ``pixels / 255``
    in ``[0, 1]``, shifted here (in place); any other world model draws in ``[-0.5, 0.5]`` and is returned as it is.

    Args:
        world_model: the world model that wrote ``output``.
        output: its ``[N, T]`` output.

    Returns:
        ``output``.
    """
    if isinstance(world_model, IsoDreamWorldModel):
        keys = output.keys(include_nested=True)
        for key in IMAGE_KEYS:
            if key in keys:
                output.set(key, output.get(key) - 0.5)
    return output


def check_windows(windows: TensorDictBase) -> None:
    """Refuse windows :func:`decomposition_scores` cannot score, saying what is wrong.

    Args:
        windows: ``[N, T]`` with ``"action"``, ``"is_init"``, ``("next", "pixels")`` uint8 ``[N, T, 3, H, W]``
            and the ground truth ``("next", "mask_agent")``, ``("next", "mask_distractors")`` bool
            ``[N, T, H, W]``.

    Raises:
        ValueError: not ``[N, T]``, a key missing, or a mask of another shape or not boolean.
    """
    if not isinstance(windows, TensorDictBase) or windows.batch_dims != 2:
        shape = tuple(windows.batch_size) if isinstance(windows, TensorDictBase) else type(windows).__name__
        raise ValueError(
            f"decomposition scores need windows as a TensorDict of batch size [N, T], got {shape}; cut flat "
            "episodes with isodream_rl.data.sprites_episodes.episode_windows"
        )
    keys = set(windows.keys(include_nested=True))
    missing = [key for key in (*_MODEL_KEYS, *TRUTH_KEYS.values()) if key not in keys]
    if missing:
        raise ValueError(
            f"the windows lack {missing}: the ground-truth masks come from make_env(..., return_masks=True) "
            "(sprites, highway, dmc_*) or collect_sprites_episodes"
        )
    pixels = windows.get(("next", "pixels"))
    if pixels.dim() != 5 or pixels.shape[2] != 3:
        raise ValueError(f'("next", "pixels") must be [N, T, 3, H, W], got {list(pixels.shape)}')
    expected = (*windows.batch_size, *pixels.shape[-2:])
    for key in TRUTH_KEYS.values():
        mask = windows.get(key)
        if tuple(mask.shape) != expected:
            raise ValueError(
                f"{key} must be [N, T, H, W] = {list(expected)} like the pixels, got {list(mask.shape)}"
            )
        if mask.dtype != torch.bool:
            raise ValueError(f"{key} must be a bool mask, got {mask.dtype}")
    for key in PART_KEYS.values():
        if key in keys:
            mask = windows.get(key)
            if tuple(mask.shape) != expected or mask.dtype != torch.bool:
                raise ValueError(
                    f"{key} must be a bool [N, T, H, W] = {list(expected)} mask like the pixels, got "
                    f"{mask.dtype} {list(mask.shape)}"
                )


def branch_assignment(output: TensorDictBase, *, threshold: float | None = None) -> dict[str, torch.Tensor]:
    """Binary masks of the branches, bool ``[*N, H, W]`` each, keyed by :data:`BRANCHES`.

    Args:
        output: a world model's output with ``("next", "mask_<branch>")`` ``[*N, 1, H, W]`` for the branches it
            has (``mask_control`` at least).
        threshold: ``None`` (default): each pixel goes to the branch of the largest mask (the masks sum to one,
            softmax or sigmoid, so this is the branch that draws most of it; ties go to the first of
            :data:`BRANCHES`), so the branches partition the frame. A number: a branch holds the pixels where
            its mask is above it (the masks may then overlap or leave pixels to none).

    Returns:
        one mask per branch of :data:`BRANCHES`; a branch the model does not have holds no pixel (the
        single-branch DreamerV2 model: ``control`` everywhere).
    """
    nxt = output.get("next")
    present = [b for b in BRANCHES if f"mask_{b}" in nxt.keys()]
    if "control" not in present:
        raise ValueError('the world model output has no ("next", "mask_control"): is it a world model\'s?')
    masks = torch.stack([nxt.get(f"mask_{b}").float().squeeze(-3) for b in present])  # [B, *N, H, W]
    if threshold is None:
        winner = masks.argmax(0)
        held = {b: winner == i for i, b in enumerate(present)}
    else:
        held = {b: masks[i] > threshold for i, b in enumerate(present)}
    empty = torch.zeros_like(held["control"])
    return {b: held.get(b, empty) for b in BRANCHES}


def _ratio(numerator: torch.Tensor, denominator: torch.Tensor) -> float:
    total = int(denominator)
    return float(numerator) / total if total else math.nan


def score_decomposition(
    output: TensorDictBase, windows: TensorDictBase, *, threshold: float | None = None
) -> dict[str, float]:
    """The scores of :func:`decomposition_scores` from a world model's output on ``windows``.

    Args:
        output: the world model's ``[N, T]`` output on ``windows`` (``("next", "reco_pixels")`` and the masks).
        windows: as :func:`check_windows` takes them.
        threshold: how masks become pixels (:func:`branch_assignment`).

    Returns:
        the flat dict of :func:`decomposition_scores`.
    """
    check_windows(windows)
    nxt = output.get("next")
    truth = {name: windows.get(key).cpu() for name, key in TRUTH_KEYS.items()}
    truth["background"] = ~truth["agent"] & ~truth["distractors"]
    held = {
        b: mask.cpu().reshape(truth["agent"].shape)
        for b, mask in branch_assignment(output, threshold=threshold).items()
    }
    pixels = windows.get(("next", "pixels")).cpu()
    target = pixels.float() / 255.0 - 0.5  # the world model's pixel range (preprocess_pixels)
    error = (nxt.get("reco_pixels").float().cpu() - target).pow(2).mean(-3)  # [N, T, H, W], over RGB
    scores = {"reco_mse": float(error.mean())}
    for name in CLASSES:
        scores[f"mse_{name}"] = _ratio(error[truth[name]].sum(), truth[name].sum())
    for branch in BRANCHES:
        for name in CLASSES:
            union = (held[branch] | truth[name]).sum()
            scores[f"iou_{branch}_vs_{name}"] = _ratio((held[branch] & truth[name]).sum(), union)
    for branch in BRANCHES:
        background = truth["background"]
        scores[f"background_share_{branch}"] = _ratio((held[branch] & background).sum(), background.sum())
    present = set(windows.keys(include_nested=True))
    for part, key in PART_KEYS.items():
        if key not in present:
            continue
        mask = windows.get(key).cpu()
        # whether the model draws it at all: a branch's mask may hold its pixels and draw the background there
        scores[f"mse_{part}"] = _ratio(error[mask].sum(), mask.sum())
        for branch in BRANCHES:
            union = (held[branch] | mask).sum()
            scores[f"iou_{branch}_vs_{part}"] = _ratio((held[branch] & mask).sum(), union)
            scores[f"{part}_share_{branch}"] = _ratio((held[branch] & mask).sum(), mask.sum())
    return scores


@torch.no_grad()
def decomposition_scores(
    world_model: nn.Module,
    windows: TensorDictBase,
    *,
    threshold: float | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """How a world model's branches split ``windows`` into the ground-truth agent, distractors and background.

    The model filters each window from zero states (posterior states, as in training: its reconstruction of
    frames it observes), and each pixel of each step goes to one branch (:func:`branch_assignment`: the
    largest mask, by default).

    The single-branch DreamerV2 baseline (``algo=dreamerv2``: the same
    :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` with the other branches off) is scored the same way:
    its one image is the ``control`` branch, which holds every pixel, so ``iou_control_vs_agent`` is the
    agent's share of the frame, and the branches it lacks hold none (``iou_free_vs_distractors = 0``,
    ``background_share_static = 0``).

    Args:
        world_model: an :class:`~isodream_rl.modules.isodream_v2.IsoDreamV2WorldModel` (or a module with its output keys).
        windows: ``[N, T]``: ``"action"`` ``[N, T, A]``, ``"is_init"`` ``[N, T, 1]``, ``("next", "pixels")``
            uint8 ``[N, T, 3, H, W]`` and the ground truth ``("next", "mask_agent")``,
            ``("next", "mask_distractors")`` bool ``[N, T, H, W]``; any other key is ignored.
        threshold: ``None`` (default) for the largest mask, or a mask level (``0.5``); see
            :func:`branch_assignment`.
        device: where the world model runs.

    Returns:
        floats, ``nan`` where a ratio has nothing to count (a class absent from every window):

        * ``iou_<branch>_vs_<class>`` for every branch of :data:`BRANCHES` and class of :data:`CLASSES`
          (the diagonal: ``iou_control_vs_agent``, ``iou_free_vs_distractors``, ``iou_static_vs_background``);
        * ``background_share_<branch>``: the fraction of the background's pixels that branch holds;
        * ``mse_<class>``: the composite's squared error per pixel and channel on that class's pixels
          (``[-0.5, 0.5]`` pixel range), and ``reco_mse`` on all of them;
        * where the windows hold a part of :data:`PART_KEYS` (``("next", "mask_target")``, bool
          ``[N, T, H, W]``): ``iou_<branch>_vs_<part>`` and ``<part>_share_<branch>``, the fraction of its
          pixels each branch holds, and ``mse_<part>``, the composite's error on its pixels (a branch may hold
          them and draw the background there: the share says where, this says whether it is drawn).

    Raises:
        ValueError: windows without the ground truth or of the wrong shapes (:func:`check_windows`).

    Examples:
        >>> from isodream_rl.modules import IsoDreamV2WorldModel, IsoDreamV2Config
        >>> from isodream_rl.data.sprites_episodes import collect_sprites_episodes, episode_windows
        >>> model = IsoDreamV2WorldModel(IsoDreamV2Config.from_preset("tiny", action_dim=2))
        >>> windows = episode_windows(collect_sprites_episodes(episodes=1, steps=8), window=8)
        >>> scores = decomposition_scores(model, windows)
        >>> 0.0 <= scores["iou_control_vs_agent"] <= 1.0
        True
    """
    check_windows(windows)
    inputs = windows.select(*_MODEL_KEYS).to(device)
    output = centred_images(world_model, world_model(inputs))
    return score_decomposition(output, windows, threshold=threshold)


#: The isolation aims (Iso-Dream's assignment): the agent in the controllable branch, out of the action-free one,
#: and the things that move without the action in the action-free branch.
ISOLATION_AIMS = {"iou_control_vs_agent": 0.7, "iou_free_vs_agent": 0.2, "iou_free_vs_distractors": 0.5}


def isolation_verdict(scores: dict[str, float]) -> dict[str, object]:
    """Where a world model's decomposition put the agent and the distractors, against :data:`ISOLATION_AIMS`.

    Args:
        scores: :func:`decomposition_scores`' output (``iou_<branch>_vs_<class>``), or those scores read back from
            a ``summary.json``, where an absent score is ``None`` (JSON ``null``) or ``nan`` (older files' ``NaN``):
            both count as missing.

    Returns:
        ``agent_branch``: the branch of :data:`BRANCHES` whose mask overlaps the agent most (``None`` without an
        agent in the windows); ``isolates_agent``: ``iou_control_vs_agent >= 0.7`` and ``iou_free_vs_agent <= 0.2``;
        ``isolates_distractors``: ``iou_free_vs_distractors >= 0.5`` (``None`` without distractor pixels in the
        windows, ``mse_distractors`` being ``nan``, ``None`` or missing);
        ``message``: one line saying where the agent landed when it is not isolated, else ``None``.
    """
    agent = {b: nan_if_none(scores.get(f"iou_{b}_vs_agent")) for b in BRANCHES}
    has_agent = not all(math.isnan(v) for v in agent.values())
    branch = max(BRANCHES, key=lambda b: -1.0 if math.isnan(agent[b]) else agent[b]) if has_agent else None
    isolates = (
        has_agent
        and agent["control"] >= ISOLATION_AIMS["iou_control_vs_agent"]
        and not agent["free"] > ISOLATION_AIMS["iou_free_vs_agent"]
    )
    # no distractor pixels in the windows (mse_distractors counts them): nothing to isolate
    has_distractors = not math.isnan(nan_if_none(scores.get("mse_distractors")))
    distractors = nan_if_none(scores.get("iou_free_vs_distractors")) if has_distractors else math.nan
    verdict: dict[str, object] = {
        "agent_branch": branch,
        "isolates_agent": bool(isolates) if has_agent else None,
        "isolates_distractors": None
        if math.isnan(distractors)
        else bool(distractors >= ISOLATION_AIMS["iou_free_vs_distractors"]),
        "message": None,
    }
    if has_agent and not isolates:
        where = {
            "free": "in the action-free branch",
            "static": "in the static branch",
            "control": "mostly in the controllable branch, short of the aims",
        }[branch]
        verdict["message"] = (
            f"the world model draws the agent {where} (mask IoU with the agent: controllable "
            f"{agent['control']:.2f}, action-free {agent['free']:.2f}, static {agent['static']:.2f}; "
            f"Iso-Dream's aim: controllable >= {ISOLATION_AIMS['iou_control_vs_agent']}, action-free <= "
            f"{ISOLATION_AIMS['iou_free_vs_agent']})"
        )
    return verdict
