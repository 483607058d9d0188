"""Meshes of street furniture and road users, each built to fill its annotation box exactly.

Body frame: x forward, y left, z up; origin at the bottom centre of the box; ``size = (width, length, height)``
in the nuScenes order. Reflectivities are LiDAR (905 nm) values in [0, 1].
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from weatheralign.world.materials import Material as M
from weatheralign.world.meshes import RGB, Mesh, box, concat, cylinder, ellipsoid, hexahedron, rod, tapered_box, torus

GLASS: RGB = (0.04, 0.05, 0.06)
TYRE: RGB = (0.03, 0.03, 0.03)
HEADLIGHT: RGB = (0.9, 0.9, 0.85)
TAILLIGHT: RGB = (0.6, 0.03, 0.03)
PLATE: RGB = (0.85, 0.85, 0.8)
SKIN_TONES: tuple[RGB, ...] = ((0.62, 0.42, 0.32), (0.45, 0.30, 0.20), (0.75, 0.55, 0.45), (0.30, 0.20, 0.14))


def _wheels(length: float, width: float, radius: float, axle_xs: list[float], tyre_width: float = 0.22) -> Mesh:
    parts = []
    for x in axle_xs:
        for side in (-1, 1):
            y = side * (width / 2 - tyre_width / 2)
            parts.append(cylinder(radius, tyre_width, M.TYRE, TYRE, 0.05, segments=12, axis="y", centre=(x, y, radius)))
    return concat(parts)


def car(size: tuple[float, float, float], paint: RGB) -> Mesh:
    """A sedan/SUV filling ``size`` (w, l, h): wheels, a slightly tapered body, a glass cabin, lights, plates."""
    w, l, h = size
    r = 0.32
    body_top = 0.3 + 0.45 * (h - 0.3)
    body = tapered_box(l, w, 0.22, body_top, l - 0.1, w - 0.06, 0.0,
                       side=(M.PAINT, paint, 0.5), top=(M.PAINT, paint, 0.5))
    cabin = tapered_box(0.55 * l, w - 0.12, body_top, h, 0.38 * l, w - 0.3, -0.05 * l,
                        side=(M.GLASS, GLASS, 0.1), top=(M.PAINT, paint, 0.5), x_centre=-0.05 * l)
    front, back = l / 2, -l / 2
    lights = concat([
        box(front - 0.02, front, -w / 2 + 0.1, -w / 2 + 0.35, body_top - 0.2, body_top - 0.08, M.LAMP, HEADLIGHT, 0.9),
        box(front - 0.02, front, w / 2 - 0.35, w / 2 - 0.1, body_top - 0.2, body_top - 0.08, M.LAMP, HEADLIGHT, 0.9),
        box(back, back + 0.02, -w / 2 + 0.1, -w / 2 + 0.35, body_top - 0.2, body_top - 0.08, M.LAMP, TAILLIGHT, 0.9),
        box(back, back + 0.02, w / 2 - 0.35, w / 2 - 0.1, body_top - 0.2, body_top - 0.08, M.LAMP, TAILLIGHT, 0.9),
        box(front - 0.015, front + 1e-3, -0.26, 0.26, 0.35, 0.47, M.PLATE, PLATE, 0.95),
        box(back - 1e-3, back + 0.015, -0.26, 0.26, 0.45, 0.57, M.PLATE, PLATE, 0.95),
    ])
    return concat([body, cabin, lights, _wheels(l, w, r, [front - 0.85, back + 0.85])])


EGO_PAINT: RGB = (0.20, 0.21, 0.22)
"""The ego's paint (a silver-grey hatch, linear albedo)."""


def ego_rear(corners: NDArray) -> Mesh:
    """The ego's rear body as the cameras see it: the solid of ``corners`` (8, 3) (`weatheralign.sensors.EgoBody.
    corners`, ego frame; bottom ring then top ring), its sloping hatch, rear face and sides painted (the face towards
    the cabin and the underside are never in view), instance 0 (not an annotation)."""
    paint = (M.PAINT, EGO_PAINT, 0.5)
    return hexahedron(np.asarray(corners, dtype=np.float64), {"top": paint, "back": paint, "left": paint,
                                                              "right": paint})


def truck(size: tuple[float, float, float], cab_paint: RGB, cargo: RGB) -> Mesh:
    """A box truck: cab with windscreen at the front, a cargo box behind, three axles."""
    w, l, h = size
    r = 0.45
    cab_l = 2.2
    x_cab = l / 2 - cab_l / 2
    cab = tapered_box(cab_l, w, 0.45, h * 0.78, cab_l - 0.3, w - 0.1, -0.15,
                      side=(M.PAINT, cab_paint, 0.5), top=(M.PAINT, cab_paint, 0.5),
                      front=(M.GLASS, GLASS, 0.1), x_centre=x_cab)
    cargo_box = box(-l / 2, l / 2 - cab_l - 0.15, -w / 2, w / 2, 0.55, h, M.PAINT, cargo, 0.6)
    chassis = box(-l / 2 + 0.3, l / 2 - 0.2, -w / 2 + 0.3, w / 2 - 0.3, 0.4, 0.6, M.METAL, (0.1, 0.1, 0.1), 0.2)
    axles = [l / 2 - 1.1, -l / 2 + 2.2, -l / 2 + 1.1]
    return concat([cab, cargo_box, chassis, _wheels(l, w, r, axles, 0.3)])


