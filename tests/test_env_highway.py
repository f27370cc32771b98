import gymnasium as gym
import numpy as np
import pytest
from highway_env import utils
from highway_env.envs.highway_env import HighwayEnv
from highway_env.vehicle.kinematics import Vehicle

from isodream_rl.envs.highway import HIGHWAY_VIEWS, HighwayIsoEnv
from isodream_rl.envs.highway_sim import HighwaySimulator, _separated_on_first_axes
from isodream_rl.envs.highway_traffic import FastIDMVehicle

STRAIGHT = np.zeros(2, dtype=np.float32)


def _place(env: HighwayIsoEnv, vehicle: Vehicle, x: float, y: float, heading: float, speed: float) -> None:
    vehicle.position = np.array([x, y], dtype=np.float64)
    vehicle.heading = heading
    vehicle.speed = speed
    vehicle.on_state_update()


def _only_cruisers(env: HighwayIsoEnv, *states: tuple[float, float, float]) -> list[Vehicle]:
    """Replaces the traffic by plain vehicles at (dx ahead of the ego, y, speed) that keep their speed."""
    ego = env.ego
    others = [Vehicle(env.road, [ego.position[0] + dx, y], 0.0, speed) for dx, y, speed in states]
    env.road.vehicles[:] = [ego, *others]
    return others


def _red_columns(frame: np.ndarray) -> np.ndarray:
    """Columns of pixels painted like vehicle slot 0 (red)."""
    r, g, b = (frame[..., c].astype(int) for c in range(3))
    return np.nonzero((r > 110) & (g < 60) & (b < 60))[1]


@pytest.mark.parametrize("view", HIGHWAY_VIEWS)
def test_spaces_and_info_follow_the_contract(view):
    env = HighwayIsoEnv(view=view, vehicles_count=5)
    assert env.observation_space == gym.spaces.Box(0, 255, (64, 64, 3), np.uint8)
    assert env.action_space.shape == (2,) and env.action_space.dtype == np.float32
    assert (env.action_space.low == -1).all() and (env.action_space.high == 1).all()
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs) and isinstance(reward, float)
    assert isinstance(terminated, bool) and isinstance(truncated, bool)
    for key in ("progress", "collision_penalty", "steer_penalty", "crashed", "off_road", "ticks"):
        assert key in info
    assert info["ticks"] == 4
    env.close()


def test_same_seed_gives_same_episode_and_other_seed_differs():
    actions = np.random.default_rng(0).uniform(-0.05, 0.3, (12, 2)).astype(np.float32)

    def rollout(seed):
        env = HighwayIsoEnv(vehicles_count=10)
        frames, rewards = [env.reset(seed=seed)[0]], []
        for action in actions:
            obs, reward, terminated, truncated, _ = env.step(action)
            frames.append(obs)
            rewards.append(reward)
            if terminated or truncated:
                break
        env.close()
        return np.stack(frames), np.array(rewards)

    frames, rewards = rollout(7)
    frames_again, rewards_again = rollout(7)
    frames_other, _ = rollout(8)
    np.testing.assert_array_equal(frames, frames_again)
    np.testing.assert_array_equal(rewards, rewards_again)
    assert not np.array_equal(frames[0], frames_other[0])


def test_fast_simulator_reproduces_highway_env_trajectories():
    config = {
        "action": {"type": "ContinuousAction"},
        "simulation_frequency": 20,
        "policy_frequency": 20,
        "vehicles_count": 12,
    }
    trajectories, lane_changes = [], []
    for simulator in (HighwayEnv(config=config), HighwaySimulator(config=config)):
        simulator.reset(seed=9)
        states, changing = [], 0
        for tick in range(100):
            # Full throttle rams the traffic ahead (at tick 34 with this seed): crash handling is compared too.
            simulator.action_type.act(np.array([1.0, 0.02 * np.sin(tick / 10)]))
            simulator.road.act()
            simulator.road.step(0.05)
            states.append([[*v.position, v.heading, v.speed, v.crashed] for v in simulator.road.vehicles])
            changing += sum(v.lane_index != v.target_lane_index for v in simulator.road.vehicles[1:])
        trajectories.append(np.array(states))
        lane_changes.append(changing)
    stock, fast = trajectories
    assert isinstance(simulator.road.vehicles[1], FastIDMVehicle)
    assert stock[-1, 0, 4] == 1.0, "the ego should have crashed"
    assert lane_changes[0] > 0, "MOBIL lane changes should be compared too"
    np.testing.assert_array_equal(stock, fast)


