"""Training and evaluation loop of the video predictor: datasets, optimisation, TorchRL logging, checkpoints
and the per-frame evaluation protocol (train 2 -> 10, test 2 -> 28 / 2 -> 18).

The run folder (``--out-dir``) is held and claimed as ``isodream-train``'s is
(:func:`~isodream_rl.run_utils.run_folder.hold_folder`), and its checkpoints are ``isodream-train``'s
(:class:`~isodream_rl.run_utils.checkpoint.CheckpointManager`: ``<out_dir>/checkpoints/step_<iteration>/``,
written atomically with a verified manifest; an unreadable newest one falls back to the one before)."""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch
from tensordict import TensorDict
from torch.utils.data import DataLoader, default_collate
from tqdm.auto import tqdm

from isodream_rl.data import (
    ArraySequences,
    BAIRDataset,
    BouncingBalls,
    RoboNetDataset,
    VideoClips,
    load_pusher_dataset,
)
from isodream_rl.run_utils.checkpoint import CheckpointError, CheckpointManager
from isodream_rl.run_utils.csv_logs import csv_log_sizes, cut_csv_logs
from isodream_rl.run_utils.device import device_error
from isodream_rl.run_utils.run_folder import RunFlags, hold_folder, refuse_another_run
from isodream_rl.run_utils.signals import StopOnSignal
from isodream_rl.video_prediction.config import PredictorConfig, variant_config
from isodream_rl.video_prediction.metrics import FrameMetrics
from isodream_rl.video_prediction.objective import VideoPredictionLoss
from isodream_rl.video_prediction.predictor import ThreeBranchPredictor

__all__ = [
    "VideoTrainConfig",
    "build_split",
    "build_predictor",
    "evaluate",
    "train",
    "load_checkpoint",
    "read_checkpoint",
    "RESUMABLE",
]

_DATASETS = ("pusher", "bair", "robonet")