def bus(size: tuple[float, float, float], paint: RGB) -> Mesh:
    """A rigid city bus: a long box whose window band is textured (`Material.BUS_BODY`), glass front."""
    w, l, h = size
    r = 0.5
    body = box(-l / 2, l / 2 - 0.05, -w / 2, w / 2, 0.3, h, M.BUS_BODY, paint, 0.55)
    screen = box(l / 2 - 0.05, l / 2, -w / 2 + 0.1, w / 2 - 0.1, 1.0, h - 0.3, M.GLASS, GLASS, 0.1)
    return concat([body, screen, _wheels(l, w, r, [l / 2 - 2.5, -l / 2 + 3.0], 0.3)])


def pedestrian(size: tuple[float, float, float], clothes: RGB, trousers: RGB, skin: RGB,
               stride: float = 0.0) -> Mesh:
    """An upright person in ``size`` (w, l, h): legs (apart by ``stride`` m along x), torso, arms, head."""
    w, l, h = size
    leg_h = 0.47 * h
    torso_top = 0.82 * h
    head_r = min(0.11, 0.065 * h)
    legs = concat([
        rod([s * stride / 2, side * 0.1, 0.0], [0.0, side * 0.1, leg_h], 0.14, M.CLOTH, trousers, 0.3)
        for s, side in ((1, -1), (-1, 1))
    ])
    torso = tapered_box(min(0.26, l * 0.5), min(0.42, w * 0.8), leg_h - 0.02, torso_top, 0.2, min(0.44, w * 0.82),
                        0.0, side=(M.CLOTH, clothes, 0.4), top=(M.CLOTH, clothes, 0.4))
    arms = concat([
        rod([side * stride * 0.2, side * w * 0.42, leg_h + 0.05], [0.0, side * w * 0.42, torso_top - 0.03], 0.09,
            M.CLOTH, clothes, 0.4) for side in (-1, 1)
    ])
    neck = cylinder(0.05, h - torso_top - 2 * head_r + 0.02, M.SKIN, skin, 0.35, segments=6,
                    centre=(0, 0, torso_top + (h - torso_top - 2 * head_r) / 2))
    head = ellipsoid((head_r * 0.95, head_r * 0.85, head_r), M.SKIN, skin, 0.35, centre=(0, 0, h - head_r),
                     rings=6, segments=8)
    mesh = concat([legs, torso, arms, neck, head])
    return _fit_xy(mesh, w, l)


def bicycle(size: tuple[float, float, float], frame: RGB, rider: tuple[RGB, RGB, RGB] | None,
            motor: bool = False) -> Mesh:
    """A bicycle (or motorcycle with ``motor``), optionally with a seated rider (clothes, trousers, skin)."""
    w, l, h = size
    r = 0.32 if not motor else 0.31
    minor = 0.025 if not motor else 0.06
    xf, xb = l / 2 - r - minor, -l / 2 + r + minor
    parts = [torus(r, minor, M.TYRE, TYRE, 0.05, (xf, 0, r + minor)),
             torus(r, minor, M.TYRE, TYRE, 0.05, (xb, 0, r + minor))]
    seat = np.array([xb + 0.35, 0, 0.95 if not motor else 0.8])
    bar = np.array([xf - 0.1, 0, 1.05 if not motor else 1.0])
    hub_f, hub_b = np.array([xf, 0, r + minor]), np.array([xb, 0, r + minor])
    crank = np.array([(xf + xb) / 2 - 0.05, 0, r + minor])
    t = 0.04 if not motor else 0.08
    parts += [rod(hub_b, seat, t, M.PAINT, frame, 0.5), rod(seat, bar, t, M.PAINT, frame, 0.5),
              rod(bar, hub_f, t, M.PAINT, frame, 0.5), rod(crank, seat, t, M.PAINT, frame, 0.5),
              rod(hub_b, crank, t, M.PAINT, frame, 0.5),
              rod(bar + [0, -0.28, 0], bar + [0, 0.28, 0], 0.03, M.METAL, (0.2, 0.2, 0.2), 0.5)]
    if motor:
        parts.append(tapered_box(0.9, 0.35, r + 0.05, 0.85, 0.7, 0.3, 0.0, side=(M.PAINT, frame, 0.5),
                                 top=(M.PAINT, frame, 0.5), x_centre=(xf + xb) / 2))
    if rider is not None:
        clothes, trousers, skin = rider
        hip = seat + [0, 0, 0.05]
        shoulder = np.array([(seat[0] + bar[0]) / 2 + 0.05, 0, h - 0.3])
        parts += [rod(hip + [0, s * 0.12, 0], crank + [0, s * 0.15, 0.05], 0.12, M.CLOTH, trousers, 0.3)
                  for s in (-1, 1)]
        parts.append(rod(hip, shoulder, 0.34, M.CLOTH, clothes, 0.4))
        parts += [rod(shoulder + [0, s * 0.2, 0], bar + [0, s * 0.25, 0], 0.08, M.CLOTH, clothes, 0.4)
                  for s in (-1, 1)]
        parts.append(ellipsoid((0.1, 0.09, 0.11), M.SKIN, skin, 0.35, centre=tuple(shoulder + [0.05, 0, 0.2]),
                               rings=6, segments=8))
    return _fit(concat(parts), size)


