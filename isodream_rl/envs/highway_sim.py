"""highway-env's highway simulation, specialised to a straight road for speed, with the same trajectories.

At 20 Hz with 30 vehicles, stock highway-env spends its ticks on lane geometry, the O(n^2) neighbour search
and collision pre-checks, and per-vehicle controller code that calls numpy on Python scalars (``np.clip`` on
one float is slow next to plain arithmetic). Here, on a road of parallel straight lanes along +x, lane geometry
is plain arithmetic, neighbours are found by bisection, and IDM's controllers and the vehicles' kinematics run on
arrays over all vehicles; only MOBIL's lane decisions stay per vehicle. Every floating-point operation that decides
a trajectory keeps highway-env's order and function: numpy's ``arcsin``, ``arctan``, ``tan``, ``power`` and
``dot`` differ in the last bit from ``math`` or a hand-written dot product on this CPU, but give the same bits on
arrays as on scalars (``np.vecdot`` runs ``np.dot``'s loop). Vehicle trajectories are therefore bit-identical to
highway-env's (``tests/test_env_highway.py`` checks it), and several times faster (measured in
docs/envs/highway.md; the env's time per step: ``bench/env_speed.py``, docs/results/env_speed.json).
"""

from __future__ import annotations

from bisect import bisect_left
from typing import Any

import numpy as np
from highway_env.envs.highway_env import HighwayEnv
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.kinematics import Vehicle

from isodream_rl.envs.highway_traffic import FastIDMVehicle, set_idm_actions, step_kinematics

__all__ = ["HighwaySimulator"]

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
                set_idm_actions(batch, road=self)
        finally:
            self._lanes_at_act = self._index_at_act = self._xy_at_act = None

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
            step_kinematics(batch, dt)
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