@dataclass
class VideoTrainConfig:
    """Everything a training run needs; the defaults are the paper's BAIR setting (Appendix D)."""

    variant: str = "isodream"
    """One of ``isodream``, ``no_action_free``, ``no_inverse``, ``predrnn``."""
    dataset: str = "pusher"
    """``pusher`` (local BAIR-like set, generated and cached), ``bair`` or ``robonet``."""
    data_path: str | None = None
    """``bair``: the ``softmotion30_44k`` directory (with ``train/`` and ``test/``); ``robonet``: a
    directory of ``.hdf5`` files (the first 80% train, the rest test, as in Iso-Dream)."""
    cache_dir: str | None = None
    """Cache of the generated pusher set (default ``$ISODREAM_DATA_DIR`` or ``~/.cache/isodream_rl``)."""
    train_sequences: int = 1000
    """Pusher sequences for training."""
    test_sequences: int = 128
    """Pusher sequences for testing (generated from a disjoint random stream)."""
    sequence_length: int = 30
    """Frames per source sequence (BAIR: 30; RoboNet-protocol tests use 20)."""
    balls: bool = True
    """Overlay bouncing balls (fixed per clip on the test split)."""
    seed: int = 0
    """Seeds the model init, data order and training balls (and, unless ``data_seed`` is set, the data)."""
    data_seed: int | None = None
    """Seeds the pusher set and the test split's balls; ``None``: ``seed``. Runs of several seeds that should
    share their data (the same test clips) set it to one value."""
    context: int = 2
    """Observed frames."""
    train_frames: int = 12
    """Frames per training clip (2 observed + 10 predicted)."""
    test_frames: int = 30
    """Frames per test clip (BAIR: 2 + 28; RoboNet: 2 + 18)."""
    batch_size: int = 8
    lr: float = 1e-4
    grad_clip: float = 10.0
    """Max gradient norm."""
    iterations: int = 80_000
    max_minutes: float | None = None
    """Stop training after this wall time even if ``iterations`` are not done."""
    eval_every: int = 5_000
    """Iterations between evaluations on the whole test split."""
    val_every: int = 250
    """Iterations between validation points (the first ``val_batches`` test batches; ``0``: none)."""
    val_batches: int = 4
    """Test batches per validation point."""
    checkpoint_every: int = 500
    """Iterations between checkpoints (a resumed run continues from the last one)."""
    eval_batches: int | None = None
    """Batches of the test split per evaluation (``None``: all)."""
    log_every: int = 50
    hidden_channels: int = 64
    num_layers: int = 2
    kernel_size: int = 5
    encoder_channels: tuple[int, int] = (32, 64)
    action_embedding: int = 64
    lambda_action: float = 1e-4
    lambda_decouple: float = 0.1
    rgb_activation: str = "sigmoid"
    """``"sigmoid"``: branch outputs bounded to ``[0, 1]``; ``"linear"``: the authors' unbounded outputs
    (:attr:`~isodream_rl.video_prediction.config.PredictorConfig.rgb_activation`)."""
    channels_last: bool = True
    """Channels-last convolutions (equal outputs, faster on CPU); ``--no-channels-last`` is the plain path."""
    precision: str = "fp32"
    """``"bf16"``: convolutions under bf16 autocast (faster per iteration on a CPU with ``avx512_bf16``;
    measured by ``bench/video_prediction.py --speed``, docs/results/video_prediction_speed.json); memories and
    losses stay fp32."""
    out_dir: str = "runs/video"
    logger: str = "csv"
    """``csv``, ``tensorboard`` (needs the ``logging`` extra) or ``""`` for none."""
    device: str = "cpu"
    threads: int = 2
    """Torch intra-op threads."""
    horizons: tuple[int, ...] = field(default=(10, 28))
    """Predicted-frame horizons summarised after evaluation (``psnr_10``, ``psnr_28``, ...)."""

    def __post_init__(self) -> None:
        for name in ("checkpoint_every", "val_batches", "eval_every", "log_every", "iterations"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.val_every < 0:
            raise ValueError(f"val_every must be >= 0 (0: no validation curve), got {self.val_every}")
        if self.dataset not in _DATASETS:
            raise ValueError(f"dataset must be one of {_DATASETS}, got {self.dataset!r}")
        if self.precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {self.precision!r}")
        if self.dataset != "pusher" and not self.data_path:
            raise ValueError(f"dataset={self.dataset!r} needs data_path")
        if not self.context < self.train_frames <= self.sequence_length:
            raise ValueError(
                f"need context < train_frames <= sequence_length, got {self.context}, "
                f"{self.train_frames}, {self.sequence_length}"
            )
        if not self.context < self.test_frames <= self.sequence_length:
            raise ValueError(
                f"need context < test_frames <= sequence_length, got {self.context}, "
                f"{self.test_frames}, {self.sequence_length}"
            )
        if max(self.horizons) > self.test_frames - self.context:
            raise ValueError(
                f"horizons {self.horizons} exceed the {self.test_frames - self.context} predicted test frames"
            )
        unusable = device_error(self.device, setting="device")
        if unusable:
            raise ValueError(unusable)

    def predictor_config(self, action_dim: int) -> PredictorConfig:
        return variant_config(
            self.variant,
            action_dim=action_dim,
            hidden_channels=self.hidden_channels,
            num_layers=self.num_layers,
            kernel_size=self.kernel_size,
            encoder_channels=tuple(self.encoder_channels),
            action_embedding=self.action_embedding,
            channels_last=self.channels_last,
            precision=self.precision,
            rgb_activation=self.rgb_activation,
        )

    @classmethod
    def from_dict(cls, values: dict) -> VideoTrainConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(values) - names
        if unknown:
            raise KeyError(f"unknown VideoTrainConfig fields {sorted(unknown)}")
        values = dict(values)
        for key in ("encoder_channels", "horizons"):
            if key in values:
                values[key] = tuple(values[key])
        return cls(**values)


def _sources(config: VideoTrainConfig, split: str):
    if config.dataset == "pusher":
        count = config.train_sequences if split == "train" else config.test_sequences
        arrays = load_pusher_dataset(
            count,
            config.sequence_length,
            seed=config.seed if config.data_seed is None else config.data_seed,
            split=split,
            cache_dir=config.cache_dir,
            workers=2,
        )
        return ArraySequences(arrays)
    if config.dataset == "bair":
        return BAIRDataset(Path(config.data_path) / split, num_frames=config.sequence_length)
    files = sorted(Path(config.data_path).glob("*.hdf5"))
    if len(files) < 2:
        raise FileNotFoundError(f"need at least 2 .hdf5 files under {config.data_path}, found {len(files)}")
    cut = max(1, int(0.8 * len(files)))
    return RoboNetDataset(files[:cut] if split == "train" else files[cut:])


def build_split(config: VideoTrainConfig, split: str) -> VideoClips:
    """Clips of one split.

    ``"train"``: every window of ``train_frames``, new random balls on every draw. ``"test"``: one clip of
    ``test_frames`` per sequence, with balls fixed per clip (a seed disjoint from the training one).

    Raises:
        FileNotFoundError: ``data_path`` is not a folder.
    """
    if config.data_path and not Path(config.data_path).is_dir():
        raise FileNotFoundError(f"data_path={config.data_path!r}: no such folder")
    if split not in ("train", "test"):
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    source = _sources(config, split)
    if split == "train":
        balls = BouncingBalls(seed=config.seed) if config.balls else None
        return VideoClips(
            source, clip_length=config.train_frames, sequence_length=config.sequence_length, distractor=balls
        )
    data_seed = config.seed if config.data_seed is None else config.data_seed
    balls = BouncingBalls(seed=data_seed + 10_007, fixed=True) if config.balls else None
    return VideoClips(
        source,
        clip_length=config.test_frames,
        sequence_length=config.sequence_length,
        stride=config.sequence_length,
        distractor=balls,
    )


def build_predictor(config: VideoTrainConfig, action_dim: int) -> ThreeBranchPredictor:
    return ThreeBranchPredictor(config=config.predictor_config(action_dim)).to(config.device)


@torch.no_grad()
def evaluate(
    model: ThreeBranchPredictor,
    loader: DataLoader,
    *,
    context: int = 2,
    device: str | torch.device = "cpu",
    max_batches: int | None = None,
) -> dict[str, torch.Tensor]:
    """Per-predicted-frame PSNR / SSIM (both flavours, see :mod:`~isodream_rl.video_prediction.metrics`).

    Returns:
        ``{"psnr": [T - context], "ssim": ..., "psnr_uint8": ..., "ssim_uint8": ...}``.
    """
    was_training = model.training
    model.eval()
    metrics = FrameMetrics()
    for i, batch in enumerate(loader):
        if max_batches is not None and i >= max_batches:
            break
        frames, actions = batch["frames"].to(device), batch["actions"].to(device)
        out = model(frames, actions, context=context)
        # Frames 1 .. context-1 were one-step predictions from observed frames: not part of the score.
        metrics.update(out["frames"][:, context - 1 :], frames[:, context:])
    model.train(was_training)
    return metrics.compute()


#: what ``state.pt`` of a video-prediction checkpoint holds for its model
MODEL_KEYS = ("model", "train_config", "predictor_config")
#: and what a run continues from
STATE_KEYS = (*MODEL_KEYS, "optimizer", "iteration", "sampler", "torch_rng", "train_seconds", "history")


def read_checkpoint(path: str | os.PathLike, *, device: str = "cpu") -> dict:
    """The state dict of a checkpoint written by :func:`train`: ``path`` is its run folder (the newest readable
    checkpoint), one of its ``checkpoints/step_*`` folders, or a single ``checkpoint.pt`` file of earlier
    versions.

    Raises:
        ValueError: no readable checkpoint there (truncated, corrupted, another format, or no dict).
    """
    path = Path(path)
    if path.is_dir():
        single = path.name.startswith("step_")
        manager = CheckpointManager(path.parent if single else path / "checkpoints")
        try:
            if single:
                return manager.load(path, required_keys=MODEL_KEYS)
            return manager.load_latest(required_keys=MODEL_KEYS)[0]
        except CheckpointError as err:
            raise ValueError(f"{path}: {err}") from err
    try:
        state = torch.load(path, map_location=device, weights_only=False)
    # torch.load raises what its unpickler meets: RuntimeError, EOFError, pickle errors
    except Exception as err:
        raise ValueError(
            f"{path} is not a readable checkpoint ({type(err).__name__}: {err}); it may be truncated or of "
            "another program: give the --out-dir of an isodream-video train run"
        ) from err
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a video-prediction checkpoint")
    return state


def load_checkpoint(
    path: str | os.PathLike, *, device: str = "cpu"
) -> tuple[ThreeBranchPredictor, VideoTrainConfig, dict]:
    """Rebuild the model of a checkpoint written by :func:`train` (``path`` as in :func:`read_checkpoint`) on
    ``device``, whichever device trained it; returns ``(model, config, state)`` (``config.device`` is ``device``).

    Raises:
        ValueError: no readable checkpoint there (:func:`read_checkpoint`).
        KeyError: a torch file, but not a video-prediction checkpoint.
    """
    state = read_checkpoint(path, device=device)
    for key in MODEL_KEYS:
        if key not in state:
            raise KeyError(f"{path} is not a video-prediction checkpoint: missing '{key}'")
    config = VideoTrainConfig.from_dict({**state["train_config"], "device": device})
    model = ThreeBranchPredictor(config=PredictorConfig.from_dict(state["predictor_config"]))
    model.load_state_dict(state["model"])
    return model.to(device), config, state


def _make_logger(config: VideoTrainConfig, out_dir: Path):
    if not config.logger:
        return None
    from torchrl.record.loggers import get_logger

    return get_logger(config.logger, logger_name=str(out_dir / "logs"), experiment_name=config.variant)


RESUMABLE = (
    "iterations",
    "max_minutes",
    "eval_every",
    "val_every",
    "checkpoint_every",
    "log_every",
    "logger",
    "device",
    "threads",
    "out_dir",
)
""":class:`VideoTrainConfig` fields a resumed run may change; every other field must equal the checkpoint's."""


class _EpochSampler:
    """Shuffled mini-batches of indices, epoch after epoch, whose position can be saved and restored.

    Each epoch is a permutation drawn from one seeded generator; the last incomplete batch is dropped.
    :meth:`state_dict` holds the generator state at the start of the current epoch and the position in it,
    so a restored sampler gives the same batches the uninterrupted one would.
    """

    def __init__(self, size: int, batch_size: int, *, seed: int) -> None:
        if size < batch_size:
            raise ValueError(f"the training split has {size} clips, fewer than batch_size={batch_size}")
        self.size, self.batch_size = size, batch_size
        self.generator = torch.Generator().manual_seed(seed)
        self._new_epoch()

    def _new_epoch(self) -> None:
        self._epoch_state = self.generator.get_state()
        self._order = torch.randperm(self.size, generator=self.generator)
        self.position = 0

    def next_batch(self) -> list[int]:
        if self.position + self.batch_size > self.size:
            self._new_epoch()
        batch = self._order[self.position : self.position + self.batch_size].tolist()
        self.position += self.batch_size
        return batch

    def state_dict(self) -> dict:
        return {"epoch_state": self._epoch_state.clone(), "position": self.position}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["epoch_state"].cpu())
        self._new_epoch()
        self.position = state["position"]


