"""The ground in the weather on the shared real frames: the water film's optics checked against photon tracing, and
one wet road and one snow cover seen by the LiDAR and the camera of each frame.

``.venv/bin/python -m benchmarks.bench_ground [--photons N]`` (skips frames whose files are absent):

1. the closed form of the radiance a wet pavement returns to a monostatic LiDAR
   (`weatheralign.ground.optics.wet_lidar_factor`) beside photon tracing through the film
   (`wet_lidar_factor_naive`) at the incidence angles a car's LiDAR meets the road at, for two pavement
   reflectivities;
2. on the real Seeing Through Fog and KITTI HDL-64 scans of ``../shared/data/real``: the ground found once
   (`weatheralign.lidar.ground_plane.fit_ground_plane`), the water depth field of `weatheralign.ground.wet.water_depth`
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
   into the camera against the camera's edited pixels, IoU over the pixels some return the camera sees lands on.

Figures: ``reports/benchmarks/ground_lidar.png`` (the factor against incidence; per real frame the returns'
intensity in bird's-eye view dry, wet and snow-covered), ``reports/benchmarks/ground_cameras.png`` (each camera dry,
wet and snow-covered, beside the real snowy Seeing Through Fog frame); numbers: ``reports/benchmarks/ground.json``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
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


def tracks_for(scan: Any) -> Any:
    """Wheel tracks along the ego's heading through the LiDAR's position (a straight road, ego in its lane)."""
    from weatheralign.ground.snow import TireTracks

    T = scan.T_global_lidar
    return TireTracks(direction=(float(T[0, 0]), float(T[1, 0])), origin=(float(T[0, 3]), float(T[1, 3])))


def ground_states(scan: Any, film_mm: float = FIGURE_FILM_MM) -> dict[str, Any]:
    """The figure's wet road and snow cover for ``scan``'s scene."""
    from weatheralign.ground.edit import GroundState
    from weatheralign.ground.snow import SnowCover
    from weatheralign.ground.wet import WetRoad

    return {"wet": GroundState(road=replace(WetRoad(), film_depth_m=film_mm / 1000.0)),
            "snow": GroundState(cover=replace(SnowCover(), depth_m=SNOW_DEPTH_M), tracks=tracks_for(scan))}


def frame_rows(name: str, scan: Any, surfaces: Any, floor: float) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The wet road on one real scan at every film depth, and the snow cover; the arrays of the figure."""
    from weatheralign.ground.edit import edit_scan

    intensity = scan.intensity_255().astype(np.float64)
    positive = intensity[intensity > 0]
    weakest = float(positive.min()) if len(positive) else floor
    ground = surfaces.on_ground
    rows: list[dict[str, Any]] = []
    figure: dict[str, Any] = {"xy": scan.points[:, :2], "dry": intensity, "weakest": weakest, "ground": ground}
    for film_mm in FILM_DEPTHS_MM:
        t0 = time.process_time()
        edited = edit_scan(scan, surfaces, ground_states(scan, film_mm)["wet"], floor)
        cpu = time.process_time() - t0
        new = np.zeros(len(intensity))
        new[edited.source_index] = edited.scan.intensity_255()
        lost = ground & ~np.isin(np.arange(len(intensity)), edited.source_index)
        below = ground & ~lost & (new < weakest) & (intensity >= weakest)
        rows.append({"frame": name, "film_mm": film_mm, "points": int(len(intensity)),
                     "ground_points": int(ground.sum()), "noise_floor": floor,
                     "mean_intensity_ratio": float(new[ground].sum() / max(intensity[ground].sum(), 1e-9)),
                     "ground_lost_share": float(lost[ground].mean()), "ground_lost": int(lost.sum()),
                     "weakest_reported": weakest, "below_weakest_share": float(below[ground].mean()), "cpu_s": cpu})
        if film_mm == FIGURE_FILM_MM:
            figure.update(wet=new, wet_lost=lost | below, wet_edited=edited.edited)
    t0 = time.process_time()
    snowy = edit_scan(scan, surfaces, ground_states(scan)["snow"], floor)
    cpu = time.process_time() - t0
    rise = (snowy.scan.points[:, :3] - scan.points[:, :3]).astype(np.float64) @ np.asarray(surfaces.plane.normal)
    covered = snowy.edited
    figure.update(snow=snowy.scan.intensity_255().astype(np.float64), snow_edited=covered)
    snow_row = {"frame": name, "snow_depth_m": SNOW_DEPTH_M, "points": int(len(intensity)),
                "covered_points": int(covered.sum()), "covered_ground_points": int((covered & ground).sum()),
                "covered_other_points": int((covered & ~ground).sum()),
                "ground_rise_m_median": float(np.median(rise[ground & covered])) if (ground & covered).any() else 0.0,
                "mean_intensity_ratio_covered": float(figure["snow"][covered].sum()
                                                      / max(intensity[covered].sum(), 1e-9)), "cpu_s": cpu}
    return rows + [snow_row], figure


