"""highway-env's highway simulation, specialised to a straight road for speed, with the same trajectories.

At 20 Hz with 30 vehicles, stock highway-env spends about 6 ms per tick on this CPU: lane geometry, the O(n^2)
neighbour search and collision pre-checks, and per-vehicle controller code that calls numpy on Python scalars
(``np.clip`` on a float alone costs microseconds). The classes here replace those hot spots for a road of parallel
straight lanes along +x. Every floating-point operation that decides a trajectory is kept in the same order and
with the same function (numpy's ``arcsin``, ``arctan``, ``tan``, ``power`` and ``dot`` differ from ``math`` in the
last bit on this CPU, so they stay numpy), which keeps vehicle trajectories bit-identical to highway-env's
(``tests/test_env_highway.py`` checks it).
"""

from __future__ import annotations

import math
from bisect import bisect_left
from typing import Any

import numpy as np
from highway_env import utils
from highway_env.envs.highway_env import HighwayEnv
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

__all__ = ["FastIDMVehicle", "HighwaySimulator"]

_LANE_WIDTH = StraightLane.DEFAULT_WIDTH
_ROAD_LENGTH = 10_000.0  # metres; an ego at the 40 m/s speed cap covers 2 km in a 1000-tick episode


class _AxisLane(StraightLane):
    """A straight lane along +x: its lane coordinates are plain differences instead of two dot products.

    The results are bit-identical: the direction vectors are exactly (1, 0) and (-0, 1).
    """

    def __init__(self, start: np.ndarray, end: np.ndarray, **kwargs: Any) -> None:
        super().__init__(start, end, **kwargs)
        if self.start[1] != self.end[1] or self.end[0] <= self.start[0]:
            raise ValueError(f"an _AxisLane runs along +x, got start={self.start} and end={self.end}")
        self._x0, self._y0 = float(self.start[0]), float(self.start[1])

    def local_coordinates(self, position: np.ndarray) -> tuple[float, float]:
        return float(position[0]) - self._x0, float(position[1]) - self._y0


class _StraightHighwayNetwork(RoadNetwork):
    """Parallel lanes along +x, like ``RoadNetwork.straight_road_network``, with a constant-time closest lane.

    The lanes share their heading and extent, so the heading and end terms of ``RoadNetwork``'s lane distance are
    equal for all lanes and the closest lane is the one with the nearest centre line (first one on a tie).
    """

    def __init__(self, *, lanes_count: int, speed_limit: float = 30.0) -> None:
        super().__init__()
        self._centres = [lane * _LANE_WIDTH for lane in range(lanes_count)]
        for lane, y in enumerate(self._centres):
            line_types = (
                LineType.CONTINUOUS_LINE if lane == 0 else LineType.STRIPED,
                LineType.CONTINUOUS_LINE if lane == lanes_count - 1 else LineType.NONE,
            )
            self.add_lane(
                "0",
                "1",
                _AxisLane([0.0, y], [_ROAD_LENGTH, y], line_types=line_types, speed_limit=speed_limit),
            )

    def get_closest_lane_index(self, position: np.ndarray, heading: float | None = None) -> LaneIndex:
        y = float(position[1])
        distances = [abs(y - centre) for centre in self._centres]
        return "0", "1", distances.index(min(distances))


