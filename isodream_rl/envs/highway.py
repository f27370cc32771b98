"""CARLA-like highway driving on highway-env: the paper's CARLA task (§4.3, Appendix A) without CARLA.

A straight highway (4 lanes by default) with other vehicles driven by highway-env's own IDM/MOBIL models, a 20 Hz
simulation, continuous [steer, throttle/brake] actions repeated for 4 ticks, and the paper's reward
r = v_ego . u_lane * dt - xi1 * I - xi2 * |steer|. Observations are 64x64 RGB frames from a forward camera on the
ego's roof (``view="first_person"``) or from an ego-centred top-down chase view (``view="top_down"``).

highway-env is slow at 20 Hz with 30 vehicles, so the simulation runs on :mod:`isodream_rl.envs.highway_sim`: the
same road, vehicles and models specialised to straight lanes and vectorised over vehicles, with bit-identical
trajectories and several times faster (measured in docs/envs/highway.md).
"""

from __future__ import annotations

import numbers

import gymnasium as gym
import numpy as np
from highway_env import utils
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road
from highway_env.vehicle.kinematics import Vehicle

from isodream_rl.envs.highway_render import CHASE_VIEW_FOLLOWS, ChaseViewRenderer, FirstPersonRenderer
from isodream_rl.envs.highway_sim import HighwaySimulator

HIGHWAY_VIEWS = ("first_person", "top_down")
"""Observation views of :class:`HighwayIsoEnv`."""

HIGHWAY_TOP_DOWN_FOLLOWS = CHASE_VIEW_FOLLOWS
"""What the top-down view's camera follows (``top_down_follow`` of :class:`HighwayIsoEnv`): ``"ego"`` or
``"road"``."""

SIMULATION_FREQUENCY = 20
"""Simulation ticks per second (dt = 0.05 s), as the authors' synchronous CARLA."""