def traffic_cone(size: tuple[float, float, float]) -> Mesh:
    """An orange cone on a square base; a retro-reflective band is textured (`Material.CONE`)."""
    w, l, h = size
    base = box(-l / 2, l / 2, -w / 2, w / 2, 0.0, 0.04, M.CONE, (0.1, 0.1, 0.1), 0.2)
    cone = cylinder(min(w, l) * 0.42, h - 0.04, M.CONE, (0.9, 0.25, 0.02), 0.5, segments=14,
                    centre=(0, 0, 0.04 + (h - 0.04) / 2), top_radius=0.025, caps=False)
    return concat([base, cone])


def barrier(size: tuple[float, float, float], colour: RGB) -> Mesh:
    """A jersey-style barrier: wide base, narrow top; the long side is the box width (nuScenes convention)."""
    w, l, h = size
    return tapered_box(l, w, 0.0, h, l * 0.45, w * 0.98, 0.0, side=(M.BARRIER, colour, 0.45),
                       top=(M.BARRIER, colour, 0.45))


def tree(height: float, crown_radius: float, rng: np.random.Generator) -> Mesh:
    """A street tree: trunk plus a rough ellipsoid crown of varying green."""
    trunk_h = max(4.0, height - 1.6 * crown_radius)  # crowns stay above people, vans and trucks
    green = (0.08 + 0.06 * rng.random(), 0.2 + 0.1 * rng.random(), 0.05 + 0.04 * rng.random())
    trunk = cylinder(0.14 + 0.06 * rng.random(), trunk_h + 0.3, M.TRUNK, (0.2, 0.13, 0.08), 0.35, segments=8,
                     centre=(0, 0, (trunk_h + 0.3) / 2), caps=False)
    crown = ellipsoid((crown_radius, crown_radius, 0.85 * crown_radius), M.FOLIAGE, green, 0.45,
                      centre=(0, 0, trunk_h + 0.8 * crown_radius), rings=7, segments=11, jitter=0.18, rng=rng)
    return concat([trunk, crown])


def street_lamp(height: float, arm_direction: float) -> Mesh:
    """A lamp post with an arm over the road in direction ``arm_direction`` (+1 = +y, -1 = -y)."""
    grey = (0.25, 0.26, 0.27)
    post = cylinder(0.09, height, M.METAL, grey, 0.4, segments=8, centre=(0, 0, height / 2), caps=False)
    arm = rod([0, 0, height - 0.3], [0, arm_direction * 1.8, height - 0.1], 0.08, M.METAL, grey, 0.4)
    head = box(-0.2, 0.2, arm_direction * 1.7 - 0.3, arm_direction * 1.7 + 0.3, height - 0.25, height - 0.05,
               M.LAMP, (0.85, 0.85, 0.8), 0.6, bottom=True)
    return concat([post, arm, head])


def traffic_sign(height: float, facing: float, colour: RGB) -> Mesh:
    """A sign pole with a square retro-reflective plate facing ``facing`` (+1 = +x)."""
    post = cylinder(0.04, height, M.METAL, (0.4, 0.4, 0.42), 0.4, segments=6, centre=(0, 0, height / 2), caps=False)
    x = facing * 0.06
    plate = box(min(x, x + facing * 0.02), max(x, x + facing * 0.02), -0.35, 0.35, height - 0.7, height, M.SIGN,
                colour, 0.9)
    return concat([post, plate])


def building(x0: float, x1: float, y0: float, y1: float, height: float, colour: RGB) -> Mesh:
    """A block building: textured facades (`Material.FACADE`) and a flat roof."""
    return box(x0, x1, y0, y1, 0.0, height, M.FACADE, colour, 0.5, top=(M.ROOF, (0.3, 0.3, 0.32), 0.3))


def _fit(mesh: Mesh, size: tuple[float, float, float]) -> Mesh:
    """Scale/translate a mesh so its bounding box is exactly the annotation box of ``size`` (w, l, h)."""
    w, l, h = size
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    scale = np.array([l, w, h]) / np.maximum(hi - lo, 1e-6)
    v = (mesh.vertices - lo) * scale + np.array([-l / 2, -w / 2, 0.0])
    return Mesh(v, mesh.triangles, mesh.material, mesh.albedo, mesh.reflectivity, mesh.instance)


def _fit_xy(mesh: Mesh, w: float, l: float) -> Mesh:
    h = float(mesh.vertices[:, 2].max())
    return _fit(mesh, (w, l, h))