class _StraightHighwayRoad(Road):
    """highway-env's ``Road`` with the two O(n^2) hot spots replaced, for a road of ``_AxisLane``s only.

    - ``neighbour_vehicles`` (front and rear vehicle in a lane, called ~35 times per tick by IDM and MOBIL): while
      ``act`` runs positions are fixed, so each lane's vehicles are sorted once per tick and searched by bisection.
      Ties resolve as in ``Road``: the last of equal front vehicles, the first of equal rear ones.
    - the collision checks after ``step``: vectorised tests select the pairs that ``Road`` would not dismiss by its
      distance pre-check and that may touch, and only those get the exact polygon check, in ``Road``'s order.
    """

    _lanes_at_act: dict[LaneIndex, list[tuple[float, int]]] | None = None
    _index_at_act: dict[int, int] | None = None
    _xy_at_act: np.ndarray | None = None

    def act(self) -> None:
        vehicles = self.vehicles
        self._lanes_at_act, self._index_at_act = {}, {id(v): i for i, v in enumerate(vehicles)}
        self._xy_at_act = np.array([v.position for v in vehicles], dtype=np.float64).reshape(-1, 2)
        try:
            if self.objects:
                super().act()
                return
            batch = []
            for vehicle in vehicles:
                if type(vehicle) is not FastIDMVehicle:
                    vehicle.act()
                elif not vehicle.crashed:
                    # Lane decisions in road order, as IDMVehicle.act makes them: MOBIL's abort rule reads the
                    # target lanes of the vehicles that decided before in this tick. Nothing else read by the
                    # controllers below changes during act, so they can run for all vehicles at once afterwards.
                    vehicle.follow_road()
                    if vehicle.enable_lane_change:
                        vehicle.change_lane_policy()
                    batch.append(vehicle)
            if batch:
                self._set_idm_actions(batch)
        finally:
            self._lanes_at_act = self._index_at_act = self._xy_at_act = None

    def _set_idm_actions(self, batch: list[FastIDMVehicle]) -> None:
        """``IDMVehicle.act``'s steering and acceleration commands for ``batch``, vectorised over vehicles.

        numpy's elementwise functions give the same bits on arrays as on the scalars highway-env passes them, so
        the steering controller (``ControlledVehicle.steering_control``) and IDM's acceleration run on arrays
        (``np.vecdot`` for the ``np.dot`` of highway-env's desired gap: the same inner loop).
        """
        cls = FastIDMVehicle
        n = len(batch)
        xy = np.array([v.position for v in batch], dtype=np.float64).reshape(n, 2)
        speed = np.array([v.speed for v in batch], dtype=np.float64)
        heading = np.array([v.heading for v in batch], dtype=np.float64)
        target_lanes = [self.network.get_lane(v.target_lane_index) for v in batch]
        # Steering towards the target lane's centre line (a straight lane's heading is the same everywhere).
        lateral = xy[:, 1] - np.array([lane.start[1] for lane in target_lanes])
        lane_heading = np.array([lane.heading for lane in target_lanes], dtype=np.float64)
        speed_not_zero = _not_zero(speed)
        lateral_speed_command = -cls.KP_LATERAL * lateral
        heading_command = np.arcsin(_clip_array(lateral_speed_command / speed_not_zero, -1, 1))
        heading_ref = lane_heading + _clip_array(heading_command, -np.pi / 4, np.pi / 4)
        heading_rate_command = cls.KP_HEADING * (((heading_ref - heading) + np.pi) % (2 * np.pi) - np.pi)
        length = np.array([v.LENGTH for v in batch], dtype=np.float64)
        slip_angle = np.arcsin(_clip_array(length / 2 / speed_not_zero * heading_rate_command, -1, 1))
        steering = _clip_array(
            np.arctan(2 * np.tan(slip_angle)), -cls.MAX_STEERING_ANGLE, cls.MAX_STEERING_ANGLE
        )
        # IDM's free-road term, 3 * (1 - (v / v0)^delta), with v0 the target speed capped by the lane's limit.
        target_speed = np.array(
            [
                _clip(v.target_speed, 0, v.lane.speed_limit)
                if v.lane and v.lane.speed_limit is not None
                else v.target_speed
                for v in batch
            ],
            dtype=np.float64,
        )
        ratio = np.maximum(speed, 0) / np.abs(_not_zero(target_speed))
        delta = np.array([v.DELTA for v in batch], dtype=np.float64)
        free_road = cls.COMFORT_ACC_MAX * (1 - np.power(ratio, delta))
        # The IDM acceleration in the current lane and, while changing lane, in the target lane too: one entry
        # per (vehicle, lane), with the interaction term where the lane has a front vehicle.
        owner, fronts, acceleration = (
            [],
            [],
            free_road[[k for k, v in enumerate(batch) for _ in _idm_lanes(v)]],
        )
        entry = 0
        for k, vehicle in enumerate(batch):
            for lane_index in _idm_lanes(vehicle):
                front, _ = self.neighbour_vehicles(vehicle, lane_index)
                if front:
                    owner.append(k)
                    fronts.append((entry, front))
                entry += 1
        if fronts:
            entries = [e for e, _ in fronts]
            acceleration[entries] -= _interaction_terms(
                speed=speed[owner],
                heading=heading[owner],
                x=xy[owner, 0],
                lane_x0=np.array([batch[k].lane.start[0] for k in owner], dtype=np.float64),
                fronts=[front for _, front in fronts],
            )
        accelerations = iter(acceleration.tolist())
        for vehicle, steer in zip(batch, steering.tolist(), strict=True):
            # When changing lane, the slower of the accelerations for the current and the target lane.
            value = min(next(accelerations) for _ in _idm_lanes(vehicle))
            vehicle.action = {"steering": steer, "acceleration": _clip(value, -cls.ACC_MAX, cls.ACC_MAX)}

    def _sorted_lane(self, lane_index: LaneIndex) -> list[tuple[float, int]]:
        """``(s, i)`` of the vehicles on a lane, sorted: lane coordinate ``s`` and index ``i`` in ``vehicles``."""
        entries = self._lanes_at_act.get(lane_index)
        if entries is None:
            lane = self.network.get_lane(lane_index)
            # _AxisLane.local_coordinates and StraightLane.on_lane, for all vehicles at once (same operations).
            s = self._xy_at_act[:, 0] - lane.start[0]
            lateral = self._xy_at_act[:, 1] - lane.start[1]
            # Road.neighbour_vehicles counts vehicles within a 1 m margin of the lane.
            on_lane = (
                (np.abs(lateral) <= lane.width / 2 + 1)
                & (s >= -lane.VEHICLE_LENGTH)
                & (s < lane.length + lane.VEHICLE_LENGTH)
            )
            (index,) = np.nonzero(on_lane)
            entries = sorted(zip(s[index].tolist(), index.tolist(), strict=True))
            self._lanes_at_act[lane_index] = entries
        return entries

    def neighbour_vehicles(
        self, vehicle: Vehicle, lane_index: LaneIndex | None = None
    ) -> tuple[Vehicle | None, Vehicle | None]:
        lane_index = lane_index or vehicle.lane_index
        if self._lanes_at_act is None or self.objects or not lane_index:
            return super().neighbour_vehicles(vehicle, lane_index)
        entries = self._sorted_lane(lane_index)
        me = self._index_at_act.get(id(vehicle), -1)
        s = self.network.get_lane(lane_index).local_coordinates(vehicle.position)[0]
        k = bisect_left(entries, (s, -1))  # entries[k:] have s_v >= s: the front side
        front = s_front = None
        for s_v, i in entries[k:]:
            if i == me:
                continue
            if s_front is not None and s_v != s_front:
                break
            front, s_front = i, s_v
        rear = None
        if k > 0:
            j = k - 1
            while j > 0 and entries[j - 1][0] == entries[k - 1][0]:
                j -= 1
            rear = entries[j][1]
        return (
            self.vehicles[front] if front is not None else None,
            self.vehicles[rear] if rear is not None else None,
        )

    def step(self, dt: float) -> None:
        if self.objects:
            super().step(dt)
            return
        vehicles = self.vehicles
        batch = []
        for vehicle in vehicles:  # each vehicle moves on its own: the order of the updates does not matter
            if type(vehicle) is FastIDMVehicle:
                batch.append(vehicle)
            else:
                vehicle.step(dt)
        if batch:
            _step_kinematics(batch, dt)
        xy = np.array([v.position for v in vehicles], dtype=np.float64).reshape(-1, 2)
        half_diagonal = np.array([v.diagonal for v in vehicles]) / 2
        speed = np.array([v.speed for v in vehicles], dtype=np.float64)
        distance = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1))
        # Road's pre-check dismisses a pair (i, j), i < j, when distance > half diagonals + speed_i * dt; the
        # 1e-6 m slack only admits extra pairs, which the exact check then dismisses itself.
        reach = half_diagonal[:, None] + half_diagonal[None, :] + speed[:, None] * dt + 1e-6
        rows, cols = np.nonzero(np.triu(distance <= reach, k=1))
        if rows.size:
            keep = ~_separated_on_first_axes(vehicles, rows, cols, xy, speed, dt)
            rows, cols = rows[keep], cols[keep]
        for i, j in zip(rows.tolist(), cols.tolist(), strict=True):
            vehicles[i].handle_collisions(vehicles[j], dt)


