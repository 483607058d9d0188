"""The ground in the weather on the shared real frames: the water film's optics checked against photon tracing, and
one wet road and one snow cover seen by the LiDAR and the camera of each frame.

``.venv/bin/python -m benchmarks.bench_ground [--photons N]`` (skips frames whose files are absent):

1. the closed form of the radiance a wet pavement returns to a monostatic LiDAR
   (`weatheralign.ground.optics.wet_lidar_factor`) beside photon tracing through the film
   (`wet_lidar_factor_naive`) at the incidence angles a car's LiDAR meets the road at, for two pavement
   reflectivities;
2. on the real Seeing Through Fog and KITTI HDL-64 scans of ``../shared/data/real``: the ground found once
   (`weatheralign.ground.surfaces.fit_ground_plane`), the water depth field of `weatheralign.ground.wet.water_depth`
   at the points' world positions, and for film depths from damp to flooded: the ground returns' mean intensity
   ratio, the share lost under the scan's estimated detector floor (`weatheralign.sensors.estimate_lidar_model`),
   and the share pushed below the weakest intensity the dry scan reports (Seeing Through Fog clamps its weakest
   returns at 24: those would read 24). Real intensities need not be linear in the received power; the ratios
   assume they are;
3. snow cover: one snow-depth field with wheel tracks along the ego's heading
   (`weatheralign.ground.snow.snow_depth`, `TireTracks`) on the ground plane and on every up-facing surface (the
   LiDAR's points' normals; a camera pixel takes the nearest return's, since a dense depth interpolated between
   rings has no normals of its own off the ground): the returns raised onto the snow and
   brightened, the camera's image under the same cover (`weatheralign.ground.camera.snow_cover_image`);
4. how well the sensors agree (`weatheralign.ground.surfaces.mask_agreement`): the LiDAR's edited returns projected
   into the camera against the camera's edited pixels, IoU over the pixels some return lands on.

Figures: ``reports/benchmarks/ground_lidar.png`` (the factor against incidence; per real frame the returns'
intensity in bird's-eye view dry, wet and snow-covered), ``reports/benchmarks/ground_cameras.png`` (each camera dry,
wet and snow-covered, beside the real snowy Seeing Through Fog frame); numbers: ``reports/benchmarks/ground.json``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import REAL, REPO, real_frames
from weatheralign.atomic import write_json

OUT = REPO / "reports" / "benchmarks"
FILM_DEPTHS_MM = (0.1, 0.25, 0.5, 1.0, 2.0)
FIGURE_FILM_MM = 0.5
SNOW_DEPTH_M = 0.05
REAL_SNOW = REAL / "stf" / "cam_stereo_left_lut_2018-02-12_15-39-23_00100_snow.png"


def optics_rows(photons: int) -> list[dict[str, float]]:
    """Closed form against photon tracing at 60-85 degrees, pavement reflectivity 0.1 and 0.5."""
    from weatheralign.ground.optics import wet_lidar_factor, wet_lidar_factor_naive

    rows = []
    for rho in (0.1, 0.5):
        for degrees in (60, 65, 70, 75, 80, 85):
            theta = np.radians(degrees)
            t0 = time.process_time()
            traced = wet_lidar_factor_naive(theta, rho, photons=photons, seed=degrees)
            rows.append({"rho": rho, "incidence_deg": degrees, "closed_form": float(wet_lidar_factor(theta, rho)),
                         "photon_tracing": traced, "tracing_cpu_s": time.process_time() - t0})
    return rows


@dataclass(frozen=True)
class LidarGround:
    """One real scan's ground and surfaces, found once for both sensors."""

    xyz: np.ndarray  # (N, 3) returns, LiDAR frame [m]
    world: np.ndarray  # (N, 3) the same in the world frame
    intensity: np.ndarray  # (N,) 0..255
    plane: Any  # GroundPlane in the LiDAR frame
    on_ground: np.ndarray  # (N,) bool
    normals: np.ndarray  # (N, 3) unit surface normals, LiDAR frame (the plane's on the ground)
    cos_up: np.ndarray  # (N,) of each return's surface normal with the world's vertical
    T_world_lidar: np.ndarray  # (4, 4)
    floor: float  # the scan's estimated detector floor (0..255)