def _check_resumable(saved: dict, config: VideoTrainConfig, path: Path) -> None:
    now = asdict(config)
    differ = [
        f"{k}: {saved.get(k)!r} -> {now[k]!r}"
        for k in now
        if k not in RESUMABLE and _plain(saved.get(k)) != _plain(now[k])
    ]
    if differ:
        raise ValueError(
            f"cannot resume {path}: settings that change the model or the data differ ({'; '.join(differ)}); "
            f"use another --out-dir, or the saved settings"
        )


def _plain(value):
    return list(value) if isinstance(value, tuple) else value


#: what a training run writes into ``out_dir`` (``checkpoint.pt``: the single-file checkpoint of earlier
#: versions): a folder holding one of them holds a run
RUN_FILES = ("checkpoints", "logs", "checkpoint.pt")
#: how ``isodream-video train`` names the run folder and the settings that let it use one holding a run
FLAGS = RunFlags(folder="--out-dir", resume="--resume", overwrite="--overwrite")


def train(
    config: VideoTrainConfig, *, progress: bool = True, resume: bool = False, overwrite: bool = False
) -> dict:
    """Train one variant; validate, checkpoint and evaluate on the way.

    Every ``val_every`` iterations the model is scored on the first ``val_batches`` batches of the test split
    (the validation curve: MSE, PSNR and SSIM over the predicted frames, logged as ``val/*`` and kept in the
    result's ``history``); every ``checkpoint_every`` iterations a checkpoint ``<out_dir>/checkpoints/step_*/``
    is written (:class:`~isodream_rl.run_utils.checkpoint.CheckpointManager`, the last two kept) with everything
    a resumed run needs (model, optimizer, the sampler's position, the random
    states of the balls, the history); every ``eval_every`` iterations and at the end the whole test split is
    evaluated. A resumed run (``resume=True`` with a checkpoint in ``out_dir``) continues to ``iterations``
    and gives the same weights as an uninterrupted run; Adam's learning rate is constant, so ``iterations``
    may be raised on resume to train longer. The first SIGINT or SIGTERM ends the iteration under way, writes a
    checkpoint and returns without the final evaluation (a second one stops at once, as isodream-train's
    :class:`~isodream_rl.run_utils.signals.StopOnSignal`).

    Writes ``<out_dir>/checkpoints/`` and TorchRL logger files under ``<out_dir>/logs``. An ``out_dir``
    holding another run is refused unless ``resume`` (continue it) or ``overwrite`` (delete it first), and it
    is held by this process while the run writes to it, as ``isodream-train`` does
    (:func:`~isodream_rl.run_utils.run_folder.hold_folder`); a resumed run cuts its CSV logs back to what they held
    at the checkpoint (:mod:`isodream_rl.run_utils.csv_logs`).

    Returns:
        ``{"iterations", "train_seconds", "metrics": {"psnr_10": .., ...}, "curves": {"psnr": [...], ..},
        "history": [{"iteration", "mse", "psnr_28", ...}], "checkpoint": path}``; a run a signal stopped returns
        ``{"iterations", "stopped_by_signal": signum, "checkpoint": path}``.

    Raises:
        ValueError: ``resume=True`` and the checkpoint was written with settings outside :data:`RESUMABLE`
            that differ from ``config``, or no checkpoint there is readable; ``out_dir`` holds another run (see
            above) or cannot be written.
        RunDirBusyError: another live process uses ``out_dir``.
        DiskFullError: the disk filled up (the message names the checkpoint to resume from).
    """
    out_dir = Path(config.out_dir)
    # the refusals, before the data are made
    refuse_another_run(out_dir, resume=resume, overwrite=overwrite, run_files=RUN_FILES, flags=FLAGS)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    train_set, test_set = build_split(config, "train"), build_split(config, "test")
    # held once the data are found
    with hold_folder(out_dir, flags=FLAGS, resume=resume, overwrite=overwrite, run_files=RUN_FILES):
        return _train(config, train_set, test_set, progress=progress, resume=resume)


