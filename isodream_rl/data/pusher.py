"""A local BAIR-like dataset: a MuJoCo table-top pusher seen from an oblique camera.

BAIR robot pushing cannot be downloaded at run time, so this generator produces the same kind of data:
a position-controlled end effector (with an arm reaching in from the back of the table) pushing three
free objects of random colour and shape, 4-d actions ``[dx, dy, 0, 0]`` as in BAIR, and the recorded
end-effector position. Actions are Ornstein-Uhlenbeck-smoothed random moves, so pushes are frequent.

Every sequence is a function of ``(seed, split, index)`` only, so the result does not depend on the
number of worker processes, and a cached file can always be regenerated bit for bit.
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

__all__ = ["generate_pusher_sequences", "load_pusher_dataset", "default_cache_dir"]

_WORKSPACE = 0.22  # half side of the square the pusher may move in (m)
_MAX_STEP = 0.03  # displacement per frame for a unit action (m)
_PHYSICS_STEPS = 10  # 5 ms physics steps per frame
_SPLIT_IDS = {"train": 0, "test": 1}
_VERSION = 1

_MJCF = """
<mujoco model="bairlike_pusher">
  <option timestep="0.005" gravity="0 0 -9.81"/>
  <visual>
    <quality shadowsize="0"/>
    <global offwidth="{size}" offheight="{size}"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.5 0.5 0.5" specular="0.1 0.1 0.1"/>
  </visual>
  <asset>
    <texture name="wood" type="2d" builtin="checker" rgb1="0.62 0.55 0.45" rgb2="0.58 0.51 0.41"
             width="64" height="64"/>
    <material name="table" texture="wood" texrepeat="6 6"/>
    <texture name="wall" type="2d" builtin="flat" rgb1="0.78 0.80 0.82" width="8" height="8"/>
    <material name="wall" texture="wall"/>
  </asset>
  <worldbody>
    <light pos="0 -0.3 1.5" dir="0 0.2 -1" castshadow="false" diffuse="0.5 0.5 0.5"/>
    <geom name="table" type="plane" size="0.5 0.5 0.01" material="table"/>
    <geom name="backdrop" type="box" pos="0 0.45 0.2" size="0.6 0.01 0.4" material="wall" contype="0"
          conaffinity="0"/>
    <geom type="box" pos="0 0.33 0.03" size="0.4 0.01 0.03" rgba="0 0 0 0"/>
    <geom type="box" pos="0 -0.33 0.03" size="0.4 0.01 0.03" rgba="0 0 0 0"/>
    <geom type="box" pos="0.33 0 0.03" size="0.01 0.4 0.03" rgba="0 0 0 0"/>
    <geom type="box" pos="-0.33 0 0.03" size="0.01 0.4 0.03" rgba="0 0 0 0"/>
    <body name="eef" mocap="true" pos="0 0 0.035">
      <geom name="gripper" type="cylinder" size="0.025 0.03" rgba="0.25 0.25 0.28 1"/>
      <geom name="arm" type="capsule" fromto="0 0 0.03 0 0.35 0.45" size="0.03" rgba="0.55 0.12 0.12 1"
            contype="0" conaffinity="0"/>
    </body>
    <camera name="oblique" pos="0 -0.5 0.5" xyaxes="1 0 0 0 0.72 0.69" fovy="45"/>
    {objects}
  </worldbody>
