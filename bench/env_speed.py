"""Milliseconds per agent step of every isodream-rl env, raw gymnasium and through ``make_env`` (TorchRL).

Usage::

    python bench/env_speed.py [--steps 300] [--only sprites highway/top_down ...] [--json PATH]

Each env runs random actions in [-1, 1] (drawn before timing, seeded); each step is timed alone and the
median over ``--steps`` steps after a short warm-up is taken, so the occasional reset does not count. The
gymnasium env and the TorchRL env are stepped alternately, so both see the same machine load. Each env runs
``--rounds`` times and the round with the lowest TorchRL median is reported: other jobs sharing the machine only
add time. The
JSON maps every env name, written as ``make_env`` takes it plus its view or background (``"sprites"``,
``"highway/first_person"``, ``"dmc/walker-walk/video_easy"``, ...), to its median ms per agent step through
TorchRL; ``"details"`` holds the raw gymnasium times, the process CPU time per step of both paths (less
sensitive than wall time to other jobs sharing the cores; it includes llvmpipe's render threads), the
targets and the machine's load average (``details["load_average"]``, before and after the run).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from isodream_rl.envs import make_env, make_gym_env  # noqa: E402
from isodream_rl.run_utils.json_io import write_json  # noqa: E402

# name -> (make_env name, cfg, target ms per agent step from issue 4 / the brief)
CASES: dict[str, tuple[str, dict, float]] = {
    "sprites": ("sprites", {"task": "reach"}, 1.0),
    "highway/first_person": ("highway", {"view": "first_person"}, 20.0),
    "highway/top_down": ("highway", {"view": "top_down"}, 12.0),
}
for _domain, _task in (("walker", "walk"), ("cheetah", "run")):
    for _background, _target in (("video_easy", 10.0), ("video_hard", 10.0), ("none", 10.0)):
        CASES[f"dmc/{_domain}-{_task}/{_background}"] = (
            f"dmc_{_domain}_{_task}",
            {"background": _background},
            _target,
        )

WARMUP = 10


class _Timer:
    """Wall-clock and process-CPU durations of timed calls."""

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def medians_ms(self) -> tuple[float, float]:
        return 1e3 * statistics.median(self.wall), 1e3 * statistics.median(self.cpu)


def _time_both(name: str, cfg: dict, actions: np.ndarray) -> tuple[_Timer, _Timer]:
    """Times ``env.step`` of the raw gymnasium env and ``step_and_maybe_reset`` of ``make_env``, reset steps
    excluded from both.

    The two envs are stepped alternately with the same actions (and the same seed, so the same episodes): both
    paths see the same machine load, which on a shared machine drifts more between two consecutive runs than the
    TorchRL overhead itself.
    """
    gym_env = make_gym_env(name, **cfg)
    gym_env.reset(seed=0)
    env = make_env(name, seed=0, **cfg)
    td = env.reset()
    gym_timer, torchrl_timer = _Timer(), _Timer()
    for i, (action, action_tensor) in enumerate(zip(actions, torch.as_tensor(actions), strict=True)):
        start, start_cpu = time.perf_counter(), time.process_time()
        _, _, terminated, truncated, _ = gym_env.step(action)
        wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        if i >= WARMUP:
            gym_timer.wall.append(wall)
            gym_timer.cpu.append(cpu)
        if terminated or truncated:
            gym_env.reset()
        td.set("action", action_tensor)
        start, start_cpu = time.perf_counter(), time.process_time()
        _, td = env.step_and_maybe_reset(td)
        wall, cpu = time.perf_counter() - start, time.process_time() - start_cpu
        if i >= WARMUP and not td["is_init"].item():
            torchrl_timer.wall.append(wall)
            torchrl_timer.cpu.append(cpu)
    gym_env.close()
    env.close()
    return gym_timer, torchrl_timer


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=300, help="timed steps per env and path (plus warm-up)")
    parser.add_argument("--only", nargs="*", default=None, help=f"subset of: {' '.join(CASES)}")
    parser.add_argument("--json", default=None, help="write the results to this JSON file")
    parser.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="timed runs per env; the least disturbed one (lowest median) counts",
    )
    args = parser.parse_args(argv)
    names = args.only or list(CASES)
    unknown = [n for n in names if n not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {unknown}; expected some of {list(CASES)}")
    torch.set_num_threads(1)

    results: dict[str, float] = {}
    details: dict = {
        "gym_ms": {},
        "torchrl_cpu_ms": {},
        "gym_cpu_ms": {},
        "targets_ms": {},
        "torchrl_ms_per_round": {},
        "steps": args.steps,
        "warmup": WARMUP,
        "rounds": args.rounds,
    }
    load_before = os.getloadavg()
    print(f"{'env':28s} {'gym ms':>8s} {'(cpu)':>7s} {'torchrl ms':>11s} {'(cpu)':>7s} {'target':>7s}")
    for case in names:
        name, cfg, target = CASES[case]
        probe = make_gym_env(name, **cfg)
        rng = np.random.default_rng(0)
        shape = probe.action_space.shape
        probe.close()
        actions = rng.uniform(-1.0, 1.0, size=(args.steps + WARMUP, *shape)).astype(np.float32)
        rounds = [_time_both(name, cfg, actions) for _ in range(args.rounds)]
        medians = [(gym.medians_ms(), torchrl.medians_ms()) for gym, torchrl in rounds]
        # Other jobs on a shared machine only ever add time: the round with the lowest median is the least
        # disturbed one.
        (gym_ms, gym_cpu), (torchrl_ms, torchrl_cpu) = min(medians, key=lambda m: m[1][0])
        details["torchrl_ms_per_round"][case] = [round(m[1][0], 3) for m in medians]
        results[case] = round(torchrl_ms, 3)
        details["gym_ms"][case] = round(gym_ms, 3)
        details["gym_cpu_ms"][case] = round(gym_cpu, 3)
        details["torchrl_cpu_ms"][case] = round(torchrl_cpu, 3)
        details["targets_ms"][case] = target
        flag = "ok" if torchrl_ms <= target else "SLOW"
        print(
            f"{case:28s} {gym_ms:8.3f} {gym_cpu:7.3f} {torchrl_ms:11.3f} {torchrl_cpu:7.3f} {target:7.1f} {flag}"
        )
    # 1-, 5- and 15-minute load averages of the machine when the run started and ended: other jobs on the same
    # cores inflate wall times (and, through shared hardware threads, CPU times too).
    details["load_average"] = {
        "before": [round(x, 2) for x in load_before],
        "after": [round(x, 2) for x in os.getloadavg()],
    }
    details["machine"] = {"cpu_count": os.cpu_count(), "python": platform.python_version()}
    details["env"] = {k: os.environ.get(k) for k in ("MUJOCO_GL", "SDL_VIDEODRIVER", "LP_NUM_THREADS")}
    out = {**results, "details": details}
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        write_json(args.json, out, indent=2)
        print(f"wrote {args.json}")
    return out


if __name__ == "__main__":
    main()