def test_progress_is_velocity_along_the_lane_times_dt():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.1, speed=20.0)
    obs, reward, terminated, truncated, info = env.step(STRAIGHT)
    expected = 20.0 * np.cos(0.1) * 0.05  # straight wheels keep speed and heading on every tick
    assert info["progress"] == pytest.approx(expected, rel=1e-9)
    assert info["steer_penalty"] == 0.0 and info["collision_penalty"] == 0.0
    assert reward == pytest.approx(expected, rel=1e-9)
    assert not terminated and not truncated and info["speed"] == pytest.approx(20.0)
    env.close()


def test_steer_penalty_is_weight_times_abs_steer_and_reward_is_the_mean_of_terms():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0, steer_weight=2.0)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=10.0)
    obs, reward, terminated, truncated, info = env.step(np.array([-0.05, 0.0], dtype=np.float32))
    assert info["steer_penalty"] == pytest.approx(2.0 * 0.05)
    # Steering turns the ego, so each tick progresses less than the last; the reward averages the 4 ticks.
    assert 0.0 < info["progress"] < 10.0 * 0.05
    assert reward == pytest.approx(info["progress"] - info["steer_penalty"] - info["collision_penalty"])
    assert env.ego.heading < 0.0, "negative steer turns left (towards lower y)"
    env.close()


def test_rear_end_crash_costs_the_documented_impulse_and_terminates():
    env = HighwayIsoEnv(view="top_down", vehicles_count=1, collision_weight=1e-4)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=30.0)
    # 0.5 m between the bumpers, closing at 20 m/s: the cars overlap after the first tick.
    _only_cruisers(env, (5.5, 4.0, 10.0))
    obs, reward, terminated, truncated, info = env.step(STRAIGHT)
    impulse = 1500.0 / 2 * 20.0
    assert info["crashed"] and terminated and not truncated
    assert info["ticks"] == 1, "the action repeat stops at the terminal tick"
    assert info["collision_impulse"] == pytest.approx(impulse)
    assert info["collision_penalty"] == pytest.approx(1e-4 * impulse)
    assert reward == pytest.approx(30.0 * 0.05 - 1e-4 * impulse)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(STRAIGHT)
    env.close()


def test_truncates_after_exactly_250_steps_of_4_ticks():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0)
    env.reset(seed=1)
    steps, truncated, terminated = 0, False, False
    while not (truncated or terminated):
        _, _, terminated, truncated, info = env.step(STRAIGHT)
        steps += 1
    assert steps == 250 and truncated and not terminated
    assert info["ticks"] == 1000
    env.close()


def test_last_step_runs_only_the_remaining_ticks():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0, max_ticks=10)
    env.reset(seed=0)
    ticks = [env.step(STRAIGHT)[4]["ticks"] for _ in range(3)]
    assert ticks == [4, 8, 10]
    env.close()


def test_leaving_the_road_terminates():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0)
    env.reset(seed=0)
    # The rightmost lane (y = 12) ends at y = 14; heading right at 25 m/s moves 0.6 m sideways per tick.
    _place(env, env.ego, x=100.0, y=13.5, heading=0.5, speed=25.0)
    _, _, terminated, truncated, info = env.step(STRAIGHT)
    assert terminated and info["off_road"] and not info["crashed"] and info["ticks"] == 1
    env.close()


def test_braking_stops_without_reversing_and_a_stopped_ego_is_stuck_at_tick_100():
    env = HighwayIsoEnv(view="top_down", vehicles_count=0)
    env.reset(seed=0)
    brake = np.array([0.0, -1.0], dtype=np.float32)
    speeds = []
    terminated = False
    while not terminated:
        _, _, terminated, _, info = env.step(brake)
        speeds.append(info["speed"])
    # 25 m/s at -5 m/s^2 stops after 100 ticks, the first stuck check.
    assert info["stuck"] and info["ticks"] == 100 and len(speeds) == 25
    assert min(speeds) == 0.0
    env.close()


def test_first_person_frames_show_sky_road_and_change_as_the_ego_moves():
    env = HighwayIsoEnv(vehicles_count=0)
    first, _ = env.reset(seed=0)
    second = env.step(STRAIGHT)[0]
    for frame in (first, second):
        assert frame.mean() > 60
        top, bottom = frame[0].mean(axis=0), frame[-1].mean(axis=0)
        assert top[2] > top[0] + 40, "the top row is sky blue"
        assert abs(bottom[0] - bottom[2]) < 20 and bottom.mean() < 160, "the bottom row is grey asphalt"
    assert (first != second).any(axis=-1).mean() > 0.01, "the lane dashes move past"
    env.close()