</mujoco>
"""

_OBJECT = """
    <body name="obj{i}" pos="{x} {y} 0.04">
      <freejoint/>
      <geom name="obj{i}" type="box" size="0.04 0.04 0.03" rgba="1 1 1 1" mass="0.3" friction="0.8 0.01 0.001"/>
    </body>"""


def default_cache_dir() -> Path:
    """``$ISODREAM_DATA_DIR`` or ``~/.cache/isodream_rl``."""
    return Path(os.environ.get("ISODREAM_DATA_DIR", Path.home() / ".cache" / "isodream_rl"))


def _build(image_size: int):
    import mujoco

    from isodream_rl.envs.mujoco_render import OffscreenRenderer

    objects = "".join(_OBJECT.format(i=i, x=0.1 * i - 0.1, y=0.0) for i in range(3))
    xml = _MJCF.format(size=image_size, objects=objects)
    model = mujoco.MjModel.from_xml_string(xml)
    # Picks a headless GL backend itself: ``mujoco.Renderer`` takes the one fixed when mujoco was first imported
    # (GLFW, which needs a display, if ``MUJOCO_GL`` was unset then).
    renderer = OffscreenRenderer(model, width=image_size, height=image_size)
    return model, mujoco.MjData(model), renderer


def _one_sequence(model, data, renderer, num_frames: int, rng: np.random.Generator):
    import mujoco

    mujoco.mj_resetData(model, data)
    # Random object look: colour, box / cylinder-like footprint and size.
    for i in range(3):
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"obj{i}")
        model.geom_rgba[gid, :3] = rng.uniform(0.05, 1.0, size=3)
        half = rng.uniform(0.03, 0.05, size=2)
        model.geom_size[gid, :2] = half
    eef = rng.uniform(-_WORKSPACE, _WORKSPACE, size=2)
    placed: list[np.ndarray] = [eef]
    for i in range(3):
        for _ in range(100):
            xy = rng.uniform(-0.2, 0.2, size=2)
            if all(np.linalg.norm(xy - p) > 0.1 for p in placed):
                break
        placed.append(xy)
        qadr = model.jnt_qposadr[
            model.body_jntadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"obj{i}")]
        ]
        yaw = rng.uniform(-np.pi, np.pi)
        data.qpos[qadr : qadr + 7] = [xy[0], xy[1], 0.031, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    data.mocap_pos[0] = [eef[0], eef[1], 0.035]
    mujoco.mj_forward(model, data)

    camera = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, "oblique")
    size = model.vis.global_.offwidth
    frames = np.empty((num_frames, size, size, 3), dtype=np.uint8)
    actions = np.zeros((num_frames, 4), dtype=np.float32)
    eef_pos = np.empty((num_frames, 3), dtype=np.float32)
    move = rng.normal(size=2) * 0.5
    goal = eef
    for t in range(num_frames):
        frames[t] = renderer.render(data, camera_id=camera)
        eef_pos[t] = data.mocap_pos[0]
        # A goal (an object, half of the time) redrawn every few frames plus OU noise: the pusher keeps
        # a heading for several frames and often runs into objects, as BAIR's arm does.
        if t % 8 == 0:
            obj = rng.integers(-3, 3)
            goal = placed[obj + 1] if obj >= 0 else rng.uniform(-_WORKSPACE, _WORKSPACE, size=2)
            if obj >= 0:
                body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"obj{obj}")
                goal = data.xpos[body, :2].copy()
        pull = np.clip((goal - data.mocap_pos[0, :2]) / _MAX_STEP, -1.0, 1.0)
        move = np.clip(0.6 * move + 0.3 * pull + 0.35 * rng.normal(size=2), -1.0, 1.0)
        start = data.mocap_pos[0, :2].copy()
        # Turn back at the workspace border instead of sticking to it.
        move = np.where(np.abs(start + _MAX_STEP * move) > _WORKSPACE, -move, move)
        target = np.clip(start + _MAX_STEP * move, -_WORKSPACE, _WORKSPACE)
        actions[t, :2] = (target - start) / _MAX_STEP
        for k in range(1, _PHYSICS_STEPS + 1):
            data.mocap_pos[0, :2] = start + (target - start) * k / _PHYSICS_STEPS
            mujoco.mj_step(model, data)
    return frames, actions, eef_pos


def _worker(args: tuple[int, str, list[int], int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    seed, split, indices, num_frames, image_size = args
    os.environ.setdefault("MUJOCO_GL", "egl")
    # llvmpipe's own threads only contend with the worker processes.
    os.environ.setdefault("LP_NUM_THREADS", "1")
    model, data, renderer = _build(image_size)
    out = [
        _one_sequence(model, data, renderer, num_frames, np.random.default_rng([seed, _SPLIT_IDS[split], i]))
        for i in indices
    ]
    renderer.close()
    return tuple(np.stack(x) for x in zip(*out))


def generate_pusher_sequences(
    num_sequences: int,
    num_frames: int,
    *,
    seed: int = 0,
    split: str = "train",
    image_size: int = 64,
    workers: int = 1,
) -> dict[str, np.ndarray]:
    """Render pusher sequences.

    Args:
        num_sequences: N.
        num_frames: T.
        seed: base seed; sequence ``i`` of a split depends on ``(seed, split, i)`` only.
        split: ``"train"`` or ``"test"`` (disjoint random streams).
        image_size: side of the square frames.
        workers: processes to render with (results are identical for any value).

    Returns:
        ``{"frames": uint8 [N, T, H, W, 3], "actions": float32 [N, T, 4], "endeffector_pos": float32
        [N, T, 3]}``; ``actions[:, t]`` moves the scene from frame ``t`` to ``t + 1`` (BAIR's convention).
    """
    if split not in _SPLIT_IDS:
        raise ValueError(f"split must be one of {sorted(_SPLIT_IDS)}, got {split!r}")
    if num_sequences < 1 or num_frames < 1:
        raise ValueError(f"need num_sequences >= 1 and num_frames >= 1, got {num_sequences}, {num_frames}")
    workers = max(1, min(workers, num_sequences))
    chunks = [c.tolist() for c in np.array_split(np.arange(num_sequences), workers)]
    jobs = [(seed, split, c, num_frames, image_size) for c in chunks]
    if workers == 1:
        parts = [_worker(jobs[0])]
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            parts = list(pool.map(_worker, jobs))
    frames, actions, eef = (np.concatenate(x) for x in zip(*parts))
    return {"frames": frames, "actions": actions, "endeffector_pos": eef}


def load_pusher_dataset(
    num_sequences: int,
    num_frames: int,
    *,
    seed: int = 0,
    split: str = "train",
    image_size: int = 64,
    cache_dir: str | os.PathLike | None = None,
    workers: int = 1,
) -> dict[str, np.ndarray]:
    """Load pusher sequences from the on-disk cache, generating (and caching) them on a miss.

    The cache file name encodes every argument that changes the data, and it is written atomically
    (temporary file + ``os.replace``), so concurrent or interrupted runs never leave a corrupt file.

    Args:
        num_sequences, num_frames, seed, split, image_size, workers: as in :func:`generate_pusher_sequences`.
        cache_dir: directory of the cache; defaults to :func:`default_cache_dir`.

    Returns:
        As :func:`generate_pusher_sequences`.

    Raises:
        ValueError: the cached file is unreadable (damaged on disk, or cut by a copy), naming it.
    """
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    key = f"v{_VERSION}-n{num_sequences}-t{num_frames}-s{seed}-{split}-{image_size}px"
    path = cache / f"pusher-{key}-{hashlib.sha1(key.encode()).hexdigest()[:8]}.npz"
    if path.exists():
        try:
            with np.load(path) as f:
                return {k: f[k] for k in ("frames", "actions", "endeffector_pos")}
        # a cut zip, a damaged member, a missing array: np.load raises each differently
        except Exception as err:
            raise ValueError(
                f"the cached pusher data {path} is unreadable ({type(err).__name__}: {err}): delete it, and it is "
                "generated again"
            ) from err
    arrays = generate_pusher_sequences(
        num_sequences, num_frames, seed=seed, split=split, image_size=image_size, workers=workers
    )
    cache.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return arrays
