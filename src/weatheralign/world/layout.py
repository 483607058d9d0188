"""Procedural urban scenes from a seed: a street with lanes, curbs, sidewalks, buildings, trees, poles, an optional
cross street, and road users with nuScenes categories, realistic sizes and constant velocities.

Everything is generated in a scene frame (road along +x, ego starting at x = 0 in the first right-hand lane) and
placed in the global frame by ``T_global_scene``. The street is built for the whole drive (``ego_speed * duration``
metres, 240 m for 20 s at 12 m/s): ground and sidewalks wherever a road user ever is, buildings and street furniture
from well behind the start to well beyond the end (`static_extent`), the cross street somewhere along the drive. Road
users are placed with a uniform density within the window around the ego (`USERS_BEHIND_M` behind to `USERS_AHEAD_M`
ahead) at every time of the scene: each moving user's start position is drawn from the interval of starts that bring it
into that window at some time, so none appears from nowhere near the ego. Road users never overlap each other, the
street furniture or the ego at any time of the scene (an exact test of their constant-velocity footprints over the whole
continuous duration, not a sampled one).
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
USERS_BEHIND_M = 100.0  # road users are placed within this distance behind the ego (the LiDAR's range) ...
USERS_AHEAD_M = 150.0  # ... and this far ahead of it, at every time of the scene [m]
STATIC_BEHIND_M = (320.0, 260.0, 200.0)  # ground + sidewalks, buildings, furniture: from this far behind the start
STATIC_AHEAD_M = (380.0, 320.0, 260.0)  # ... to at least this far ahead of the start ...
STATIC_BEYOND_M = (360.0, 300.0, 240.0)  # ... and this far beyond the end of the drive [m]
MAX_TRAFFIC_SPEED = 13.0  # fastest road user [m/s] (vehicles in a lane: 3..13 m/s; cyclists, pedestrians slower)
PLACEMENT_TRIES = 4  # positions tried per road user before it is left out (occupied elsewhere at some time)

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
    """Scene-frame description of the street used by procedural textures and the map: lanes per direction, half
    width of the road (lanes + parking) and sidewalk width [m], the cross street's centre x and half width [m] (None:
    no cross street); ``x_extent`` (x_min, x_max) [m] of ground, road and sidewalks (`street_extent`) and
    ``built_extent`` of the buildings along the street."""

    lanes_per_direction: int
    road_half_width: float
    sidewalk_width: float
    crossing_x: float | None
    crossing_half_width: float
    x_extent: tuple[float, float] = (-320.0, 380.0)
    built_extent: tuple[float, float] = (-260.0, 320.0)


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
    """Axis-aligned scene-frame footprints of placed road users, each moving at constant velocity, for rejection
    sampling over the continuous scene time [0, ``duration``] (exact: no two footprints overlap at any instant).

    A footprint is a row (x, y, vx, vy, half_x, half_y): centre at t = 0 [m], velocity [m/s], half extents [m]."""

    duration: float
    rows: F64 = field(default_factory=lambda: np.zeros((0, 6)))

    @staticmethod
    def footprint(x: float, y: float, vx: float, vy: float, half_x: float, half_y: float) -> F64:
        return np.array([x, y, vx, vy, half_x, half_y], np.float64)

    def free(self, fp: F64) -> bool:
        """Whether ``fp`` overlaps no placed footprint at any time in [0, duration]. Per axis, the centres' relative
        offset ``d0 + dv t`` is within the summed half extents on an open time interval; the footprints overlap when
        both axes' intervals and [0, duration] intersect in more than a point."""
        if not len(self.rows):
            return True
        lo = np.zeros(len(self.rows))
        hi = np.full(len(self.rows), self.duration)
        for axis in (0, 1):
            d0 = fp[axis] - self.rows[:, axis]
            dv = fp[2 + axis] - self.rows[:, 2 + axis]
            reach = fp[4 + axis] + self.rows[:, 4 + axis]
            moving = dv != 0.0
            with np.errstate(divide="ignore", invalid="ignore"):
                t0 = np.where(moving, (-reach - d0) / dv, -np.inf)
                t1 = np.where(moving, (reach - d0) / dv, np.inf)
            still_apart = ~moving & (np.abs(d0) >= reach)
            lo = np.maximum(lo, np.minimum(t0, t1))
            hi = np.minimum(hi, np.where(still_apart, -np.inf, np.maximum(t0, t1)))
        return not bool(np.any(lo < hi))

    def add(self, fp: F64) -> None:
        self.rows = np.vstack([self.rows, fp[None]])