def _is_number(value) -> bool:
    """A real number, not a bool or a string (whose comparisons would fail without naming the argument)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


class HighwayIsoEnv(gym.Env):
    """CARLA-like highway driving from pixels (the paper's CARLA task on highway-env).

    Each agent step repeats the action for ``action_repeat`` ticks of dt = 0.05 s and returns the mean of the per-tick
    rewards (as the authors' CARLA env), so the default 1000 ticks are 250 agent steps. The per-tick reward is

        r = v_ego . u_lane * dt - collision_weight * I - steer_weight * |steer|

    with ``v_ego`` highway-env's velocity of the ego, ``u_lane`` the unit direction of its closest lane, and ``I``
    a collision impulse proxy (highway-env has no contact physics): on the tick the ego first crashes, the impulse
    of a perfectly inelastic collision of two equal cars, ``I = vehicle_mass / 2 * |v_ego - v_other|`` in N s,
    summed over the vehicles it overlaps.

    The episode terminates when the ego crashes, leaves the road (its centre beyond the road edge) or is stuck
    (speed below ``stuck_speed`` at a multiple of ``stuck_check_ticks`` ticks), and is truncated at ``max_ticks``
    ticks. Unlike the authors' CARLA, a crash ends the episode: highway-env then takes the ego's controls for good
    (it brakes to a stop and the crash flag never clears), so the rest of the episode would show actions without
    effect, contradicting the controllable/noncontrollable split Iso-Dream learns.

    Args:
        view (str, optional): ``"first_person"`` (forward roof camera, 60 degree field of view, as in the paper) or
            ``"top_down"`` (a chase view from above: ``top_down_follow``). Defaults to ``"first_person"``.
        vehicles_count (int, optional): other vehicles. Defaults to 30.
        lanes_count (int, optional): lanes of the highway. Defaults to 4.
        action_repeat (int, optional): ticks per agent step. Defaults to 4.
        max_ticks (int, optional): ticks per episode before truncation. Defaults to 1000.
        image_size (int, optional): side of the square observation. Defaults to 64.
        collision_weight (float, optional): xi1, weight of the collision impulse. Defaults to 1e-4.
        steer_weight (float, optional): xi2, weight of |steer|. Defaults to 1.0.
        render_mode (str, optional): ``None`` or ``"rgb_array"`` (``render()`` returns the last observation).
        vehicle_mass (float, optional): mass of every car in kg, for the impulse proxy. Defaults to 1500.
        vehicles_density (float, optional): highway-env's traffic density (1: about 20 m between spawned
            vehicles). Defaults to 1.0.
        stuck_speed (float, optional): speed in m/s under which the ego counts as stuck. Defaults to 0.02.
        stuck_check_ticks (int, optional): the stuck check runs every this many ticks. Defaults to 100.
        masks (bool, optional): put the ground-truth masks in ``info`` at every reset and step (below; one
            more drawing of the vehicles per frame, a segmentation pass in the first-person view). Defaults to
            ``True`` (``make_env`` and ``make_gym_env``: off unless ``return_masks=True``).
        top_down_follow (str, optional): what the top-down view's camera follows. ``"ego"``: it is centred on
            the ego, which then stays at the same pixels in every frame (only the road shifts sideways when the
            ego changes lane). ``"road"``: it follows the ego along the road but stays centred on the road's
            centre line (the middle of all lanes), so steering and lane changes move the ego across the frame:
            the ego's own motion is visible, which the decomposition scores need. The whole road width must fit
            in the image (``lanes_count * 4 m * top_down_scaling <= image_size``). Top-down view only.
            Defaults to ``"ego"``.
        top_down_scaling (float, optional): pixels per metre of the top-down view (at 1.5, 43 m of road and a
            3x7 pixel ego in a 64x64 frame). Top-down view only. Defaults to 1.5.

    Ground truth (``masks=True``), bool ``[image_size, image_size]`` at the observation's resolution, exact to
    the pixel and disjoint:

    - ``info["mask_agent"]``: the visible pixels of the ego (top-down view); the first-person camera sits on
      the ego's roof and the ego is not drawn, so there it is all ``False``;
    - ``info["mask_vehicles"]``: the visible pixels of the other vehicles;
    - ``info["mask_distractors"]``: the same pixels as ``mask_vehicles``, under the name every env uses for
      its moving noncontrollable things (:func:`isodream_rl.evaluation.decomposition_scores`).

    Examples:
        >>> env = HighwayIsoEnv(vehicles_count=10)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, obs.dtype
        ((64, 64, 3), dtype('uint8'))
        >>> obs, reward, terminated, truncated, info = env.step(np.array([0.0, 0.2], dtype=np.float32))
        >>> info["ticks"]
        4
        >>> env.close()
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": SIMULATION_FREQUENCY}

    def __init__(
        self,
        *,
        view: str = "first_person",
        vehicles_count: int = 30,
        lanes_count: int = 4,
        action_repeat: int = 4,
        max_ticks: int = 1000,
        image_size: int = 64,
        collision_weight: float = 1e-4,
        steer_weight: float = 1.0,
        render_mode: str | None = None,
        vehicle_mass: float = 1500.0,
        vehicles_density: float = 1.0,
        stuck_speed: float = 0.02,
        stuck_check_ticks: int = 100,
        masks: bool = True,
        top_down_follow: str = "ego",
        top_down_scaling: float = 1.5,
    ) -> None:
        if view not in HIGHWAY_VIEWS:
            raise ValueError(f"Unknown view {view!r}. Valid views: {', '.join(map(repr, HIGHWAY_VIEWS))}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"Unknown render_mode {render_mode!r}. Valid: None, 'rgb_array'")
        for name, value, low in (
            ("vehicles_count", vehicles_count, 0),
            ("lanes_count", lanes_count, 1),
            ("action_repeat", action_repeat, 1),
            ("max_ticks", max_ticks, 1),
            ("image_size", image_size, 8),
            ("stuck_check_ticks", stuck_check_ticks, 1),
        ):
            if not _is_number(value) or int(value) != value or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        for name, value in (
            ("collision_weight", collision_weight),
            ("steer_weight", steer_weight),
            ("vehicle_mass", vehicle_mass),
            ("stuck_speed", stuck_speed),
        ):
            if not _is_number(value) or not value >= 0:
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        if not _is_number(vehicles_density) or not vehicles_density > 0:
            raise ValueError(f"vehicles_density must be > 0, got {vehicles_density!r}")
        if not isinstance(top_down_follow, str) or top_down_follow not in HIGHWAY_TOP_DOWN_FOLLOWS:
            raise ValueError(
                f"Unknown top_down_follow {top_down_follow!r}. "
                f"Valid: {', '.join(map(repr, HIGHWAY_TOP_DOWN_FOLLOWS))}"
            )
        if not _is_number(top_down_scaling) or not 0 < top_down_scaling < np.inf:
            raise ValueError(f"top_down_scaling must be a finite number > 0, got {top_down_scaling!r}")
        if view != "top_down" and (top_down_follow != "ego" or top_down_scaling != 1.5):
            raise ValueError(
                f"top_down_follow and top_down_scaling apply to view='top_down' only; with view={view!r} leave "
                f"them at their defaults ('ego', 1.5), got top_down_follow={top_down_follow!r}, "
                f"top_down_scaling={top_down_scaling!r}"
            )
        road_pixels = lanes_count * StraightLane.DEFAULT_WIDTH * top_down_scaling
        if top_down_follow == "road" and road_pixels > image_size:
            raise ValueError(
                f"top_down_follow='road' needs the whole road in view, but {lanes_count} lanes of "
                f"{StraightLane.DEFAULT_WIDTH:g} m at top_down_scaling={top_down_scaling!r} px/m are "
                f"{road_pixels:g} pixels wide, more than image_size={image_size}"
            )
        self.view = view
        self.vehicles_count = int(vehicles_count)
        self.lanes_count = int(lanes_count)
        self.action_repeat = int(action_repeat)
        self.max_ticks = int(max_ticks)
        self.image_size = int(image_size)
        self.collision_weight = float(collision_weight)
        self.steer_weight = float(steer_weight)
        self.render_mode = render_mode
        self.vehicle_mass = float(vehicle_mass)
        self.stuck_speed = float(stuck_speed)
        self.stuck_check_ticks = int(stuck_check_ticks)
        self.masks = bool(masks)
        self.top_down_follow = top_down_follow
        self.top_down_scaling = float(top_down_scaling)
        self.dt = 1.0 / SIMULATION_FREQUENCY
        self.metadata = {**self.metadata, "render_fps": SIMULATION_FREQUENCY / self.action_repeat}
        self.observation_space = gym.spaces.Box(0, 255, (self.image_size, self.image_size, 3), np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

        self._sim = HighwaySimulator(
            config={
                "action": {"type": "ContinuousAction"},
                # highway-env's default Kinematics observation (pandas) is costly and unused here.
                "observation": {"type": "AttributesObservation", "attributes": []},
                "simulation_frequency": SIMULATION_FREQUENCY,
                "policy_frequency": SIMULATION_FREQUENCY,
                "lanes_count": self.lanes_count,
                "vehicles_count": self.vehicles_count,
                "vehicles_density": float(vehicles_density),
                "duration": self.max_ticks * self.dt,
                "offscreen_rendering": True,
            }
        )
        if view == "first_person":
            self._renderer = FirstPersonRenderer(
                lanes_count=self.lanes_count, max_vehicles=self.vehicles_count, image_size=self.image_size
            )
        else:
            self._renderer = ChaseViewRenderer(
                image_size=self.image_size, scaling=self.top_down_scaling, follow=self.top_down_follow
            )
        self._ticks = 0
        self._done = True
        self._crashed_before = False
        self._last_obs: np.ndarray | None = None

    @property
    def road(self) -> Road:
        """highway-env's road: lanes and vehicles (the ego included)."""
        return self._sim.road

    @property
    def ego(self) -> Vehicle:
        """The vehicle the agent drives."""
        return self._sim.vehicle

    @property
    def ticks(self) -> int:
        """Simulation ticks since the last reset."""
        return self._ticks

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Starts an episode: new traffic, the ego at 25 m/s in a random lane.

        Args:
            seed (int, optional): seeds this episode and the following ones.
            options (dict, optional): unused.

        Returns:
            tuple: uint8 observation [image_size, image_size, 3] and the info dict (all reward terms zero).
        """
        super().reset(seed=seed)
        self._sim.reset(seed=int(self.np_random.integers(2**31 - 1)))
        self._ticks = 0
        self._done = False
        self._crashed_before = False
        self._last_obs = self._observe()
        info = self._info(progress=0.0, collision=0.0, steer=0.0, impulse=0.0, stuck=False)
        info["distance"] = 0.0
        return self._last_obs, self._with_masks(info)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Applies [steer, throttle/brake] for ``action_repeat`` ticks (fewer if the episode ends sooner).

        Args:
            action (np.ndarray): shape [2], clipped to [-1, 1]. steer -1 is full left (highway-env's pi/4 rad
                wheel angle); throttle/brake +-1 is +-5 m/s^2, and braking stops the car without reversing.

        Returns:
            tuple: observation [image_size, image_size, 3] uint8, reward (mean over the ticks run), terminated,
            truncated, and info with the mean reward terms ``progress``, ``collision_penalty``,
            ``steer_penalty``, and ``collision_impulse`` (N s, summed), ``distance`` (metres along the lane
            over the ticks run, summed), ``crashed``, ``off_road``, ``stuck``, ``speed`` (m/s) and ``ticks``.
        """
        if self._done:
            raise RuntimeError("step() called on a finished episode (or before reset()); call reset() first")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (2,):
            raise ValueError(
                f"expected an action of shape (2,) [steer, throttle/brake], got shape {action.shape}"
            )
        if not np.isfinite(action).all():
            raise ValueError(f"the action must be finite, got {action}")
        steer, throttle = np.clip(action, -1.0, 1.0)
        totals = np.zeros(4)  # progress, collision penalty, steer penalty, impulse
        ticks_run = 0
        terminated = stuck = False
        for _ in range(min(self.action_repeat, self.max_ticks - self._ticks)):
            self._tick(steer, throttle)
            ticks_run += 1
            impulse = self._collision_impulse()
            progress = self.progress()
            totals += (progress, self.collision_weight * impulse, self.steer_weight * abs(steer), impulse)
            stuck = self._ticks % self.stuck_check_ticks == 0 and self.ego.speed < self.stuck_speed
            terminated = self.ego.crashed or not self.ego.on_road or stuck
            if terminated:
                break
        truncated = self._ticks >= self.max_ticks
        self._done = terminated or truncated
        progress, collision, steer_penalty = totals[:3] / ticks_run
        reward = progress - collision - steer_penalty
        self._last_obs = self._observe()
        info = self._info(
            progress=progress, collision=collision, steer=steer_penalty, impulse=totals[3], stuck=stuck
        )
        info["distance"] = float(totals[0])
        return self._last_obs, float(reward), bool(terminated), bool(truncated), self._with_masks(info)

    def progress(self) -> float:
        """The progress term v_ego . u_lane * dt of the current state, in metres (the reward before penalties)."""
        ego = self.ego
        lane = ego.lane
        longitudinal = lane.local_coordinates(ego.position)[0]
        heading = lane.heading_at(longitudinal)
        return float(ego.velocity @ np.array([np.cos(heading), np.sin(heading)])) * self.dt

    def render(self) -> np.ndarray | None:
        """The last observation (``render_mode="rgb_array"``), or ``None``."""
        if self.render_mode != "rgb_array" or self._last_obs is None:
            return None
        return self._last_obs.copy()

    def close(self) -> None:
        if self.view == "first_person":
            self._renderer.close()
        self._sim.close()

    def _tick(self, steer: float, throttle: float) -> None:
        # highway-env's ContinuousAction is ordered [acceleration, steering]. It is applied on every tick because
        # the vehicle clips its stored command in place (speed limit, crash).
        self._sim.action_type.act(np.array([throttle, steer]))
        self.road.act()
        self.road.step(self.dt)
        # CARLA's brake stops the car; highway-env's kinematics would drive it backwards.
        self.ego.speed = max(self.ego.speed, 0.0)
        self._ticks += 1

    def _collision_impulse(self) -> float:
        """Impulse proxy in N s: nonzero on the tick the ego first crashes (highway-env's crash flag never clears)."""
        ego = self.ego
        if not ego.crashed or self._crashed_before:
            return 0.0
        self._crashed_before = True
        others = [v for v in self.road.vehicles if v is not ego]
        if not others:
            return 0.0
        zero = np.zeros(2)
        # A crash is flagged when the polygons overlap after the tick, so the partners overlap the ego now.
        partners = [
            v for v in others if utils.are_polygons_intersecting(ego.polygon(), v.polygon(), zero, zero)[0]
        ]
        if not partners:
            partners = [min(others, key=lambda v: np.linalg.norm(v.position - ego.position))]
        return sum(
            0.5 * self.vehicle_mass * float(np.linalg.norm(ego.velocity - v.velocity)) for v in partners
        )

    def _observe(self) -> np.ndarray:
        if self.view == "first_person":
            others = [v for v in self.road.vehicles if v is not self.ego]
            return self._renderer.render(self.ego, others)
        return self._renderer.render(self.road, self.ego)

    def _with_masks(self, info: dict) -> dict:
        """``info`` with the ground-truth masks of the last observation (see the class docstring)."""
        if not self.masks:
            return info
        if self.view == "first_person":
            vehicles = self._renderer.vehicle_mask()
            agent = np.zeros_like(vehicles)
        else:
            agent, vehicles = self._renderer.masks(self.road, self.ego)
        info.update(mask_agent=agent, mask_vehicles=vehicles, mask_distractors=vehicles.copy())
        return info

    def _info(self, *, progress: float, collision: float, steer: float, impulse: float, stuck: bool) -> dict:
        return {
            "progress": float(progress),
            "collision_penalty": float(collision),
            "steer_penalty": float(steer),
            "collision_impulse": float(impulse),
            "crashed": bool(self.ego.crashed),
            "off_road": not self.ego.on_road,
            "stuck": bool(stuck),
            "speed": float(self.ego.speed),
            "ticks": self._ticks,
        }
