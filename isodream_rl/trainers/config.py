"""Training configuration: typed dataclasses (the Hydra schema) and the cross-field checks run before training.

The YAML groups in ``isodream_rl/configs`` (``env``, ``size``, ``algo``) fill these dataclasses; Hydra checks
types against them, and :func:`validate_config` rejects impossible combinations with a message saying what to
change, before any env or model is built. The settings only some learners read are ``None`` here, "the learner's
value": each learner's table gives it (:mod:`isodream_rl.trainers.learners`), and a value given for a learner that
does not read it is refused.
"""

from __future__ import annotations

import importlib.util
import typing
from dataclasses import dataclass, field, make_dataclass
from typing import Any

from isodream_rl.modules.isodream_v2.config import DREAMERV2, PAPER_EXACT, IsoDreamV2Config
from isodream_rl.modules.sizes import SIZE_PRESETS
from isodream_rl.objectives.isodream_v2.world_model import FREE_BRANCH_MODES
from isodream_rl.run_utils.device import device_error
from isodream_rl.trainers.learners import WORLD_MODEL_FIELDS, resolved, unread_setting_errors
from isodream_rl.trainers.renames import drop_unread_settings, renamed_algo_error, saved_algo_name
from isodream_rl.trainers.world_model_config import MODES, WorldModelModeConfig, world_model_mode_errors
from isodream_rl.user_errors import ConfigError

POLICY_INPUTS = ("controllable", "attention", "concat")
COLLECTOR_BACKENDS = ("sync", "multiprocess", "ray", "distributed")
REMOTE_BACKENDS = ("ray", "distributed")
DISTRIBUTED_LAUNCHERS = ("mp", "submitit", "submitit_delayed")
DISTRIBUTED_BACKENDS = ("gloo", "nccl", "mpi", "ucc")
LOGGER_BACKENDS = ("csv", "tensorboard", "wandb")
_ALL_BRANCHES = {"free_branch": True, "static_branch": True, "inverse_dynamics": True}
#: The branch switches of each ``algo=<name>`` preset: their one home (the algo YAML files set the other
#: fields). ``AlgoConfig``'s switches left ``None`` take these (:func:`resolve_algo`); a name not here takes
#: ``isodream``'s. The single-branch ones are DreamerV2's (:data:`~isodream_rl.modules.isodream_v2.config.DREAMERV2`).
#: Which learner each name builds: :mod:`isodream_rl.trainers.learners`.
ALGO_BRANCHES: dict[str, dict[str, bool]] = {
    "isodream": _ALL_BRANCHES,
    "isodream_v2": _ALL_BRANCHES,
    "isodream_paper": _ALL_BRANCHES,
    "dreamerv2": DREAMERV2,
    "isodream_no_inverse": {**_ALL_BRANCHES, "inverse_dynamics": False},
    "isodream_no_attention": _ALL_BRANCHES,
    "isodream_no_static": {**_ALL_BRANCHES, "static_branch": False},
    "torchrl_dreamer": DREAMERV2,
    "torchrl_dreamer_v3": DREAMERV2,
}
ALGO_NAMES = tuple(ALGO_BRANCHES)


@dataclass
class EnvConfig:
    """Which environment to train on and how many copies to run."""

    name: str = "sprites"
    """``"sprites"``, ``"highway"``, ``"dmc_<domain>_<task>"`` (see ``isodream_rl.envs.env_names``) or a registered
    gymnasium id with a ``Box`` action space (observed through its render, resized to 64x64)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Constructor arguments of the env class (e.g. ``task``, ``vehicles_count``, ``background``), or
    ``gymnasium.make`` keywords; with ``factory``, that callable's keywords."""
    factory: str = ""
    """Your own TorchRL env instead of ``name``: ``"package.module:function"``, a callable that returns an
    ``EnvBase`` from ``**kwargs`` with uint8 ``"pixels"`` ``[3, 64, 64]``, a float ``"action"`` in ``[-1, 1]``,
    ``("next", "reward")`` ``[1]`` and ``"is_init"`` (``isodream_rl.envs.wrap_gym_env`` makes one of a
    gymnasium env). ``name`` then only names the run."""
    num_envs: int = 1
    """Envs collecting in parallel; above 1 a multi-process TorchRL collector runs one env per process."""
    action_repeat: int = 1
    """Simulator steps per agent step, as the env applies it (only used to report simulator frames)."""
    domain: str = "sprites"
    """The kind of scene, ``"carla"``, ``"dmc"`` or ``"sprites"``, set by the env group (``configs/domain/``): which
    of the paper's per-domain choices apply (the policy input and the reward's inputs in ``algo``; a learner's own
    per-domain values in its table, :mod:`isodream_rl.trainers.learners`)."""


