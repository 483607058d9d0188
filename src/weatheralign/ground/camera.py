"""A wet road in a camera image, from the same water-depth field and the same ground as the LiDAR sees.

Per ground pixel, in linear light, with ``c`` the share of the surface under water (`weatheralign.ground.wet`):

    L = (1 - c) L_dry + c (k(theta_v) L_dry + R(theta_v) L_reflected)

- ``k = (1 - r_e) T(theta_v) / (n^2 (1 - rho r_i))``: the pavement seen through the water under diffuse daylight
  (Lekner & Dorf 1988: light enters with ``1 - r_e``, is scattered ``1 / (1 - rho r_i)`` times over, leaves towards
  the camera with ``T(theta_v) / n^2``), per colour channel with the pavement's reflectivity ``rho`` scaled by the
  pixel's own colour: the wet road is darker and more saturated;
- ``R(theta_v) L_reflected``: the Fresnel mirror image of the scene at the viewing angle ``theta_v`` from the
  road's normal, found by marching the mirrored ray through the camera's own range map (screen-space reflection);
  rays that leave the image or pass every surface see ``sky`` radiance. Puddles (water above the macrotexture) are
  sharp mirrors; a thin film's broken surface smears its reflection, mostly along the image's columns, as the glossy
  lobe of a rough surface seen at a grazing angle does (``film_blur_px``: rows, columns).

Lying snow (`snow_cover_image`) over the share ``c`` of a pixel's surface (`weatheralign.ground.snow.snow_coverage`,
from the same depth field and surface normals as the LiDAR's):

    L = (1 - c) L_under + c A s L_sky (1 + g)

- ``A L_sky``: a Lambertian surface of albedo ``A`` under a sky of uniform radiance ``L_sky`` has radiance
  ``A L_sky``; its colour is the sky light's, a quarter of the way from neutral (snow also answers the light of its
  surroundings and the sun's);
- ``s``: the surface's own shading kept (buildings' and cars' shadows, a street canyon's smaller share of the sky):
  the dry image's luminance smoothed over ``shading_px`` on the snowy pixels, relative to its 90th percentile there,
  taken at ``shading_strength`` (the dry luminance mixes the light with the surface's albedo: dark asphalt beside
  pale concrete is not a shadow; snowfall's diffuse light casts soft shadows);
- ``g``: the snow surface's grain, fractal noise of world position (so every camera sees the same), contrast
  ``grain``;
- ``L_under``: what shows between thin snow and in wheel tracks; on the ground the pavement darkened as wet
  (`weatheralign.ground.optics.wet_albedo`: melt water).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter

from weatheralign.ground.kernels import screen_space_reflection_kernel
from weatheralign.ground.optics import fresnel_reflectance, hemispherical_reflectance, wet_albedo
from weatheralign.ground.snow import SnowCover
from weatheralign.ground.wet import WetRoad, fractal_noise, wetted_share

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class CameraGeometry:
    """A pinhole camera: intrinsics ``K`` (3, 3) [px] and ``T_world_cam`` (4, 4) camera (OpenCV axes) -> world."""

    K: F64
    T_world_cam: F64

    def rays_world(self, height: int, width: int) -> F64:
        """(H, W, 3) unit ray directions in the world frame through the pixel centres."""
        v, u = np.mgrid[0:height, 0:width]
        return self.rays_at(np.column_stack([v.ravel(), u.ravel()])).reshape(height, width, 3)

    def rays_at(self, pixels: NDArray[np.int64]) -> F64:
        """(P, 3) unit ray directions in the world frame through the centres of ``pixels`` (P, 2) (row, col)."""
        pixels = np.asarray(pixels)
        u, v = pixels[:, 1].astype(np.float64), pixels[:, 0].astype(np.float64)
        K_inv, R = np.linalg.inv(self.K), self.T_world_cam[:3, :3]
        x, y, z = (K_inv[k, 0] * u + K_inv[k, 1] * v + K_inv[k, 2] for k in range(3))  # coordinate by coordinate
        length = np.sqrt(x * x + y * y + z * z)
        x, y, z = x / length, y / length, z / length
        return np.column_stack([R[k, 0] * x + R[k, 1] * y + R[k, 2] * z for k in range(3)])

    def project(self, points_world: F64) -> tuple[F64, F64, F64]:
        """Pixel coordinates (u, v) and ray length [m] of world points (..., 3); the depth is negative behind."""
        T_cam_world = np.linalg.inv(self.T_world_cam)
        return self.project_camera(points_world @ T_cam_world[:3, :3].T + T_cam_world[:3, 3])

    def project_camera(self, cam: F64) -> tuple[F64, F64, F64]:
        """`project` of points (..., 3) given in the camera's own frame."""
        z = cam[..., 2]
        safe = np.where(z > 1e-6, z, 1e-6)
        uv = cam @ self.K.T
        return uv[..., 0] / safe, uv[..., 1] / safe, np.where(z > 1e-6, np.linalg.norm(cam, axis=-1), -1.0)