def _idm_lanes(vehicle: FastIDMVehicle) -> tuple[LaneIndex, ...]:
    """The lanes whose front vehicle limits ``vehicle``'s IDM acceleration: its own, and its target while
    changing lane."""
    if vehicle.lane_index == vehicle.target_lane_index:
        return (vehicle.lane_index,)
    return vehicle.lane_index, vehicle.target_lane_index


def _interaction_terms(
    *, speed: np.ndarray, heading: np.ndarray, x: np.ndarray, lane_x0: np.ndarray, fronts: list[Vehicle]
) -> np.ndarray:
    """IDM's interaction term ``3 * (desired_gap / gap)^2`` of K vehicles behind their front vehicles, [K].

    ``speed``, ``heading``, ``x`` describe the K following vehicles and ``lane_x0`` the start of their current
    lanes, which highway-env measures the gap along. Same operations as ``IDMVehicle.acceleration``.
    """
    cls = FastIDMVehicle
    front_speed = np.array([f.speed for f in fronts], dtype=np.float64)
    front_heading = np.array([f.heading for f in fronts], dtype=np.float64)
    front_x = np.array([f.position[0] for f in fronts], dtype=np.float64)
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    front_direction = np.stack([np.cos(front_heading), np.sin(front_heading)], axis=1)
    dv = np.vecdot(speed[:, None] * direction - front_speed[:, None] * front_direction, direction)
    ab = -cls.COMFORT_ACC_MAX * cls.COMFORT_ACC_MIN
    desired_gap = cls.DISTANCE_WANTED + speed * cls.TIME_WANTED + speed * dv / (2 * math.sqrt(ab))
    gap = desired_gap / _not_zero((front_x - lane_x0) - (x - lane_x0))
    return cls.COMFORT_ACC_MAX * (gap * gap)


