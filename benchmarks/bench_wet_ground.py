"""A wet road on the shared real scans: the water film's optics checked against photon tracing, and what it does to
real ground returns.

``.venv/bin/python -m benchmarks.bench_wet_ground [--photons N]`` (skips frames whose files are absent):

1. the closed form of the radiance a wet pavement returns to a monostatic LiDAR
   (`weatheralign.ground.optics.wet_lidar_factor`) beside photon tracing through the film
   (`wet_lidar_factor_naive`) at the incidence angles a car's LiDAR meets the road at, for two pavement
   reflectivities;
2. on the real Seeing Through Fog and KITTI HDL-64 scans of ``../shared/data/real``: the ground found with open3d's
   RANSAC plane fit, the water depth field of `weatheralign.ground.wet.water_depth` at the points' world positions,
   and for film depths from damp to flooded: the ground returns' mean intensity ratio, the share lost under the
   scan's estimated detector floor (`weatheralign.sensors.estimate_lidar_model`), and the share pushed below the
   weakest intensity the dry scan reports (Seeing Through Fog clamps its weakest returns at 24: those would read
   24). Real intensities need not be linear in the received power; the ratios assume they are.

3. the same ground plane and water-depth field in each frame's camera (`weatheralign.ground.camera`, dense depth from
   the scan): the wet road's image, and how well the two sensors agree on the ground (the share of the LiDAR's
   ground points that project onto the camera's ground pixels, and of its other points).

Figures: ``reports/benchmarks/wet_ground.png`` (the factor against incidence; per real frame the ground's intensity
in bird's-eye view dry and wet), ``reports/benchmarks/wet_ground_cameras.png`` (each camera dry and wet); numbers:
``reports/benchmarks/wet_ground.json``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import REPO, real_frames
from weatheralign.atomic import write_json

OUT = REPO / "reports" / "benchmarks"
FILM_DEPTHS_MM = (0.1, 0.25, 0.5, 1.0, 2.0)
FIGURE_FILM_MM = 0.5


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


def ground_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit normal pointing up (3,), offset ``d``: ``n . x + d = 0``) of the dominant plane below the sensor
    (open3d RANSAC, seeded), fitted to points (N, 3) lower than 1 m under the sensor."""
    import open3d as o3d

    o3d.utility.random.seed(0)
    low = np.nonzero(points[:, 2] < -1.0)[0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[low].astype(np.float64)))
    (a, b, c, d), inliers = cloud.segment_plane(distance_threshold=0.15, ransac_n=3, num_iterations=2000)
    sign = 1.0 if c >= 0 else -1.0
    length = float(np.linalg.norm([a, b, c]))
    return np.array([a, b, c]) * sign / length, d * sign / length


def frame_rows(name: str, frame: Any) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """The wet road on one real frame at every film depth; the arrays of the figure's film depth."""
    from weatheralign.ground.wet import WetRoad, incidence_angle, water_depth, wet_ground
    from weatheralign.sensors import estimate_lidar_model

    scan = frame.lidar
    xyz = scan.points[:, :3].astype(np.float64)
    scale = 255.0 / scan.intensity_max
    intensity = scan.points[:, 3].astype(np.float64) * scale
    floor = estimate_lidar_model([scan], rotation_hz=10.0).noise_floor
    positive = intensity[intensity > 0]
    weakest = float(positive.min()) if len(positive) else floor
    normal, offset = ground_plane(xyz)
    ground = np.abs(xyz @ normal + offset) < 0.15
    T = scan.T_global_ego @ scan.T_ego_lidar
    world_xy = (xyz[ground] @ T[:3, :3].T + T[:3, 3])[:, :2]
    theta = incidence_angle(xyz[ground], np.zeros(3), normal)
    rows, figure = [], {}
    for film_mm in FILM_DEPTHS_MM:
        road = replace(WetRoad(), film_depth_m=film_mm / 1000.0)
        depth = water_depth(world_xy, road, seed=0)
        t0 = time.process_time()
        effect = wet_ground(intensity[ground], theta, depth, road, floor)
        rows.append({"frame": name, "film_mm": film_mm, "points": int(len(xyz)), "ground_points": int(ground.sum()),
                     "noise_floor": floor, "incidence_deg_median": float(np.degrees(np.median(theta))),
                     "mean_intensity_ratio": float(effect.intensity.sum() / max(intensity[ground].sum(), 1e-9)),
                     "ground_lost_share": float(effect.lost.mean()), "ground_lost": int(effect.lost.sum()),
                     "weakest_reported": weakest, "below_weakest_share": float(np.mean(
                         (effect.intensity < weakest) & (intensity[ground] >= weakest))),
                     "puddle_share": float(np.mean(depth >= road.puddle_depth_m)),
                     "cpu_s": time.process_time() - t0})
        if film_mm == FIGURE_FILM_MM:
            figure = {"xy": xyz[ground, :2], "dry": intensity[ground], "wet": effect.intensity, "weakest": weakest,
                      "lost": effect.lost | ((effect.intensity < weakest) & (intensity[ground] >= weakest)),
                      "normal": normal, "offset": offset}
    return rows, figure