def screen_space_reflection(image: F64, range_map: F64, camera: CameraGeometry, pixels: NDArray[np.int64],
                            rays: F64, normal: F64, sky: F64, max_distance_m: float = 80.0, steps: int = 64,
                            thickness_m: float = 1.5, start_m: float = 0.5) -> F64:
    """`screen_space_reflection_naive`'s march, compiled (`weatheralign.ground.kernels`)."""
    start, step = mirrored_rays(range_map, camera, pixels, rays, np.asarray(normal, dtype=np.float64))
    distances = start_m * (max_distance_m / start_m) ** (np.arange(steps) / (steps - 1))
    return screen_space_reflection_kernel(
        np.ascontiguousarray(image, dtype=np.float64), np.ascontiguousarray(range_map, dtype=np.float64),
        np.ascontiguousarray(camera.K, dtype=np.float64), np.ascontiguousarray(start), np.ascontiguousarray(step),
        np.asarray(sky, dtype=np.float64), distances, float(thickness_m), SSR_BISECTIONS)


def mirrored_rays(range_map: F64, camera: CameraGeometry, pixels: NDArray[np.int64], rays: F64,
                  normal: F64) -> tuple[F64, F64]:
    """The mirrored rays of ground ``pixels`` (P, 2) whose camera rays are ``rays`` (P, 3) (world frame) off a
    surface of unit ``normal`` (3,), in the camera's frame: (their starts on the ground (P, 3) [m], their unit
    directions (P, 3)), so that a point along one is ``start + step * distance``."""
    origin = camera.T_world_cam[:3, 3]
    ground = origin + rays * range_map[pixels[:, 0], pixels[:, 1], None]
    mirrored = rays - 2.0 * (rays @ normal)[:, None] * normal
    T_cam_world = np.linalg.inv(camera.T_world_cam)
    return ground @ T_cam_world[:3, :3].T + T_cam_world[:3, 3], mirrored @ T_cam_world[:3, :3].T


SSR_BISECTIONS = 8
"""Halvings of the step in which a mirrored ray passes behind a surface."""