class _Scores:
    """The per-frame scores of a training run on the test clips, logged under ``val/`` or ``eval/``; the
    validations appended to ``history``."""

    def __init__(self, config: VideoTrainConfig, model, test_loader, *, logger, history: list) -> None:
        self.config, self.model, self.test_loader = config, model, test_loader
        self.logger, self.history = logger, history

    def curves(self, step: int, *, max_batches: int | None, prefix: str) -> dict[str, torch.Tensor]:
        """PSNR/SSIM per frame on at most ``max_batches`` test batches, their summary logged under ``prefix``."""
        config = self.config
        curves = evaluate(
            self.model,
            self.test_loader,
            context=config.context,
            device=config.device,
            max_batches=max_batches,
        )
        if self.logger is not None:
            for key, value in FrameMetrics.summarize(curves, config.horizons).items():
                self.logger.log_scalar(f"{prefix}/{key}", value, step=step)
        return curves

    def validate(self, step: int) -> None:
        """The validation batches' summary, appended to the history."""
        curves = self.curves(step, max_batches=self.config.val_batches, prefix="val")
        summary = FrameMetrics.summarize(curves, self.config.horizons)
        self.history.append({"iteration": step, **{k: round(v, 5) for k, v in summary.items()}})


def _checkpoints(out_dir: Path, *, resume: bool) -> CheckpointManager:
    """The checkpoints of ``out_dir`` (the last two kept).

    Raises:
        ValueError: ``resume`` of a folder that holds only the single ``checkpoint.pt`` of an earlier version.
    """
    checkpoints = CheckpointManager(out_dir / "checkpoints", keep=2)
    if resume and (out_dir / "checkpoint.pt").exists() and not checkpoints.checkpoints():
        raise ValueError(
            f"cannot resume {out_dir}: its checkpoint.pt is of an earlier version (isodream-video eval still "
            "reads it); start a new --out-dir"
        )
    return checkpoints


