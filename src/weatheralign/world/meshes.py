"""Triangle meshes with per-triangle material, albedo, LiDAR reflectivity and instance id.

Object builders return meshes in the object's body frame: x forward, y left, z up, origin at the bottom centre of
its annotation box, so the tight box of the mesh is the annotation box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from weatheralign.world.materials import Material

RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Mesh:
    """vertices (V, 3) float64 m; triangles (T, 3) int32; material (T,) uint8; albedo (T, 3) float32 linear RGB;
    reflectivity (T,) float32 LiDAR reflectivity at 905 nm in [0, 1]; instance (T,) int32 (0 = background)."""

    vertices: NDArray[np.float64]
    triangles: NDArray[np.int32]
    material: NDArray[np.uint8]
    albedo: NDArray[np.float32]
    reflectivity: NDArray[np.float32]
    instance: NDArray[np.int32]

    @property
    def num_triangles(self) -> int:
        return len(self.triangles)

    def transformed(self, rotation: NDArray, translation: NDArray) -> Mesh:
        """The mesh moved by ``p -> R p + t`` (R (3, 3), t (3,))."""
        v = self.vertices @ np.asarray(rotation).T + np.asarray(translation)
        return Mesh(v, self.triangles, self.material, self.albedo, self.reflectivity, self.instance)

    def with_instance(self, instance: int) -> Mesh:
        """The same mesh with every triangle labelled ``instance``."""
        return Mesh(self.vertices, self.triangles, self.material, self.albedo, self.reflectivity,
                    np.full(self.num_triangles, instance, dtype=np.int32))


def empty_mesh() -> Mesh:
    return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.uint8), np.zeros((0, 3), np.float32),
                np.zeros(0, np.float32), np.zeros(0, np.int32))


def concat(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all ``meshes`` (triangle order preserved)."""
    meshes = [m for m in meshes if m.num_triangles]
    if not meshes:
        return empty_mesh()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]).astype(np.int32),
        np.concatenate([m.material for m in meshes]),
        np.concatenate([m.albedo for m in meshes]),
        np.concatenate([m.reflectivity for m in meshes]),
        np.concatenate([m.instance for m in meshes]),
    )


def _surface(vertices: NDArray, triangles: NDArray, material: Material, albedo: RGB, reflectivity: float) -> Mesh:
    n = len(triangles)
    return Mesh(np.asarray(vertices, np.float64), np.asarray(triangles, np.int32), np.full(n, material, np.uint8),
                np.tile(np.asarray(albedo, np.float32), (n, 1)), np.full(n, reflectivity, np.float32),
                np.zeros(n, np.int32))


# Faces of a hexahedron with corners ordered: bottom (0..3) counter-clockwise from (-x,-y), top (4..7) above them.
_HEX_FACES = {
    "bottom": [(0, 2, 1), (0, 3, 2)],
    "top": [(4, 5, 6), (4, 6, 7)],
    "front": [(1, 2, 6), (1, 6, 5)],  # +x
    "back": [(0, 4, 7), (0, 7, 3)],  # -x
    "left": [(2, 3, 7), (2, 7, 6)],  # +y
    "right": [(0, 1, 5), (0, 5, 4)],  # -y
}


def hexahedron(corners: NDArray, faces: dict[str, tuple[Material, RGB, float]]) -> Mesh:
    """A six-faced solid from corners (8, 3) (bottom ring then top ring, counter-clockwise from (-x, -y)).

    ``faces`` maps face names (bottom, top, front, back, left, right) to (material, albedo, reflectivity); faces not
    named are omitted.
    """
    parts = [_surface(corners, _HEX_FACES[name], *spec) for name, spec in faces.items()]
    return concat(parts)


def box_corners(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> NDArray[np.float64]:
    """Corners (8, 3) of an axis-aligned box in hexahedron order."""
    return np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                     [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)


def box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, material: Material, albedo: RGB,
        reflectivity: float, top: tuple[Material, RGB, float] | None = None, bottom: bool = False) -> Mesh:
    """Axis-aligned box; sides use ``material``, the top ``top`` (default same), bottom only if ``bottom``."""
    side = (material, albedo, reflectivity)
    faces = {"front": side, "back": side, "left": side, "right": side, "top": top or side}
    if bottom:
        faces["bottom"] = side
    return hexahedron(box_corners(x0, x1, y0, y1, z0, z1), faces)