def lidar_ground(frame: Any) -> LidarGround:
    """The scan's ground plane and its returns' surface orientation."""
    from weatheralign.ground.surfaces import fit_ground_plane, median_over_neighbours, point_normals
    from weatheralign.sensors import estimate_lidar_model

    scan = frame.lidar
    xyz = scan.points[:, :3].astype(np.float64)
    plane = fit_ground_plane(xyz)
    T = scan.T_global_ego @ scan.T_ego_lidar
    on_ground = plane.contains(xyz)
    normals = np.where(on_ground[:, None], np.asarray(plane.normal), point_normals(xyz, np.zeros(3)))
    cos_up = median_over_neighbours(xyz, np.abs((normals @ T[:3, :3].T)[:, 2]))  # one stray normal holds no snow
    return LidarGround(xyz, xyz @ T[:3, :3].T + T[:3, 3], scan.points[:, 3].astype(np.float64)
                       * (255.0 / scan.intensity_max), plane, on_ground, normals, cos_up, T,
                       estimate_lidar_model([scan], rotation_hz=10.0).noise_floor)


def tracks_for(ground: LidarGround) -> Any:
    """Wheel tracks along the ego's heading through the LiDAR's position (a straight road, ego in its lane)."""
    from weatheralign.ground.snow import TireTracks

    heading = ground.T_world_lidar[:3, 0]
    return TireTracks(direction=(float(heading[0]), float(heading[1])),
                      origin=(float(ground.T_world_lidar[0, 3]), float(ground.T_world_lidar[1, 3])))