def box_half_extents(size: tuple[float, float, float], yaw: float) -> tuple[float, float]:
    """Half extents (along x, along y) [m] of the axis-aligned bounds of a box of ``size`` (width, length, height)
    turned by ``yaw`` about z (length along the body x)."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    return c * size[1] / 2 + s * size[0] / 2, s * size[1] / 2 + c * size[0] / 2


def start_interval(vx: float, ego_speed: float, duration: float) -> tuple[float, float]:
    """Scene-frame x [m] at t = 0 of the road users moving along the street at ``vx`` [m/s] that are within the window
    from `USERS_BEHIND_M` behind to `USERS_AHEAD_M` ahead of the ego at some time in [0, ``duration``] (the ego at
    ``ego_speed`` from x = 0): drawn uniformly from it, users of that velocity fill the window uniformly at all
    times."""
    drift = (vx - ego_speed) * duration  # how far such a user moves relative to the ego during the scene
    return -USERS_BEHIND_M - max(drift, 0.0), USERS_AHEAD_M - min(drift, 0.0)


def static_extent(kind: int, ego_speed: float, duration: float) -> tuple[float, float]:
    """Scene-frame x range [m] of the static world's part ``kind`` (0: ground and sidewalks, 1: buildings, 2: street
    furniture): from `STATIC_BEHIND_M` behind the start to `STATIC_AHEAD_M` ahead of it or `STATIC_BEYOND_M` beyond
    the end of the drive, whichever is farther (a short scene keeps the street of the first 6-keyframe scenes)."""
    return -STATIC_BEHIND_M[kind], max(STATIC_AHEAD_M[kind], ego_speed * duration + STATIC_BEYOND_M[kind])


def street_extent(ego_speed: float, duration: float) -> tuple[float, float]:
    """Scene-frame x range [m] of ground and sidewalks: `static_extent` 0, and 30 m beyond every position of any road
    user during the scene (placed by `start_interval`, at most `MAX_TRAFFIC_SPEED` either way)."""
    lo, hi = static_extent(0, ego_speed, duration)
    lo = min(lo, -USERS_BEHIND_M - MAX_TRAFFIC_SPEED * duration - 30.0)
    hi = max(hi, start_interval(-MAX_TRAFFIC_SPEED, ego_speed, duration)[1] + 30.0)
    return float(np.floor(lo)), float(np.ceil(hi))


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


def _static_world(rng: np.random.Generator, road: RoadGeometry,
                  furniture_extent: tuple[float, float]) -> tuple[list[Mesh], list[tuple[float, float]]]:
    """Ground, sidewalks with curbs (over ``road.x_extent``), buildings (over ``road.built_extent``), trees, lamps and
    signs (over ``furniture_extent``) in the scene frame; also the (x, y) of the street furniture, which road users
    must keep clear of."""
    W, sw = road.road_half_width, road.sidewalk_width
    x_lo, x_hi = road.x_extent
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
        for s0, s1 in segments(*road.built_extent):
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
        for s0, s1 in segments(*furniture_extent):
            x = s0 + rng.uniform(2, 8)
            while x < s1 - 2:
                y = side * (W + 0.75)
                furniture.append((x, y))
                kind = rng.random()
                if kind < 0.6:
                    parts.append(objects.tree(rng.uniform(5, 9), rng.uniform(1.4, 2.6), rng)
                                 .transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                elif kind < 0.88:
                    parts.append(objects.street_lamp(rng.uniform(7, 9), -side)
                                 .transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                else:
                    parts.append(objects.traffic_sign(rng.uniform(2.4, 3.0), -side,
                                                      _pick(rng, ((0.8, 0.1, 0.1), (0.1, 0.3, 0.8), (0.9, 0.9, 0.9))))
                                 .transformed(np.eye(3), [x, y, CURB_HEIGHT]))
                x += rng.uniform(9, 18)
    return parts, furniture


EGO_LENGTH, EGO_WIDTH = 4.9, 2.0  # the ego's footprint [m] (kept clear of road users with margins)
COUNT_WINDOW_M = 240.0  # road-user counts are drawn per this length of their start interval [m]


def _count(rng: np.random.Generator, low: int, high: int, length: float) -> int:
    """A count drawn in [low, high) per `COUNT_WINDOW_M`, scaled to ``length`` [m] (a density along the street)."""
    return int(round(int(rng.integers(low, high)) * length / COUNT_WINDOW_M))


def generate_layout(name: str, seed: int, t_start: float, duration: float, ego_speed_range: tuple[float, float],
                    origin: F64, heading: float) -> SceneLayout:
    """A procedural scene from ``seed``, built for the ego's whole drive.

    Args:
        t_start: time [s] at which the ego is at x = 0; ``duration`` [s] the time span the scene must cover: the street
            reaches far beyond the drive, road users fill the window around the ego at every time of it, and none
            overlap during ``[t_start, t_start + duration]``.
        origin: (2,) global position [m] of the scene frame origin; ``heading``: road direction in global [rad].
    """
    rng = np.random.default_rng(seed)
    lanes = int(rng.integers(1, 3))
    parking = bool(rng.random() < 0.65)
    W = lanes * LANE_WIDTH + (PARKING_WIDTH if parking else 0.0)
    crossing_at = float(rng.random()) if rng.random() < 0.6 else None  # where along the drive, 0..1
    sidewalk = float(rng.uniform(3.0, 5.0))
    ego_speed = float(rng.uniform(*ego_speed_range))
    drive = ego_speed * duration
    # the cross street 25 m .. (40 m beyond the end of the drive or 80 m, whichever is farther) ahead of the start
    crossing = None if crossing_at is None else 25.0 + (max(80.0, drive + 40.0) - 25.0) * crossing_at
    road = RoadGeometry(lanes, W, sidewalk, crossing, 7.5, street_extent(ego_speed, duration),
                        static_extent(1, ego_speed, duration))
    ego_lane_y = -LANE_WIDTH / 2
    T_global_scene = make_transform(yaw_matrix(heading), np.array([origin[0], origin[1], 0.0]))

    static_parts, furniture = _static_world(rng, road, static_extent(2, ego_speed, duration))
    place = _Placement(rng, _initial_occupancy(road, furniture, ego_lane_y, ego_speed, duration), T_global_scene,
                       heading, t_start, ego_speed, duration)
    _lane_traffic(place, road)
    _cyclists(place, road)
    if parking:
        _parked_cars(place, road)
    _pedestrians(place, road)
    if crossing is not None:
        _crossing_waiters(place, road)
    _parked_bicycles(place, road)
    _construction_zone(place, road, drive)

    R_scene = T_global_scene[:3, :3]
    actors = place.actors
    static_mesh = concat([p.transformed(R_scene, T_global_scene[:3, 3]) for p in static_parts]
                         + [a.mesh.transformed(yaw_matrix(a.yaw), a.position) for a in actors if not a.moving])
    sun = _sun_direction(rng)
    return SceneLayout(name, seed, T_global_scene, road, static_mesh, tuple(actors), ego_speed, ego_lane_y, t_start,
                       duration, sun)


def _initial_occupancy(road: RoadGeometry, furniture: list[tuple[float, float]], ego_lane_y: float,
                       ego_speed: float, duration: float) -> _Occupancy:
    """What road users must keep clear of: the street furniture at its (x, y) [m], the sidewalk's gap at the cross
    street and the ego (driving at ``ego_speed`` [m/s] along y = ``ego_lane_y``), with margins."""
    W, sw, crossing = road.road_half_width, road.sidewalk_width, road.crossing_x
    occ = _Occupancy(duration)
    for fx, fy in furniture:  # trunks, posts (lamp heads and crowns overhang above head height)
        occ.add(occ.footprint(fx, fy, 0.0, 0.0, 0.35, 0.35))
    if crossing is not None:  # no sidewalk across the cross street: nobody stands or walks there
        for side in (-1.0, 1.0):
            occ.add(occ.footprint(crossing, side * (W + sw / 2), 0.0, 0.0, road.crossing_half_width, sw / 2))
    occ.add(occ.footprint(0.0, ego_lane_y, ego_speed, 0.0, EGO_LENGTH / 2 + 1.5, EGO_WIDTH / 2 + 0.3))
    return occ


@dataclass
class _Placement:
    """Places road users one by one (`add`), each where its footprint stays clear of everything placed before during
    the whole scene, drawing from the scene's random stream ``rng``; ``actors`` in the order placed."""

    rng: np.random.Generator
    occ: _Occupancy
    T_global_scene: F64
    heading: float  # road direction in the global frame [rad]
    t_start: float  # [s]
    ego_speed: float  # [m/s]
    duration: float  # [s]
    actors: list[Actor] = field(default_factory=list)

    def add(self, category: str, attribute: str, size: tuple[float, float, float], mesh: Mesh, xs: list[float],
            y: float, z: float, yaw: float, vx: float, vy: float, *, margin: float, lateral: float) -> bool:
        """Place the road user at the first free start x of ``xs`` (scene frame, t = 0), its footprint grown by
        ``margin`` along x and ``lateral`` along y [m]."""
        occ = self.occ
        half_x, half_y = box_half_extents(size, yaw)
        for x in xs:
            fp = occ.footprint(x, y, vx, vy, half_x + margin, half_y + lateral)
            if occ.free(fp):
                break
        else:
            return False
        occ.add(fp)
        instance = len(self.actors) + 1
        pos = (self.T_global_scene @ np.array([x, y, z, 1.0]))[:3]
        vel = self.T_global_scene[:3, :3] @ np.array([vx, vy, 0.0])
        self.actors.append(Actor(instance, category, attribute, tuple(float(s) for s in size), pos,
                                 self.heading + yaw, vel, self.t_start, mesh.with_instance(instance)))
        return True

    def start_interval(self, vx: float) -> tuple[float, float]:
        """`start_interval` of users moving at ``vx`` [m/s] in this scene."""
        return start_interval(vx, self.ego_speed, self.duration)

    def starts(self, vx: float, first: float | None = None) -> list[float]:
        """`PLACEMENT_TRIES` start positions for a user moving at ``vx``: ``first`` (when given), then uniform draws
        from its `start_interval`."""
        lo, hi = self.start_interval(vx)
        xs = [] if first is None else [first]
        return xs + [float(self.rng.uniform(lo, hi)) for _ in range(PLACEMENT_TRIES - len(xs))]

    def union_start(self, vx_min: float, vx_max: float, count: tuple[int, int]) -> tuple[int, float, float]:
        """For users drawing their own velocity in [vx_min, vx_max] (along x): how many to draw (``count`` per
        `COUNT_WINDOW_M` of the union) and the union of their start intervals. A user's first start is drawn from the
        union and the user is left out unless it lies in its own interval, so every velocity fills the window with the
        same density."""
        lo, hi = self.start_interval(vx_max)[0], self.start_interval(vx_min)[1]
        return _count(self.rng, *count, hi - lo), lo, hi

    def within(self, x: float, vx: float) -> bool:
        """Whether the start ``x`` [m] lies in the `start_interval` of users moving at ``vx``."""
        lo, hi = self.start_interval(vx)
        return lo <= x <= hi


