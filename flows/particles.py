"""`particles` stage: define the shared snow and rain fields (one per scene and condition), validate them, and
write them for the `simulate` stage.

Writes ``<paths.data>/particles/fields.json`` (the exact field of every scene and condition),
``reports/particles/details.json`` (its headline in ``metrics.json``) and figures (size histograms against the
distributions; a side view of a materialised region with the LiDAR beams and a camera's field of view).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import gather, parse_stage_args, run_stage
from tasks.tracking import StageTracker
from weatheralign import atomic
from weatheralign.config import Params
from weatheralign.data.nuscenes import load_frame, open_nuscenes
from weatheralign.geometry import invert, transform_from_quaternion
from weatheralign.manifest import manifest_path, read_manifest
from weatheralign.medium.conditions import PRECIPITATION, FieldSpec, field_spec
from weatheralign.medium.validation import camera_air_volume, check_region, lidar_air_volume
from weatheralign.viz import particle_side_view, size_histogram_figure

LIDAR_REACH_M = 80.0
CAMERA_DEPTH_M = 60.0


@dataclass(frozen=True)
class RigGeometry:
    """What the expected particle counts and the side view need of the dataset's own sensors (the calibration of its
    first sample): the LiDAR's mount (ego x, z) [m], ring elevations [deg] and counting reach [m]; the front
    camera's mount (ego x, z) [m], intrinsics (3, 3) and image size [px]."""

    lidar_xz: tuple[float, float]
    elevations_deg: tuple[float, ...]
    lidar_reach_m: float
    camera_xz: tuple[float, float]
    camera_K: np.ndarray
    camera_width: int
    camera_height: int


def rig_geometry(params: Params) -> RigGeometry:
    """The `RigGeometry` of the `world` output (its manifest's LiDAR model; the calibrated sensors of its first
    sample; ``CAM_FRONT``, else the first camera)."""
    world = read_manifest(manifest_path(params.paths.data, "world"))
    nusc = open_nuscenes(Path(world.dataroot), world.version)
    frame = load_frame(nusc, nusc.scene[0]["first_sample_token"])
    cam = frame.cameras.get("CAM_FRONT") or next(iter(frame.cameras.values()))
    lidar = world.sensors.lidar
    return RigGeometry((float(frame.lidar.T_ego_lidar[0, 3]), float(frame.lidar.T_ego_lidar[2, 3])),
                       tuple(lidar.elevations_deg), min(LIDAR_REACH_M, lidar.max_range_m),
                       (float(cam.T_ego_cam[0, 3]), float(cam.T_ego_cam[2, 3])), cam.K, cam.width, cam.height)


def scene_anchors(params: Params) -> list[tuple[str, float, np.ndarray]]:
    """(scene name, first keyframe time [s], T_global_ego (4, 4) there) of every scene of the `world` output (named by
    its manifest)."""
    world = read_manifest(manifest_path(params.paths.data, "world"))
    tables = Path(world.dataroot) / world.version
    load = lambda name: json.loads((tables / f"{name}.json").read_text())  # noqa: E731
    samples = {s["token"]: s for s in load("sample")}
    poses = {p["token"]: p for p in load("ego_pose")}
    lidar_pose = {sd["sample_token"]: poses[sd["ego_pose_token"]] for sd in load("sample_data")
                  if sd["is_key_frame"] and sd["filename"].startswith("samples/LIDAR_TOP/")}
    out = []
    for scene in load("scene"):
        first = samples[scene["first_sample_token"]]
        pose = lidar_pose[first["token"]]
        out.append((scene["name"], first["timestamp"] * 1e-6,
                    transform_from_quaternion(pose["rotation"], pose["translation"])))
    return out


@task(name="validate-field", cache_policy=NO_CACHE)
def validate_condition(specs: list[FieldSpec], anchors: list[tuple[str, float, np.ndarray]], regions: int,
                       max_particles: int, rig: RigGeometry) -> dict:
    """Materialise sample regions of the first scenes' fields and compare them with the size distribution; the
    particles the dataset's LiDAR and front camera can see (``rig``: its own calibration)."""
    checks = []
    for k in range(regions):
        spec = specs[k % len(specs)]
        name, t0, T_global_ego = anchors[k % len(anchors)]
        field = spec.field()
        centre = T_global_ego[:3, :3] @ np.array([12.0 + 6.0 * k, 0.0, 3.0]) + T_global_ego[:3, 3]
        checks.append(check_region(field, centre, t0, max_particles))
    field = specs[0].field()
    spectrum = field.spectrum
    lidar_volume = lidar_air_volume(rig.lidar_reach_m, rig.lidar_xz[1], field.z_max,
                                    (min(rig.elevations_deg), max(rig.elevations_deg)))
    camera_volume = camera_air_volume(rig.camera_K, rig.camera_width, rig.camera_height, rig.camera_xz[1],
                                      CAMERA_DEPTH_M, field.z_max)
    n = field.number_density()
    return {
        "number_density_per_m3": n,
        "mean_diameter_mm": spectrum.moment(1) * 1e3,
        "extinction_per_m": field.extinction(),
        "visibility_m": float(np.log(20.0) / field.extinction()),
        "density_ge_1mm_per_m3": field.number_density(1e-3),
        "lidar_air_volume_m3": lidar_volume,
        "expected_particles_lidar_volume": n * lidar_volume,
        "camera_front_volume_m3": camera_volume,
        "expected_particles_camera_front": n * camera_volume,
        "regions": [{"scene": anchors[k % len(anchors)][0], "side_m": c.side, "expected": c.expected,
                     "realised": c.realised, "z_score": c.z_score, "size_chi2_pvalue": c.chi2_pvalue}
                    for k, c in enumerate(checks)],
        "max_abs_z_score": max(abs(c.z_score) for c in checks),
        "min_size_chi2_pvalue": min(c.chi2_pvalue for c in checks),
        "_diameters": np.concatenate([c.diameters for c in checks]),
    }


