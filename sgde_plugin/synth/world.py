"""The procedural street: ground, facades, sidewalks, poles, parked and moving cars, and the ego path.

World frame: x along the street, y to the left, z up; the ground is the plane z = 0. The road is
asphalt for |y| < ROAD_HALF_M with two driving lanes (ego lane centre y = EGO_LANE_Y) and a
parking strip on each side, sidewalks (raised boxes) up to the facades. Everything is an
analytic primitive: yaw-oriented boxes (buildings, sidewalk slabs, car parts, lamp arms) and
vertical cylinders (poles). Moving boxes have a constant velocity; the ego drives at EGO_SPEED_MPS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ..geometry import make_transform, yaw_pitch_roll_to_rotation
from .ego_body import EgoBody
from .noise import NoiseBank, make_noise_bank

# materials
GROUND, FACADE, CAR_BODY, CAR_GLASS, TYRE, SIDEWALK, POLE, METAL = range(8)

ROAD_HALF_M = 6.0
LANE_WIDTH_M = 3.5
EGO_LANE_Y = -1.75
EGO_SPEED_MPS = 6.0
SIDEWALK_HEIGHT_M = 0.15
STREET_X = (-160.0, 800.0)
MAX_FRAMES = 1000  # 100 s at 10 Hz keeps the ego inside the street

_WALL_COLOURS = np.array([
    [0.62, 0.33, 0.25], [0.72, 0.62, 0.48], [0.55, 0.55, 0.52], [0.80, 0.77, 0.70],
    [0.45, 0.36, 0.30], [0.66, 0.50, 0.38], [0.58, 0.62, 0.66], [0.76, 0.70, 0.56],
])
_CAR_COLOURS = np.array([
    [0.75, 0.08, 0.06], [0.10, 0.18, 0.45], [0.85, 0.85, 0.83], [0.12, 0.12, 0.13],
    [0.55, 0.57, 0.60], [0.20, 0.40, 0.22], [0.80, 0.62, 0.10], [0.35, 0.22, 0.15],
])


@dataclass(frozen=True, eq=False)
class World:
    """A static scene description: primitive arrays (time-zero poses and velocities) plus texture bank.

    Boxes: centre (N, 3), half sizes (N, 3), yaw about z (N,), velocity (N, 3), material (N,),
    colour (N, 3) in [0, 1], params (N, 6) material-specific (facades: floor height, window spacing,
    window width, window height, brick flag, building top; the last two columns of every box are
    not used) and texture offsets (N, 2) metres. Poles: base centre (M, 2), radius (M,), height (M,).
    """

    seed: int
    box_center: np.ndarray
    box_half: np.ndarray
    box_yaw: np.ndarray
    box_velocity: np.ndarray
    box_material: np.ndarray
    box_color: np.ndarray
    box_params: np.ndarray
    box_tex_offset: np.ndarray
    pole_xy: np.ndarray
    pole_radius: np.ndarray
    pole_height: np.ndarray
    pole_color: np.ndarray
    noise: NoiseBank
    sun: np.ndarray
    ego_speed: float = EGO_SPEED_MPS
    ego_lane_y: float = EGO_LANE_Y
    ego_body: EgoBody | None = None  # drawn in every camera when set (`synth.ego_body`)

    @property
    def n_boxes(self) -> int:
        """Number of boxes."""
        return int(self.box_center.shape[0])

    @property
    def n_poles(self) -> int:
        """Number of poles."""
        return int(self.pole_xy.shape[0])

    def box_centers(self, time_s: float) -> np.ndarray:
        """Box centres at time `time_s` (moving cars advanced along their velocity)."""
        return self.box_center + self.box_velocity * float(time_s)

    def ego_pose(self, time_s: float) -> np.ndarray:
        """ego_to_world at `time_s`: constant speed along the street with a gentle lane sway."""
        t = float(time_s)
        w = 2 * math.pi / 9.0
        x = self.ego_speed * t
        y = self.ego_lane_y + 0.25 * math.sin(w * t)
        yaw = math.atan2(0.25 * w * math.cos(w * t), self.ego_speed)
        return make_transform(yaw_pitch_roll_to_rotation(yaw), np.array([x, y, 0.0]))


class _Boxes:
    """Accumulates box rows while the world is generated."""

    def __init__(self) -> None:
        self.rows: list[tuple] = []

    def add(self, center: Sequence[float], half: Sequence[float], yaw: float = 0.0,
            velocity: Sequence[float] = (0.0, 0.0, 0.0), material: int = FACADE,
            color: Sequence[float] = (0.5, 0.5, 0.5), params: Sequence[float] = (0.0,) * 6,
            tex_offset: Sequence[float] = (0.0, 0.0)) -> None:
        """One box row: centre, half sizes, yaw, velocity, material, colour, material parameters, texture offset."""
        self.rows.append((center, half, yaw, velocity, material, color, params, tex_offset))

    def arrays(self) -> dict[str, np.ndarray]:
        """The rows as the world's box arrays."""
        cols = list(zip(*self.rows))
        return {
            "box_center": np.asarray(cols[0], dtype=np.float64).reshape(-1, 3),
            "box_half": np.asarray(cols[1], dtype=np.float64).reshape(-1, 3),
            "box_yaw": np.asarray(cols[2], dtype=np.float64),
            "box_velocity": np.asarray(cols[3], dtype=np.float64).reshape(-1, 3),
            "box_material": np.asarray(cols[4], dtype=np.int64),
            "box_color": np.asarray(cols[5], dtype=np.float64).reshape(-1, 3),
            "box_params": np.asarray(cols[6], dtype=np.float64).reshape(-1, 6),
            "box_tex_offset": np.asarray(cols[7], dtype=np.float64).reshape(-1, 2),
        }


