"""World-model demo: learn the three-branch decomposition of the sprites scene from random-action data.

``isodream-demo`` collects random-action episodes of :class:`~isodream_rl.envs.sprites.SpritesEnv`, trains
:class:`~isodream_rl.modules.IsoDreamWorldModel` with :class:`~isodream_rl.objectives.IsoDreamModelLoss`
for a few minutes on CPU, then, on held-out episodes, writes a PNG grid (ground truth, composite, each
branch's component and mask over time) and scores the learned masks against the ground-truth masks (IoU).
At the end it also probes what each branch's state knows (:mod:`isodream_rl.recipes.latent_probe`: the
held-out R^2 of a linear read-out of each sprite's position, from each branch's state and from the
encoder's trunk and branch embeddings), which scores the single-branch baseline (``--model dreamerv2``, no
masks) and Iso-Dream alike. Everything it needs is generated locally.

The model and loss are the library's defaults (docs/concepts.md, "Where we depart from the paper", names the
runs of docs/results/world_model_demo.md behind each); the one setting of the demo's own is the data's:
random actions held for 8 steps (a new one each step only makes the agent jitter in place, and the
background branch absorbs it).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from isodream_rl.process_settings import use_huge_pages

# before torch is imported: PyTorch reads it at its first allocation
use_huge_pages()

import torch  # noqa: E402
from torchrl.record.loggers.csv import CSVLogger  # noqa: E402
from tqdm import tqdm  # noqa: E402

from isodream_rl.envs.sprites import AGENT_COLOURS, DISTRACTOR_COLOURS, SPRITE_SIZE  # noqa: E402
from isodream_rl.modules import IsoDreamWorldModel, WorldModelConfig  # noqa: E402
from isodream_rl.modules.config import (  # noqa: E402
    CLAMP_GRADIENTS,
    DECODER_INPUTS,
    FREE_DECODER_INPUTS,
    INVERSE_INPUTS,
    MASK_MODES,
    PRECISIONS,
)
from isodream_rl.modules.encoder import preprocess_pixels  # noqa: E402
from isodream_rl.objectives import IsoDreamModelLoss  # noqa: E402
from isodream_rl.objectives.pyramid import PyramidImageTerm  # noqa: E402
from isodream_rl.objectives.world_model import FREE_BRANCH_MODES, LAMBDA_INVERSE  # noqa: E402
from isodream_rl.recipes.latent_probe import probe  # noqa: E402
from isodream_rl.recipes.sprites_data import (  # noqa: E402
    collect_sprites_episodes,
    episode_windows,
    make_window_buffer,
    model_input,
)
from isodream_rl.recipes.visualize import branch_grid, mask_iou, save_png  # noqa: E402

#: the library's defaults, which the flags below start from
DEFAULTS = WorldModelConfig(action_dim=1)


def default_precision(device: torch.device) -> str:
    """bf16 where it is fast (AMX CPUs, bf16-capable GPUs), else fp32."""
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    amx = getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()
    return "bf16" if amx else "fp32"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--steps", type=int, default=3000, help="world-model updates (3000: ~25 min on one CPU core)"
    )
    p.add_argument("--batch-size", type=int, default=8, help="windows per update")
    p.add_argument("--window", type=int, default=16, help="steps per window (T)")
    p.add_argument("--size", default="small", choices=["paper", "small", "tiny"], help="model size preset")
    p.add_argument(
        "--model",
        choices=["isodream", "dreamerv2"],
        default="isodream",
        help="the three-branch model, or the single-branch DreamerV2 ablation (no noncontrollable, static or "
        "inverse branch: the baseline, scored by its reconstruction of each disc)",
    )
    p.add_argument("--episodes", type=int, default=60, help="random-action training episodes")
    p.add_argument("--episode-length", type=int, default=96, help="a multiple of --window")
    p.add_argument(
        "--backgrounds",
        type=int,
        default=8,
        help="size of the scene's background pool shared by training and held-out episodes (0: a new one each)",
    )
    p.add_argument(
        "--action-hold",
        type=int,
        default=8,
        help="steps each random action is kept (1: a new one every step, the agent then jitters in place)",
    )
    p.add_argument(
        "--sprite-size",
        type=float,
        default=SPRITE_SIZE,
        help=f"sprite half-width as a fraction of the frame ({SPRITE_SIZE}: 9-pixel discs; SpritesEnv's sprite_size)",
    )
    p.add_argument(
        "--distractors",
        type=int,
        default=None,
        help="distractor discs in the scene (SpritesEnv's num_distractors; default 3, or one per "
        "--distractor-colours)",
    )
    p.add_argument(
        "--distractor-colours",
        default=None,
        help="comma-separated colours of the distractors, one per disc, drawn in this order (names of "
        "SpritesEnv's DISTRACTOR_COLOURS; default: red,blue,yellow,... for --distractors discs)",
    )
    p.add_argument(
        "--agent-colour",
        choices=sorted(AGENT_COLOURS),
        default="white",
        help="the agent's fill colour (SpritesEnv's agent_colour; its border stays black)",
    )
    p.add_argument(
        "--mask-mode",
        choices=MASK_MODES,
        default="softmax",
        help="softmax over the three mask logits, or the authors' independent sigmoids with 1 - M^s - M^z "
        "for the background (WorldModelConfig.mask_mode)",
    )
    p.add_argument(
        "--static-mask-bias",
        type=float,
        default=None,
        help=f"initial bias of the background's mask logit (default {DEFAULTS.static_mask_bias:g}, "
        "WorldModelConfig.static_mask_bias; softmax mode only: in sigmoid mode the background has no logit)",
    )
    p.add_argument(
        "--static-mask-bias-schedule",
        type=parse_schedule,
        default=(),
        help="a change of that bias during training (not in the paper): comma-separated UPDATE:OFFSET points, "
        "the offset added to the initial bias, linear from 0 at update 0 through the points, held after the "
        "last (e.g. '2500:0,3500:3' raises it by 3 over updates 2500-3500: a weak prior first lets the "
        "noncontrollable component learn the whole frame, the raise then hands the background back to the "
        "static branch)",
    )
    p.add_argument(
        "--inverse-input",
        choices=INVERSE_INPUTS,
        default=DEFAULTS.inverse_input,
        help="inverse-dynamics input: control-embedding differences (authors' code) or posterior states (paper, "
        "which the posterior solves through h_t without the pixels) (WorldModelConfig.inverse_input)",
    )
    p.add_argument(
        "--decoder-input",
        choices=DECODER_INPUTS,
        default=DEFAULTS.decoder_input,
        help="controllable component from the posterior (as the authors' DMC setting) or from the one-step "
        "prior (paper) (WorldModelConfig.decoder_input)",
    )
    p.add_argument(
        "--free-decoder-input",
        choices=FREE_DECODER_INPUTS,
        default=DEFAULTS.free_decoder_input,
        help="noncontrollable component from the posterior z_t (paper) or the action-free prior z~_t, which "
        "can draw only what moves predictably without actions (WorldModelConfig.free_decoder_input)",
    )
    p.add_argument(
        "--clamp-gradient",
        choices=CLAMP_GRADIENTS,
        default=DEFAULTS.clamp_gradient,
        help="backward of the components' clamp: the gradients pointing back into the pixel range, or none "
        "beyond it (the authors' clamp, with which a branch whose colours all overshoot stays dead) "
        "(WorldModelConfig.clamp_gradient)",
    )
    p.add_argument(
        "--free-branch-loss",
        choices=FREE_BRANCH_MODES,
        default="kl",
        help="noncontrollable branch learns with its KL (CARLA-style) or from the reconstruction only (DMC-style)",
    )
    p.add_argument("--lambda-kl-free", type=float, default=1.0, help="beta2, the weight of KL_z")
    p.add_argument(
        "--lambda-reco-pyramid",
        type=float,
        default=0.0,
        help="weight of the coarse-to-fine image term on levels 1..L of a Gaussian pyramid "
        "(PyramidImageTerm, an extra term of IsoDreamModelLoss; 0: off, the paper's loss)",
    )
    p.add_argument(
        "--pyramid-levels",
        type=int,
        default=3,
        help="pyramid levels L of --lambda-reco-pyramid (PyramidImageTerm.levels)",
    )
    p.add_argument(
        "--reco-pyramid-from",
        type=int,
        default=0,
        help="update at which --lambda-reco-pyramid starts; its weight then rises linearly over --ramp-updates (0: "
        "from the start). Started once the controllable branch holds the agent: with it from the start, seed "
        "1's controllable branch took a disc instead (docs/results/world_model_demo.md)",
    )
    p.add_argument(
        "--ramp-updates",
        type=int,
        default=None,
        help="updates over which --lambda-reco-pyramid rises to its weight once it starts (default: as many "
        "as it waited)",
    )
    p.add_argument("--free-nats", type=float, default=1.0, help="free nats of each branch's batch-mean KL")
    p.add_argument(
        "--lambda-inverse",
        type=float,
        default=LAMBDA_INVERSE,
        help="alpha, the inverse-dynamics loss scale (IsoDreamModelLoss's default; at the paper's 1 the "
        "embedding-difference inverse does not learn against the pixel-sum image loss)",
    )
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument(
        "--adam-eps",
        type=float,
        default=1e-5,
        help="Adam's epsilon (1e-5: the authors'; the encoder heads' mean gradients start at ~5e-7 to 3e-6)",
    )
    p.add_argument("--precision", choices=PRECISIONS, default=None, help="default: bf16 where fast")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--eval-every",
        type=int,
        default=200,
        help="updates between pictures / mask scores (0: only after the last update)",
    )
    p.add_argument(
        "--probe-episodes",
        type=int,
        default=32,
        help="fresh episodes for the final latent probe (half fit, half score; 0: no probe)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/world_model_demo", help="output folder (logs, PNG, checkpoint)")
    p.add_argument(
        "--resume",
        default=None,
        help="a world_model.pt of an earlier run with the same settings: continue from its update count to --steps",
    )
    args = p.parse_args(argv)
    if args.eval_every < 0:
        p.error(f"--eval-every must be >= 0, got {args.eval_every}")
    return args


def evaluate(loss: IsoDreamModelLoss, data, *, window: int, device) -> tuple[dict, object]:
    """Mask IoU of the learned masks against the ground truth on held-out episodes.

    Also ``free_covers_distractor_{i}``: the fraction of distractor ``i``'s visible pixels where the
    noncontrollable mask is above 0.5 (which distractors the branch has taken, one by one), and
    ``reco_error_distractor_{i}``: the composite's squared error on those pixels (summed over RGB, in the
    ``[-0.5, 0.5]`` pixel range), which tells a disc drawn by the wrong branch (low error) from a disc not
    drawn at all (error of the disc against the background, ~0.3-0.5); ``reco_error_agent`` the same on
    the agent's pixels. ``{branch}_on_background``: the fraction of the pixels of neither the agent nor a
    distractor where that branch's mask is above 0.5 (a branch sharing the background with the static one,
    which the IoU counts only against the objects' area).
    """
    windows = episode_windows(data, window=window)  # episodes are a multiple of the window long
    model = loss.world_model
    with torch.no_grad():
        out = model(model_input(windows).to(device))
    nxt, truth = out["next"].cpu(), windows["next"]
    scores = {}
    for branch in ("control", "free"):
        if f"mask_{branch}" in nxt.keys():
            for gt in ("agent", "distractors"):
                scores[f"iou_{branch}_vs_{gt}"] = mask_iou(nxt[f"mask_{branch}"], truth[f"mask_{gt}"])
    ids = truth.get("distractor_ids", None)
    if ids is not None:
        # where each dynamic branch's mask holds a pixel
        held = {
            b: nxt[f"mask_{b}"].reshape(ids.shape) > 0.5
            for b in ("control", "free")
            if f"mask_{b}" in nxt.keys()
        }
        taken = held.get("free")
        target = preprocess_pixels(truth["pixels"])
        error = (nxt["reco_pixels"].float() - target).pow(2).sum(-3).reshape(ids.shape)
        for i in range(1, int(ids.max()) + 1):
            pixels = ids == i
            count = pixels.sum().clamp(min=1)
            if taken is not None:
                scores[f"free_covers_distractor_{i - 1}"] = float((taken & pixels).sum() / count)
            scores[f"reco_error_distractor_{i - 1}"] = float(error[pixels].sum() / count)
        agent = truth["mask_agent"].reshape(ids.shape).bool()
        scores["reco_error_agent"] = float(error[agent].sum() / agent.sum().clamp(min=1))
        background = ~agent & (ids == 0)
        for branch, mask in held.items():
            scores[f"{branch}_on_background"] = float(
                (mask & background).sum() / background.sum().clamp(min=1)
            )
    return scores, out.cpu()


def save_checkpoint(
    path: Path, config, loss: IsoDreamModelLoss, optimizer, step: int, *, scene: dict | None = None
) -> Path:
    """Write the world model, its config, the optimiser and the update count atomically (temporary file,
    then rename): an interrupted write never leaves a truncated checkpoint. ``scene``: the data's settings
    (background pool, action hold, window), which the latent probe reads to make episodes like these."""
    tmp = path.with_suffix(".tmp")
    state = {
        "config": config.to_dict(),
        "model": loss.world_model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "step": step,
    }
    if scene is not None:
        state["scene"] = dict(scene)
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(path, config, loss: IsoDreamModelLoss, optimizer) -> int:
    """Restore a :func:`save_checkpoint` file into ``loss.world_model`` and ``optimizer``; returns its update count.

    Raises a ``ValueError`` naming the fields if the saved model configuration differs from ``config``
    (fields the file predates must hold their defaults).
    """
    state = torch.load(path, map_location="cpu", weights_only=False)
    defaults = WorldModelConfig(action_dim=config.action_dim).to_dict()
    current = config.to_dict()
    differ = {
        key: (state["config"].get(key, defaults[key]), value)
        for key, value in current.items()
        if key != "precision" and state["config"].get(key, defaults[key]) != value
    }
    if differ:
        raise ValueError(f"{path} was trained with other settings (saved, now): {differ}")
    loss.world_model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    return int(state["step"])


def ramp_weight(weight: float, step: int, start: int, length: int | None = None) -> float:
    """0 before update ``start``, then linearly up to ``weight`` at update ``start + length``
    (``length`` defaults to ``start``; ``start = 0``: ``weight`` throughout). The schedule
    ``((start, 0), (start + length, weight))`` of :func:`schedule_value`."""
    if not start:
        return weight
    length = start if length is None else length
    # length <= 0: the schedule jumps from 0 to weight at update start
    return schedule_value(((start, 0.0), (start + max(length, 0), weight)), step)


def parse_schedule(text: str) -> tuple[tuple[int, float], ...]:
    """``"U0:V0,U1:V1,..."`` -> ``((U0, V0), (U1, V1), ...)``; updates non-negative and increasing."""
    try:
        points = tuple((int(u), float(v)) for u, v in (item.split(":") for item in text.split(",") if item))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: expected UPDATE:VALUE points, e.g. '2500:0,3500:3'"
        ) from None
    updates = [u for u, _ in points]
    if not points or updates[0] < 0 or any(b <= a for a, b in zip(updates, updates[1:])):
        raise argparse.ArgumentTypeError(f"{text!r}: the updates must be non-negative and increasing")
    return points


def schedule_value(points: tuple[tuple[int, float], ...], step: int) -> float:
    """The piecewise-linear schedule ``points`` at update ``step``: linear from 0 at update 0 through the points
    (a point at update 0 sets the start), the last value held after the last point; 0 before update 0."""
    if not points or step < 0:
        return 0.0
    for (u0, v0), (u1, v1) in zip(((0, 0.0), *points), points):
        if step < u1:
            return v0 + (v1 - v0) * max(0.0, step - u0) / (u1 - u0)
    return points[-1][1]


def main(argv=None) -> dict:
    args = parse_args(argv)
    torch.manual_seed(args.seed)
    device = torch.device(args.device)
    precision = args.precision or default_precision(device)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.episode_length % args.window:
        raise SystemExit(
            f"--episode-length ({args.episode_length}) must be a multiple of --window ({args.window})"
        )

    colours = None
    if args.distractor_colours:
        colours = tuple(c.strip() for c in args.distractor_colours.split(","))
        unknown = sorted(set(colours) - set(DISTRACTOR_COLOURS))
        if unknown:
            raise SystemExit(f"--distractor-colours: unknown {unknown}; valid: {sorted(DISTRACTOR_COLOURS)}")
        if args.distractors not in (None, len(colours)):
            raise SystemExit(
                f"--distractors {args.distractors} but --distractor-colours names {len(colours)} colours"
            )
        args.distractors = len(colours)
    elif args.distractors is None:
        args.distractors = 3
    print(f"collecting {args.episodes} random-action sprites episodes of {args.episode_length} steps ...")
    scene = {
        "num_backgrounds": args.backgrounds or None,
        "background_seed": args.seed,
        "action_hold": args.action_hold,
        "sprite_size": args.sprite_size,
        "num_distractors": args.distractors,
        "distractor_colours": colours,
        "agent_colour": args.agent_colour,
    }
    train = collect_sprites_episodes(
        episodes=args.episodes, steps=args.episode_length, seed=args.seed, **scene
    )
    held_out = collect_sprites_episodes(episodes=4, steps=args.episode_length, seed=args.seed + 1, **scene)
    # what the checkpoint records and the final probe uses: the scene and how it was cut into windows
    data_scene = {**scene, "window": args.window, "episode_length": args.episode_length}
    buffer = make_window_buffer(train, batch_size=args.batch_size, window=args.window)

    if args.static_mask_bias is None:
        args.static_mask_bias = DEFAULTS.static_mask_bias
    elif args.static_mask_bias and args.mask_mode != "softmax":
        raise SystemExit(
            "--static-mask-bias needs --mask-mode softmax (in sigmoid mode the background has no logit)"
        )
    if args.static_mask_bias_schedule and (args.mask_mode != "softmax" or args.model != "isodream"):
        raise SystemExit(
            "--static-mask-bias-schedule needs --mask-mode softmax and --model isodream (the background's logit)"
        )
    options = {
        "precision": precision,
        "mask_mode": args.mask_mode,
        "static_mask_bias": args.static_mask_bias,
        "inverse_input": args.inverse_input,
        "decoder_input": args.decoder_input,
        "free_decoder_input": args.free_decoder_input,
        "clamp_gradient": args.clamp_gradient,
    }
    if args.model == "dreamerv2":
        config = WorldModelConfig.dreamerv2(args.size, action_dim=2, **options)
    else:
        config = WorldModelConfig.from_preset(args.size, action_dim=2, **options)
    pyramid = (
        [PyramidImageTerm(levels=args.pyramid_levels, lambda_reco_pyramid=args.lambda_reco_pyramid)]
        if args.lambda_reco_pyramid
        else []
    )
    loss = IsoDreamModelLoss(
        IsoDreamWorldModel(config, device=device),
        lambda_inverse=args.lambda_inverse,
        lambda_kl_free=args.lambda_kl_free,
        free_nats=args.free_nats,
        free_branch_loss=args.free_branch_loss,
        extra_terms=pyramid,
    )
    optimizer = torch.optim.Adam(loss.parameters(), lr=args.lr, eps=args.adam_eps)
    logger = CSVLogger(exp_name="world_model_demo", log_dir=str(out_dir))
    logger.log_hparams({**config.to_dict(), **{k: v for k, v in vars(args).items() if k != "out"}})

    first = load_checkpoint(args.resume, config, loss, optimizer) if args.resume else 0
    if first >= args.steps:
        raise SystemExit(f"{args.resume} is already at update {first}; ask for more --steps")
    bar = tqdm(
        range(first, args.steps),
        desc=f"world model ({args.size}, {precision})",
        unit="update",
        initial=first,
        total=args.steps,
    )
    start = time.perf_counter()
    for step in bar:
        # the bias holds the schedule's offset of update step - 1 (also when resumed): move it to this update's
        change = schedule_value(args.static_mask_bias_schedule, step) - schedule_value(
            args.static_mask_bias_schedule, step - 1
        )
        if change:
            loss.world_model.shift_static_mask_bias(change)
        if pyramid and args.reco_pyramid_from:
            pyramid[0].lambda_reco_pyramid = ramp_weight(
                args.lambda_reco_pyramid, step, args.reco_pyramid_from, args.ramp_updates
            )
        batch = buffer.sample().reshape(args.batch_size, args.window).to(device)
        losses, _ = loss(batch)
        total = loss.total(losses)
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        torch.nn.utils.clip_grad_norm_(loss.parameters(), 100.0)
        optimizer.step()
        if step % 20 == 0 or step == args.steps - 1:
            values = {k: v.item() for k, v in losses.items()}
            values["updates_per_s"] = (step + 1 - first) / (time.perf_counter() - start)
            for key, value in values.items():
                logger.log_scalar(key, value, step=step)
            bar.set_postfix(loss=f"{total.item():.1f}", mse=f"{values['reco_mse']:.4f}")
        if (args.eval_every and (step + 1) % args.eval_every == 0) or step == args.steps - 1:
            scores, out = evaluate(loss, held_out, window=args.window, device=device)
            # the same scores on as many training episodes (both are flat [episodes * steps], episodes of
            # one length): a gap to the held-out scores is memorisation
            seen, _ = evaluate(loss, train[: held_out.shape[0]], window=args.window, device=device)
            scores.update({f"train_{k}": v for k, v in seen.items()})
            for key, value in scores.items():
                logger.log_scalar(key, value, step=step + 1)
            picture = save_png(branch_grid(out, sample=0, steps=args.window), out_dir / "branches.png")
            # at every evaluation, so a long run cut short still leaves its latest model
            checkpoint = save_checkpoint(
                out_dir / "world_model.pt",
                config,
                loss,
                optimizer,
                step + 1,
                scene=data_scene,
            )
            bar.write(
                f"update {step + 1}: "
                + ", ".join(f"{k} {v:.3f}" for k, v in scores.items() if not k.startswith("train_"))
            )

    seconds = time.perf_counter() - start
    if args.probe_episodes:
        # what each branch's state knows, on fresh episodes of the same scene (seeds the demo never trains on)
        probed = probe(
            loss.world_model, episodes=args.probe_episodes, seed=args.seed + 1000, encoder=True, **data_scene
        )
        scores.update({f"probe_{k}": v for k, v in probed.items()})
        for key, value in probed.items():
            logger.log_scalar(f"probe_{key}", value, step=args.steps)
    summary = {
        "updates": args.steps,
        "seconds": round(seconds, 1),
        "precision": precision,
        "size": args.size,
        **{k: round(v, 3) for k, v in scores.items()},
        "png": str(picture),
        "checkpoint": str(checkpoint),
        "logs": str(Path(logger.log_dir)),
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    print(f"picture: {picture}\ncheckpoint: {checkpoint}\nlogs (CSV): {logger.log_dir}")
    return summary


if __name__ == "__main__":
    main()
