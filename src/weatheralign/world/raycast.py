"""Ray casting against the scene geometry (open3d `RaycastingScene`, Embree) for every sensor.

Static geometry lives in one cached BVH. Moving actors are handled exactly for both kinds of sensor:
- a global-shutter camera at time t casts against a small BVH of the actors posed at t;
- a rolling LiDAR casts each beam at its own firing time into each actor's body frame (ray moved by the inverse
  actor pose at that time), so that a 50 ms sweep sees a moving car where it is at each firing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from weatheralign.world.layout import Actor, SceneLayout
from weatheralign.world.meshes import Mesh, concat
from weatheralign.geometry import yaw_matrix


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
    """An Embree BVH of ``mesh`` (its triangle ids index the mesh's per-triangle arrays)."""
    scene = o3d.t.geometry.RaycastingScene(nthreads=nthreads)
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene


def cast_rays(scene: o3d.t.geometry.RaycastingScene, origins: NDArray,
              directions: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Cast rays (N, 3) + unit (N, 3): hit distance (N,) [m] (inf = miss), triangle id (N,), normal (N, 3)."""
    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = directions
    out = scene.cast_rays(o3d.core.Tensor(rays))
    t = out["t_hit"].numpy().astype(np.float64)
    prim = out["primitive_ids"].numpy().astype(np.int64)
    normal = out["primitive_normals"].numpy()
    return t, prim, normal


class WorldRaycaster:
    """Casts rays into one `SceneLayout` at given times."""

    def __init__(self, layout: SceneLayout, nthreads: int = 0) -> None:
        self.layout = layout
        self.nthreads = nthreads
        self._static = scene_of_mesh(layout.static_mesh, nthreads) if layout.static_mesh.num_triangles else None
        self._moving: tuple[Actor, ...] = tuple(a for a in layout.actors if a.moving)
        self._moving_scenes = [scene_of_mesh(a.mesh, nthreads) for a in self._moving]
        self._moving_radius = np.array([np.linalg.norm(a.mesh.vertices, axis=1).max() for a in self._moving])

    def _empty_hits(self, n: int) -> tuple[NDArray, NDArray, NDArray, int]:
        return np.full(n, np.inf), np.zeros((n, 3), np.float32), np.zeros(n, np.int64), 0

    def _finish(self, t: NDArray, normal: NDArray, tri: NDArray, source: NDArray, meshes: list[Mesh],
                directions: NDArray) -> Hits:
        n = len(t)
        material = np.zeros(n, np.uint8)
        albedo = np.zeros((n, 3), np.float32)
        refl = np.zeros(n, np.float32)
        inst = np.zeros(n, np.int32)
        for k, mesh in enumerate(meshes):
            sel = np.flatnonzero((source == k) & np.isfinite(t))
            if len(sel) == 0:
                continue
            ids = tri[sel]
            material[sel] = mesh.material[ids]
            albedo[sel] = mesh.albedo[ids]
            refl[sel] = mesh.reflectivity[ids]
            inst[sel] = mesh.instance[ids]
        flip = np.einsum("ij,ij->i", normal, directions) > 0
        normal = np.where(flip[:, None], -normal, normal).astype(np.float32)
        return Hits(t, normal, material, albedo, refl, inst)

    def cast_at_time(self, origins: NDArray, directions: NDArray, time: float) -> Hits:
        """Cast rays (N, 3) origins, (N, 3) unit directions, global frame, all at one instant ``time`` [s]."""
        n = len(origins)
        t, normal, tri, _ = self._empty_hits(n)
        source = np.full(n, -1, np.int64)
        meshes: list[Mesh] = []
        if self._static is not None:
            t, tri, normal = cast_rays(self._static, origins, directions)
            source[np.isfinite(t)] = 0
            meshes.append(self.layout.static_mesh)
        moving = self.moving_mesh_at(time)
        if moving.num_triangles:
            tm, trim, nm = cast_rays(scene_of_mesh(moving, self.nthreads), origins, directions)
            closer = tm < t
            t = np.where(closer, tm, t)
            tri = np.where(closer, trim, tri)
            normal = np.where(closer[:, None], nm, normal)
            source[closer] = len(meshes)
            meshes.append(moving)
        return self._finish(t, normal, tri, source, meshes, directions)

    def moving_mesh_at(self, time: float) -> Mesh:
        """All moving actors posed at ``time`` [s], in the global frame."""
        return concat([a.mesh.transformed(yaw_matrix(a.yaw), a.position_at(time)) for a in self._moving])

    def occluded_at_time(self, origins: NDArray, directions: NDArray, time: float) -> NDArray[np.bool_]:
        """(N,) whether each ray (global frame, at ``time``) hits anything at all (shadow rays)."""
        rays = np.empty((len(origins), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = directions
        rays_t = o3d.core.Tensor(rays)
        occ = np.zeros(len(origins), bool)
        if self._static is not None:
            occ |= self._static.test_occlusions(rays_t).numpy().astype(bool)
        moving = self.moving_mesh_at(time)
        if moving.num_triangles:
            occ |= scene_of_mesh(moving, self.nthreads).test_occlusions(rays_t).numpy().astype(bool)
        return occ

    def cast_rolling(self, origins: NDArray, directions: NDArray, times: NDArray) -> Hits:
        """Cast rays whose times differ (a rolling LiDAR sweep): each ray sees every moving actor where it is at
        that ray's time ``times`` (N,) [s]. Origins/directions (N, 3) in the global frame."""
        n = len(origins)
        t, normal, tri, _ = self._empty_hits(n)
        source = np.full(n, -1, np.int64)
        meshes: list[Mesh] = []
        if self._static is not None:
            t, tri, normal = cast_rays(self._static, origins, directions)
            source[np.isfinite(t)] = 0
            meshes.append(self.layout.static_mesh)
        normal = normal.astype(np.float32)
        for actor, scene, radius in zip(self._moving, self._moving_scenes, self._moving_radius):
            centre = actor.position_at(times)  # (N, 3)
            rel = centre - origins
            along = np.einsum("ij,ij->i", rel, directions)
            perp2 = np.einsum("ij,ij->i", rel, rel) - along**2
            cand = np.flatnonzero((perp2 < radius**2) & (along > -radius) & (along - radius < t))
            if len(cand) == 0:
                continue
            R = yaw_matrix(actor.yaw)
            o_body = (origins[cand] - centre[cand]) @ R  # R^T (o - p)
            d_body = directions[cand] @ R
            tb, trib, nb = cast_rays(scene, o_body, d_body)
            closer = tb < t[cand]
            idx = cand[closer]
            t[idx] = tb[closer]
            tri[idx] = trib[closer]
            normal[idx] = (nb[closer] @ R.T).astype(np.float32)
            source[idx] = len(meshes)
            meshes.append(actor.mesh)
        return self._finish(t, normal, tri, source, meshes, directions)