@pytest.mark.parametrize(("lateral", "side"), [(4.0, "right"), (-4.0, "left"), (0.0, "centre")])
def test_first_person_view_puts_vehicles_on_their_side(lateral, side):
    env = HighwayIsoEnv(vehicles_count=1)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
    _only_cruisers(env, (15.0, 4.0 + lateral, 20.0))
    frame = env.step(STRAIGHT)[0]
    columns = _red_columns(frame)
    assert columns.size > 4, "the car ahead is visible"
    middle = frame.shape[1] / 2
    if side == "right":
        assert columns.mean() > middle + 8
    elif side == "left":
        assert columns.mean() < middle - 8
    else:
        assert abs(columns.mean() - middle) < 4
    env.close()


def test_top_down_view_follows_the_ego_with_driving_pointing_up():
    env = HighwayIsoEnv(view="top_down", vehicles_count=1)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
    _only_cruisers(env, (15.0, 4.0, 20.0))
    frame = env.step(STRAIGHT)[0].astype(int)
    # highway-env paints plain (non-IDM) vehicles yellow; the scaling is 1.5 px/m.
    yellow = np.argwhere((frame[..., 0] > 150) & (frame[..., 1] > 150) & (frame[..., 2] < 80))
    ego, ahead = yellow[yellow[:, 0] > 32], yellow[yellow[:, 0] <= 32]
    assert ego.size and ahead.size
    assert abs(ego[:, 1].mean() - 32) < 2 and abs(ego[:, 0].mean() - 64 * 0.7) < 2
    assert abs(ahead[:, 1].mean() - 32) < 2, "same lane, same column"
    assert ego[:, 0].mean() - ahead[:, 0].mean() == pytest.approx(15.0 * 1.5, abs=2), "15 m ahead is up"
    env.close()


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="'first_person', 'top_down'"):
        HighwayIsoEnv(view="bird")
    with pytest.raises(ValueError, match="vehicles_count"):
        HighwayIsoEnv(vehicles_count=-1)
    with pytest.raises(ValueError, match="render_mode"):
        HighwayIsoEnv(render_mode="human")
    env = HighwayIsoEnv(view="top_down", vehicles_count=0)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(STRAIGHT)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\).*got shape \(3,\)"):
        env.step(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.nan, 0.0]))
    env.close()


def test_first_person_renderer_makes_its_gl_context_at_the_first_render():
    env = HighwayIsoEnv(vehicles_count=2)
    renderer = env._renderer._renderer
    assert renderer.backend is None  # nothing to inherit through fork from a constructed env
    env.reset(seed=0)
    assert renderer.backend in ("egl", "osmesa", "glfw")
    env.close()


def test_collision_prefilter_never_dismisses_a_pair_the_exact_check_finds_touching():
    rng = np.random.default_rng(0)
    n, dt = 3000, 0.05
    # Pairs around contact: b offset by about a car length or width (often just touching), any headings.
    offset = np.stack([rng.choice([0.0, 5.0, -5.0], n), rng.choice([0.0, 2.0, -2.0, 4.0], n)], axis=1)
    offset += rng.normal(0.0, 0.3, (n, 2))
    headings = np.where(
        rng.random((n, 2)) < 0.7, rng.normal(0.0, 0.05, (n, 2)), rng.uniform(-np.pi, np.pi, (n, 2))
    )
    speeds = rng.uniform(0.0, 40.0, (n, 2))
    vehicles = []
    for k in range(n):
        vehicles.append(Vehicle(None, [0.0, 0.0], headings[k, 0], speeds[k, 0]))
        vehicles.append(Vehicle(None, offset[k], headings[k, 1], speeds[k, 1]))
    xy = np.array([v.position for v in vehicles])
    speed = np.array([v.speed for v in vehicles])
    rows, cols = np.arange(0, 2 * n, 2), np.arange(1, 2 * n, 2)
    dismissed = _separated_on_first_axes(vehicles, rows, cols, xy, speed, dt)
    touching = np.array(
        [
            any(
                utils.are_polygons_intersecting(a.polygon(), b.polygon(), a.velocity * dt, b.velocity * dt)[
                    :2
                ]
            )
            for a, b in zip(vehicles[0::2], vehicles[1::2], strict=True)
        ]
    )
    assert touching.any() and dismissed.any() and not touching.all()
    assert not (dismissed & touching).any()