def tapered_box(length: float, width: float, z0: float, z1: float, top_length: float, top_width: float,
                top_shift_x: float, side: tuple[Material, RGB, float], top: tuple[Material, RGB, float],
                front: tuple[Material, RGB, float] | None = None,
                back: tuple[Material, RGB, float] | None = None, x_centre: float = 0.0) -> Mesh:
    """A box whose top rectangle is smaller (cabins, cargo, torsos); centred at ``x_centre``, y = 0."""
    bl, bw, tl, tw = length / 2, width / 2, top_length / 2, top_width / 2
    xc, xt = x_centre, x_centre + top_shift_x
    corners = np.array([[xc - bl, -bw, z0], [xc + bl, -bw, z0], [xc + bl, bw, z0], [xc - bl, bw, z0],
                        [xt - tl, -tw, z1], [xt + tl, -tw, z1], [xt + tl, tw, z1], [xt - tl, tw, z1]])
    return hexahedron(corners, {"left": side, "right": side, "top": top, "front": front or side,
                                "back": back or side})


def cylinder(radius: float, height: float, material: Material, albedo: RGB, reflectivity: float,
             segments: int = 12, axis: str = "z", centre: tuple[float, float, float] = (0, 0, 0),
             caps: bool = True, top_radius: float | None = None) -> Mesh:
    """A (truncated-cone) cylinder along ``axis`` centred at ``centre``; ``top_radius`` makes a frustum/cone."""
    r1 = radius if top_radius is None else top_radius
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring0 = np.stack([radius * np.cos(a), radius * np.sin(a), np.full(segments, -height / 2)], 1)
    ring1 = np.stack([r1 * np.cos(a), r1 * np.sin(a), np.full(segments, height / 2)], 1)
    verts = [ring0, ring1, [[0, 0, -height / 2], [0, 0, height / 2]]]
    v = np.concatenate(verts).astype(np.float64)
    i = np.arange(segments)
    j = (i + 1) % segments
    tris = [np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)]
    if caps:
        c0, c1 = 2 * segments, 2 * segments + 1
        tris += [np.stack([np.full(segments, c0), j, i], 1),
                 np.stack([np.full(segments, c1), segments + i, segments + j], 1)]
    t = np.concatenate(tris)
    if axis == "x":
        v = v[:, [2, 0, 1]]
    elif axis == "y":
        v = v[:, [1, 2, 0]]
    return _surface(v + np.asarray(centre), t, material, albedo, reflectivity)


def ellipsoid(radii: tuple[float, float, float], material: Material, albedo: RGB, reflectivity: float,
              centre: tuple[float, float, float] = (0, 0, 0), rings: int = 8, segments: int = 12,
              jitter: float = 0.0, rng: np.random.Generator | None = None) -> Mesh:
    """UV ellipsoid with semi-axes ``radii`` [m]; ``jitter`` (fraction) roughens it (tree crowns) using ``rng``."""
    th = np.linspace(0, np.pi, rings + 1)
    ph = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    unit = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    scale = np.ones(len(unit))
    if jitter and rng is not None:
        scale = 1.0 + jitter * rng.uniform(-1, 1, len(unit))
    v = unit * np.asarray(radii) * scale[:, None] + np.asarray(centre)
    tris = []
    for r in range(rings):
        for s in range(segments):
            a, b = r * segments + s, r * segments + (s + 1) % segments
            c, d = a + segments, b + segments
            tris += [(a, c, b), (b, c, d)]
    return _surface(v, np.array(tris), material, albedo, reflectivity)


def torus(major: float, minor: float, material: Material, albedo: RGB, reflectivity: float,
          centre: tuple[float, float, float], segments: int = 16, tube_segments: int = 5) -> Mesh:
    """A torus in the x-z plane (a wheel rolling along x) centred at ``centre``."""
    u = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    w = np.linspace(0, 2 * np.pi, tube_segments, endpoint=False)
    U, W = np.meshgrid(u, w, indexing="ij")
    x = (major + minor * np.cos(W)) * np.cos(U)
    z = (major + minor * np.cos(W)) * np.sin(U)
    y = minor * np.sin(W)
    v = np.stack([x, y, z], -1).reshape(-1, 3) + np.asarray(centre)
    tris = []
    for i in range(segments):
        for k in range(tube_segments):
            a = i * tube_segments + k
            b = ((i + 1) % segments) * tube_segments + k
            c = i * tube_segments + (k + 1) % tube_segments
            d = ((i + 1) % segments) * tube_segments + (k + 1) % tube_segments
            tris += [(a, b, d), (a, d, c)]
    return _surface(v, np.array(tris), material, albedo, reflectivity)


def rod(p0: NDArray | list[float], p1: NDArray | list[float], thickness: float, material: Material, albedo: RGB,
        reflectivity: float) -> Mesh:
    """A square-section bar from ``p0`` to ``p1`` (bicycle frames, arms, lamp arms)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.linalg.norm(d))
    m = box(0, length, -thickness / 2, thickness / 2, -thickness / 2, thickness / 2, material, albedo, reflectivity,
            bottom=True)
    x = d / length
    helper = np.array([0, 0, 1.0]) if abs(x[2]) < 0.9 else np.array([0, 1.0, 0])
    y = np.cross(helper, x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return m.transformed(np.stack([x, y, z], 1), p0)