def _step_kinematics(batch: list[FastIDMVehicle], dt: float) -> None:
    """``IDMVehicle.step`` for all of ``batch``: highway-env's kinematic bicycle model on arrays (numpy's
    elementwise functions give the same bits on arrays as on scalars)."""
    for vehicle in batch:
        vehicle.timer += dt
        vehicle.clip_actions()
    steering = np.array([v.action["steering"] for v in batch], dtype=np.float64)
    acceleration = np.array([v.action["acceleration"] for v in batch], dtype=np.float64)
    speed = np.array([v.speed for v in batch], dtype=np.float64)
    heading = np.array([v.heading for v in batch], dtype=np.float64)
    length = np.array([v.LENGTH for v in batch], dtype=np.float64)
    beta = np.arctan(1 / 2 * np.tan(steering))  # slip angle at the centre of mass
    course = heading + beta
    displacement = np.stack([speed * np.cos(course), speed * np.sin(course)], axis=1) * dt
    new_heading = heading + speed * np.sin(beta) / (length / 2) * dt
    new_speed = speed + acceleration * dt
    for vehicle, step, h, v in zip(
        batch, displacement, new_heading.tolist(), new_speed.tolist(), strict=True
    ):
        vehicle.position += step
        if vehicle.impact is not None:
            vehicle.position += vehicle.impact
            vehicle.crashed = True
            vehicle.impact = None
        vehicle.heading, vehicle.speed = h, v
        vehicle.on_state_update()


def _separated_on_first_axes(
    vehicles: list[Vehicle], rows: np.ndarray, cols: np.ndarray, xy: np.ndarray, speed: np.ndarray, dt: float
) -> np.ndarray:
    """Which pairs ``(rows[k], cols[k])`` highway-env's polygon check surely finds apart, bool [K].

    ``utils.are_polygons_intersecting(a, b, ...)`` (separating axis test) first projects both cars, and car a swept
    by the relative displacement over ``dt``, onto a's longitudinal and lateral axes; a gap on either axis makes it
    report neither a collision nor a future one. The same gaps are computed here in closed form for many pairs at
    once. A pair counts as apart only with a gap above 1e-6 m, far beyond the rounding difference of the two
    computations, so the exact check still runs for every pair where it could find contact. Side-by-side cars in
    adjacent lanes, most pairs the distance pre-check admits, are dismissed here.
    """
    heading = np.array([v.heading for v in vehicles], dtype=np.float64)
    length = np.array([v.LENGTH for v in vehicles], dtype=np.float64)
    width = np.array([v.WIDTH for v in vehicles], dtype=np.float64)
    cos, sin = np.cos(heading), np.sin(heading)
    displacement = (speed * dt)[:, None] * np.stack([cos, sin], axis=1)
    a, b = rows, cols
    along = np.stack([cos[a], sin[a]], axis=1)  # a's longitudinal axis
    across = np.stack([-sin[a], cos[a]], axis=1)  # a's lateral axis
    delta = xy[b] - xy[a]
    relative = displacement[a] - displacement[b]
    # b's orientation relative to a: the half extents of b's rectangle along a's axes.
    cos_ab = cos[a] * cos[b] + sin[a] * sin[b]
    sin_ab = cos[a] * sin[b] - sin[a] * cos[b]
    half_b_along = 0.5 * (length[b] * np.abs(cos_ab) + width[b] * np.abs(sin_ab))
    half_b_across = 0.5 * (length[b] * np.abs(sin_ab) + width[b] * np.abs(cos_ab))
    gap_along = (
        np.abs((delta * along).sum(1)) - 0.5 * length[a] - half_b_along - np.abs((relative * along).sum(1))
    )
    gap_across = (
        np.abs((delta * across).sum(1)) - 0.5 * width[a] - half_b_across - np.abs((relative * across).sum(1))
    )
    return np.maximum(gap_along, gap_across) > 1e-6