def _frame_without(env: HighwayIsoEnv, keep) -> np.ndarray:
    """The current view drawn again with only the vehicles ``keep`` selects (the road state is restored)."""
    vehicles = list(env.road.vehicles)
    env.road.vehicles[:] = [v for v in vehicles if keep(v)]
    try:
        if env.view == "first_person":
            return env._renderer.render(env.ego, [v for v in env.road.vehicles if v is not env.ego])
        return env._renderer.render(env.road, env.ego)
    finally:
        env.road.vehicles[:] = vehicles


@pytest.mark.parametrize(
    ("view", "top_down"),
    [(view, {}) for view in HIGHWAY_VIEWS]
    + [
        ("top_down", {"top_down_follow": "road"}),
        ("top_down", {"top_down_follow": "road", "top_down_scaling": 2.5}),
    ],
    ids=["first_person", "top_down", "top_down-road", "top_down-road-2.5"],
)
def test_masks_are_exactly_the_pixels_each_vehicle_group_is_drawn_on(view, top_down):
    env = HighwayIsoEnv(view=view, vehicles_count=2, **top_down)
    obs, info = env.reset(seed=0)
    assert {"mask_agent", "mask_vehicles", "mask_distractors"} <= set(info)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
    _only_cruisers(env, (12.0, 4.0, 20.0), (20.0, 8.0, 20.0))
    obs, *_, info = env.step(STRAIGHT)
    agent, vehicles = info["mask_agent"], info["mask_vehicles"]
    for mask in (agent, vehicles, info["mask_distractors"]):
        assert mask.shape == obs.shape[:2] and mask.dtype == bool
    np.testing.assert_array_equal(vehicles, info["mask_distractors"])
    assert vehicles.sum() > 10 and not (agent & vehicles).any()
    # the pixels that change when the other vehicles are left out are exactly mask_vehicles, and likewise
    # for the ego (drawn in the top-down view only: the first-person camera rides on it)
    without_others = _frame_without(env, lambda v: v is env.ego)
    np.testing.assert_array_equal((obs != without_others).any(-1), vehicles)
    without_ego = _frame_without(env, lambda v: v is not env.ego)
    np.testing.assert_array_equal((obs != without_ego).any(-1), agent)
    assert agent.sum() > 10 if view == "top_down" else not agent.any()
    env.close()


def test_a_vehicle_drawn_over_the_ego_hides_it_in_the_masks():
    env = HighwayIsoEnv(view="top_down", vehicles_count=1)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
    _only_cruisers(env, (2.0, 4.5, 20.0))  # overlapping the ego, drawn after it
    alone = env._renderer.masks(env.road, env.ego)
    env.road.vehicles[:] = [env.ego]
    ego_alone, _ = env._renderer.masks(env.road, env.ego)
    agent, vehicles = alone
    assert (ego_alone & vehicles).any() and not (agent & vehicles).any()
    np.testing.assert_array_equal(agent | (ego_alone & vehicles), ego_alone)
    env.close()


def test_masks_can_be_switched_off():
    env = HighwayIsoEnv(view="top_down", vehicles_count=2, masks=False)
    _, info = env.reset(seed=0)
    assert "mask_agent" not in info and "mask_agent" not in env.step(STRAIGHT)[-1]
    env.close()


def _ego_column_and_lateral(follow: str, scaling: float, steers) -> tuple[np.ndarray, np.ndarray]:
    """The ego mask's centroid column and the ego's highway-env y, from a placed start (lane 1, heading 0, no
    traffic) and after each steer of ``steers``."""
    env = HighwayIsoEnv(view="top_down", vehicles_count=0, top_down_follow=follow, top_down_scaling=scaling)
    env.reset(seed=0)
    _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
    _only_cruisers(env)
    info = env.step(STRAIGHT)[-1]
    columns, lateral = [], []
    for steer in [None, *steers]:
        if steer is not None:
            *_, terminated, _, info = env.step(np.array([steer, 0.0], dtype=np.float32))
            assert not terminated
        columns.append(np.nonzero(info["mask_agent"])[1].mean())
        lateral.append(env.ego.position[1])
    env.close()
    return np.array(columns), np.array(lateral)