def _side_view(spec: FieldSpec, anchor: tuple[str, float, np.ndarray], rig: RigGeometry, path: Path) -> None:
    name, t0, T_global_ego = anchor
    field = spec.field()
    min_d = 6e-3 if spec.condition == "snow" else 2.5e-3  # only the large ones, so that one can see through
    x0, x1, z1 = -4.0, 40.0, 14.0
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (-0.5, 0.5) for z in (0.0, z1)])
    world = corners @ T_global_ego[:3, :3].T + T_global_ego[:3, 3]
    particles = field.materialize(world.min(0), world.max(0), t0, min_diameter=min_d)
    T = invert(T_global_ego)
    local = particles.positions @ T[:3, :3].T + T[:3, 3]
    keep = (np.abs(local[:, 1]) <= 0.5) & (local[:, 0] >= x0) & (local[:, 0] <= x1) & (local[:, 2] >= 0)
    fig = particle_side_view(local[keep][:, [0, 2]], particles.diameters[keep], rig.lidar_xz,
                             np.asarray(rig.elevations_deg), rig.camera_xz,
                             float(np.degrees(np.arctan(rig.camera_height / 2 / rig.camera_K[1, 1]))),
                             (x0, x1, -0.5, z1),
                             f"{spec.condition} over {name}: 1 m thick slab along the ego axis, "
                             f"D >= {min_d * 1e3:g} mm")
    fig.savefig(path, dpi=110)
    plt.close(fig)


@flow(name="particles", log_prints=True)
def particles_flow(params: Params) -> dict:
    """Define, validate and write the shared particle fields."""
    with StageTracker(params, "particles") as tracker:
        tracker.log_params({"particles": params.particles.model_dump(mode="json")})
        anchors = scene_anchors(params)
        rig = rig_geometry(params)
        specs = {c: [field_spec(params.particles, c, name, t0) for name, t0, _ in anchors] for c in PRECIPITATION}
        futures = [validate_condition.submit(specs[c], anchors, params.particles.validation_regions,
                                             params.particles.validation_max_particles, rig) for c in PRECIPITATION]
        results = dict(zip(PRECIPITATION, gather(futures, "particles: validating fields", params.run.show_progress)))
        out = params.paths.data / "particles" / "fields.json"
        atomic.write_json(out, {c: [s.to_dict() for s in specs[c]] for c in PRECIPITATION}, indent=1)

        diameters = {c: r.pop("_diameters") for c, r in results.items()}
        pdfs = {}
        for c in PRECIPITATION:
            spectrum = specs[c][0].field().spectrum
            grid = np.linspace(spectrum.d_min, float(np.quantile(diameters[c], 0.999)), 300)
            pdfs[c] = (grid, spectrum.pdf(grid))
        fig = size_histogram_figure(diameters, pdfs)
        hist = tracker.reports / "size_histograms.png"
        fig.savefig(hist, dpi=110)
        plt.close(fig)
        tracker.log_artifact(hist, "figures")
        for c in PRECIPITATION:
            side = tracker.reports / f"side_view_{c}.png"
            _side_view(specs[c][0], anchors[0], rig, side)
            tracker.log_artifact(side, "figures")
        metrics = {"fields_file": str(out), "num_scenes": len(anchors), **results}
        tracker.finish(metrics, headline(metrics), logged={"num_scenes": len(anchors)}, children={
            c: ({"weather": c, "severity": f"{getattr(params.particles, c).rate_mm_h:g} mm/h"}, results[c])
            for c in PRECIPITATION})
    return metrics


HEADLINE = ("number_density_per_m3", "extinction_per_m")
"""Per precipitation, the figures of reports/particles/metrics.json (the rest, sizes and the per-region checks
included, in details.json and the MLflow child run of each precipitation)."""


def headline(details: dict) -> dict:
    """Per precipitation its `HEADLINE` figures."""
    return {c: {k: details[c].get(k) for k in HEADLINE} for c in PRECIPITATION if c in details}


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("particles", argv)
    return run_stage(particles_flow, params)


if __name__ == "__main__":
    main()