def _lane_traffic(place: _Placement, road: RoadGeometry) -> None:
    """Moving and stopped vehicles, per lane (one speed per lane; the ego's lane at the ego's speed)."""
    rng, lanes = place.rng, road.lanes_per_direction
    for direction in (1.0, -1.0):
        for k in range(lanes):
            y = direction * -(LANE_WIDTH / 2 + k * LANE_WIDTH)
            is_ego_lane = direction > 0 and k == 0
            speed = place.ego_speed if is_ego_lane else float(rng.uniform(3.0, MAX_TRAFFIC_SPEED))
            if not is_ego_lane and rng.random() < 0.15:
                speed = 0.0
            lo, hi = place.start_interval(direction * speed)
            for _ in range(_count(rng, 3, 8, hi - lo)):
                kind = _pick(rng, ("car",) * 14 + ("truck",) * 2 + ("bus",) + ("motorcycle",))
                if k == lanes - 1 and kind in ("truck", "bus") and lanes > 1:
                    kind = "car"
                category, size, mesh = _vehicle(rng, kind)
                attribute = "vehicle.moving" if speed > 0 else "vehicle.stopped"
                if category == "vehicle.motorcycle":
                    attribute = "cycle.with_rider"
                yaw = 0.0 if direction > 0 else np.pi
                place.add(category, attribute, size, mesh, place.starts(direction * speed), y, 0.0, yaw,
                          direction * speed, 0.0, margin=2.0, lateral=0.05)