def camera_wet(name: str, frame: Any, normal_lidar: np.ndarray, offset_lidar: float) -> tuple[dict[str, Any],
                                                                                              list[np.ndarray]]:
    """The wet road in the frame's first camera, from the same ground plane and water-depth field as the LiDAR:
    (numbers, [clean, wet] sRGB uint8 images). Dense depth from the scan (`camera_range_map`); ground pixels are
    those within 0.15 m of the LiDAR's ground plane."""
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import decode_srgb_u8, encode_srgb_u8
    from weatheralign.ground.camera import CameraGeometry, wet_road_image
    from weatheralign.ground.wet import WetRoad, water_depth

    view = next(iter(frame.cameras.values()))
    image = view.load_image()
    t0 = time.process_time()
    range_map = camera_range_map(view, frame.lidar, image).astype(np.float64)
    depth_cpu = time.process_time() - t0
    scan = frame.lidar
    T_world_lidar = scan.T_global_ego @ scan.T_ego_lidar
    camera = CameraGeometry(np.asarray(view.K, np.float64), view.T_global_cam)
    height, width = range_map.shape
    rays = camera.rays_world(height, width)
    finite = np.isfinite(range_map)
    points_world = camera.T_world_cam[:3, 3] + rays * np.where(finite, range_map, 0.0)[..., None]
    T_lidar_world = np.linalg.inv(T_world_lidar)
    points_lidar = points_world @ T_lidar_world[:3, :3].T + T_lidar_world[:3, 3]
    ground = finite & (np.abs(points_lidar @ normal_lidar + offset_lidar) < 0.15)
    road = replace(WetRoad(), film_depth_m=FIGURE_FILM_MM / 1000.0)
    depth = np.zeros(range_map.shape)
    depth[ground] = water_depth(points_world[ground][:, :2], road, seed=0)
    linear = decode_srgb_u8(image).astype(np.float64)
    sky_rows = ~finite[: max(height // 8, 1)]
    sky = linear[: max(height // 8, 1)][sky_rows].mean(axis=0) if sky_rows.any() else linear[:4].reshape(-1, 3).mean(0)
    normal_world = T_world_lidar[:3, :3] @ normal_lidar
    t0 = time.process_time()
    wet = wet_road_image(linear, np.where(finite, range_map, np.inf), camera, ground, depth, road, normal_world, sky)
    wet_cpu = time.process_time() - t0
    # agreement: the LiDAR's ground points projected into the camera against the camera's ground pixels
    xyz = scan.points[:, :3].astype(np.float64)
    lidar_ground = np.abs(xyz @ normal_lidar + offset_lidar) < 0.15
    world = xyz @ T_world_lidar[:3, :3].T + T_world_lidar[:3, 3]
    u, v, length = camera.project(world)
    col, row = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
    seen = (length > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
    on_camera_ground = np.zeros(len(xyz), bool)
    on_camera_ground[seen] = ground[row[seen], col[seen]]
    numbers = {"frame": name, "camera": view.channel, "ground_pixels_share": float(ground.mean()),
               "wet_pixels_share": float((depth > 0).mean()), "puddle_pixels_share": float(
                   (depth >= road.texture_depth_m).mean()),
               "lidar_ground_on_camera_ground": float(on_camera_ground[seen & lidar_ground].mean()),
               "lidar_other_on_camera_ground": float(on_camera_ground[seen & ~lidar_ground].mean()),
               "dense_depth_cpu_s": depth_cpu, "wet_road_cpu_s": wet_cpu}
    return numbers, [image, encode_srgb_u8(wet.astype(np.float32))]


def figure(optics: list[dict[str, float]], frames: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from weatheralign.ground.optics import wet_lidar_factor

    fig, axes = plt.subplots(1, 1 + 2 * len(frames), figsize=(5 + 8 * len(frames), 4.9))
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
        vmax = np.percentile(f["dry"], 98)
        for j, key in enumerate(("dry", "wet")):
            ax = axes[1 + 2 * i + j]
            keep = ~f["lost"] if key == "wet" else np.ones(len(f["dry"]), bool)
            sc = ax.scatter(f["xy"][keep, 0], f["xy"][keep, 1], c=f[key][keep], s=0.3, cmap="viridis", vmin=0,
                            vmax=vmax)
            if key == "wet":
                ax.scatter(f["xy"][f["lost"], 0], f["xy"][f["lost"], 1], s=0.3, c="red")
            lost = f"\n{int(f['lost'].sum())} red: lost or under {f['weakest']:.1f}" if key == "wet" else ""
            ax.set(title=f"{name}: ground, {key}" + (f", film {FIGURE_FILM_MM} mm" if key == "wet" else "") + lost,
                   xlim=(-40, 40), ylim=(-40, 40), aspect="equal", xlabel="x [m]", ylabel="y [m]")
            fig.colorbar(sc, ax=ax, shrink=0.7, label="intensity (0..255)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def camera_figure(tiles: list[list[np.ndarray]], names: list[str], path: Path) -> None:
    """Per real frame its camera image dry (left) and wet (right), at most 900 px wide each."""
    from PIL import Image, ImageDraw

    rows = []
    for (dry, wet), name in zip(tiles, names):
        scale = min(1.0, 900 / dry.shape[1])
        size = (int(dry.shape[1] * scale), int(dry.shape[0] * scale))
        pair = []
        for img, text in ((dry, f"{name}: dry"), (wet, f"{name}: wet road, film {FIGURE_FILM_MM} mm + puddles")):
            tile = Image.fromarray(img).resize(size, Image.BILINEAR)
            ImageDraw.Draw(tile).text((8, 8), text, fill=(255, 255, 0))
            pair.append(np.asarray(tile))
        rows.append(np.concatenate(pair, axis=1))
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
        frame_result, figures[name] = frame_rows(name, frame)
        rows += frame_result
        numbers, images = camera_wet(name, frame, figures[name]["normal"], figures[name]["offset"])
        cameras.append(numbers)
        tiles.append(images)
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"optics": optics, "real_frames": rows, "cameras": cameras}
    write_json(OUT / "wet_ground.json", result)
    figure(optics, figures, OUT / "wet_ground.png")
    camera_figure(tiles, [c["frame"] for c in cameras], OUT / "wet_ground_cameras.png")
    for c in cameras:
        print(f"{c['frame']:6s} camera: ground pixels {c['ground_pixels_share']:.1%}, LiDAR ground points on camera "
              f"ground {c['lidar_ground_on_camera_ground']:.1%}, other points {c['lidar_other_on_camera_ground']:.1%}")
    for r in rows:
        print(f"{r['frame']:6s} film {r['film_mm']:4.2f} mm: ground {r['ground_points']}, intensity x "
              f"{r['mean_intensity_ratio']:.3f}, lost {r['ground_lost']} ({r['ground_lost_share']:.1%}), "
              f"below the weakest reported ({r['weakest_reported']:.1f}) {r['below_weakest_share']:.1%}")
    return result


if __name__ == "__main__":
    main()