@pytest.mark.parametrize("scaling", [1.5, 2.5])
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_the_road_view_shows_the_ego_steering_across_the_frame_and_the_ego_view_does_not(scaling, side):
    # an S: 2 m towards one side, ending straight (heading 0 again) so the ego's sprite is not turned
    steers = side * np.array([0.2, 0.2, -0.2, -0.2, 0.0])
    ego_columns, lateral = _ego_column_and_lateral("ego", scaling, steers)
    road_columns, road_lateral = _ego_column_and_lateral("road", scaling, steers)
    np.testing.assert_array_equal(lateral, road_lateral)  # the view does not change the driving
    assert abs(lateral[-1] - lateral[0]) > 1.9
    moved = (lateral[-1] - lateral[0]) * scaling  # pixels; +y (the driver's right) is the frame's right
    # ego-centred: the ego's pixels only wobble as its sprite turns, and are back where they were once straight
    assert np.abs(ego_columns - ego_columns[0]).max() < 1
    assert ego_columns[-1] == ego_columns[0]
    # road-centred: the ego crosses the frame by its lateral motion (to a pixel of rounding)
    shift = road_columns[-1] - road_columns[0]
    assert abs(shift) >= 2.5 and np.sign(shift) == side
    assert abs(shift - moved) <= 1.5


def test_the_road_view_keeps_the_whole_road_in_view_and_its_masks_exact_while_steering():
    env = HighwayIsoEnv(view="top_down", vehicles_count=20, top_down_follow="road", top_down_scaling=2.5)
    obs, info = env.reset(seed=0)
    rng = np.random.default_rng(0)
    columns, frames = [], 0
    while True:
        agent, vehicles = info["mask_agent"], info["mask_vehicles"]
        assert not (agent & vehicles).any()
        if env.ego.on_road:
            assert agent.any()
            columns.append(np.nonzero(agent)[1].mean())
        np.testing.assert_array_equal((obs != _frame_without(env, lambda v: v is not env.ego)).any(-1), agent)
        np.testing.assert_array_equal((obs != _frame_without(env, lambda v: v is env.ego)).any(-1), vehicles)
        frames += 1
        if frames == 25:
            break
        obs, _, terminated, truncated, info = env.step(
            np.array([rng.uniform(-0.2, 0.2), 0.1], dtype=np.float32)
        )
        if terminated or truncated:
            break
    assert frames >= 5 and np.ptp(columns) >= 2, (frames, columns)
    # the paved road (its two edge lines) spans the same columns in every frame, within the image
    grass = (obs.astype(int) == (71, 128, 51)).all(-1)
    paved = np.nonzero(~grass.all(0))[0]
    assert 0 < paved[0] and paved[-1] < 63 and paved[-1] - paved[0] + 1 == pytest.approx(16 * 2.5, abs=2)
    env.close()


@pytest.mark.parametrize("follow", ["ego", "road"])
def test_a_larger_top_down_scaling_draws_a_larger_ego(follow):
    counts = []
    for scaling in (1.5, 2.5):
        env = HighwayIsoEnv(
            view="top_down", vehicles_count=0, top_down_follow=follow, top_down_scaling=scaling
        )
        env.reset(seed=0)
        _place(env, env.ego, x=100.0, y=4.0, heading=0.0, speed=20.0)
        counts.append(env.step(STRAIGHT)[-1]["mask_agent"].sum())
        env.close()
    # a 5 m x 2 m car: about 7x3 pixels at 1.5 px/m, 12x5 at 2.5
    assert 15 <= counts[0] <= 30 and counts[1] > 2 * counts[0], counts


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"view": "top_down", "top_down_follow": "lane"}, r"top_down_follow 'lane'.*'ego', 'road'"),
        ({"view": "top_down", "top_down_follow": None}, r"top_down_follow None"),
        ({"view": "top_down", "top_down_scaling": 0}, r"top_down_scaling .*> 0, got 0"),
        ({"view": "top_down", "top_down_scaling": -1.5}, r"top_down_scaling .*got -1.5"),
        ({"view": "top_down", "top_down_scaling": float("nan")}, r"top_down_scaling .*got nan"),
        ({"view": "top_down", "top_down_scaling": "2"}, r"top_down_scaling .*got '2'"),
        ({"top_down_follow": "road"}, r"view='top_down' only.*top_down_follow='road'"),
        ({"view": "first_person", "top_down_scaling": 2.5}, r"view='top_down' only.*top_down_scaling=2.5"),
        (
            {"view": "top_down", "top_down_follow": "road", "top_down_scaling": 5.0},
            r"whole road in view.*top_down_scaling=5.0.*80 pixels wide",
        ),
    ],
)
def test_bad_top_down_options_raise_clear_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        HighwayIsoEnv(vehicles_count=0, **kwargs)


def test_the_default_top_down_options_are_accepted_with_either_view():
    for view in HIGHWAY_VIEWS:
        HighwayIsoEnv(view=view, vehicles_count=0, top_down_follow="ego", top_down_scaling=1.5).close()
    # an ego-centred view may zoom in further than the road fits
    HighwayIsoEnv(view="top_down", vehicles_count=0, top_down_scaling=5.0).close()
