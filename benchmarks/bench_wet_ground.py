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

Figure: ``reports/benchmarks/wet_ground.png`` (the factor against incidence; per real frame the ground's intensity
in bird's-eye view dry and wet); numbers: ``reports/benchmarks/wet_ground.json``.
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


def ground_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unit normal pointing up (3,), inlier mask (N,)) of the dominant plane below the sensor (open3d RANSAC,
    seeded), fitted to points (N, 3) lower than 1 m under the sensor."""
    import open3d as o3d

    o3d.utility.random.seed(0)
    low = np.nonzero(points[:, 2] < -1.0)[0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[low].astype(np.float64)))
    (a, b, c, d), inliers = cloud.segment_plane(distance_threshold=0.15, ransac_n=3, num_iterations=2000)
    normal = np.array([a, b, c]) * (1.0 if c >= 0 else -1.0)
    offset = d * (1.0 if c >= 0 else -1.0)
    distance = points @ normal + offset
    return normal / np.linalg.norm(normal), np.abs(distance) < 0.15


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
    normal, ground = ground_plane(xyz)
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
                      "lost": effect.lost | ((effect.intensity < weakest) & (intensity[ground] >= weakest))}
    return rows, figure


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


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=2_000_000)
    args = parser.parse_args(argv)
    optics = optics_rows(args.photons)
    rows, figures = [], {}
    for name, load in real_frames().items():
        frame_result, figures[name] = frame_rows(name, load())
        rows += frame_result
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"optics": optics, "real_frames": rows}
    write_json(OUT / "wet_ground.json", result)
    figure(optics, figures, OUT / "wet_ground.png")
    for r in rows:
        print(f"{r['frame']:6s} film {r['film_mm']:4.2f} mm: ground {r['ground_points']}, intensity x "
              f"{r['mean_intensity_ratio']:.3f}, lost {r['ground_lost']} ({r['ground_lost_share']:.1%}), "
              f"below the weakest reported ({r['weakest_reported']:.1f}) {r['below_weakest_share']:.1%}")
    return result


if __name__ == "__main__":
    main()