def screen_space_reflection_naive(image: F64, range_map: F64, camera: CameraGeometry, pixels: NDArray[np.int64],
                                  rays: F64, normal: F64, sky: F64, max_distance_m: float = 80.0, steps: int = 64,
                                  thickness_m: float = 1.5, start_m: float = 0.5) -> F64:
    """Radiance (P, 3) seen along the mirrored rays of ground ``pixels`` (P, 2) (row, col), whose camera rays are
    ``rays`` (P, 3) (unit, world frame: `CameraGeometry.rays_world` at those pixels): each ray is marched from
    ``start_m`` beyond its ground point (clear of the noise of a real range map) in ``steps`` geometrically growing
    steps up to ``max_distance_m``; the first sample that lies
    behind the surface the camera sees at its pixel (by less than ``thickness_m``) takes that pixel's radiance; a ray
    that leaves the image or passes every surface sees ``sky`` (3,)."""
    height, width = range_map.shape
    start, step = mirrored_rays(range_map, camera, pixels, rays, np.asarray(normal, dtype=np.float64))
    out = np.tile(np.asarray(sky, dtype=np.float64), (len(pixels), 1))
    pending = np.ones(len(pixels), dtype=bool)
    distances = start_m * (max_distance_m / start_m) ** (np.arange(steps) / (steps - 1))

    def look(index: NDArray[np.int64], distance: F64) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray, NDArray]:
        """For rays ``index`` at ``distance``: (inside the image, behind the seen surface, row, col)."""
        u, v, length = camera.project_camera(start[index] + step[index] * distance[:, None])
        col, row = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        inside = (length > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        seen = range_map[np.where(inside, row, 0), np.where(inside, col, 0)]
        return inside, inside & (length > seen) & (length < seen + thickness_m), row, col

    previous = 0.0
    for distance in distances:
        index = np.nonzero(pending)[0]
        if len(index) == 0:
            break
        inside, hit, row, col = look(index, np.full(len(index), distance))
        pending[index[~inside]] = False  # left the image: the sky (or what no pixel shows)
        index = index[hit]
        if len(index):  # bisect between the last step in front of a surface and the first behind it
            low, high = np.full(len(index), previous), np.full(len(index), distance)
            for _ in range(SSR_BISECTIONS):
                middle = 0.5 * (low + high)
                behind = look(index, middle)[1]
                high, low = np.where(behind, middle, high), np.where(behind, low, middle)
            _, _, row, col = look(index, high)
            out[index] = image[row, col]
            pending[index] = False
        previous = distance
    return out


def strided_reflection(image: F64, range_map: F64, camera: CameraGeometry, pixels: NDArray[np.int64], rays: F64,
                       normal: F64, sky: F64, stride: int) -> F64:
    """`screen_space_reflection` of ``pixels`` (P, 2) traced only at the top-left pixel of each ``stride`` x
    ``stride`` block that is among them (the others of the block take its radiance); a pixel whose block corner is
    not among them is traced itself."""
    if stride <= 1:
        return screen_space_reflection(image, range_map, camera, pixels, rays, normal, sky)
    index = np.full(range_map.shape, -1, dtype=np.int64)
    index[pixels[:, 0], pixels[:, 1]] = np.arange(len(pixels))
    corner = index[pixels[:, 0] // stride * stride, pixels[:, 1] // stride * stride]
    traced = np.nonzero((corner < 0) | (corner == np.arange(len(pixels))))[0]
    radiance = screen_space_reflection(image, range_map, camera, pixels[traced], rays[traced], normal, sky)
    slot = np.full(len(pixels), -1, dtype=np.int64)
    slot[traced] = np.arange(len(traced))
    source = np.where(corner < 0, np.arange(len(pixels)), corner)
    return radiance[slot[source]]


def wet_road_image(image: F64, range_map: F64, camera: CameraGeometry, ground_mask: NDArray[np.bool_],
                   water_depth_m: F64, road: WetRoad, normal: F64, sky: F64,
                   film_blur_px: tuple[int, int] = (31, 5), reflection_stride: int = 2) -> F64:
    """The linear-light image (H, W, 3) with its ``ground_mask`` pixels (H, W) wet under ``water_depth_m`` (H, W) [m]
    (module docstring); ``normal`` the road's unit normal in the world frame, ``sky`` (3,) the radiance rays that
    escape see. The mirror image is traced for every ``reflection_stride``-th row and column and shared by the
    pixels of each stride x stride block (`strided_reflection`). Pixels off the ground, or dry, are returned
    unchanged."""
    gain, offset = wet_road_layers(image, range_map, camera, ground_mask, water_depth_m, road, normal, sky,
                                   film_blur_px, reflection_stride)
    return np.asarray(image, dtype=np.float64) * gain + offset


def wet_road_layers(image: F64, range_map: F64, camera: CameraGeometry, ground_mask: NDArray[np.bool_],
                    water_depth_m: F64, road: WetRoad, normal: F64, sky: F64,
                    film_blur_px: tuple[int, int] = (31, 5), reflection_stride: int = 2) -> tuple[F64, F64]:
    """`wet_road_image` as ``(gain, offset)`` (H, W, 3): the wet image is ``image * gain + offset`` (gain 1 and
    offset 0 where nothing changes), so that layers found at a coarser resolution can edit the full image."""
    return _wet_layers(image, range_map, camera, ground_mask, [water_depth_m], road, normal, sky, film_blur_px,
                       reflection_stride)[0]


class WetLayers(NamedTuple):
    """A wet road's camera layers, each ``(gain, offset)`` (H, W, 3) of ``image * gain + offset``: under the film
    everywhere, and under a puddle everywhere; a pixel takes the puddle's where
    `weatheralign.ground.wet.puddle_margin` > 0 at its ground point."""

    film: tuple[F64, F64]
    puddle: tuple[F64, F64]


def wet_road_layer_pair(image: F64, range_map: F64, camera: CameraGeometry, ground_mask: NDArray[np.bool_],
                        film_depth_m: F64, road: WetRoad, normal: F64, sky: F64,
                        film_blur_px: tuple[int, int] = (31, 5), reflection_stride: int = 2) -> WetLayers:
    """`wet_road_layers` under the film of ``film_depth_m`` (H, W) [m] and under a puddle of ``road.puddle_depth_m``
    on every ``ground_mask`` pixel, the mirror image traced once: layers found on a coarse grid then meet at the
    shoreline each full-size pixel finds for itself, not at the coarse grid's steps."""
    puddle = np.full(np.shape(range_map), road.puddle_depth_m)
    film, deep = _wet_layers(image, range_map, camera, ground_mask, [film_depth_m, puddle], road, normal, sky,
                             film_blur_px, reflection_stride)
    return WetLayers(film, deep)


def _wet_layers(image: F64, range_map: F64, camera: CameraGeometry, ground_mask: NDArray[np.bool_],
                depths_m: list[F64], road: WetRoad, normal: F64, sky: F64, film_blur_px: tuple[int, int],
                reflection_stride: int) -> list[tuple[F64, F64]]:
    """``(gain, offset)`` (H, W, 3) of the road under each water depth field of ``depths_m`` ((H, W) [m] each), the
    mirror image traced once for the pixels any of them wets."""
    image = np.asarray(image, dtype=np.float64)
    ground = np.argwhere(ground_mask)  # only the ground's pixels are asked anything
    shares = [wetted_share(np.asarray(depth)[ground[:, 0], ground[:, 1]], road.texture_depth_m) for depth in depths_m]
    wet = np.any(np.stack(shares) > 0, axis=0)
    pixels = ground[wet]
    if len(pixels) == 0:
        return [(np.ones_like(image), np.zeros_like(image)) for _ in depths_m]
    rows, cols = pixels[:, 0], pixels[:, 1]
    n = road.refractive_index
    rays = camera.rays_at(pixels)
    theta_v = np.arccos(np.clip(np.abs(rays @ normal), 0.0, 1.0))
    dry = image[rows, cols]
    colour = dry / np.maximum(dry.mean(axis=1, keepdims=True), 1e-6)
    rho = np.clip(road.pavement_reflectivity * colour, 0.0, 0.95)
    r_e, r_i = hemispherical_reflectance(1.0, n), hemispherical_reflectance(n, 1.0)
    reflectance = fresnel_reflectance(theta_v, 1.0, n)[:, None]
    through_water = (1.0 - r_e) * (1.0 - reflectance) / (n**2 * (1.0 - rho * r_i))
    sharp = strided_reflection(image, range_map, camera, pixels, rays, normal, sky, reflection_stride)
    puddles = [np.asarray(depth)[rows, cols] >= road.texture_depth_m for depth in depths_m]
    soft = sharp
    if max(film_blur_px) > 1 and not all(puddle.all() for puddle in puddles):
        # a film's broken surface: a mirror image smeared vertically, over the box around the wet pixels (a margin of
        # a window of zeros: the filter's reflected border adds nothing there)
        top, left = np.maximum(pixels.min(axis=0) - film_blur_px, 0)
        bottom, right = np.minimum(pixels.max(axis=0) + film_blur_px + 1, range_map.shape)
        box = (rows - top, cols - left)
        layer = np.zeros((bottom - top, right - left, 3))
        layer[box] = sharp
        weight = np.zeros(layer.shape[:2])
        weight[box] = 1.0
        norm = uniform_filter(weight, size=film_blur_px)[box]
        soft = uniform_filter(layer, size=(*film_blur_px, 1))[box] / np.maximum(norm, 1e-9)[:, None]
    flat = rows * image.shape[1] + cols  # rows of the (H * W, 3) views of the layers
    out = []
    for share, puddle in zip(shares, puddles, strict=True):
        gain, offset = np.ones_like(image), np.zeros_like(image)
        c = share[wet][:, None]
        gain.reshape(-1, 3)[flat] = (1.0 - c) + c * through_water
        offset.reshape(-1, 3)[flat] = c * reflectance * np.where(puddle[:, None], sharp, soft)
        out.append((gain, offset))
    return out


def snow_cover_image(image: F64, coverage: F64, points_world: F64, ground_mask: NDArray[np.bool_], cover: SnowCover,
                     sky: F64, seed: int, shading_px: int = 31, shading_strength: float = 0.5, grain: float = 0.05,
                     grain_cell_m: float = 0.4) -> F64:
    """The linear-light image (H, W, 3) with lying snow over the share ``coverage`` (H, W) of each pixel's surface
    (module docstring); ``points_world`` (H, W, 3) [m] the pixels' surfaces (nan: sky), ``ground_mask`` (H, W) the
    road's pixels, ``sky`` (3,) the sky's radiance. Pixels without snow are returned unchanged."""
    gain, offset = snow_cover_layers(image, coverage, points_world, ground_mask, cover, sky, seed, shading_px,
                                     shading_strength, grain, grain_cell_m)
    return np.asarray(image, dtype=np.float64) * gain + offset


def snow_cover_layers(image: F64, coverage: F64, points_world: F64, ground_mask: NDArray[np.bool_], cover: SnowCover,
                      sky: F64, seed: int, shading_px: int = 31, shading_strength: float = 0.5, grain: float = 0.05,
                      grain_cell_m: float = 0.4) -> tuple[F64, F64]:
    """`snow_cover_image` as ``(gain, offset)`` (H, W, 3): the snowy image is ``image * gain + offset``."""
    image = np.asarray(image, dtype=np.float64)
    gain, offset = np.ones_like(image), np.zeros_like(image)
    snowy = coverage > 0
    pixels = np.argwhere(snowy)
    if len(pixels) == 0:
        return gain, offset
    rows, cols = pixels[:, 0], pixels[:, 1]
    weight = uniform_filter(snowy.astype(np.float64), shading_px)[rows, cols]
    around = uniform_filter(np.where(snowy, image @ LUMINANCE, 0.0), shading_px)[rows, cols] / np.maximum(weight, 1e-9)
    reference = max(float(np.percentile(around, 90)), 1e-6)
    shading = 1.0 - shading_strength * (1.0 - np.clip(around / reference, 0.2, 1.0))[:, None]
    sky = np.asarray(sky, dtype=np.float64)
    sky_luminance = max(float(sky @ LUMINANCE), 1e-6)
    tint = 0.75 + 0.25 * sky / sky_luminance
    g = 1.0 + grain * (2.0 * fractal_noise(points_world[rows, cols, :2], grain_cell_m, seed + 11, octaves=3) - 1.0)
    snow = cover.visible_albedo * sky_luminance * tint * shading * g[:, None]
    melt = float(wet_albedo(cover.pavement_reflectivity) / cover.pavement_reflectivity)
    c = coverage[rows, cols][:, None]
    flat = rows * image.shape[1] + cols  # rows of the (H * W, 3) views of the layers
    gain.reshape(-1, 3)[flat] = (1.0 - c) * np.where(ground_mask[rows, cols, None], melt, 1.0)
    offset.reshape(-1, 3)[flat] = c * snow
    return gain, offset


LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB primaries, linear light

__all__ = ["CameraGeometry", "LUMINANCE", "mirrored_rays", "screen_space_reflection", "screen_space_reflection_naive",
           "snow_cover_image", "snow_cover_layers", "strided_reflection", "WetLayers", "wet_road_image",
           "wet_road_layer_pair", "wet_road_layers"]
