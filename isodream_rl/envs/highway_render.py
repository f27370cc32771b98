"""Image views of a highway-env road: a first-person roof camera (MuJoCo) and a top-down chase view (pygame).

highway-env only draws top-down, so the first-person view rebuilds the scene in 3-D each frame: one MuJoCo mocap
box per vehicle, the road, its markings and grass, and a forward camera on the ego's roof like the paper's CARLA
camera (60 degree field of view, 1.6 m forward and 1.7 m up). The scene is copied into MuJoCo and rendered; MuJoCo
simulates nothing. Coordinates: highway-env is x forward along the road, y to the driver's right (screen down); MuJoCo
is right-handed with z up, so a highway-env point (x, y) maps to (x, -y, z) and a heading h to a yaw of -h.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

from isodream_rl.process_settings import pygame_offscreen

# before pygame initialises a display, which highway-env's viewer does
pygame_offscreen()

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pygame  # noqa: E402
from highway_env.road.graphics import LaneGraphics, RoadGraphics, WorldSurface  # noqa: E402
from highway_env.road.lane import AbstractLane  # noqa: E402
from highway_env.road.road import Road  # noqa: E402
from highway_env.vehicle.graphics import VehicleGraphics  # noqa: E402
from highway_env.vehicle.kinematics import Vehicle  # noqa: E402
from PIL import Image  # noqa: E402

from isodream_rl.envs.mujoco_render import OffscreenRenderer  # noqa: E402

# Distinct car paints, cycled over the other vehicles (RGB in [0, 1]).
_CAR_COLOURS = (
    (0.80, 0.12, 0.10),
    (0.10, 0.30, 0.75),
    (0.90, 0.90, 0.88),
    (0.95, 0.70, 0.10),
    (0.15, 0.55, 0.25),
    (0.20, 0.20, 0.22),
    (0.55, 0.20, 0.60),
    (0.60, 0.62, 0.66),
)
# Lane dashes: 6 m painted every 18 m (German motorway markings). Half the period exceeds the 8 m the ego covers in
# one agent step (4 ticks of 0.05 s) at highway-env's 40 m/s speed cap, so between two frames the dashes never seem
# to move backwards.
_DASH_LENGTH = 6.0
_DASH_PERIOD = 18.0
_LINE_WIDTH = 0.3
_ASPHALT = (84, 84, 90)
_PAINT = (240, 240, 240)
_GRASS = (71, 128, 51)
_SKY_TOP = np.array([90.0, 140.0, 215.0])
_SKY_HORIZON = np.array([215.0, 228.0, 240.0])
_HIDDEN_GROUP = 3  # geom group of culled cars, switched off in the scene options
_MASK_KEY = np.array([255, 0, 255], dtype=np.uint8)  # no highway-env vehicle paint: the top-down masks' key


class FirstPersonRenderer:
    """Forward camera on the ego's roof, drawing the highway-env state with MuJoCo boxes.

    The road is one textured box (the lane markings are in the texture, so far dashes are filtered by mipmaps
    instead of flickering), the grass a plane, each other vehicle a body box and a dark cabin box; vehicles behind
    the camera or beyond ``view_distance`` are skipped. There is no skybox: MuJoCo leaves empty pixels black and
    they are filled with a sky gradient afterwards (nothing in the scene is pure black), which is cheaper on
    llvmpipe (docs/envs/highway.md).

    Args:
        lanes_count (int): number of lanes of the straight highway (lane centres at highway-env y = 0, w, 2w, ...).
        max_vehicles (int): number of other vehicles the scene has slots for.
        lane_width (float, optional): lane width w in metres. Defaults to 4.0 (highway-env's).
        image_size (int, optional): side of the square image in pixels. Defaults to 64.
        fovy (float, optional): vertical (= horizontal, the image is square) field of view in degrees.
            Defaults to 60.
        camera_offset (tuple of float, optional): camera position in the ego frame (forward, left, up) in metres.
            Defaults to (1.6, 0.0, 1.7), the paper's CARLA camera.
        view_distance (float, optional): how far ahead road, grass and vehicles are drawn, in metres.
            Defaults to 400.

    Examples:
        >>> renderer = FirstPersonRenderer(lanes_count=4, max_vehicles=30)
        >>> frame = renderer.render(ego, others)  # doctest: +SKIP
        >>> frame.shape, frame.dtype  # doctest: +SKIP
        ((64, 64, 3), dtype('uint8'))
    """

    def __init__(
        self,
        *,
        lanes_count: int,
        max_vehicles: int,
        lane_width: float = 4.0,
        image_size: int = 64,
        fovy: float = 60.0,
        camera_offset: tuple[float, float, float] = (1.6, 0.0, 1.7),
        view_distance: float = 400.0,
    ) -> None:
        if lanes_count < 1 or max_vehicles < 0 or image_size < 8 or view_distance <= 0:
            raise ValueError(
                "expected lanes_count >= 1, max_vehicles >= 0, image_size >= 8 and view_distance > 0, got "
                f"lanes_count={lanes_count}, max_vehicles={max_vehicles}, image_size={image_size}, "
                f"view_distance={view_distance}"
            )
        self.max_vehicles = max_vehicles
        self.image_size = image_size
        self.view_distance = view_distance
        xml = _scene_xml(
            lanes_count=lanes_count,
            lane_width=lane_width,
            max_vehicles=max_vehicles,
            image_size=image_size,
            fovy=fovy,
            camera_offset=camera_offset,
            view_distance=view_distance,
        )
        texture = _road_texture(lanes_count=lanes_count, lane_width=lane_width)
        self._model = mujoco.MjModel.from_xml_string(xml, assets={"road.png": texture})
        self._data = mujoco.MjData(self._model)
        self._ground = self._model.body("ground").mocapid[0]
        self._ego = self._model.body("ego").mocapid[0]
        self._cars = np.array(
            [self._model.body(f"car{i}").mocapid[0] for i in range(max_vehicles)], dtype=int
        )
        self._car_geoms = np.array(
            [
                [self._model.geom(f"car{i}_{part}").id for part in ("body", "cabin")]
                for i in range(max_vehicles)
            ],
            dtype=int,
        ).reshape(max_vehicles, 2)
        self._camera = self._model.camera("roof").id
        self._scene_option = mujoco.MjvOption()
        self._scene_option.geomgroup[_HIDDEN_GROUP] = 0
        self._sky = _sky_gradient(image_size)
        # Makes its GL context at the first render (see mujoco_render): construction stays fork-safe.
        self._renderer = OffscreenRenderer(self._model, width=image_size, height=image_size)

    def render(self, ego: Vehicle, others: Sequence[Vehicle]) -> np.ndarray:
        """Draws the view from the ego's roof.

        Args:
            ego (Vehicle): the vehicle carrying the camera (not drawn).
            others (sequence of Vehicle): the other vehicles, at most ``max_vehicles``; the vehicle at index ``i``
                always gets the same paint.

        Returns:
            np.ndarray: uint8 RGB image of shape [image_size, image_size, 3].
        """
        n = len(others)
        if n > self.max_vehicles:
            raise ValueError(f"the scene has {self.max_vehicles} vehicle slots, got {n} vehicles")
        model, data = self._model, self._data
        ego_xy = np.asarray(ego.position, dtype=np.float64)
        # The ground moves in whole dash periods, so the markings stay fixed in the world as the ego drives.
        data.mocap_pos[self._ground] = (np.floor(ego_xy[0] / _DASH_PERIOD) * _DASH_PERIOD, 0.0, 0.0)
        data.mocap_pos[self._ego] = (ego_xy[0], -ego_xy[1], 0.0)
        data.mocap_quat[self._ego] = _yaw_quaternion(np.array([ego.heading]))[0]
        visible = np.zeros(self.max_vehicles, dtype=bool)
        if n:
            xy = np.array([v.position for v in others], dtype=np.float64).reshape(n, 2)
            ids = self._cars[:n]
            data.mocap_pos[ids, 0] = xy[:, 0]
            data.mocap_pos[ids, 1] = -xy[:, 1]
            data.mocap_quat[ids] = _yaw_quaternion(np.array([v.heading for v in others], dtype=np.float64))
            # A car centred more than its half diagonal (2.7 m) behind the camera cannot be in a forward view.
            ahead = (xy - ego_xy) @ np.array([np.cos(ego.heading), np.sin(ego.heading)])
            visible[:n] = (ahead > -3.0) & (ahead < self.view_distance)
        model.geom_group[self._car_geoms] = np.where(visible, 0, _HIDDEN_GROUP)[:, None]
        # mj_kinematics places the bodies; cameras are only moved by mj_camlight.
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        frame = self._renderer.render(data, camera_id=self._camera, scene_option=self._scene_option)
        np.copyto(frame, self._sky, where=(frame == 0).all(axis=-1, keepdims=True))
        return frame

    def vehicle_mask(self) -> np.ndarray:
        """The pixels of the other vehicles in the last :meth:`render`'s frame, bool ``[image_size,
        image_size]``, from MuJoCo's segmentation pass of the same scene (exact: no multisampling). The ego
        carries the camera and is not drawn, so this view has no ego pixels."""
        ids = self._renderer.render_geom_ids(
            self._data, camera_id=self._camera, scene_option=self._scene_option
        )
        return np.isin(ids, self._car_geoms)

    def close(self) -> None:
        """Releases the GL context."""
        self._renderer.close()


def _yaw_quaternion(heading: np.ndarray) -> np.ndarray:
    """MuJoCo quaternions (w, x, y, z), shape [n, 4], for highway-env headings of shape [n] (yaw = -heading)."""
    half = -0.5 * heading
    zeros = np.zeros_like(half)
    return np.stack([np.cos(half), zeros, zeros, np.sin(half)], axis=1)


def _road_texture(*, lanes_count: int, lane_width: float, px_per_metre: int = 16) -> bytes:
    """PNG of one dash period of road. Rows run across the road, from its edge at highway-env y = -w/2 (row 0) to
    y = (lanes - 1/2) w; columns run along it from the start of a dash."""
    rows = int(round(lanes_count * lane_width * px_per_metre))
    cols = int(round(_DASH_PERIOD * px_per_metre / 4))  # along the road a 4x coarser grid is enough
    texture = np.empty((rows, cols, 3), dtype=np.uint8)
    texture[:] = _ASPHALT
    line = max(1, int(round(_LINE_WIDTH * px_per_metre)))
    texture[:line] = _PAINT
    texture[-line:] = _PAINT
    dash = int(round(_DASH_LENGTH / _DASH_PERIOD * cols))
    for lane in range(1, lanes_count):
        first = int(round(lane * lane_width * px_per_metre)) - line // 2
        texture[first : first + line, :dash] = _PAINT
    buffer = io.BytesIO()
    Image.fromarray(texture).save(buffer, format="PNG")
    return buffer.getvalue()


def _sky_gradient(image_size: int) -> np.ndarray:
    """Sky for a level camera, shape [image_size, image_size, 3]: deep blue at the top, pale at the horizon."""
    rows = np.arange(image_size) + 0.5
    elevation = np.clip(1.0 - 2.0 * rows / image_size, 0.0, 1.0) ** 0.7
    colour = _SKY_HORIZON + (_SKY_TOP - _SKY_HORIZON) * elevation[:, None]
    return np.repeat(colour.round().astype(np.uint8)[:, None, :], image_size, axis=1)


def _scene_xml(
    *,
    lanes_count: int,
    lane_width: float,
    max_vehicles: int,
    image_size: int,
    fovy: float,
    camera_offset: tuple[float, float, float],
    view_distance: float,
) -> str:
    """MJCF of the scene: a mocap ground (grass and textured road), a mocap ego carrying the camera, and one mocap
    car per vehicle slot."""
    # The road box starts 1.5 dash periods behind the ego and its half-length is whole periods, so its centre is
    # half a period past a period boundary: with the texture mapping below, dashes start at x = 0 mod period, where
    # highway-env's top-down view draws them too.
    back = 1.5 * _DASH_PERIOD
    half_length = np.ceil((view_distance + back) / 2 / _DASH_PERIOD) * _DASH_PERIOD
    centre = half_length - back
    road_half_width = lanes_count * lane_width / 2
    # Lane centres are at highway-env y = i * w, i.e. MuJoCo y = -i * w; the road spans half a lane beyond them.
    road_centre = -(lanes_count - 1) * lane_width / 2
    # A box maps a uniform 2-D texture as u = 1/2 + x * texrepeat / 2 in its own frame (v likewise, from +y), so
    # texrepeat = 2 / period makes one texture span a dash period along the road and the road's width across it.
    repeat_u, repeat_v = 2 / _DASH_PERIOD, 1 / road_half_width
    grass = " ".join(f"{c / 255:.3f}" for c in _GRASS)
    cars = []
    for i in range(max_vehicles):
        r, g, b = _CAR_COLOURS[i % len(_CAR_COLOURS)]
        cars.append(
            f'<body name="car{i}" mocap="true">'
            f'<geom name="car{i}_body" type="box" size="2.5 1.0 0.45" pos="0 0 0.75" rgba="{r} {g} {b} 1"/>'
            f'<geom name="car{i}_cabin" type="box" size="1.3 0.9 0.3" pos="-0.3 0 1.5" rgba="0.12 0.14 0.17 1"/>'
            "</body>"
        )
    forward, left, up = camera_offset
    # numquads=1: MuJoCo otherwise splits each box face into 4x4 quads, which triples the llvmpipe render time.
    # A plane's third size is its rendering grid spacing: a fine grid costs milliseconds.
    # znear and zfar are fractions of the extent (20 m): 0.2 m and 1 km.
    return f"""