def frame_rows(name: str, g: LidarGround) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The wet road on one real frame at every film depth, and the snow cover; the arrays of the figure."""
    from weatheralign.ground.snow import SnowCover, snow_coverage, snow_covered_ground, snow_depth
    from weatheralign.ground.wet import WetRoad, incidence_angle, water_depth, wet_ground

    positive = g.intensity[g.intensity > 0]
    weakest = float(positive.min()) if len(positive) else g.floor
    ground = g.on_ground
    normal = np.asarray(g.plane.normal)
    theta = incidence_angle(g.xyz[ground], np.zeros(3), normal)
    rows: list[dict[str, Any]] = []
    figure: dict[str, Any] = {"xy": g.xyz[:, :2], "dry": g.intensity, "weakest": weakest, "ground": ground}
    for film_mm in FILM_DEPTHS_MM:
        road = replace(WetRoad(), film_depth_m=film_mm / 1000.0)
        depth = water_depth(g.world[ground, :2], road, seed=0)
        t0 = time.process_time()
        effect = wet_ground(g.intensity[ground], theta, depth, road, g.floor)
        below = (effect.intensity < weakest) & (g.intensity[ground] >= weakest)
        rows.append({"frame": name, "film_mm": film_mm, "points": int(len(g.xyz)), "ground_points": int(ground.sum()),
                     "noise_floor": g.floor, "incidence_deg_median": float(np.degrees(np.median(theta))),
                     "mean_intensity_ratio": float(effect.intensity.sum() / max(g.intensity[ground].sum(), 1e-9)),
                     "ground_lost_share": float(effect.lost.mean()), "ground_lost": int(effect.lost.sum()),
                     "weakest_reported": weakest, "below_weakest_share": float(np.mean(below)),
                     "puddle_share": float(np.mean(depth >= road.puddle_depth_m)),
                     "cpu_s": time.process_time() - t0})
        if film_mm == FIGURE_FILM_MM:
            wet = g.intensity.copy()
            wet[ground] = effect.intensity
            lost = np.zeros(len(g.xyz), bool)
            lost[ground] = effect.lost | below
            figure.update(wet=wet, wet_lost=lost, wet_edited=ground.copy())
    cover = replace(SnowCover(), depth_m=SNOW_DEPTH_M)
    t0 = time.process_time()
    level = snow_depth(g.world[:, :2], cover, seed=0, tracks=tracks_for(g))
    coverage, depth = snow_coverage(level, g.cos_up, cover)
    effect = snow_covered_ground(g.xyz, np.zeros(3), g.normals, g.intensity, depth, cover, coverage=coverage)
    snow_cpu = time.process_time() - t0
    edited = coverage > 0.5
    rise = (effect.points - g.xyz) @ normal
    figure.update(snow=effect.intensity, snow_edited=edited)
    snow_row = {"frame": name, "snow_depth_m": SNOW_DEPTH_M, "points": int(len(g.xyz)),
                "covered_points": int(edited.sum()), "covered_ground_points": int((edited & ground).sum()),
                "covered_other_points": int((edited & ~ground).sum()),
                "ground_rise_m_median": float(np.median(rise[ground & edited])) if (ground & edited).any() else 0.0,
                "mean_intensity_ratio_covered": float(effect.intensity[edited].sum()
                                                      / max(g.intensity[edited].sum(), 1e-9)),
                "cpu_s": snow_cpu}
    return rows + [snow_row], figure


def camera_ground(name: str, frame: Any, g: LidarGround, figure: dict[str, Any]) -> tuple[dict[str, Any],
                                                                                          list[np.ndarray]]:
    """The wet road and the snow cover in the frame's first camera, from the same ground plane, fields and
    surface rule as the LiDAR: (numbers, [clean, wet, snowy] sRGB uint8 images). Dense depth from the scan
    (`camera_range_map`)."""
    from scipy.ndimage import gaussian_filter

    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import decode_srgb_u8, encode_srgb_u8
    from weatheralign.ground.camera import CameraGeometry, snow_cover_image, wet_road_image
    from weatheralign.ground.snow import SnowCover, snow_coverage, snow_depth
    from weatheralign.ground.surfaces import mask_agreement, nearest_return_values, pixel_normals
    from weatheralign.ground.wet import WetRoad, water_depth

    view = next(iter(frame.cameras.values()))
    image = view.load_image()
    t0 = time.process_time()
    range_map = camera_range_map(view, frame.lidar, image).astype(np.float64)
    depth_cpu = time.process_time() - t0
    camera = CameraGeometry(np.asarray(view.K, np.float64), view.T_global_cam)
    t0 = time.process_time()
    surfaces = pixel_normals(range_map, camera)
    finite = np.isfinite(range_map)
    plane_world = g.plane.transformed(g.T_world_lidar)
    ground = finite & plane_world.contains(np.nan_to_num(surfaces.points_world))
    normal_world = np.asarray(plane_world.normal)
    surfaces_cpu = time.process_time() - t0
    linear = decode_srgb_u8(image).astype(np.float64)
    height = range_map.shape[0]
    sky_rows = ~finite[: max(height // 8, 1)]
    sky = linear[: max(height // 8, 1)][sky_rows].mean(axis=0) if sky_rows.any() else linear[:4].reshape(-1, 3).mean(0)
    road = replace(WetRoad(), film_depth_m=FIGURE_FILM_MM / 1000.0)
    water = np.zeros(range_map.shape)
    water[ground] = water_depth(surfaces.points_world[ground][:, :2], road, seed=0)
    t0 = time.process_time()
    wet = wet_road_image(linear, np.where(finite, range_map, np.inf), camera, ground, water, road, normal_world, sky)
    wet_cpu = time.process_time() - t0
    cover = replace(SnowCover(), depth_m=SNOW_DEPTH_M)
    t0 = time.process_time()
    lidar_cos_up = nearest_return_values(surfaces.points_world.reshape(-1, 3), g.world, g.cos_up
                                         ).reshape(range_map.shape)  # dense depth's own normals are facets
    known = np.isfinite(lidar_cos_up) | ground
    cos_up = np.where(ground, normal_world[2], np.nan_to_num(lidar_cos_up))
    level = np.zeros(range_map.shape)
    level[known] = snow_depth(surfaces.points_world[known][:, :2], cover, seed=0, tracks=tracks_for(g))
    coverage = gaussian_filter(np.where(known, snow_coverage(level, cos_up, cover)[0], 0.0), 1.5)  # soft edges
    snowy = snow_cover_image(linear, coverage, surfaces.points_world, ground, cover, sky, seed=0)
    snow_cpu = time.process_time() - t0
    wet_agreement = mask_agreement(g.world, figure["wet_edited"], camera, ground & (water > 0))
    snow_agreement = mask_agreement(g.world, figure["snow_edited"], camera, coverage > 0.5)
    numbers = {"frame": name, "camera": view.channel, "ground_pixels_share": float(ground.mean()),
               "wet_pixels_share": float((water > 0).mean()),
               "puddle_pixels_share": float((water >= road.texture_depth_m).mean()),
               "snow_pixels_share": float((coverage > 0.5).mean()),
               "snow_other_pixels_share": float(((coverage > 0.5) & ~ground).mean()),
               "wet_iou": wet_agreement.iou, "wet_lidar_on_camera": wet_agreement.lidar_on_camera,
               "wet_camera_on_lidar": wet_agreement.camera_on_lidar,
               "snow_iou": snow_agreement.iou, "snow_lidar_on_camera": snow_agreement.lidar_on_camera,
               "snow_camera_on_lidar": snow_agreement.camera_on_lidar, "compared_pixels": snow_agreement.pixels,
               "dense_depth_cpu_s": depth_cpu, "surfaces_cpu_s": surfaces_cpu, "wet_road_cpu_s": wet_cpu,
               "snow_cover_cpu_s": snow_cpu}
    return numbers, [image, encode_srgb_u8(wet.astype(np.float32)), encode_srgb_u8(snowy.astype(np.float32))]


def figure(optics: list[dict[str, float]], frames: dict[str, dict[str, Any]], path: Path) -> None:
    """The wet factor against incidence; per real frame the returns' intensity in bird's-eye view, dry, wet (lost
    ones red) and snow-covered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from weatheralign.ground.optics import wet_lidar_factor

    fig, axes = plt.subplots(1, 1 + 3 * len(frames), figsize=(5 + 12.5 * len(frames), 4.9))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    grid = np.linspace(55, 89, 200)
    for rho, colour in ((0.1, "tab:blue"), (0.5, "tab:orange")):
        ax.plot(grid, wet_lidar_factor(np.radians(grid), rho), color=colour, label=f"closed form, rho = {rho}")
        pts = [r for r in optics if r["rho"] == rho]
        ax.plot([r["incidence_deg"] for r in pts], [r["photon_tracing"] for r in pts], "o", color=colour,
                mfc="none", label=f"photon tracing, rho = {rho}")
    ax.set(xlabel="incidence angle from the road's normal [deg]", ylabel="ground return, wet / dry",
           title="water over pavement (no film absorption)", ylim=(0, 0.8))
    ax.legend(fontsize=8)
    for i, (name, f) in enumerate(frames.items()):
        vmax = np.percentile(f["dry"][f["ground"]], 98)
        titles = {"dry": "dry", "wet": f"wet, film {FIGURE_FILM_MM} mm: red lost or under {f['weakest']:.1f}",
                  "snow": f"snow {SNOW_DEPTH_M * 100:.0f} cm: {int(f['snow_edited'].sum())} returns covered"}
        for j, key in enumerate(("dry", "wet", "snow")):
            ax = axes[1 + 3 * i + j]
            keep = ~f["wet_lost"] if key == "wet" else np.ones(len(f["dry"]), bool)
            sc = ax.scatter(f["xy"][keep, 0], f["xy"][keep, 1], c=f[key][keep], s=0.3, cmap="viridis", vmin=0,
                            vmax=vmax)
            if key == "wet":
                ax.scatter(f["xy"][f["wet_lost"], 0], f["xy"][f["wet_lost"], 1], s=0.3, c="red")
            ax.set(title=f"{name}: {titles[key]}", xlim=(-40, 40), ylim=(-40, 40), aspect="equal", xlabel="x [m]",
                   ylabel="y [m]")
            ax.title.set_fontsize(9)
            fig.colorbar(sc, ax=ax, shrink=0.7, label="intensity (0..255)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def camera_figure(tiles: list[list[np.ndarray]], names: list[str], path: Path) -> None:
    """Per real frame its camera image dry, wet and snow-covered, at most 640 px wide each; below, the real snowy
    Seeing Through Fog frame when it is there."""
    from PIL import Image, ImageDraw

    labels = ("dry", f"wet road, film {FIGURE_FILM_MM} mm + puddles", f"snow cover {SNOW_DEPTH_M * 100:.0f} cm")
    rows = []
    for images, name in zip(tiles, names):
        scale = min(1.0, 640 / images[0].shape[1])
        size = (int(images[0].shape[1] * scale), int(images[0].shape[0] * scale))
        row = []
        for img, text in zip(images, labels):
            tile = Image.fromarray(img).resize(size, Image.BILINEAR)
            ImageDraw.Draw(tile).text((8, 8), f"{name}: {text}", fill=(255, 255, 0))
            row.append(np.asarray(tile))
        rows.append(np.concatenate(row, axis=1))
    if REAL_SNOW.is_file():
        real = Image.open(REAL_SNOW).convert("RGB")
        real = real.resize((640, int(real.height * 640 / real.width)), Image.BILINEAR)
        ImageDraw.Draw(real).text((8, 8), "real snowfall (Seeing Through Fog, another drive)", fill=(255, 255, 0))
        rows.append(np.asarray(real))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=2_000_000)
    args = parser.parse_args(argv)
    optics = optics_rows(args.photons)
    rows, figures, cameras, tiles = [], {}, [], []
    for name, load in real_frames().items():
        frame = load()
        g = lidar_ground(frame)
        frame_result, figures[name] = frame_rows(name, g)
        rows += frame_result
        numbers, images = camera_ground(name, frame, g, figures[name])
        cameras.append(numbers)
        tiles.append(images)
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"optics": optics, "real_frames": rows, "cameras": cameras}
    write_json(OUT / "ground.json", result)
    figure(optics, figures, OUT / "ground_lidar.png")
    camera_figure(tiles, [c["frame"] for c in cameras], OUT / "ground_cameras.png")
    for c in cameras:
        print(f"{c['frame']:6s} camera: ground pixels {c['ground_pixels_share']:.1%}, snow pixels "
              f"{c['snow_pixels_share']:.1%}; IoU LiDAR vs camera: wet {c['wet_iou']:.3f}, snow {c['snow_iou']:.3f}")
    for r in rows:
        if "film_mm" in r:
            print(f"{r['frame']:6s} film {r['film_mm']:4.2f} mm: ground {r['ground_points']}, intensity x "
                  f"{r['mean_intensity_ratio']:.3f}, lost {r['ground_lost']} ({r['ground_lost_share']:.1%}), "
                  f"below the weakest reported ({r['weakest_reported']:.1f}) {r['below_weakest_share']:.1%}")
        else:
            print(f"{r['frame']:6s} snow {r['snow_depth_m']} m: covered {r['covered_points']} returns "
                  f"({r['covered_ground_points']} ground, {r['covered_other_points']} other), ground raised "
                  f"{r['ground_rise_m_median']:.3f} m, intensity x {r['mean_intensity_ratio_covered']:.2f}")
    return result


if __name__ == "__main__":
    main()