def _restore(
    config: VideoTrainConfig, checkpoints: CheckpointManager, *, model, optimizer, sampler, balls
) -> tuple[dict, Path]:
    """Load the newest readable checkpoint of ``checkpoints`` into the model, the optimiser, the sampler, the
    distractors' random state and torch's; its state and folder.

    Raises:
        ValueError: no readable checkpoint, or one saved with settings that change the training.
    """
    try:
        state, checkpoint = checkpoints.load_latest(required_keys=STATE_KEYS)
    except CheckpointError as err:
        raise ValueError(f"cannot resume {config.out_dir}: {err}") from err
    _check_resumable(state["train_config"], config, checkpoint)
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    sampler.load_state_dict(state["sampler"])
    if balls is not None and state.get("balls_rng") is not None:
        balls.load_state_dict(state["balls_rng"])
    torch.set_rng_state(state["torch_rng"].cpu())  # map_location may have moved it
    return state, checkpoint


def _update(
    config: VideoTrainConfig, loss_fn: VideoPredictionLoss, optimizer, train_set, indices
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """One training iteration on the clips ``indices`` of ``train_set``: ``(losses, their sum, gradient norm)``."""
    batch = default_collate([train_set[i] for i in indices])
    td = TensorDict(
        {"frames": batch["frames"].to(config.device), "actions": batch["actions"].to(config.device)},
        batch_size=[config.batch_size],
    )
    losses = loss_fn(td)
    total = sum(losses.values())
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(loss_fn.predictor.parameters(), config.grad_clip)
    optimizer.step()
    return losses, total, grad_norm


def _train(config: VideoTrainConfig, train_set, test_set, *, progress: bool, resume: bool) -> dict:
    """:func:`train` in the ``out_dir`` it holds."""
    out_dir = Path(config.out_dir)
    loss_fn = VideoPredictionLoss(
        build_predictor(config, train_set[0]["actions"].shape[-1]),
        lambda_action=config.lambda_action,
        lambda_decouple=config.lambda_decouple,
        context=config.context,
    )
    model = loss_fn.predictor
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    sampler = _EpochSampler(len(train_set), config.batch_size, seed=config.seed)
    balls = train_set.distractor
    test_loader = DataLoader(test_set, batch_size=config.batch_size)
    checkpoints = _checkpoints(out_dir, resume=resume)
    checkpoint: Path | None = None
    step, previous_seconds, history = 0, 0.0, []
    log_sizes: dict[str, int] | None = {}  # a run resumed without a checkpoint starts its logs again
    if resume and checkpoints.checkpoints():
        state, checkpoint = _restore(
            config, checkpoints, model=model, optimizer=optimizer, sampler=sampler, balls=balls
        )
        step, previous_seconds, history = state["iteration"], state["train_seconds"], state["history"]
        log_sizes = state.get("log_sizes")
    if resume and log_sizes is not None:  # rows written after the checkpoint are of a timeline that ended
        cut_csv_logs(out_dir / "logs", log_sizes)
    logger = _make_logger(config, out_dir)
    metrics: dict[str, float] | None = None

    def save(step: int) -> None:
        nonlocal checkpoint
        checkpoint = checkpoints.save(
            step,
            {
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "iteration": step,
                "train_config": asdict(config),
                "predictor_config": model.config.to_dict(),
                "metrics": metrics,
                "sampler": sampler.state_dict(),
                "balls_rng": None if balls is None else balls.state_dict(),
                "torch_rng": torch.get_rng_state(),
                "train_seconds": previous_seconds + time.monotonic() - start,
                "history": history,
                "log_sizes": csv_log_sizes(out_dir / "logs"),
            },
        )

    scores = _Scores(config, model, test_loader, logger=logger, history=history)

    start = time.monotonic()
    deadline = math.inf if config.max_minutes is None else start + 60 * config.max_minutes
    if step == 0 and config.val_every:
        scores.validate(0)
    bar = tqdm(total=config.iterations, initial=step, disable=not progress, desc=config.variant)
    model.train()
    with StopOnSignal() as signals:
        while step < config.iterations and time.monotonic() < deadline and signals.received is None:
            losses, total, grad_norm = _update(config, loss_fn, optimizer, train_set, sampler.next_batch())
            step += 1
            bar.update(1)
            if step % config.log_every == 0 or step == 1:
                bar.set_postfix(loss=f"{float(total.detach()):.4f}")
                if logger is not None:
                    scalars = {
                        **losses,
                        "grad_norm": grad_norm,
                        "seconds": previous_seconds + time.monotonic() - start,
                    }
                    for key, value in scalars.items():
                        logger.log_scalar(f"train/{key}", float(value), step=step)
            if config.val_every and step % config.val_every == 0:
                scores.validate(step)
            if step % config.eval_every == 0 and step < config.iterations:
                metrics = FrameMetrics.summarize(
                    scores.curves(step, max_batches=config.eval_batches, prefix="eval"), config.horizons
                )
            if step % config.checkpoint_every == 0:
                save(step)
    bar.close()
    if signals.received is not None:  # a checkpoint where it stopped, and no final evaluation
        save(step)
        return {"iterations": step, "stopped_by_signal": signals.received, "checkpoint": str(checkpoint)}
    train_seconds = previous_seconds + time.monotonic() - start
    if config.val_every and (not history or history[-1]["iteration"] != step):
        scores.validate(step)
    curves = scores.curves(step, max_batches=config.eval_batches, prefix="eval")
    metrics = FrameMetrics.summarize(curves, config.horizons)
    save(step)
    return {
        "iterations": step,
        "train_seconds": train_seconds,
        "metrics": metrics,
        "curves": {k: [round(float(x), 5) for x in v] for k, v in curves.items()},
        "history": history,
        "checkpoint": str(checkpoint),
    }