<mujoco model="highway_first_person">
  <statistic extent="20" center="0 0 0"/>
  <visual>
    <global offwidth="{image_size}" offheight="{image_size}"/>
    <quality shadowsize="0" offsamples="0" numquads="1"/>
    <map znear="0.01" zfar="50"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.3 0.3 0.3" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="road" type="2d" file="road.png"/>
    <material name="road" texture="road" texuniform="true" texrepeat="{repeat_u} {repeat_v}" specular="0"/>
    <material name="grass" rgba="{grass} 1" specular="0"/>
  </asset>
  <worldbody>
    <light directional="true" dir="0.4 0.3 -1" diffuse="0.5 0.5 0.5" specular="0 0 0" castshadow="false"/>
    <body name="ground" mocap="true">
      <geom type="plane" size="{half_length} {half_length} {half_length}" pos="{centre} 0 0" material="grass"/>
      <geom type="box" size="{half_length} {road_half_width} 0.025" pos="{centre} {road_centre} 0.025"
            material="road"/>
    </body>
    <body name="ego" mocap="true">
      <camera name="roof" pos="{forward} {left} {up}" xyaxes="0 -1 0 0 0 1" fovy="{fovy}"/>
    </body>
    {"".join(cars)}
  </worldbody>
</mujoco>
"""


class _LaneGraphics(LaneGraphics):
    """highway-env's lane drawing with the first-person view's dashes. highway-env's own 4.33 m period is shorter
    than the 5 m an ego at 25 m/s moves per agent step, so its dashes would seem to creep forward."""

    STRIPE_SPACING = _DASH_PERIOD
    STRIPE_LENGTH = _DASH_LENGTH
    STRIPE_WIDTH = _LINE_WIDTH


CHASE_VIEW_FOLLOWS = ("ego", "road")
"""What :class:`ChaseViewRenderer`'s camera follows: the ego (ego-centred) or the road (laterally fixed)."""


