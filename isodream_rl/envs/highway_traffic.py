"""highway-env's IDM/MOBIL traffic for the fast straight road: the same commands and motion, over all vehicles at once.

:class:`FastIDMVehicle` is highway-env's ``IDMVehicle``; :func:`set_idm_actions` and :func:`step_kinematics` compute
its per-tick commands (``IDMVehicle.act``) and motion (``Vehicle.step``) for many vehicles with numpy arrays, with the
same floating-point operations as highway-env, so the results are bit-identical (see ``highway_sim``).
"""

from __future__ import annotations

import math

import numpy as np
from highway_env import utils
from highway_env.road.road import LaneIndex, Road
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

__all__ = ["FastIDMVehicle", "set_idm_actions", "step_kinematics"]


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

    On the fast road, ``act`` and ``step`` run for all vehicles at once (:func:`set_idm_actions`,
    :func:`step_kinematics`). IDM's ``acceleration`` and ``desired_gap``, which MOBIL calls six times per lane
    decision, are restated with Python scalar arithmetic where it gives the same bits as highway-env's numpy calls.
    MOBIL, spawning and behavior randomisation are inherited, so a seeded reset draws the same traffic.
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


def set_idm_actions(batch: list[FastIDMVehicle], *, road: Road) -> None:
    """Sets ``IDMVehicle.act``'s steering and acceleration commands of every vehicle in ``batch`` at once.

    Call it after the lane decisions (``follow_road``, ``change_lane_policy``) of the tick, with ``road``'s
    vehicle positions unchanged since. The commands are those of highway-env's ``IDMVehicle.act``, bit for bit.

    numpy's elementwise functions give the same bits on arrays as on the scalars highway-env passes them, so
    the steering controller (``ControlledVehicle.steering_control``) and IDM's acceleration run on arrays
    (``np.vecdot`` for the ``np.dot`` of highway-env's desired gap: the same inner loop).

    Args:
        batch (list of FastIDMVehicle): the vehicles to command, not crashed.
        road (Road): their road, for lanes and neighbour search.
    """
    cls = FastIDMVehicle
    n = len(batch)
    xy = np.array([v.position for v in batch], dtype=np.float64).reshape(n, 2)
    speed = np.array([v.speed for v in batch], dtype=np.float64)
    heading = np.array([v.heading for v in batch], dtype=np.float64)
    target_lanes = [road.network.get_lane(v.target_lane_index) for v in batch]
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
    steering = _clip_array(np.arctan(2 * np.tan(slip_angle)), -cls.MAX_STEERING_ANGLE, cls.MAX_STEERING_ANGLE)
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
            front, _ = road.neighbour_vehicles(vehicle, lane_index)
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


def step_kinematics(batch: list[FastIDMVehicle], dt: float) -> None:
    """``IDMVehicle.step`` for all of ``batch``: highway-env's kinematic bicycle model on arrays (numpy's
    elementwise functions give the same bits on arrays as on scalars).

    Args:
        batch (list of FastIDMVehicle): the vehicles to move, each with its ``action`` of this tick.
        dt (float): time step in seconds.
    """
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