def _not_zero(x: np.ndarray, eps: float = 1e-2) -> np.ndarray:
    """``utils.not_zero`` elementwise: values within ``eps`` of zero pushed out to +-eps."""
    return np.where(np.abs(x) > eps, x, np.where(x >= 0, eps, -eps))


def _clip_array(x: np.ndarray, low: float, high: float) -> np.ndarray:
    """``np.clip`` of a NaN-free array, without the dispatch overhead of ``np.clip`` on small arrays."""
    return np.minimum(np.maximum(x, low), high)


def _clip(x: float, low: float, high: float) -> float:
    """``np.clip`` of a non-NaN scalar, the same value without numpy's microseconds of call overhead."""
    return min(max(x, low), high)


class FastIDMVehicle(IDMVehicle):
    """highway-env's IDM (longitudinal) and MOBIL (lane change) vehicle, with the same decisions and trajectories.

    On the fast road, ``act`` and ``step`` run for all vehicles at once (``_StraightHighwayRoad``). IDM's
    ``acceleration`` and ``desired_gap``, which MOBIL and the interaction term call many times per tick, are
    restated with Python scalar arithmetic where it gives the same bits as highway-env's numpy calls. MOBIL,
    spawning and behaviour randomisation are inherited, so a seeded reset draws the same traffic.
    """

    def acceleration(
        self,
        ego_vehicle: Vehicle | None,
        front_vehicle: Vehicle | None = None,
        rear_vehicle: Vehicle | None = None,
    ) -> float:
        if not ego_vehicle or not isinstance(ego_vehicle, Vehicle):
            return 0
        target_speed = getattr(ego_vehicle, "target_speed", 0)
        lane = ego_vehicle.lane
        if lane and lane.speed_limit is not None:
            target_speed = _clip(target_speed, 0, lane.speed_limit)
        ratio = max(ego_vehicle.speed, 0) / abs(utils.not_zero(target_speed))
        acceleration = self.COMFORT_ACC_MAX * (1 - np.power(ratio, self.DELTA))
        if front_vehicle:
            acceleration -= self._interaction(ego_vehicle, front_vehicle)
        return acceleration

    def _interaction(self, ego_vehicle: Vehicle, front_vehicle: Vehicle) -> float:
        gap = self.desired_gap(ego_vehicle, front_vehicle) / utils.not_zero(
            ego_vehicle.lane_distance_to(front_vehicle)
        )
        return self.COMFORT_ACC_MAX * (gap * gap)  # np.power(gap, 2) is exactly gap * gap

    def desired_gap(
        self, ego_vehicle: Vehicle, front_vehicle: Vehicle = None, projected: bool = True
    ) -> float:
        if projected:
            # np.dot(ego.velocity - front.velocity, ego.direction), with the arrays built from the same scalars.
            speed, cos, sin = ego_vehicle.speed, math.cos(ego_vehicle.heading), math.sin(ego_vehicle.heading)
            front_speed, front_heading = front_vehicle.speed, front_vehicle.heading
            relative = np.array(
                (
                    speed * cos - front_speed * math.cos(front_heading),
                    speed * sin - front_speed * math.sin(front_heading),
                )
            )
            dv = np.dot(relative, np.array((cos, sin)))
        else:
            dv = ego_vehicle.speed - front_vehicle.speed
        ab = -self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN
        return (
            self.DISTANCE_WANTED
            + ego_vehicle.speed * self.TIME_WANTED
            + ego_vehicle.speed * dv / (2 * math.sqrt(ab))
        )


class HighwaySimulator(HighwayEnv):
    """highway-env's ``highway-v0`` on the fast straight road, its traffic made of :class:`FastIDMVehicle`.

    Only its scene (``road``, ``vehicle``) and reset are used: :class:`~isodream_rl.envs.highway.HighwayIsoEnv`
    runs the ticks itself, skipping highway-env's per-step observation and reward.
    """

    @classmethod
    def default_config(cls) -> dict[str, Any]:
        config = super().default_config()
        config["other_vehicles_type"] = f"{FastIDMVehicle.__module__}.{FastIDMVehicle.__qualname__}"
        return config

    def _create_road(self) -> None:
        self.road = _StraightHighwayRoad(
            network=_StraightHighwayNetwork(lanes_count=self.config["lanes_count"]),
            np_random=self.np_random,
            record_history=self.config["show_trajectories"],
        )