@dataclass
class _ModelSizes:
    """The behavior's widths and the world model's size preset (the rest of ``model`` is :data:`ModelConfig`)."""

    size: str = "small"
    """A size preset, a key of ``isodream_rl.modules.sizes.SIZE_PRESETS``."""
    actor_units: int = 400
    """Width of the actor MLP (4 layers in the paper)."""
    value_units: int = 400
    """Width of the value MLP (3 layers in the paper)."""
    attention_dim: int = 500
    """Width of the future-state attention's Q/K/V projections (500 in the authors' code)."""
    free_hidden_fraction: float | None = None
    """The default learner's (``algo=isodream``) action-free branch width per unit of its controllable branch's
    (``None``: the learner's table, 0.5; ``isodream_rl.trainers.isodream``)."""

    def world_model_fields(self) -> dict[str, Any]:
        """The ``IsoDreamV2Config`` fields this section sets (those not ``None``), as ``{field: value}``."""
        return {name: getattr(self, name) for name in WORLD_MODEL_FIELDS if getattr(self, name) is not None}


def _world_model_section() -> list[tuple[str, Any, Any]]:
    """``IsoDreamV2Config``'s fields as optional schema fields, default ``None``: "the preset's value"."""
    hints = typing.get_type_hints(IsoDreamV2Config)
    return [(name, hints[name] | None, field(default=None)) for name in WORLD_MODEL_FIELDS]


#: The ``model`` section: the size preset and behavior widths (``_ModelSizes``), then every field of
#: :class:`~isodream_rl.modules.isodream_v2.config.IsoDreamV2Config` but ``action_dim``, typed as there and ``None`` by
#: default: ``None`` keeps the size preset's value, or the one the algo sets (``world_model_overrides``), and a
#: value replaces it (``model.precision=bf16``, ``model.depth=8``). Derived from ``IsoDreamV2Config``, the one
#: home of the field list, so a field added there is a setting here with no change. The DreamerV2-style learner
#: reads them all; the others read the few their learner's table names
#: (:func:`~isodream_rl.trainers.learners.model_fields_read`) and refuse the rest.
ModelConfig = make_dataclass("ModelConfig", _world_model_section(), bases=(_ModelSizes,))
ModelConfig.__module__ = __name__
ModelConfig.__doc__ = (
    "World-model and behavior sizes: ``size`` picks a preset of ``IsoDreamV2Config``, whose fields "
    "``model.<field>`` may set (``None``: the preset's or the algo's value)."
)