def _jitter(rng: np.random.Generator, colour: np.ndarray, amount: float) -> tuple[float, float, float]:
    return tuple(np.clip(colour * (1 + rng.uniform(-amount, amount, 3)), 0.02, 0.98).tolist())


def add_car(boxes: _Boxes, rng: np.random.Generator, x: float, y: float, yaw: float, speed: float = 0.0) -> None:
    """A car of four boxes (body, cabin, two wheel axles) centred at (x, y), heading `yaw`, moving at `speed`."""
    length, width = rng.uniform(3.9, 4.8), rng.uniform(1.70, 1.90)
    body_top, cabin_h = rng.uniform(0.95, 1.10), rng.uniform(0.45, 0.58)
    colour = _jitter(rng, _CAR_COLOURS[rng.integers(len(_CAR_COLOURS))], 0.08)
    c, s = math.cos(yaw), math.sin(yaw)
    vel = (speed * c, speed * s, 0.0)
    off = tuple(rng.uniform(0, 100, 2).tolist())

    def at(dx: float) -> tuple[float, float]:
        return x + c * dx, y + s * dx

    bx, by = at(0.0)
    boxes.add((bx, by, (0.30 + body_top) / 2), (length / 2, width / 2, (body_top - 0.30) / 2), yaw, vel,
              CAR_BODY, colour, tex_offset=off)
    cab_len = length * rng.uniform(0.48, 0.56)
    cx, cy = at(-0.06 * length)
    boxes.add((cx, cy, body_top + cabin_h / 2), (cab_len / 2, width / 2 - 0.08, cabin_h / 2), yaw,
              vel, CAR_GLASS, colour, tex_offset=off)
    for dx in (0.31 * length, -0.31 * length):
        wx, wy = at(dx)
        boxes.add((wx, wy, 0.33), (0.33, width / 2 - 0.04, 0.33), yaw, vel, TYRE, (0.06, 0.06, 0.07),
                  tex_offset=off)


def _buildings(boxes: _Boxes, rng: np.random.Generator, side: float) -> None:
    x = STREET_X[0]
    while x < STREET_X[1]:
        width = rng.uniform(8.0, 22.0)
        front = 9.0 + rng.uniform(0.0, 3.0)
        depth = rng.uniform(8.0, 14.0)
        height = rng.uniform(7.0, 24.0)
        colour = _jitter(rng, _WALL_COLOURS[rng.integers(len(_WALL_COLOURS))], 0.10)
        floor_h = rng.uniform(2.9, 3.5)
        spacing = rng.uniform(2.2, 3.3)
        win_w = rng.uniform(0.8, min(1.6, spacing - 0.6))
        win_h = rng.uniform(1.2, min(1.9, floor_h - 0.9))
        brick = float(rng.random() < 0.5)
        params = (floor_h, spacing, win_w, win_h, brick, height)
        boxes.add((x + width / 2, side * (front + depth / 2), height / 2), (width / 2, depth / 2, height / 2),
                  0.0, material=FACADE, color=colour, params=params, tex_offset=tuple(rng.uniform(0, 100, 2)))
        x += width + (rng.uniform(1.5, 4.0) if rng.random() < 0.25 else 0.0)


def _street_ends(boxes: _Boxes, rng: np.random.Generator) -> None:
    for x in (STREET_X[0] - 8.0, STREET_X[1] + 8.0):
        colour = _jitter(rng, _WALL_COLOURS[rng.integers(len(_WALL_COLOURS))], 0.1)
        params = (3.2, 2.8, 1.2, 1.5, 1.0, 18.0)
        boxes.add((x, 0.0, 9.0), (6.0, 40.0, 9.0), 0.0, material=FACADE, color=colour, params=params,
                  tex_offset=tuple(rng.uniform(0, 100, 2)))


