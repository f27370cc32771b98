"""The local BAIR-like pusher set, bouncing balls and clip windowing."""

import numpy as np
import pytest
import torch

from isodream_rl.data import (
    ArraySequences,
    BouncingBalls,
    VideoClips,
    ball_trajectories,
    generate_pusher_sequences,
    load_pusher_dataset,
    overlay_balls,
)


@pytest.fixture(scope="module")
def pusher():
    return generate_pusher_sequences(2, 6, seed=3)


def test_pusher_arrays_have_bair_shapes(pusher):
    assert pusher["frames"].shape == (2, 6, 64, 64, 3) and pusher["frames"].dtype == np.uint8
    assert pusher["actions"].shape == (2, 6, 4)
    assert pusher["endeffector_pos"].shape == (2, 6, 3)
    assert not pusher["actions"][..., 2:].any()  # [dx, dy, 0, 0] like BAIR


def test_pusher_actions_explain_end_effector_motion(pusher):
    moves = np.diff(pusher["endeffector_pos"][..., :2], axis=1)
    np.testing.assert_allclose(moves / 0.03, pusher["actions"][:, :-1, :2], atol=1e-4)


def test_pusher_is_deterministic_and_cached(pusher, tmp_path):
    again = load_pusher_dataset(2, 6, seed=3, cache_dir=tmp_path)
    np.testing.assert_array_equal(again["frames"], pusher["frames"])
    assert len(list(tmp_path.glob("*.npz"))) == 1
    cached = load_pusher_dataset(2, 6, seed=3, cache_dir=tmp_path)
    np.testing.assert_array_equal(cached["actions"], pusher["actions"])
    other = generate_pusher_sequences(1, 2, seed=3, split="test")
    assert not np.array_equal(other["frames"][0, 0], pusher["frames"][0, 0])


def test_balls_stay_inside_and_move_four_pixels_per_axis():
    pos = ball_trajectories(200, rng=np.random.default_rng(0))
    assert pos.shape == (200, 3, 2)
    assert pos.min() >= 3 and pos.max() <= 60
    steps = np.abs(np.diff(pos, axis=0))
    assert steps.max() <= 4 + 1e-9
    assert np.isclose(steps, 4).mean() > 0.8  # anything else is a bounce


def test_overlay_draws_pure_colour_discs():
    frames = np.zeros((1, 64, 64, 3), np.uint8)
    pos = np.array([[[10.0, 20.0], [40.0, 40.0], [50.0, 10.0]]])
    out = overlay_balls(frames, pos, radius=3)
    np.testing.assert_array_equal(out[0, 10, 20], [255, 0, 0])
    np.testing.assert_array_equal(out[0, 40, 43], [0, 255, 0])
    np.testing.assert_array_equal(out[0, 50, 10], [0, 0, 255])
    assert (out[0].sum(-1) > 0).sum() == 3 * 29  # a radius-3 digital disc has 29 pixels


def test_fixed_balls_depend_only_on_clip_index():
    clip = np.zeros((5, 64, 64, 3), np.uint8)
    a, b = BouncingBalls(fixed=True, seed=1), BouncingBalls(fixed=True, seed=1)
    np.testing.assert_array_equal(a(clip, 7), b(clip, 7))
    np.testing.assert_array_equal(a(clip, 7), a(clip, 7))
    assert not np.array_equal(a(clip, 7), a(clip, 8))
    moving = BouncingBalls(seed=1)
    assert not np.array_equal(moving(clip, 7), moving(clip, 7))


def test_clips_are_float_windows_of_every_sequence():
    frames = np.arange(2 * 6 * 4 * 4 * 3, dtype=np.int64).reshape(2, 6, 4, 4, 3).astype(np.uint8)
    actions = np.arange(2 * 6 * 4, dtype=np.float32).reshape(2, 6, 4)
    clips = VideoClips(
        ArraySequences({"frames": frames, "actions": actions}), clip_length=4, sequence_length=6
    )
    assert len(clips) == 2 * 3
    item = clips[4]  # sequence 1, start 1
    assert item["frames"].shape == (4, 3, 4, 4) and item["frames"].dtype == torch.float32
    torch.testing.assert_close(
        item["frames"][0], torch.from_numpy(frames[1, 1]).permute(2, 0, 1).float() / 255
    )
    torch.testing.assert_close(item["actions"], torch.from_numpy(actions[1, 1:5]))
    one_per_sequence = VideoClips(
        ArraySequences({"frames": frames, "actions": actions}), clip_length=6, sequence_length=6, stride=6
    )
    assert len(one_per_sequence) == 2


def test_pusher_renders_headless_whatever_mujoco_gl_was_at_import():
    """``mujoco.Renderer`` would take GLFW (no display here) when mujoco was imported with ``MUJOCO_GL`` unset,
    as ``import torchrl.envs`` does; the pusher picks a headless backend itself, in the workers too."""
    import os
    import subprocess
    import sys

    code = (
        "import torchrl.envs, mujoco\n"
        "from isodream_rl.data.pusher import generate_pusher_sequences\n"
        "a = generate_pusher_sequences(2, 3, seed=1, workers=2)\n"
        "assert a['frames'].shape == (2, 3, 64, 64, 3) and a['frames'].std() > 0\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