def camera_ground(name: str, frame: Any, surfaces: Any, figure: dict[str, Any], channel: str | None = None
                  ) -> tuple[dict[str, Any], list[np.ndarray]]:
    """The wet road and the snow cover in one camera of the frame (the first unless ``channel``), from the same
    ground plane, fields and surfaces as the LiDAR: (numbers, [clean, wet, snowy] sRGB uint8 images). The exact
    range map where the dataset has one, else a dense depth from the scan (`camera_range_map`)."""
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import decode_srgb_u8, encode_srgb_u8
    from weatheralign.ground.camera import CameraGeometry
    from weatheralign.ground.edit import edit_image
    from weatheralign.ground.surfaces import mask_agreement

    view = frame.cameras[channel] if channel else next(iter(frame.cameras.values()))
    image = view.load_image()
    t0 = time.process_time()
    range_map = camera_range_map(view, frame.lidar, image).astype(np.float64)
    depth_cpu = time.process_time() - t0
    camera = CameraGeometry(np.asarray(view.K, np.float64), view.T_global_cam)
    linear = decode_srgb_u8(image).astype(np.float64)
    finite = np.isfinite(range_map)
    rows = max(range_map.shape[0] // 8, 1)
    sky_rows = ~finite[:rows]
    sky = linear[:rows][sky_rows].mean(axis=0) if sky_rows.any() else linear[:4].reshape(-1, 3).mean(0)
    numbers: dict[str, Any] = {"frame": name, "camera": view.channel, "dense_depth_cpu_s": depth_cpu,
                               "exact_range": view.range_path is not None}
    images = [image]
    for kind, state in ground_states(frame.lidar).items():
        t0 = time.process_time()
        out = edit_image(linear, range_map, camera, view.range_path is not None, surfaces, frame.lidar.T_global_lidar,
                         state, sky)
        numbers[f"{kind}_cpu_s"] = time.process_time() - t0
        agreement = mask_agreement(surfaces.world, figure[f"{kind}_edited"], camera, out.edited, range_map=range_map)
        numbers.update({f"{kind}_pixels_share": float(out.edited.mean()), f"{kind}_iou": agreement.iou,
                        f"{kind}_lidar_on_camera": agreement.lidar_on_camera,
                        f"{kind}_camera_on_lidar": agreement.camera_on_lidar, "compared_pixels": agreement.pixels})
        images.append(encode_srgb_u8(out.linear.astype(np.float32)))
    return numbers, images


def synthetic_frame(sample_index: int = 5) -> tuple[Any, np.ndarray] | None:
    """A frame of the synthetic world under ``data/world`` (None when it has not been rendered) and its LiDAR
    returns' materials."""
    import json

    from weatheralign.data.nuscenes import load_frame, read_point_extras

    manifest = REPO / "data" / "manifests" / "world.json"
    if not manifest.is_file():
        return None
    from nuscenes.nuscenes import NuScenes

    info = json.loads(manifest.read_text())
    root = REPO / info["dataroot"]
    nusc = NuScenes(version=info["version"], dataroot=str(root), verbose=False)
    token = nusc.sample[sample_index]["token"]
    frame = load_frame(nusc, token, cameras=("CAM_FRONT",))
    lidar = nusc.get("sample_data", nusc.get("sample", token)["data"]["LIDAR_TOP"])
    return frame, read_point_extras(root, lidar["filename"])["material"]


def figure(optics: list[dict[str, float]], frames: dict[str, dict[str, Any]], path: Path) -> None:
    """The wet factor against incidence; per real frame the returns' intensity in bird's-eye view, dry, wet (lost
    ones red) and snow-covered."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from weatheralign.ground.optics import wet_lidar_factor

    fig = plt.figure(figsize=(5.5 + 13.5, 4.4 * len(frames)))
    grid = fig.add_gridspec(len(frames), 4, width_ratios=(1.2, 1, 1, 1))
    ax = fig.add_subplot(grid[:, 0])
    incidence = np.linspace(55, 89, 200)
    for rho, colour in ((0.1, "tab:blue"), (0.5, "tab:orange")):
        ax.plot(incidence, wet_lidar_factor(np.radians(incidence), rho), color=colour,
                label=f"closed form, rho = {rho}")
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
            ax = fig.add_subplot(grid[i, 1 + j])
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
    from weatheralign.ground.edit import scan_surfaces
    from weatheralign.sensors import estimate_lidar_model
    from weatheralign.world.materials import Material

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=2_000_000)
    args = parser.parse_args(argv)
    optics = optics_rows(args.photons)
    rows, figures, cameras, tiles, synthetic = [], {}, [], [], {}
    frames: dict[str, Any] = {name: load() for name, load in real_frames().items()}
    world = synthetic_frame()
    if world is not None:
        frames["synthetic"] = world[0]
    for name, frame in frames.items():
        t0 = time.process_time()
        surfaces = scan_surfaces(frame.lidar)
        surfaces_cpu = time.process_time() - t0
        floor = (0.5 if name == "synthetic" else estimate_lidar_model([frame.lidar], rotation_hz=10.0).noise_floor)
        frame_result, figures[name] = frame_rows(name, frame.lidar, surfaces, floor)
        rows += [{**r, "surfaces_cpu_s": surfaces_cpu} for r in frame_result]
        numbers, images = camera_ground(name, frame, surfaces, figures[name])
        cameras.append(numbers)
        tiles.append(images)
        if name == "synthetic":
            truth = np.isin(world[1], [Material.ROAD, Material.SIDEWALK, Material.CURB])
            found = surfaces.on_ground
            synthetic = {"ground_precision": float((found & truth).sum() / max(found.sum(), 1)),
                         "ground_recall": float((found & truth).sum() / max(truth.sum(), 1)),
                         "returns": int(len(truth)), "surfaces_cpu_s": surfaces_cpu}
    OUT.mkdir(parents=True, exist_ok=True)
    result = {"optics": optics, "frames": rows, "cameras": cameras, "synthetic_ground_vs_materials": synthetic}
    write_json(OUT / "ground.json", result)
    figure(optics, figures, OUT / "ground_lidar.png")
    camera_figure(tiles, [c["frame"] for c in cameras], OUT / "ground_cameras.png")
    if synthetic:
        print(f"synthetic: the plane's ground against the world's road / sidewalk / curb materials: precision "
              f"{synthetic['ground_precision']:.3f}, recall {synthetic['ground_recall']:.3f}")
    for c in cameras:
        print(f"{c['frame']:9s} {c['camera']}: IoU LiDAR vs camera: wet {c['wet_iou']:.3f}, snow {c['snow_iou']:.3f};"
              f" CPU wet {c['wet_cpu_s']:.2f} s, snow {c['snow_cpu_s']:.2f} s")
    for r in rows:
        if "film_mm" in r:
            print(f"{r['frame']:9s} film {r['film_mm']:4.2f} mm: ground {r['ground_points']}, intensity x "
                  f"{r['mean_intensity_ratio']:.3f}, lost {r['ground_lost']} ({r['ground_lost_share']:.1%}), "
                  f"below the weakest reported ({r['weakest_reported']:.1f}) {r['below_weakest_share']:.1%}")
        else:
            print(f"{r['frame']:9s} snow {r['snow_depth_m']} m: covered {r['covered_points']} returns "
                  f"({r['covered_ground_points']} ground, {r['covered_other_points']} other), ground raised "
                  f"{r['ground_rise_m_median']:.3f} m, intensity x {r['mean_intensity_ratio_covered']:.2f}")
    return result


if __name__ == "__main__":
    main()
