"""Ray casting against the scene geometry for every sensor.

Any set of rays (a rolling LiDAR sweep) is cast with open3d `RaycastingScene` (Embree): static geometry lives in one
cached BVH, each moving actor has its own cached BVH in its body frame. Every ray is cast at its own time: rays that
can reach an actor (its bounding sphere where it is at the ray's time, found by a numba kernel that tests chunks of
consecutive rays before single rays) are moved into the actor's body frame by the inverse actor pose at that time
and cast there, so that a 50 ms sweep sees a moving car where it is at each firing.

The two big coherent ray sets of a camera image are answered by `raster` instead, with the same results at a fraction
of the cost: pixel rays (one origin, one instant) by rasterising every triangle with the actors posed at that
instant; shadow rays (one direction, the sun) by `SunGrid`s of the static scene (built once) and of the posed actors.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import open3d as o3d
from numba import njit
from numpy.typing import NDArray

from weatheralign.geometry import yaw_matrix
from weatheralign.world.layout import Actor, SceneLayout
from weatheralign.world.meshes import Mesh
from weatheralign.world.raster import (
    MAX_MOVING_SUN_CELLS,
    SunGrid,
    TriangleTable,
    Vec3,
    gather_rows,
    pinhole_depth,
    pixel_ranges,
    sun_blocked,
    sun_grid,
    triangle_normals,
)


@dataclass(frozen=True)
class Hits:
    """Ray hits: ``range`` (N,) float64 metres along the unit ray (inf = no hit); ``normal`` (N, 3) float32 unit
    geometric normal facing the ray origin; per-hit triangle attributes ``material`` (N,) uint8, ``albedo`` (N, 3),
    ``reflectivity`` (N,) float32 and ``instance`` (N,) int32 (0 = background)."""

    range: NDArray[np.float64]
    normal: NDArray[np.float32]
    material: NDArray[np.uint8]
    albedo: NDArray[np.float32]
    reflectivity: NDArray[np.float32]
    instance: NDArray[np.int32]


def scene_of_mesh(mesh: Mesh, nthreads: int) -> o3d.t.geometry.RaycastingScene:
    """An Embree BVH of ``mesh`` (its triangle ids index the mesh's per-triangle arrays), committed (open3d builds
    the BVH on the first query: done here, so later concurrent queries only read it)."""
    scene = o3d.t.geometry.RaycastingScene(nthreads=nthreads)
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    scene.cast_rays(o3d.core.Tensor(np.array([[0.0, 0.0, 0.0, 0.0, 0.0, 1.0]], np.float32)), nthreads=1)
    return scene


def cast_rays(scene: o3d.t.geometry.RaycastingScene, origins: NDArray, directions: NDArray,
              nthreads: int = 0) -> tuple[NDArray, NDArray, NDArray]:
    """Cast rays (N, 3) + unit (N, 3) with ``nthreads`` native threads (0: all cores): hit distance (N,) [m]
    (inf = miss), triangle id (N,), normal (N, 3)."""
    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = directions
    out = scene.cast_rays(o3d.core.Tensor(rays), nthreads=nthreads)
    t = out["t_hit"].numpy().astype(np.float64)
    prim = out["primitive_ids"].numpy().astype(np.int64)
    normal = out["primitive_normals"].numpy()
    return t, prim, normal


RAY_CHUNK = 64  # consecutive rays that share one bounding cone in the candidate search


@njit(nogil=True, cache=True, inline="always")
def _chunk_bounds(origins: NDArray, dirs: NDArray, times: NDArray, tmax: NDArray, lo: int,
                  hi: int) -> tuple[Vec3, float, Vec3, float, float, float, float]:
    """Bounds of rays ``lo:hi``: origin centre and radius, direction cone axis and cosine of its half-angle (-1:
    unbounded), time range, largest ``tmax``."""
    x0 = y0 = z0 = np.inf
    x1 = y1 = z1 = -np.inf
    ax = ay = az = 0.0
    t0, t1, far = np.inf, -np.inf, 0.0
    for i in range(lo, hi):
        x0, x1 = min(x0, origins[i, 0]), max(x1, origins[i, 0])
        y0, y1 = min(y0, origins[i, 1]), max(y1, origins[i, 1])
        z0, z1 = min(z0, origins[i, 2]), max(z1, origins[i, 2])
        ax, ay, az = ax + dirs[i, 0], ay + dirs[i, 1], az + dirs[i, 2]
        t0, t1, far = min(t0, times[i]), max(t1, times[i]), max(far, tmax[i])
    centre = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (z0 + z1))
    spread = 0.5 * np.sqrt((x1 - x0) ** 2 + (y1 - y0) ** 2 + (z1 - z0) ** 2)
    norm = np.sqrt(ax * ax + ay * ay + az * az)
    if norm < 1e-6:
        return centre, spread, (0.0, 0.0, 0.0), -1.0, t0, t1, far
    ax, ay, az = ax / norm, ay / norm, az / norm
    cos_cone = 1.0
    for i in range(lo, hi):
        cos_cone = min(cos_cone, dirs[i, 0] * ax + dirs[i, 1] * ay + dirs[i, 2] * az)
    return centre, spread, (ax, ay, az), cos_cone, t0, t1, far


@njit(nogil=True, cache=True, inline="always")
def _chunk_may_reach(centre: Vec3, spread: float, axis: Vec3, cos_cone: float, far: float, sphere: Vec3,
                     radius: float) -> bool:
    """Whether any ray from within ``spread`` of ``centre`` in the cone (``axis``, ``cos_cone``), no longer than
    ``far``, can meet the ball of ``radius`` around ``sphere`` (a conservative test)."""
    rx, ry, rz = sphere[0] - centre[0], sphere[1] - centre[1], sphere[2] - centre[2]
    dist = np.sqrt(rx * rx + ry * ry + rz * rz)
    reach = radius + spread
    if dist <= reach:
        return True
    if dist - reach > far:
        return False
    if cos_cone <= 0.0:
        return True
    # the angle between the axis and the ball <= the cone's half-angle + the ball's angular radius
    sin_b = reach / dist
    cos_sum = cos_cone * np.sqrt(1.0 - sin_b * sin_b) - np.sqrt(1.0 - cos_cone * cos_cone) * sin_b
    return rx * axis[0] + ry * axis[1] + rz * axis[2] >= cos_sum * dist


@njit(nogil=True, cache=True)
def _actor_candidates(origins: NDArray, dirs: NDArray, times: NDArray, tmax: NDArray, positions: NDArray,
                      velocities: NDArray, t_refs: NDArray, radii: NDArray) -> tuple[NDArray, NDArray]:
    """Rays (N,) that pass within ``radii`` (A,) of actor bottom-centres ``positions + velocities (t - t_refs)``
    ((A, 3), (A, 3), (A,)) at each ray's own ``times`` (N,), in front of the origin and before ``tmax`` (N,) [m].

    Returns ray indices grouped by actor (ascending within an actor) and (A + 1,) start offsets per actor.
    """
    n, n_act = len(origins), len(radii)
    speeds = np.sqrt((velocities**2).sum(axis=1))
    pairs = np.empty((max(1024, n // 16), 2), np.int64)
    count = 0
    for lo in range(0, n, RAY_CHUNK):
        hi = min(lo + RAY_CHUNK, n)
        centre, spread, axis, cos_cone, t0, t1, far = _chunk_bounds(origins, dirs, times, tmax, lo, hi)
        for a in range(n_act):
            dt = 0.5 * (t0 + t1) - t_refs[a]
            sphere = (positions[a, 0] + velocities[a, 0] * dt, positions[a, 1] + velocities[a, 1] * dt,
                      positions[a, 2] + velocities[a, 2] * dt)
            reach = radii[a] + speeds[a] * 0.5 * (t1 - t0)  # the ball around the actor over the chunk's times
            if not _chunk_may_reach(centre, spread, axis, cos_cone, far, sphere, reach):
                continue
            r = radii[a]
            for i in range(lo, hi):
                dt = times[i] - t_refs[a]
                rel0 = positions[a, 0] + velocities[a, 0] * dt - origins[i, 0]
                rel1 = positions[a, 1] + velocities[a, 1] * dt - origins[i, 1]
                rel2 = positions[a, 2] + velocities[a, 2] * dt - origins[i, 2]
                along = rel0 * dirs[i, 0] + rel1 * dirs[i, 1] + rel2 * dirs[i, 2]
                perp2 = rel0 * rel0 + rel1 * rel1 + rel2 * rel2 - along * along
                if perp2 < r * r and along > -r and along - r < tmax[i]:
                    if count == len(pairs):
                        grown = np.empty((2 * len(pairs), 2), np.int64)
                        grown[:count] = pairs
                        pairs = grown
                    pairs[count, 0], pairs[count, 1] = i, a
                    count += 1
    starts = np.zeros(n_act + 1, np.int64)
    for k in range(count):
        starts[pairs[k, 1] + 1] += 1
    starts = np.cumsum(starts)
    fill = starts[:-1].copy()
    rays = np.empty(count, np.int64)
    for k in range(count):  # stable counting sort by actor
        a = pairs[k, 1]
        rays[fill[a]] = pairs[k, 0]
        fill[a] += 1
    return rays, starts


@njit(nogil=True, cache=True)
def _finish_kernel(gid: NDArray, normal: NDArray, dirs: NDArray, tri_material: NDArray,
                   tri_albedo: NDArray, tri_reflectivity: NDArray, tri_instance: NDArray, material: NDArray,
                   albedo: NDArray, reflectivity: NDArray, instance: NDArray) -> None:
    """Per-hit triangle attributes by global triangle id ``gid`` (N,) (-1: none), normals turned towards the ray
    origin in place."""
    for i in range(len(gid)):
        g = gid[i]
        if g >= 0:
            material[i], reflectivity[i], instance[i] = tri_material[g], tri_reflectivity[g], tri_instance[g]
            for c in range(3):
                albedo[i, c] = tri_albedo[g, c]
        else:
            material[i], reflectivity[i], instance[i] = 0, 0.0, 0
            for c in range(3):
                albedo[i, c] = 0.0
        if normal[i, 0] * dirs[i, 0] + normal[i, 1] * dirs[i, 1] + normal[i, 2] * dirs[i, 2] > 0:
            for c in range(3):
                normal[i, c] = -normal[i, c]


class WorldRaycaster:
    """Casts rays into one `SceneLayout` at given times."""

    def __init__(self, layout: SceneLayout, nthreads: int = 0, ego_body: Mesh | None = None) -> None:
        """``ego_body``: the ego's own body (ego frame), seen by the cameras only (`camera_depth`; a LiDAR does not
        report its own car), posed with the ego at each camera's time."""
        self.layout = layout
        self.nthreads = nthreads
        self._static = scene_of_mesh(layout.static_mesh, nthreads) if layout.static_mesh.num_triangles else None
        self._moving: tuple[Actor, ...] = tuple(a for a in layout.actors if a.moving)
        self._moving_scenes = [scene_of_mesh(a.mesh, nthreads) for a in self._moving]
        self._moving_radius = np.array([np.linalg.norm(a.mesh.vertices, axis=1).max() for a in self._moving])
        self._moving_positions = np.array([a.position for a in self._moving], np.float64).reshape(-1, 3)
        self._moving_velocities = np.array([a.velocity for a in self._moving], np.float64).reshape(-1, 3)
        self._moving_t_refs = np.array([a.t_ref for a in self._moving], np.float64)
        # one triangle table: the static mesh, then each moving actor's mesh (global triangle id = offset + id)
        meshes = [layout.static_mesh, *(a.mesh for a in self._moving)]
        self._offsets = np.cumsum([0] + [m.num_triangles for m in meshes])
        self._tri_material = np.concatenate([m.material for m in meshes])
        self._tri_albedo = np.concatenate([m.albedo for m in meshes]).astype(np.float32)
        self._tri_reflectivity = np.concatenate([m.reflectivity for m in meshes]).astype(np.float32)
        self._tri_instance = np.concatenate([m.instance for m in meshes]).astype(np.int32)
        vertex_offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
        self._triangles = np.concatenate([m.triangles.astype(np.int64) + o for m, o in zip(meshes, vertex_offsets)])
        self._static_counts = (len(layout.static_mesh.vertices), layout.static_mesh.num_triangles)
        self._normals = [triangle_normals(m) for m in meshes]  # static: global frame; actors: body frame
        self._static_normals32 = self._normals[0].astype(np.float32)
        self._posed: tuple[float, tuple[NDArray, NDArray]] | None = None
        # the moving actors translate and never turn: their vertices turned and placed at t_ref, each vertex's
        # velocity and t_ref, their turned normals (`_moving_at`)
        turns = [yaw_matrix(a.yaw) for a in self._moving]
        self._moving_base = np.concatenate(
            [np.zeros((0, 3))] + [a.mesh.vertices @ R.T + a.position for a, R in zip(self._moving, turns)])
        self._moving_velocity = np.concatenate(
            [np.zeros((0, 3))] + [np.broadcast_to(a.velocity, (len(a.mesh.vertices), 3)) for a in self._moving])
        self._moving_t_ref = np.concatenate(
            [np.zeros(0)] + [np.full(len(a.mesh.vertices), a.t_ref) for a in self._moving])
        self._moving_normals = np.concatenate(
            [np.zeros((0, 3))] + [n @ R.T for n, R in zip(self._normals[1:], turns)])
        # the cameras' triangle table: the same, then the ego body's triangles (their vertices follow the actors')
        self._ego = ego_body
        cam_meshes = meshes if ego_body is None else [*meshes, ego_body]
        cam_vertex_offsets = np.cumsum([0] + [len(m.vertices) for m in cam_meshes])
        self._cam_triangles = np.concatenate([m.triangles.astype(np.int64) + o
                                              for m, o in zip(cam_meshes, cam_vertex_offsets)])
        self._cam_table = (np.concatenate([m.material for m in cam_meshes]),
                           np.concatenate([m.albedo for m in cam_meshes]).astype(np.float32),
                           np.concatenate([m.reflectivity for m in cam_meshes]).astype(np.float32),
                           np.concatenate([m.instance for m in cam_meshes]).astype(np.int32))
        self._ego_normals = np.zeros((0, 3)) if ego_body is None else triangle_normals(ego_body)

    def cast_rolling(self, origins: NDArray, directions: NDArray, times: NDArray) -> Hits:
        """Cast rays whose times differ (a rolling LiDAR sweep): each ray sees every moving actor where it is at
        that ray's time ``times`` (N,) [s]. Origins/directions (N, 3) in the global frame.

        Static geometry by its BVH; moving actors by `_actor_candidates` (the rays that pass near an actor at their
        own times), cast into the actor's BVH in its body frame."""
        n = len(origins)
        if self._static is not None:
            t, tri, normal = cast_rays(self._static, origins, directions, self.nthreads)
            gid = np.where(np.isfinite(t), tri, -1)
            normal = normal.astype(np.float32, copy=False)
        else:
            t, gid, normal = np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3), np.float32)
        if self._moving:
            origins = np.ascontiguousarray(origins, np.float64)
            directions = np.ascontiguousarray(directions, np.float64)
            times = np.ascontiguousarray(times, np.float64)
            rays, starts = _actor_candidates(origins, directions, times, t, self._moving_positions,
                                             self._moving_velocities, self._moving_t_refs, self._moving_radius)
            for k, actor in enumerate(self._moving):
                idx = rays[starts[k]:starts[k + 1]]
                if not len(idx):
                    continue
                R = yaw_matrix(actor.yaw)
                o_body = (origins[idx] - actor.position_at(times[idx])) @ R  # R^T (o - p)
                tb, trib, nb = cast_rays(self._moving_scenes[k], o_body, directions[idx] @ R, self.nthreads)
                closer = tb < t[idx]
                sel = idx[closer]
                t[sel] = tb[closer]
                gid[sel] = self._offsets[k + 1] + trib[closer]
                normal[sel] = (nb[closer] @ R.T).astype(np.float32)
        return self._finish(t, gid, normal, directions)

    def _finish(self, t: NDArray, gid: NDArray, normal: NDArray, directions: NDArray,
                camera: bool = False) -> Hits:
        """`Hits` from hit distances (N,), global triangle ids (N,) (-1: none) and normals (N, 3) float32 (turned
        towards the ray origin in place); ``camera``: ids of the cameras' table (with the ego body)."""
        n = len(t)
        hits = Hits(t, normal, np.empty(n, np.uint8), np.empty((n, 3), np.float32), np.empty(n, np.float32),
                    np.empty(n, np.int32))
        table = self._cam_table if camera else (self._tri_material, self._tri_albedo, self._tri_reflectivity,
                                                self._tri_instance)
        _finish_kernel(gid, normal, directions, *table, hits.material, hits.albedo, hits.reflectivity, hits.instance)
        return hits

    def cast_at_time(self, origins: NDArray, directions: NDArray, time: float) -> Hits:
        """Cast rays (N, 3) origins, (N, 3) unit directions, global frame, all at one instant ``time`` [s]."""
        return self.cast_rolling(origins, directions, np.full(len(origins), time))

    def camera_depth(self, K: NDArray, T_global_cam: NDArray, width: int, height: int,
                     time: float) -> tuple[NDArray[np.float64], NDArray[np.int64], TriangleTable]:
        """The nearest triangle along each pixel-centre ray (row-major, H*W) of a pinhole camera with intrinsics ``K``
        (3, 3) and pose ``T_global_cam`` (4, 4) at ``time`` [s], by rasterising every triangle with an exact per-pixel
        ray test (`raster.pinhole_depth`; of coincident surfaces, the later triangle): the inverse camera depth
        (H*W,) [1/m] (0: nothing), the triangle (H*W,) (-1: nothing) and the `TriangleTable` it indexes (the scene
        posed at ``time``)."""
        R, o = T_global_cam[:3, :3], T_global_cam[:3, 3]
        moving, moving_normals = self._moving_at(time)
        parts, normals = [self.layout.static_mesh.vertices, moving], [self._static_normals32, moving_normals]
        if self._ego is not None:
            T_global_ego = self.layout.T_global_ego(time)
            parts.append(self._ego.vertices @ T_global_ego[:3, :3].T + T_global_ego[:3, 3])
            normals.append(self._ego_normals @ T_global_ego[:3, :3].T)
        verts_cam = (np.concatenate(parts) - o) @ R  # R^T (v - o)
        inv_depth, gid = pinhole_depth(verts_cam, self._cam_triangles, K, width, height)
        normal = np.concatenate(normals).astype(np.float32)
        return inv_depth, gid, TriangleTable(normal, *self._cam_table)

    def cast_camera(self, K: NDArray, T_global_cam: NDArray, width: int, height: int, time: float,
                    directions: NDArray) -> Hits:
        """Hits of the pixel-centre rays (row-major, H*W) of a pinhole camera with intrinsics ``K`` (3, 3) and pose
        ``T_global_cam`` (4, 4) at ``time`` [s]; ``directions`` (H*W, 3) are those rays' unit global directions.

        The same as `cast_at_time` of those rays (of coincident surfaces, the later triangle), computed by
        rasterising every triangle with an exact per-pixel ray test (`camera_depth`; several times cheaper than
        tracing each pixel).
        """
        inv_depth, gid, tris = self.camera_depth(K, T_global_cam, width, height, time)
        normal = gather_rows(tris.normal, gid)
        return self._finish(pixel_ranges(inv_depth, K, width), gid, normal, directions, camera=True)

    def _moving_at(self, time: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The moving actors' vertices (V, 3) (in the order of `_triangles`) and triangle normals (T, 3) posed at
        ``time`` [s], global frame (the last instant's are kept: a camera asks twice)."""
        last = self._posed
        if last is not None and last[0] == time:
            return last[1]
        posed = self._moving_base + self._moving_velocity * (time - self._moving_t_ref)[:, None], self._moving_normals
        self._posed = (time, posed)
        return posed

    @cached_property
    def _sun_grid(self) -> SunGrid:
        mesh = self.layout.static_mesh
        return sun_grid(mesh.vertices, mesh.triangles, self.layout.sun_direction)

    def moving_sun_grid(self, time: float) -> SunGrid | None:
        """The `SunGrid` of the moving actors posed at ``time`` [s] (None: no moving actors)."""
        if not self._moving:
            return None
        n_vertices, n_triangles = self._static_counts
        return sun_grid(self._moving_at(time)[0], self._triangles[n_triangles:] - n_vertices,
                        self.layout.sun_direction, MAX_MOVING_SUN_CELLS)

    @property
    def static_sun_grid(self) -> SunGrid:
        """The `SunGrid` of the static scene (built on first use)."""
        return self._sun_grid

    def sun_blocked(self, points: NDArray, time: float) -> NDArray[np.bool_]:
        """(N,) whether the ray from each global point (N, 3) towards the sun meets anything at ``time`` [s] (shadow
        rays; by `SunGrid`: the static one of the scene, and one of the moving actors posed at ``time``)."""
        blocked = sun_blocked(self._sun_grid, points)
        moving = self.moving_sun_grid(time)
        if moving is not None:
            blocked |= sun_blocked(moving, points)
        return blocked