def _cyclists(place: _Placement, road: RoadGeometry) -> None:
    """Cyclists along the outer edge of each direction's lanes."""
    rng, lanes = place.rng, road.lanes_per_direction
    for direction in (1.0, -1.0):
        n, lo, hi = place.union_start(min(3.0 * direction, 6.5 * direction), max(3.0 * direction, 6.5 * direction),
                                      (0, 3))
        for _ in range(n):
            size = (rng.uniform(0.55, 0.7), rng.uniform(1.65, 1.85), rng.uniform(1.6, 1.8))
            vx = direction * float(rng.uniform(3.0, 6.5))
            x0 = float(rng.uniform(lo, hi))
            if not place.within(x0, vx):
                continue
            rider = (_pick(rng, CLOTHES), _pick(rng, CLOTHES), _pick(rng, objects.SKIN_TONES))
            mesh = objects.bicycle(size, _pick(rng, CAR_COLOURS), rider)
            y = direction * -(lanes * LANE_WIDTH - 0.05 - size[0] / 2)
            place.add("vehicle.bicycle", "cycle.with_rider", size, mesh, place.starts(vx, x0), y, 0.0,
                      0.0 if direction > 0 else np.pi, vx, 0.0, margin=1.0, lateral=0.25)


def _parked_cars(place: _Placement, road: RoadGeometry) -> None:
    """Cars and trucks parked along both parking lanes, with gaps, none in front of the cross street."""
    rng, lanes, crossing = place.rng, road.lanes_per_direction, road.crossing_x
    static_lo, static_hi = place.start_interval(0.0)
    for side in (-1.0, 1.0):
        y = side * (lanes * LANE_WIDTH + PARKING_WIDTH / 2)
        x = static_lo + float(rng.uniform(0, 5))
        while x < static_hi:
            category, size, mesh = _vehicle(rng, "car" if rng.random() < 0.92 else "truck")
            x += size[1] / 2
            if rng.random() < 0.7 and (crossing is None or abs(x - crossing) > road.crossing_half_width + 6):
                place.add(category, "vehicle.parked", size, mesh, [x], y + side * 0.1, 0.0,
                          0.0 if side < 0 else np.pi, 0.0, 0.0, margin=0.1, lateral=0.03)
            x += size[1] / 2 + float(rng.uniform(0.8, 6.0))