class ChaseViewRenderer:
    """Top-down view that follows the ego, turned so that driving points up, drawn with highway-env's graphics.

    highway-env fills everything grey; here the ground outside the paved road is grass, so leaving the road shows.

    Args:
        image_size (int, optional): side of the square image in pixels. Defaults to 64.
        scaling (float, optional): pixels per metre. Defaults to 1.5 (about 43 m of road in view).
        ego_from_bottom (float, optional): fraction of the image height below the ego. Defaults to 0.3.
        follow (str, optional): ``"ego"``: the camera is centred on the ego, which then stays at the same place
            in the frame (only the road shifts sideways when it changes lane). ``"road"``: the camera follows the
            ego along the road but stays centred on the road's centre line (the middle of all lanes), so
            steering and lane changes move the ego across the frame. Defaults to ``"ego"``.
    """

    def __init__(
        self, *, image_size: int = 64, scaling: float = 1.5, ego_from_bottom: float = 0.3, follow: str = "ego"
    ) -> None:
        if image_size < 8 or not scaling > 0 or not 0.0 <= ego_from_bottom <= 1.0:
            raise ValueError(
                "expected image_size >= 8, scaling > 0 and ego_from_bottom in [0, 1], got "
                f"image_size={image_size}, scaling={scaling}, ego_from_bottom={ego_from_bottom}"
            )
        if follow not in CHASE_VIEW_FOLLOWS:
            raise ValueError(f"Unknown follow {follow!r}. Valid: {', '.join(map(repr, CHASE_VIEW_FOLLOWS))}")
        self.follow = follow
        size = (image_size, image_size)
        # A plain Surface needs no display, so this bypasses highway-env's EnvViewer and its SDL driver checks.
        self._surface = WorldSurface(size, 0, pygame.Surface(size))
        self._surface.scaling = scaling
        # highway-env draws the road along +x (rightwards); after the quarter turn in render(), left is the bottom.
        self._surface.centering_position = [ego_from_bottom, 0.5]

    def render(self, road: Road, ego: Vehicle) -> np.ndarray:
        """Draws the road and its vehicles around the ego.

        Args:
            road (Road): the highway-env road, made of straight lanes along +x.
            ego (Vehicle): the vehicle the view follows.

        Returns:
            np.ndarray: uint8 RGB image of shape [image_size, image_size, 3].
        """
        surface = self._surface
        lanes = road.network.lanes_list()
        top, bottom = self._move_window(lanes, ego)
        surface.fill(_GRASS)
        left, upper = surface.pos2pix(min(lane.start[0] for lane in lanes), top)
        right, lower = surface.pos2pix(max(lane.end[0] for lane in lanes), bottom)
        pygame.draw.rect(surface, _ASPHALT, (left, upper, right - left, lower - upper))
        for lane in lanes:
            _LaneGraphics.display(lane, surface)
        RoadGraphics.display_traffic(road, surface, offscreen=True)
        return self._image()

    def masks(self, road: Road, ego: Vehicle) -> tuple[np.ndarray, np.ndarray]:
        """The visible pixels of the ego and of the other vehicles in :meth:`render`'s frame of the same state.

        Each group is drawn again alone, with highway-env's own vehicle drawing, on a key colour no vehicle
        has; vehicles are drawn in ``road.vehicles`` order, so one drawn after the ego hides it where they
        overlap (a crash) and one drawn before is hidden by it.

        Returns:
            ``(mask_agent, mask_vehicles)``: bool ``[image_size, image_size]`` each, disjoint.
        """
        self._move_window(road.network.lanes_list(), ego)
        vehicles = list(road.vehicles)
        index = next((i for i, v in enumerate(vehicles) if v is ego), len(vehicles))
        agent = self._footprint([ego])
        after = self._footprint(vehicles[index + 1 :])
        before = self._footprint(vehicles[:index])
        return agent & ~after, after | (before & ~agent)

    def _move_window(self, lanes: Sequence[AbstractLane], ego: Vehicle) -> tuple[float, float]:
        """Places the view for the ego (on the ego, or on the road's centre line level with it: ``follow``).

        Args:
            lanes: the road's lanes (``road.network.lanes_list()``).
            ego: the vehicle the view follows.

        Returns:
            tuple: highway-env y of the paved road's two edges (smaller first).
        """
        top = min(lane.start[1] - lane.width / 2 for lane in lanes)
        bottom = max(lane.start[1] + lane.width / 2 for lane in lanes)
        if self.follow == "ego":
            self._surface.move_display_window_to(ego.position)
        else:
            self._surface.move_display_window_to(np.array([ego.position[0], (top + bottom) / 2]))
        return top, bottom

    def _footprint(self, vehicles: Sequence[Vehicle]) -> np.ndarray:
        """Pixels covered by ``vehicles`` drawn alone (bool ``[image_size, image_size]``)."""
        surface = self._surface
        surface.fill(_MASK_KEY)
        for vehicle in vehicles:
            VehicleGraphics.display(vehicle, surface, offscreen=True)
        return (self._image() != _MASK_KEY).any(axis=-1)

    def _image(self) -> np.ndarray:
        # surfarray is [x, y, rgb]; a counter-clockwise quarter turn makes +x (driving) point up and keeps the
        # driver's right (+y, screen down) on the right.
        return np.ascontiguousarray(np.rot90(pygame.surfarray.array3d(self._surface).transpose(1, 0, 2)))