def _sidewalks(boxes: _Boxes, rng: np.random.Generator) -> None:
    seg = 12.0
    x = STREET_X[0] - 2.0
    while x < STREET_X[1] + 2.0:
        for side in (1.0, -1.0):
            y = side * (ROAD_HALF_M + 4.0)
            boxes.add((x + seg / 2, y, SIDEWALK_HEIGHT_M / 2), (seg / 2, 4.0, SIDEWALK_HEIGHT_M / 2), 0.0,
                      material=SIDEWALK, color=(0.60, 0.58, 0.54), tex_offset=(0.0, 0.0))
        x += seg


def _parked_cars(boxes: _Boxes, rng: np.random.Generator) -> None:
    for side in (1.0, -1.0):
        x = STREET_X[0] + rng.uniform(0, 5)
        while x < STREET_X[1]:
            if rng.random() < 0.7:
                yaw = (0.0 if side < 0 else math.pi) + rng.normal(0.0, 0.03)
                add_car(boxes, rng, x + 2.3, side * (ROAD_HALF_M - 1.25), yaw)
            x += 4.8 + rng.uniform(0.8, 7.0)


def _moving_cars(boxes: _Boxes, rng: np.random.Generator) -> None:
    # the ego lane: cars ahead and behind keep their gap (same speed as the ego)
    for gap in (rng.uniform(13.0, 17.0), rng.uniform(32.0, 40.0), -rng.uniform(12.0, 15.0)):
        add_car(boxes, rng, gap, EGO_LANE_Y, 0.0, EGO_SPEED_MPS)
    # oncoming lane, spread so that some are always near the ego during MAX_FRAMES
    x = STREET_X[0]
    x_end = (EGO_SPEED_MPS + 10.0) * MAX_FRAMES / 10.0 + 200.0  # where they meet the ego
    while x < x_end:
        add_car(boxes, rng, x, -EGO_LANE_Y, math.pi, rng.uniform(7.0, 10.0))
        x += rng.uniform(25.0, 60.0)


def _poles(boxes: _Boxes, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    xy, radius, height = [], [], []
    for side in (1.0, -1.0):
        x = STREET_X[0] + rng.uniform(0, 10)
        while x < STREET_X[1]:
            y = side * (ROAD_HALF_M + 0.6)
            h = rng.uniform(5.5, 7.5)
            xy.append((x, y))
            radius.append(rng.uniform(0.08, 0.13))
            height.append(h)
            # lamp arm reaching over the road
            boxes.add((x, y - side * 0.8, h - 0.15), (0.06, 0.8, 0.06), 0.0, material=METAL,
                      color=(0.35, 0.36, 0.38), tex_offset=tuple(rng.uniform(0, 100, 2)))
            x += rng.uniform(18.0, 30.0)
    n = len(xy)
    colours = np.tile([[0.42, 0.43, 0.45]], (n, 1)) * rng.uniform(0.8, 1.2, (n, 1))
    return np.asarray(xy).reshape(-1, 2), np.asarray(radius), np.asarray(height), colours


def build_world(seed: int) -> World:
    """The procedural street of a seed (same seed, same world)."""
    rng = np.random.default_rng([int(seed), 0x5EED])
    boxes = _Boxes()
    for side in (1.0, -1.0):
        _buildings(boxes, rng, side)
    _street_ends(boxes, rng)
    _sidewalks(boxes, rng)
    _parked_cars(boxes, rng)
    _moving_cars(boxes, rng)
    pole_xy, pole_r, pole_h, pole_c = _poles(boxes, rng)
    sun = np.array([0.35, 0.45, 0.82])
    return World(
        seed=int(seed),
        **boxes.arrays(),
        pole_xy=pole_xy,
        pole_radius=pole_r,
        pole_height=pole_h,
        pole_color=pole_c,
        noise=make_noise_bank(int(rng.integers(2**31))),
        sun=sun / np.linalg.norm(sun),
    )


def with_companions(world: World, boxes: list[tuple], time_s: float = 0.0) -> World:
    """The world plus boxes that drive along with the ego (metal material).

    Each entry is (centre, half sizes, yaw, colour) in ego coordinates at `time_s`; the box gets the
    ego's velocity, so it stays beside the car (the ego's lane sway moves it by at most 0.25 m).
    """
    if not boxes:
        return world

    pose = world.ego_pose(time_s)
    heading = math.atan2(pose[1, 0], pose[0, 0])
    extra = _Boxes()
    for center, half, yaw, colour in boxes:
        c = pose @ np.array([*center, 1.0])
        start = c[:3] - np.array([world.ego_speed * time_s, 0.0, 0.0])
        extra.add(tuple(start), tuple(half), yaw + heading, (world.ego_speed, 0.0, 0.0), METAL, tuple(colour),
                  tex_offset=(float(abs(c[0]) % 100), float(abs(c[1]) % 100)))
    new = extra.arrays()
    return replace(world, **{k: np.concatenate([getattr(world, k), v]) for k, v in new.items()})