def _pedestrians(place: _Placement, road: RoadGeometry) -> None:
    """Pedestrians walking or standing on the sidewalks."""
    rng, W, sw = place.rng, road.road_half_width, road.sidewalk_width
    n, lo, hi = place.union_start(-1.7, 1.7, (8, 22))
    for _ in range(n):
        side = 1.0 if rng.random() < 0.5 else -1.0
        y = side * (W + rng.uniform(1.4, sw - 0.4))
        walking = rng.random() < 0.75
        vx = (1.0 if rng.random() < 0.5 else -1.0) * float(rng.uniform(0.9, 1.7)) if walking else 0.0
        x0 = float(rng.uniform(lo, hi))
        if not place.within(x0, vx):
            continue
        size, mesh = _person(rng, walking)
        if walking:
            place.add("human.pedestrian.adult", "pedestrian.moving", size, mesh, place.starts(vx, x0), y, CURB_HEIGHT,
                      0.0 if vx > 0 else np.pi, vx, 0.0, margin=0.3, lateral=0.09)
        else:
            place.add("human.pedestrian.adult", "pedestrian.standing", size, mesh, place.starts(0.0, x0), y,
                      CURB_HEIGHT, float(rng.uniform(-np.pi, np.pi)), 0.0, 0.0, margin=0.2, lateral=0.06)