@dataclass
class AlgoConfig:
    """The algorithm variant: which branches exist, how they learn and what the policy reads.

    The fields from ``paper_exact`` on are read by some learners only (:mod:`isodream_rl.trainers.learners`):
    ``None`` is the learner's value, and a value is refused for a learner that does not read it."""

    name: str = "isodream"
    """Preset name, one of ``ALGO_NAMES``; it picks the learner (:mod:`isodream_rl.trainers.learners`): Iso-Dream on
    DreamerV3's learner for ``isodream`` and its ablations, the DreamerV2-style one for ``isodream_v2``,
    ``isodream_paper``, ``dreamerv2`` and a name of your own; the other fields set the variant."""
    free_branch: bool | None = None
    """The action-free (noncontrollable) branch (``None``: the preset's, :data:`ALGO_BRANCHES`)."""
    static_branch: bool | None = None
    """The static background branch (``None``: the preset's)."""
    inverse_dynamics: bool | None = None
    """The inverse-dynamics cell and its loss (``None``: the preset's)."""
    reward_uses_free: bool = False
    """Reward head on ``[s, h, z, h']`` (CARLA) instead of ``[s, h]`` (DMC)."""
    policy_input: str = "attention"
    """``"controllable"`` ([s, h], DMC), ``"attention"`` (eq. 6, CARLA) or ``"concat"`` ([s, h, z, h'])."""
    attention_window: int = 5
    """tau, the number of noncontrollable states the attention reads (current plus tau - 1 future)."""
    horizon: int = 15
    """L, the imagination horizon."""
    lambda_inverse: float | None = None
    """alpha, the weight of the inverse-dynamics loss (both Iso-Dream learners; each has its own value)."""
    paper_exact: bool | None = None
    """The DreamerV2-style learner: the paper's settings where the library's defaults depart from them
    (``IsoDreamV2Config.paper_exact``; ``algo=isodream_paper``), and eq. 5's ``lambda_inverse``."""
    free_branch_loss: str | None = None
    """The DreamerV2-style learner: ``"kl"`` (CARLA: the free branch has its KL term) or ``"recon_only"`` (DMC, paper
    §3.2)."""
    attention_through_actor: bool | None = None
    """The DreamerV2-style learner: let the actor loss train the attention too (the authors train it with the value
    loss only)."""
    gamma: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: discount of the lambda-returns (DreamerV3's learners
    discount by their continuation head)."""
    lmbda: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: lambda of the lambda-returns."""
    actor_entropy: float | None = None
    """The DreamerV2-style learner: entropy bonus of the actor loss."""
    actor_loc_penalty: float | None = None
    """The DreamerV2-style learner: weight of the squared pre-tanh action mean in the actor loss
    (``IsoDreamV2ActorLoss(loc_penalty=...)``): keeps the policy from locking in on an early model error; 0 is the
    paper's loss (``algo=isodream_paper``)."""
    exploration_noise: float | None = None
    """The DreamerV2-style learner: std of the Gaussian noise added to the acting policy's sampled actions during
    collection (clamped to [-1, 1]; 0 as the authors; DreamerV1 and TorchRL's Dreamer example use 0.3)."""
    lambda_reward: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: weight of the reward log-loss (``reward_scale``: 2 in the
    authors' DMC and CARLA configs)."""
    free_nats: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: free nats of each branch's KL."""
    kl_balance: float | None = None
    """The DreamerV2-style learner: DreamerV2 KL balancing."""
    slow_target_every: int | None = None
    """The DreamerV2-style learner: updates between hard copies of the value network into its slow target."""


@dataclass
class TrainConfig:
    """Collection schedule, replay, optimisers and fault handling (Algorithm 1 and Appendix E)."""

    total_steps: int = 100_000
    """Agent steps to collect (prefill included)."""
    prefill_steps: int = 2500
    """Random-policy steps before the first update."""
    train_every: int = 5
    """Agent steps per update (the train ratio)."""
    frames_per_batch: int = 100
    """Agent steps per collector batch, all envs together; a multiple of ``train_every * num_envs``."""
    batch_size: int = 50
    """Replay windows per update (B)."""
    sequence_length: int = 50
    """Length of each replay window (T)."""
    buffer_size: int = 100_000
    """Replay capacity in agent steps (uint8 pixels on disk: ~12 KB per step)."""
    world_model_lr: float = 3e-4
    """Adam learning rate of the world model."""
    actor_lr: float = 8e-5
    """Adam learning rate of the actor."""
    value_lr: float = 8e-5
    """Adam learning rate of the value network and the future-state attention."""
    adam_eps: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: Adam epsilon of all three optimisers (DreamerV3's learners:
    their ``DreamerV3Optimizer``'s own)."""
    grad_clip: float | None = None
    """The DreamerV2-style learner and TorchRL's Dreamer: gradient-norm clip of all three optimisers (DreamerV3's
    learners clip adaptively)."""
    world_model_warmup: int = 0
    """Updates of the world model alone (after the prefill) before the actor and value start learning;
    0 as the authors (DreamerV1 calls this pretraining)."""
    lr_warmup: int | None = None
    """DreamerV3's learners (``algo=isodream``, its ablations, ``algo=torchrl_dreamer_v3``): updates of linear
    learning-rate warm-up of their ``DreamerV3Optimizer`` (the first update has learning rate 0)."""
    max_nonfinite_updates: int = 5
    """K: this many updates in a row with a NaN/inf loss or gradient stop the run."""
    collector_backend: str = "sync"
    """``"sync"`` (one process; a multi-process collector when ``num_envs > 1``), ``"multiprocess"``,
    ``"ray"`` or ``"distributed"`` (TorchRL's distributed collectors, for more than one machine); each of the
    ``env.num_envs`` workers runs one env."""
    ray_address: str = ""
    """``ray``: address of a running Ray cluster (``"auto"``, ``"ray://head:10001"``); empty starts a local one."""
    collector_cpus: int = 2
    """``ray`` without an address: CPUs of the local Ray cluster (one per worker)."""
    distributed_launcher: str = "mp"
    """``distributed``: ``"mp"`` (worker processes on this machine), ``"submitit"`` or ``"submitit_delayed"``
    (SLURM jobs on other nodes; needs ``pip install submitit``)."""
    distributed_backend: str = "gloo"
    """``distributed``: the ``torch.distributed`` backend (``"gloo"`` on CPU; ``"nccl"`` between GPUs)."""
    distributed_port: int = 10003
    """``distributed``: TCP port of the rendezvous on this (the learner's) machine; the next two ports are used
    too."""
    slurm_kwargs: dict[str, Any] = field(default_factory=dict)
    """``distributed`` with submitit: the SLURM executor's parameters (``timeout_min``, ``slurm_partition``...)."""
    device: str = "cpu"
    """Where the models train (``"cpu"`` or ``"cuda"``)."""
    seed: int = 0
    """Seeds torch, numpy, python and the envs."""
    threads: int = 2
    """``torch.set_num_threads``."""


@dataclass
class LoggingConfig:
    """Where and how often to log."""

    backend: str = "csv"
    """TorchRL logger: ``"csv"``, ``"tensorboard"`` or ``"wandb"``."""
    log_every: int = 500
    """Agent steps between scalar logs (updates in ``mode=world_model``)."""
    eval_every: int = 5000
    """Agent steps between evaluations (episodes with the mode action plus an open-loop prediction GIF);
    0 disables them. In ``mode=world_model``: updates between held-out scores and branch pictures (0: after
    the last update only)."""
    eval_episodes: int = 1
    """Episodes per evaluation."""
    final_eval_episodes: int = 10
    """Episodes of the evaluation after the last update, written with the task's reference policies (random,
    best constant action, scripted) and the normalised score to ``<run_dir>/summary.json``; 0 skips it."""
    video_context: int = 5
    """Context frames of the open-loop prediction (>= 2: the world model filters windows of 2 steps or more); the
    rest of the window is imagined."""
    video_length: int = 20
    """Frames per open-loop prediction (context included)."""
    project: str = "isodream-rl"
    """W&B project."""
    offline: bool = False
    """W&B without a server: the run is written under ``<run_dir>/logs/wandb`` (as ``WANDB_MODE=offline``)."""
    progress_bar: bool = True
    """TorchRL's tqdm bar (env steps/s and updates/s in its description)."""


@dataclass
class CheckpointConfig:
    """Checkpoint schedule and resume."""

    every_updates: int = 500
    """Updates between checkpoints (one is also written at the end and on SIGINT/SIGTERM)."""
    keep: int = 2
    """Checkpoints kept on disk (the newest ``keep``); at least 2, so a corrupted newest one has a fallback."""
    replay: bool = True
    """Save the replay buffer with each checkpoint (needed for an exact resume)."""
    resume: bool = False
    """Continue from the newest readable checkpoint in ``run_dir``."""


@dataclass
class RunConfig:
    """The whole training configuration (the Hydra root)."""

    mode: str = "rl"
    """``"rl"``: Algorithm 1 (world model, actor and value on collected data); ``"world_model"``: the world model
    alone on random-action episodes, scored on held-out ones (``world_model`` below; ``exp=world_model``)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    world_model: WorldModelModeConfig = field(default_factory=WorldModelModeConfig)
    size_name: str = "small"
    """Name of the chosen ``size`` group (used in the default ``run_dir``)."""
    run_dir: str = "runs/default"
    """Logs, checkpoints and pictures go here; ``resume=true`` needs the same ``run_dir``. A folder that holds
    another run's files is refused unless ``resume`` or ``overwrite`` is set (``trainers/run_dir.py``)."""
    resume: bool = False
    """Shortcut for ``checkpoint.resume``."""
    overwrite: bool = False
    """Delete the run already in ``run_dir`` (its checkpoints, logs, pictures, ``run_config.json`` and
    ``summary.json``) before starting; without it, such a folder is refused."""

    def __post_init__(self):
        resolve_algo(self.algo)


def resolve_algo(algo: AlgoConfig) -> AlgoConfig:
    """Fill the branch switches of ``algo`` left ``None`` with :data:`ALGO_BRANCHES` of ``algo.name`` (in place;
    returned). Runs when a :class:`RunConfig` is made (Hydra's ``OmegaConf.to_object``, ``config_from_dict``,
    ``RunConfig()``); a value given anywhere is kept."""
    for name, value in ALGO_BRANCHES.get(algo.name, ALGO_BRANCHES["isodream"]).items():
        if getattr(algo, name) is None:
            setattr(algo, name, value)
    return algo


def _choice(errors: list[str], name: str, value, valid) -> None:
    if value not in valid:
        errors.append(f"{name}={value!r} is not one of {list(valid)}")


def _positive(errors: list[str], name: str, value, minimum: int | float = 1) -> None:
    if value is not None and value < minimum:
        errors.append(f"{name}={value} must be >= {minimum}")


def _name_errors(cfg: RunConfig) -> list[str]:
    """The mode, a former ``algo`` name, the settings the learner does not read, the device and the seed."""
    errors: list[str] = []
    _choice(errors, "mode", cfg.mode, MODES)
    renamed = renamed_algo_error(cfg.algo.name)
    errors += [renamed] if renamed else unread_setting_errors(cfg)
    unusable = device_error(cfg.train.device)
    if unusable:
        errors.append(unusable)
    if not 0 <= cfg.train.seed < 2**32:  # numpy's seed range
        errors.append(f"train.seed={cfg.train.seed} must be in [0, 2**32 - 1]")
    return errors


def _model_errors(cfg: RunConfig) -> list[str]:
    """The ``model.<field>`` values given, as the DreamerV2-style world model checks them when it is built."""
    if cfg.model.size not in SIZE_PRESETS:
        return []
    try:
        IsoDreamV2Config.from_preset(cfg.model.size, action_dim=1, **world_model_overrides(cfg))
    except (TypeError, ValueError) as err:
        return [f"model={cfg.model.world_model_fields()} with the algo's branches: {err}"]
    return []


def _learner_value_errors(cfg: RunConfig) -> list[str]:
    """The values of the learner-specific settings of ``cfg`` (resolved: each its learner's or the one given) that
    no learner can train with; ``None`` is a setting the learner does not read."""
    algo, train = cfg.algo, cfg.train
    errors: list[str] = []
    for name in ("world_model_lr", "actor_lr", "value_lr"):  # 0 freezes that part (tests use it)
        if not getattr(train, name) >= 0:
            errors.append(f"train.{name}={getattr(train, name)} must be >= 0")
    for name in ("adam_eps", "grad_clip"):
        value = getattr(train, name)
        if value is not None and not value > 0:
            errors.append(f"train.{name}={value} must be > 0")
    _positive(errors, "train.lr_warmup", train.lr_warmup, 0)
    _positive(errors, "algo.slow_target_every", algo.slow_target_every)
    if algo.free_branch_loss is not None:
        _choice(errors, "algo.free_branch_loss", algo.free_branch_loss, FREE_BRANCH_MODES)
    for name in ("actor_loc_penalty", "exploration_noise"):
        value = getattr(algo, name)
        if value is not None and value < 0:
            errors.append(f"algo.{name}={value} must be >= 0")
    if algo.gamma is not None and not 0.0 < algo.gamma <= 1.0:
        errors.append(f"algo.gamma={algo.gamma} must be in (0, 1]")
    if algo.lmbda is not None and not 0.0 <= algo.lmbda <= 1.0:
        errors.append(f"algo.lmbda={algo.lmbda} must be in [0, 1]")
    return errors


def _branch_errors(algo: AlgoConfig) -> list[str]:
    """The settings that read a branch, or the attention, the variant does not have."""
    errors: list[str] = []
    _choice(errors, "algo.policy_input", algo.policy_input, POLICY_INPUTS)
    if algo.policy_input in ("attention", "concat") and not algo.free_branch:
        errors.append(
            f"algo.policy_input={algo.policy_input!r} reads the noncontrollable branch, but "
            "algo.free_branch=false: set algo.policy_input=controllable or algo.free_branch=true"
        )
    if algo.attention_through_actor and algo.policy_input != "attention":
        errors.append(
            f"algo.attention_through_actor=true trains the future-state attention, but algo.policy_input="
            f"{algo.policy_input!r} has none: set algo.policy_input=attention or algo.attention_through_actor=false"
        )
    if algo.reward_uses_free and not algo.free_branch:
        errors.append(
            "algo.reward_uses_free=true needs the noncontrollable branch: set algo.reward_uses_free=false "
            "or algo.free_branch=true"
        )
    if algo.free_branch_loss == "recon_only" and not algo.free_branch:
        errors.append(
            "algo.free_branch_loss=recon_only configures the noncontrollable branch, which is off "
            "(algo.free_branch=false): set algo.free_branch_loss=kl or algo.free_branch=true"
        )
    return errors


def _schedule_errors(cfg: RunConfig) -> list[str]:
    """Counts that must be positive, and the collection, replay and evaluation schedules that do not fit together."""
    train, env, logging = cfg.train, cfg.env, cfg.logging
    errors: list[str] = []
    _choice(errors, "model.size", cfg.model.size, SIZE_PRESETS)
    for name, value in (
        ("env.num_envs", env.num_envs),
        ("env.action_repeat", env.action_repeat),
        ("train.total_steps", train.total_steps),
        ("train.train_every", train.train_every),
        ("train.frames_per_batch", train.frames_per_batch),
        ("train.batch_size", train.batch_size),
        ("train.sequence_length", train.sequence_length),
        ("train.max_nonfinite_updates", train.max_nonfinite_updates),
        ("train.threads", train.threads),
        ("train.collector_cpus", train.collector_cpus),
        ("algo.horizon", cfg.algo.horizon),
        ("algo.attention_window", cfg.algo.attention_window),
        ("checkpoint.every_updates", cfg.checkpoint.every_updates),
        ("logging.log_every", logging.log_every),
        ("logging.eval_episodes", logging.eval_episodes),
    ):
        _positive(errors, name, value)
    _positive(errors, "checkpoint.keep", cfg.checkpoint.keep, 2)
    _positive(errors, "train.prefill_steps", train.prefill_steps, 0)
    _positive(errors, "train.world_model_warmup", train.world_model_warmup, 0)
    _positive(errors, "logging.eval_every", logging.eval_every, 0)
    _positive(errors, "logging.final_eval_episodes", logging.final_eval_episodes, 0)
    if 0 < logging.eval_every <= logging.log_every:
        errors.append(
            f"logging.eval_every={logging.eval_every} must exceed logging.log_every={logging.log_every}: "
            "TorchRL's Trainer writes a scalar only once more than log_every steps have passed since its last "
            "write, so evaluations closer together than that would not be logged"
        )
    if train.frames_per_batch >= 1 and train.frames_per_batch % (train.train_every * env.num_envs):
        errors.append(
            f"train.frames_per_batch={train.frames_per_batch} must be a multiple of train.train_every * "
            f"env.num_envs = {train.train_every * env.num_envs}"
        )
    window_steps = train.sequence_length * env.num_envs
    if train.buffer_size < window_steps:
        errors.append(
            f"train.buffer_size={train.buffer_size} cannot hold one window per env "
            f"(train.sequence_length * env.num_envs = {window_steps})"
        )
    if train.prefill_steps < window_steps and train.prefill_steps < train.total_steps:
        errors.append(
            f"train.prefill_steps={train.prefill_steps} is shorter than one replay window per env "
            f"(train.sequence_length * env.num_envs = {window_steps}): raise the prefill or shorten the window"
        )
    if logging.video_context >= logging.video_length or logging.video_context < 2:
        errors.append(
            f"logging.video_context={logging.video_context} must be >= 2 and below "
            f"logging.video_length={logging.video_length}"
        )
    if logging.video_length > train.sequence_length:
        errors.append(
            f"logging.video_length={logging.video_length} must not exceed train.sequence_length="
            f"{train.sequence_length} (the prediction reads one replay window)"
        )
    return errors


def _collection_errors(cfg: RunConfig) -> list[str]:
    """The collector backend, its launcher and what it needs installed; the logger; a custom env factory; the
    replay a resume needs."""
    train, env = cfg.train, cfg.env
    errors: list[str] = []
    _choice(errors, "train.collector_backend", train.collector_backend, COLLECTOR_BACKENDS)
    _choice(errors, "logging.backend", cfg.logging.backend, LOGGER_BACKENDS)
    _choice(errors, "train.distributed_launcher", train.distributed_launcher, DISTRIBUTED_LAUNCHERS)
    _choice(errors, "train.distributed_backend", train.distributed_backend, DISTRIBUTED_BACKENDS)
    if env.num_envs > 1 and train.collector_backend == "sync" and train.frames_per_batch < env.num_envs:
        errors.append("train.frames_per_batch must be at least env.num_envs")
    if train.collector_backend == "ray":
        if importlib.util.find_spec("ray") is None:
            errors.append(
                "train.collector_backend=ray needs Ray: pip install 'isodream-rl[distributed]' (or 'ray[default]')"
            )
        if not train.ray_address and train.collector_cpus < env.num_envs:
            errors.append(
                f"train.collector_cpus={train.collector_cpus} is fewer than the env.num_envs={env.num_envs} Ray "
                "workers (one CPU each): raise train.collector_cpus or give train.ray_address"
            )
    if (
        train.collector_backend == "distributed"
        and train.distributed_launcher.startswith("submitit")
        and importlib.util.find_spec("submitit") is None
    ):
        errors.append(
            f"train.distributed_launcher={train.distributed_launcher} needs submitit: pip install submitit, or "
            "set train.distributed_launcher=mp to start the workers on this machine"
        )
    if train.collector_backend in REMOTE_BACKENDS and cfg.model.channels_last:
        errors.append(
            f"model.channels_last=true cannot be used with train.collector_backend="
            f"{train.collector_backend}: its weight transfer sends dense tensors only; drop the setting"
        )
    if env.factory:
        module, _, attribute = env.factory.partition(":")
        found = importlib.util.find_spec(module) is not None if module and attribute else False
        if not found or not callable(getattr(importlib.import_module(module), attribute, None)):
            errors.append(
                f"env.factory={env.factory!r} must name a callable as 'package.module:function' that returns a "
                "TorchRL EnvBase"
            )
    if (cfg.resume or cfg.checkpoint.resume) and not cfg.checkpoint.replay:
        errors.append(
            "resume=true restores the replay buffer from the checkpoint: set checkpoint.replay=true (a resumed "
            "run with an empty buffer would sample windows that do not exist)"
        )
    return errors


def validate_config(cfg: RunConfig) -> None:
    """Check cross-field constraints; raise :class:`ConfigError` listing every problem and its fix.

    The settings of ``cfg``'s learner are checked at the values it reads (each its table's where ``cfg`` leaves it
    ``None``, :func:`~isodream_rl.trainers.learners.resolved`); a value given for a setting it does not read is
    refused, naming the learners that read it.

    Args:
        cfg: a filled :class:`RunConfig`.

    Raises:
        ConfigError: with one line per problem, naming the field(s) and what to change.
    """
    errors = _name_errors(cfg)
    settings = resolved(cfg)
    errors += _model_errors(settings) + _learner_value_errors(settings)
    if cfg.mode == "world_model":
        errors += world_model_mode_errors(settings)
    else:
        errors += _branch_errors(settings.algo) + _schedule_errors(cfg) + _collection_errors(cfg)
    if errors:
        raise ConfigError("invalid training configuration:\n  - " + "\n  - ".join(errors))


#: ``(section, field) -> value``: fields added with a default that changes what a run does; a configuration saved
#: before such a field existed ran with this value, which it keeps when it is read back (resumed, probed).
FORMER_BEHAVIOUR = {("algo", "actor_loc_penalty"): 0.0}


def config_from_dict(data: dict) -> RunConfig:
    """Rebuild a :class:`RunConfig` from ``dataclasses.asdict`` output (as stored in checkpoints and
    ``run_config.json``); fields added since it was written take their defaults, except those of
    :data:`FORMER_BEHAVIOUR`, which take the value the run was trained with; a ``model.overrides`` dict (written
    before the ``model`` section had the world model's fields) sets those fields; an ``algo.name`` saved before a
    rename is read as its name today, and the settings its learner does not read are dropped
    (:mod:`isodream_rl.trainers.renames`)."""
    import dataclasses

    sections = {f.name: f.type for f in dataclasses.fields(RunConfig)}
    data = {name: value for name, value in data.items() if name in sections}
    for (section, key), value in FORMER_BEHAVIOUR.items():
        if isinstance(data.get(section), dict):
            data[section] = {key: value, **data[section]}
    model = data.get("model")
    if isinstance(model, dict) and "overrides" in model:  # before model.<field>
        data["model"] = {**model["overrides"], **{key: v for key, v in model.items() if key != "overrides"}}
    if isinstance(data.get("algo"), dict) and "name" in data["algo"]:
        name = saved_algo_name(data["algo"]["name"])
        data = drop_unread_settings({**data, "algo": {**data["algo"], "name": name}})
    kwargs = {}
    for name, value in data.items():
        section_type = globals().get(str(sections[name]))
        kwargs[name] = section_type(**value) if isinstance(value, dict) and section_type else value
    return RunConfig(**kwargs)


def world_model_overrides(cfg: RunConfig) -> dict[str, Any]:
    """The ``IsoDreamV2Config`` fields set by the algorithm preset, merged with those ``model`` sets."""
    algo = cfg.algo
    fields_from_algo = {
        **(PAPER_EXACT if algo.paper_exact else {}),
        "free_branch": algo.free_branch,
        "static_branch": algo.static_branch,
        "inverse_dynamics": algo.inverse_dynamics,
        "reward_uses_free": algo.reward_uses_free,
    }
    if not algo.static_branch:
        fields_from_algo["mask_mode"] = "softmax"
    if cfg.train.collector_backend in REMOTE_BACKENDS:
        # Ray's and torch.distributed's weight transfers send dense tensors only.
        fields_from_algo["channels_last"] = False
    return {**fields_from_algo, **cfg.model.world_model_fields()}
