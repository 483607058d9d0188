"""Procedural urban scenes from a seed: a street with lanes, curbs, sidewalks, buildings, trees, poles, an optional
cross street, and road users with nuScenes categories, realistic sizes and constant velocities.

Everything is generated in a scene frame (road along +x, ego starting at x = 0 in the first right-hand lane) and
placed in the global frame by ``T_global_scene``. Road users never overlap each other or the ego during the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from weatheralign.geometry import invert, make_transform, yaw_matrix
from weatheralign.world import objects
from weatheralign.world.materials import Material as M
from weatheralign.world.meshes import RGB, Mesh, box, concat

F64 = NDArray[np.float64]

LANE_WIDTH = 3.5
PARKING_WIDTH = 2.5
CURB_HEIGHT = 0.15
SCENE_X_RANGE = (-90.0, 150.0)  # where road users are placed, scene frame [m]

CAR_COLOURS: tuple[RGB, ...] = ((0.6, 0.6, 0.62), (0.05, 0.05, 0.06), (0.8, 0.8, 0.8), (0.35, 0.02, 0.02),
                                (0.05, 0.1, 0.3), (0.25, 0.27, 0.3), (0.5, 0.45, 0.35), (0.7, 0.7, 0.75),
                                (0.1, 0.25, 0.12))
CLOTHES: tuple[RGB, ...] = ((0.05, 0.05, 0.07), (0.4, 0.05, 0.05), (0.1, 0.15, 0.35), (0.5, 0.5, 0.5),
                            (0.6, 0.45, 0.2), (0.15, 0.3, 0.15), (0.8, 0.8, 0.78), (0.45, 0.1, 0.35))
FACADES: tuple[RGB, ...] = ((0.45, 0.2, 0.14), (0.6, 0.55, 0.45), (0.5, 0.5, 0.52), (0.7, 0.68, 0.62),
                            (0.35, 0.33, 0.32), (0.55, 0.35, 0.25), (0.62, 0.6, 0.55))


@dataclass(frozen=True)
class Actor:
    """An annotated object. Pose at time t: bottom centre ``position + velocity (t - t_ref)``, heading ``yaw``.

    ``mesh`` is in the body frame (origin at the bottom centre of the box); ``size`` is (width, length, height).
    """

    instance: int
    category: str
    attribute: str
    size: tuple[float, float, float]
    position: F64
    yaw: float
    velocity: F64
    t_ref: float
    mesh: Mesh

    @property
    def moving(self) -> bool:
        return bool(np.any(self.velocity != 0.0))

    def position_at(self, t: float | NDArray) -> F64:
        """Bottom-centre position(s) [m] at time(s) ``t`` [s]: (3,) or (N, 3)."""
        dt = np.asarray(t, dtype=np.float64) - self.t_ref
        return self.position + np.multiply.outer(dt, self.velocity)

    def box_center_at(self, t: float) -> F64:
        """(3,) geometric centre of the annotation box at ``t``."""
        return self.position_at(t) + np.array([0.0, 0.0, self.size[2] / 2])

    def T_global_body(self, t: float) -> F64:
        """(4, 4) body -> global at time ``t``."""
        return make_transform(yaw_matrix(self.yaw), self.position_at(t))


@dataclass(frozen=True)
class RoadGeometry:
    """Scene-frame description of the street used by procedural textures and the map."""

    lanes_per_direction: int
    road_half_width: float
    sidewalk_width: float
    crossing_x: float | None
    crossing_half_width: float


@dataclass(frozen=True)
class SceneLayout:
    """One procedural scene.

    Attributes:
        T_global_scene: (4, 4) scene frame -> global.
        static_mesh: all non-moving geometry in the global frame (parked/static actors labelled by instance).
        actors: annotated objects (moving and static); instance ids start at 1.
        ego_speed: [m/s]; ego drives along +x of the scene frame at y = ``ego_lane_y`` from x = 0 at ``t_start``.
        sun_direction: (3,) unit vector towards the sun, global frame.
    """

    name: str
    seed: int
    T_global_scene: F64
    road: RoadGeometry
    static_mesh: Mesh
    actors: tuple[Actor, ...]
    ego_speed: float
    ego_lane_y: float
    t_start: float
    duration: float
    sun_direction: F64
    sky_zenith: F64 = field(default_factory=lambda: np.array([0.18, 0.32, 0.62]))
    sky_horizon: F64 = field(default_factory=lambda: np.array([0.62, 0.7, 0.8]))

    def T_global_ego(self, t: float) -> F64:
        """(4, 4) ego -> global at time ``t`` [s] (constant speed, straight lane)."""
        x = self.ego_speed * (t - self.t_start)
        return self.T_global_scene @ make_transform(np.eye(3), np.array([x, self.ego_lane_y, 0.0]))

    @property
    def T_scene_global(self) -> F64:
        """(4, 4) global -> scene, the rigid inverse of ``T_global_scene``."""
        return invert(self.T_global_scene)


@dataclass
class _Occupancy:
    """Axis-aligned scene-frame footprints of placed road users over time, for rejection sampling."""

    times: F64
    boxes: list[F64] = field(default_factory=list)  # each (T, 4): xmin, xmax, ymin, ymax per time

    def footprint(self, x: float, y: float, vx: float, vy: float, half_l: float, half_w: float) -> F64:
        cx = x + vx * self.times
        cy = y + vy * self.times
        return np.stack([cx - half_l, cx + half_l, cy - half_w, cy + half_w], 1)

    def free(self, fp: F64) -> bool:
        for other in self.boxes:
            overlap = (fp[:, 0] < other[:, 1]) & (other[:, 0] < fp[:, 1]) & (fp[:, 2] < other[:, 3]) & (
                other[:, 2] < fp[:, 3])
            if overlap.any():
                return False
        return True


def _pick(rng: np.random.Generator, options: tuple) -> object:
    return options[int(rng.integers(len(options)))]


def _vehicle(rng: np.random.Generator, kind: str) -> tuple[str, tuple[float, float, float], Mesh]:
    if kind == "car":
        size = (rng.uniform(1.75, 2.05), rng.uniform(4.2, 5.0), rng.uniform(1.45, 1.85))
        return "vehicle.car", size, objects.car(size, _pick(rng, CAR_COLOURS))
    if kind == "truck":
        size = (rng.uniform(2.3, 2.6), rng.uniform(6.5, 9.5), rng.uniform(2.9, 3.6))
        return "vehicle.truck", size, objects.truck(size, _pick(rng, CAR_COLOURS), (0.85, 0.85, 0.83))
    if kind == "bus":
        size = (rng.uniform(2.75, 2.95), rng.uniform(10.5, 12.5), rng.uniform(3.2, 3.5))
        return "vehicle.bus.rigid", size, objects.bus(size, _pick(rng, ((0.85, 0.75, 0.1), (0.1, 0.3, 0.6),
                                                                         (0.8, 0.15, 0.1))))
    if kind == "motorcycle":
        size = (rng.uniform(0.7, 0.95), rng.uniform(1.9, 2.3), rng.uniform(1.45, 1.65))
        rider = (_pick(rng, CLOTHES), _pick(rng, CLOTHES), _pick(rng, objects.SKIN_TONES))
        return "vehicle.motorcycle", size, objects.bicycle(size, _pick(rng, CAR_COLOURS), rider, motor=True)
    raise ValueError(f"unknown vehicle kind {kind!r}")


def _person(rng: np.random.Generator, walking: bool) -> tuple[tuple[float, float, float], Mesh]:
    h = rng.uniform(1.55, 1.92)
    size = (rng.uniform(0.55, 0.75), rng.uniform(0.5, 0.85) if walking else rng.uniform(0.4, 0.6), h)
    mesh = objects.pedestrian(size, _pick(rng, CLOTHES), _pick(rng, CLOTHES), _pick(rng, objects.SKIN_TONES),
                              stride=0.45 if walking else 0.0)
    return size, mesh


def _static_world(rng: np.random.Generator, road: RoadGeometry) -> tuple[list[Mesh], list[tuple[float, float]]]:
    """Ground, sidewalks with curbs, buildings, trees, lamps and signs in the scene frame; also the (x, y) of the
    street furniture, which road users must keep clear of."""
    W, sw = road.road_half_width, road.sidewalk_width
    x_lo, x_hi = -320.0, 380.0
    parts = [box(x_lo, x_hi, -400, 400, -1.0, 0.0, M.ROAD, (0.16, 0.16, 0.17), 0.12)]
    furniture: list[tuple[float, float]] = []
    gaps: list[tuple[float, float]] = []
    if road.crossing_x is not None:
        gaps.append((road.crossing_x - road.crossing_half_width, road.crossing_x + road.crossing_half_width))

    def segments(lo: float, hi: float) -> list[tuple[float, float]]:
        out, start = [], lo
        for g0, g1 in gaps:
            if g0 > start:
                out.append((start, min(g0, hi)))
            start = max(start, g1)
        if start < hi:
            out.append((start, hi))
        return out

    for side in (-1.0, 1.0):
        y_in, y_out = side * W, side * (W + sw)
        for s0, s1 in segments(x_lo, x_hi):
            parts.append(box(s0, s1, min(y_in, y_out), max(y_in, y_out), -1.0, CURB_HEIGHT, M.CURB,
                             (0.5, 0.5, 0.48), 0.35, top=(M.SIDEWALK, (0.42, 0.41, 0.39), 0.3)))
        # buildings: a row of blocks behind the sidewalk
        for s0, s1 in segments(-260.0, 320.0):
            x = s0 + rng.uniform(0, 4)
            while x < s1 - 6:
                width = min(rng.uniform(8, 26), s1 - x)
                setback = rng.uniform(0.0, 2.5) if rng.random() < 0.7 else rng.uniform(4, 9)
                depth = rng.uniform(10, 22)
                height = rng.uniform(6, 32) if rng.random() < 0.85 else rng.uniform(35, 55)
                y0 = side * (W + sw + setback)
                y1 = side * (W + sw + setback + depth)
                parts.append(objects.building(x, x + width, min(y0, y1), max(y0, y1), height,
                                              _pick(rng, FACADES)))
                x += width + (rng.uniform(0, 1.5) if rng.random() < 0.75 else rng.uniform(4, 10))
        # street furniture near the curb
        for s0, s1 in segments(-200.0, 260.0):
            x = s0 + rng.uniform(2, 8)
            while x < s1 - 2:
                y = side * (W + 0.75)
                furniture.append((x, y))
                kind = rng.random()
                if kind < 0.6:
                    parts.append(objects.tree(rng.uniform(5, 9), rng.uniform(1.4, 2.6), rng)
                                 .transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                elif kind < 0.88:
                    parts.append(objects.street_lamp(rng.uniform(7, 9), -side).transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                else:
                    parts.append(objects.traffic_sign(rng.uniform(2.4, 3.0), -side,
                                                      _pick(rng, ((0.8, 0.1, 0.1), (0.1, 0.3, 0.8), (0.9, 0.9, 0.9))))
                                 .transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                x += rng.uniform(9, 18)
    return parts, furniture


def generate_layout(name: str, seed: int, t_start: float, duration: float, ego_speed_range: tuple[float, float],
                    origin: F64, heading: float) -> SceneLayout:
    """A procedural scene from ``seed``.

    Args:
        t_start: time [s] at which the ego is at x = 0; ``duration`` [s] the time span the scene must cover.
        origin: (2,) global position [m] of the scene frame origin; ``heading``: road direction in global [rad].
    """
    rng = np.random.default_rng(seed)
    lanes = int(rng.integers(1, 3))
    parking = bool(rng.random() < 0.65)
    W = lanes * LANE_WIDTH + (PARKING_WIDTH if parking else 0.0)
    crossing = float(rng.uniform(25, 80)) if rng.random() < 0.6 else None
    road = RoadGeometry(lanes, W, float(rng.uniform(3.0, 5.0)), crossing, 7.5)
    ego_speed = float(rng.uniform(*ego_speed_range))
    ego_lane_y = -LANE_WIDTH / 2
    T_global_scene = make_transform(yaw_matrix(heading), np.array([origin[0], origin[1], 0.0]))

    static_parts, furniture = _static_world(rng, road)
    times = np.linspace(0.0, duration, 25)
    occ = _Occupancy(times)
    for fx, fy in furniture:  # trunks, posts (lamp heads and crowns overhang above head height)
        occ.boxes.append(occ.footprint(fx, fy, 0.0, 0.0, 0.35, 0.35))
    ego_len, ego_w = 4.9, 2.0
    occ.boxes.append(occ.footprint(0.0, ego_lane_y, ego_speed, 0.0, ego_len / 2 + 1.5, ego_w / 2 + 0.3))

    actors: list[Actor] = []
    R_scene = T_global_scene[:3, :3]

    def add(category: str, attribute: str, size: tuple[float, float, float], mesh: Mesh, x: float, y: float,
            z: float, yaw: float, vx: float, vy: float, margin: float) -> bool:
        half_l = size[1] / 2 if abs(np.sin(yaw)) < 1e-6 else max(size[:2]) / 2
        half_w = size[0] / 2 if abs(np.sin(yaw)) < 1e-6 else max(size[:2]) / 2
        fp = occ.footprint(x, y, vx, vy, half_l + margin, half_w + margin * 0.3)
        if not occ.free(fp):
            return False
        occ.boxes.append(fp)
        instance = len(actors) + 1
        pos = (T_global_scene @ np.array([x, y, z, 1.0]))[:3]
        vel = R_scene @ np.array([vx, vy, 0.0])
        actors.append(Actor(instance, category, attribute, tuple(float(s) for s in size), pos, heading + yaw, vel,
                            t_start, mesh.with_instance(instance)))
        return True

    x_lo, x_hi = SCENE_X_RANGE
    # moving and stopped traffic, per lane
    for direction in (1.0, -1.0):
        for k in range(lanes):
            y = direction * -(LANE_WIDTH / 2 + k * LANE_WIDTH)
            is_ego_lane = direction > 0 and k == 0
            speed = ego_speed if is_ego_lane else float(rng.uniform(3.0, 13.0))
            if not is_ego_lane and rng.random() < 0.15:
                speed = 0.0
            for _ in range(int(rng.integers(3, 8))):
                kind = _pick(rng, ("car",) * 14 + ("truck",) * 2 + ("bus",) + ("motorcycle",))
                if k == lanes - 1 and kind in ("truck", "bus") and lanes > 1:
                    kind = "car"
                category, size, mesh = _vehicle(rng, kind)
                x = float(rng.uniform(x_lo, x_hi))
                attribute = "vehicle.moving" if speed > 0 else "vehicle.stopped"
                if category == "vehicle.motorcycle":
                    attribute = "cycle.with_rider"
                yaw = 0.0 if direction > 0 else np.pi
                add(category, attribute, size, mesh, x, y, 0.0, yaw, direction * speed, 0.0, margin=2.0)
    # cyclists close to the outer edge of each direction
    for direction in (1.0, -1.0):
        for _ in range(int(rng.integers(0, 3))):
            size = (rng.uniform(0.55, 0.7), rng.uniform(1.65, 1.85), rng.uniform(1.6, 1.8))
            rider = (_pick(rng, CLOTHES), _pick(rng, CLOTHES), _pick(rng, objects.SKIN_TONES))
            mesh = objects.bicycle(size, _pick(rng, CAR_COLOURS), rider)
            y = direction * -(lanes * LANE_WIDTH - 0.55)
            add("vehicle.bicycle", "cycle.with_rider", size, mesh, float(rng.uniform(x_lo, x_hi)), y, 0.0,
                0.0 if direction > 0 else np.pi, direction * float(rng.uniform(3.0, 6.5)), 0.0, margin=1.0)
    # parked cars
    if parking:
        for side in (-1.0, 1.0):
            y = side * (lanes * LANE_WIDTH + PARKING_WIDTH / 2)
            x = x_lo + float(rng.uniform(0, 5))
            while x < x_hi:
                category, size, mesh = _vehicle(rng, "car" if rng.random() < 0.92 else "truck")
                x += size[1] / 2
                if rng.random() < 0.7 and (crossing is None or abs(x - crossing) > road.crossing_half_width + 6):
                    add(category, "vehicle.parked", size, mesh, x, y + side * 0.1, 0.0,
                        0.0 if side < 0 else np.pi, 0.0, 0.0, margin=0.1)
                x += size[1] / 2 + float(rng.uniform(0.8, 6.0))
    # pedestrians on the sidewalks
    for _ in range(int(rng.integers(8, 22))):
        side = 1.0 if rng.random() < 0.5 else -1.0
        y = side * (W + rng.uniform(1.4, road.sidewalk_width - 0.4))
        walking = rng.random() < 0.75
        size, mesh = _person(rng, walking)
        if walking:
            sign = 1.0 if rng.random() < 0.5 else -1.0
            speed = float(rng.uniform(0.9, 1.7))
            add("human.pedestrian.adult", "pedestrian.moving", size, mesh, float(rng.uniform(x_lo, x_hi)), y,
                CURB_HEIGHT, 0.0 if sign > 0 else np.pi, sign * speed, 0.0, margin=0.3)
        else:
            add("human.pedestrian.adult", "pedestrian.standing", size, mesh, float(rng.uniform(x_lo, x_hi)), y,
                CURB_HEIGHT, float(rng.uniform(-np.pi, np.pi)), 0.0, 0.0, margin=0.2)
    # people waiting at the crossing
    if crossing is not None:
        for _ in range(int(rng.integers(0, 4))):
            side = 1.0 if rng.random() < 0.5 else -1.0
            size, mesh = _person(rng, False)
            x = crossing + road.crossing_half_width + 2.0 * (1 if rng.random() < 0.5 else -1) + rng.uniform(-1.2, 1.2)
            add("human.pedestrian.adult", "pedestrian.standing", size, mesh, x, side * (W + rng.uniform(0.5, 1.2)),
                CURB_HEIGHT, -side * np.pi / 2, 0.0, 0.0, margin=0.1)
    # parked bicycles
    for _ in range(int(rng.integers(0, 4))):
        side = 1.0 if rng.random() < 0.5 else -1.0
        size = (rng.uniform(0.5, 0.65), rng.uniform(1.6, 1.8), rng.uniform(1.0, 1.15))
        mesh = objects.bicycle(size, _pick(rng, CAR_COLOURS), None)
        add("vehicle.bicycle", "cycle.without_rider", size, mesh, float(rng.uniform(x_lo, x_hi)),
            side * (W + road.sidewalk_width - 0.6), CURB_HEIGHT, 0.0, 0.0, 0.0, margin=0.1)
    # a construction zone: cones along a line, barriers behind them
    if rng.random() < 0.6:
        side = 1.0 if rng.random() < 0.5 else -1.0
        y_line = side * (W - 0.6)  # on the road along the curb
        x0 = float(rng.uniform(10, 90))
        for i in range(int(rng.integers(4, 10))):
            size = (rng.uniform(0.35, 0.45), rng.uniform(0.35, 0.45), rng.uniform(0.7, 1.0))
            add("movable_object.trafficcone", "", size, objects.traffic_cone(size), x0 + 2.5 * i, y_line, 0.0,
                float(rng.uniform(-np.pi, np.pi)), 0.0, 0.0, margin=0.0)
        for i in range(int(rng.integers(1, 5))):
            size = (rng.uniform(2.0, 2.6), rng.uniform(0.45, 0.6), rng.uniform(0.8, 1.05))
            colour = (0.8, 0.8, 0.78) if rng.random() < 0.5 else (0.75, 0.15, 0.05)
            add("movable_object.barrier", "", size, objects.barrier(size, colour),
                x0 + 3.0 * i, side * (W + road.sidewalk_width * 0.5), CURB_HEIGHT, np.pi / 2, 0.0, 0.0, margin=0.0)

    static_mesh = concat([p.transformed(R_scene, T_global_scene[:3, 3]) for p in static_parts]
                         + [a.mesh.transformed(yaw_matrix(a.yaw), a.position) for a in actors if not a.moving])
    sun_az = rng.uniform(-np.pi, np.pi)
    sun_el = np.deg2rad(rng.uniform(25, 60))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    return SceneLayout(name, seed, T_global_scene, road, static_mesh, tuple(actors), ego_speed, ego_lane_y, t_start,
                       duration, sun)