def _crossing_waiters(place: _Placement, road: RoadGeometry) -> None:
    """People standing at the cross street's corners, facing the road."""
    rng, W, crossing = place.rng, road.road_half_width, road.crossing_x
    for _ in range(int(rng.integers(0, 4))):
        side = 1.0 if rng.random() < 0.5 else -1.0
        size, mesh = _person(rng, False)
        x = crossing + road.crossing_half_width + 2.0 * (1 if rng.random() < 0.5 else -1) + rng.uniform(-1.2, 1.2)
        place.add("human.pedestrian.adult", "pedestrian.standing", size, mesh, [x],
                  side * (W + rng.uniform(0.5, 1.2)), CURB_HEIGHT, -side * np.pi / 2, 0.0, 0.0, margin=0.1,
                  lateral=0.03)


def _parked_bicycles(place: _Placement, road: RoadGeometry) -> None:
    """Bicycles parked at the outer edge of the sidewalks."""
    rng, W, sw = place.rng, road.road_half_width, road.sidewalk_width
    static_lo, static_hi = place.start_interval(0.0)
    for _ in range(_count(rng, 0, 4, static_hi - static_lo)):
        side = 1.0 if rng.random() < 0.5 else -1.0
        size = (rng.uniform(0.5, 0.65), rng.uniform(1.6, 1.8), rng.uniform(1.0, 1.15))
        mesh = objects.bicycle(size, _pick(rng, CAR_COLOURS), None)
        place.add("vehicle.bicycle", "cycle.without_rider", size, mesh, place.starts(0.0), side * (W + sw - 0.6),
                  CURB_HEIGHT, 0.0, 0.0, 0.0, margin=0.1, lateral=0.03)


def _construction_zone(place: _Placement, road: RoadGeometry, drive: float) -> None:
    """In some scenes (``drive`` [m] the ego's distance) a construction zone: cones along a line near the curb,
    barriers on the sidewalk behind them."""
    rng, W, sw = place.rng, road.road_half_width, road.sidewalk_width
    if rng.random() >= 0.6:
        return
    side = 1.0 if rng.random() < 0.5 else -1.0
    y_line = side * (W - 0.35)  # on the road along the curb
    x0 = float(rng.uniform(10, drive + 90))
    for i in range(int(rng.integers(4, 10))):
        size = (rng.uniform(0.35, 0.45), rng.uniform(0.35, 0.45), rng.uniform(0.7, 1.0))
        place.add("movable_object.trafficcone", "", size, objects.traffic_cone(size), [x0 + 2.5 * i], y_line, 0.0,
                  float(rng.uniform(-np.pi, np.pi)), 0.0, 0.0, margin=0.0, lateral=0.0)
    for i in range(int(rng.integers(1, 5))):
        size = (rng.uniform(2.0, 2.6), rng.uniform(0.45, 0.6), rng.uniform(0.8, 1.05))
        colour = (0.8, 0.8, 0.78) if rng.random() < 0.5 else (0.75, 0.15, 0.05)
        place.add("movable_object.barrier", "", size, objects.barrier(size, colour), [x0 + 3.0 * i],
                  side * (W + sw * 0.5), CURB_HEIGHT, np.pi / 2, 0.0, 0.0, margin=0.0, lateral=0.0)


def _sun_direction(rng: np.random.Generator) -> F64:
    """(3,) unit vector towards the sun: a random azimuth, 25..60° elevation."""
    sun_az = rng.uniform(-np.pi, np.pi)
    sun_el = np.deg2rad(rng.uniform(25, 60))
    return np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
