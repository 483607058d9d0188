"""Writer of the 13 nuScenes tables of the synthetic world (+ map mask and custom ``splits.json``) from rendered sample
records.

Tokens are deterministic (hashes of identifying parts), so the same world gives byte-identical tables.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from weatheralign import atomic
from weatheralign.geometry import apply, quaternion_wxyz, yaw_matrix
from weatheralign.world.build import SampleResult, SceneSpec, token

CATEGORY_DESCRIPTIONS = {
    "vehicle.car": "Vehicle designed primarily for personal use, e.g. sedans, hatch-backs, wagons, vans, SUVs.",
    "vehicle.truck": "Vehicles primarily designed to haul cargo including pick-ups, lorrys, trucks and semi-tractors.",
    "vehicle.bus.rigid": "Rigid bus.",
    "vehicle.bicycle": "Human or electric powered 2-wheeled vehicle designed to travel at lower speeds.",
    "vehicle.motorcycle": "Gasoline or electric powered 2-wheeled vehicle designed to move rapidly.",
    "human.pedestrian.adult": "Adult subcategory.",
    "movable_object.barrier": "Temporary road barrier placed in the scene in order to redirect traffic.",
    "movable_object.trafficcone": "All types of traffic cone.",
}
ATTRIBUTES = ["vehicle.moving", "vehicle.stopped", "vehicle.parked", "cycle.with_rider", "cycle.without_rider",
              "pedestrian.sitting_lying_down", "pedestrian.standing", "pedestrian.moving"]
VISIBILITY_LEVELS = [("1", "v0-40"), ("2", "v40-60"), ("3", "v60-80"), ("4", "v80-100")]
MAP_RESOLUTION_M = 0.1
MAP_SIZE_M = 1000.0
LOCATION = "weatheralign-synthetic-city"


@dataclass(frozen=True)
class SensorCalibration:
    """A sensor of the rig: channel, modality, ``T_ego_sensor`` (4, 4) and intrinsics (3, 3) for cameras."""

    channel: str
    modality: str
    T_ego_sensor: NDArray[np.float64]
    intrinsic: NDArray[np.float64] | None


@dataclass(frozen=True)
class RoadFootprint:
    """A street's drivable area for the map: scene -> global transform, half width, optional crossing x [m], and the
    street's scene-frame x range [m] (`RoadGeometry.x_extent`)."""

    T_global_scene: NDArray[np.float64]
    road_half_width: float
    crossing_x: float | None
    crossing_half_width: float
    x_extent: tuple[float, float] = (-200.0, 260.0)


def _sensor_records(seed: int, sensors: Sequence[SensorCalibration]) -> tuple[list[dict], list[dict]]:
    sensor, calib = [], []
    for s in sensors:
        s_tok = token(seed, "sensor", s.channel)
        sensor.append({"token": s_tok, "channel": s.channel, "modality": s.modality})
        calib.append({
            "token": token(seed, "calibrated_sensor", s.channel), "sensor_token": s_tok,
            "translation": [float(v) for v in s.T_ego_sensor[:3, 3]],
            "rotation": quaternion_wxyz(s.T_ego_sensor[:3, :3]),
            "camera_intrinsic": [] if s.intrinsic is None else [[float(v) for v in row] for row in s.intrinsic],
        })
    return sensor, calib


def build_tables(seed: int, specs: Sequence[SceneSpec], results: Sequence[SampleResult],
                 sensors: Sequence[SensorCalibration]) -> dict[str, list[dict]]:
    """All 13 tables as lists of records. ``results`` may come in any order; every scene must be complete."""
    by_scene: dict[int, list[SampleResult]] = defaultdict(list)
    for r in results:
        by_scene[r.scene_index].append(r)
    sensor, calibrated = _sensor_records(seed, sensors)
    calib_by_channel = {s["channel"]: c["token"] for s, c in zip(sensor, calibrated)}
    cat_tok = {name: token(seed, "category", name) for name in CATEGORY_DESCRIPTIONS}
    attr_tok = {name: token(seed, "attribute", name) for name in ATTRIBUTES}
    tables: dict[str, list[dict]] = {name: [] for name in (
        "category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log", "scene",
        "sample", "sample_data", "sample_annotation", "map")}
    tables["category"] = [{"token": cat_tok[n], "name": n, "description": d} for n, d in CATEGORY_DESCRIPTIONS.items()]
    tables["attribute"] = [{"token": attr_tok[n], "name": n, "description": n.replace(".", ": ").replace("_", " ")}
                           for n in ATTRIBUTES]
    tables["visibility"] = [{"token": t, "level": lvl, "description": f"visibility of whole object is {lvl[1:]} %"}
                            for t, lvl in VISIBILITY_LEVELS]
    tables["sensor"], tables["calibrated_sensor"] = sensor, calibrated

    for spec in specs:
        samples = sorted(by_scene.get(spec.index, []), key=lambda r: r.sample_index)
        if not samples:
            raise ValueError(f"scene {spec.name}: no rendered samples")
        log_tok = token(seed, "log", spec.log_name)
        tables["log"].append({"token": log_tok, "logfile": spec.log_name, "vehicle": "weatheralign-ego",
                              "date_captured": "2026-11-21", "location": LOCATION})
        scene_tok = token(seed, "scene", spec.name)
        sample_toks = [token(seed, "sample", spec.name, r.sample_index) for r in samples]
        tables["scene"].append({"token": scene_tok, "log_token": log_tok, "nbr_samples": len(samples),
                                "first_sample_token": sample_toks[0], "last_sample_token": sample_toks[-1],
                                "name": spec.name, "description": f"synthetic street, seed {spec.seed}"})
        chains: dict[str, list[dict]] = defaultdict(list)  # sample_data chain per channel
        for k, (r, s_tok) in enumerate(zip(samples, sample_toks)):
            tables["sample"].append({"token": s_tok, "timestamp": r.timestamp_us,
                                     "prev": sample_toks[k - 1] if k else "",
                                     "next": sample_toks[k + 1] if k + 1 < len(samples) else "",
                                     "scene_token": scene_tok})
            for rec in r.lidar + r.cameras:
                sd_tok = token(seed, "sample_data", rec.filename)
                ep_tok = token(seed, "ego_pose", rec.filename)
                tables["ego_pose"].append({"token": ep_tok, "timestamp": rec.timestamp_us,
                                           "rotation": rec.ego_rotation, "translation": rec.ego_translation})
                chains[rec.channel].append({
                    "token": sd_tok, "sample_token": s_tok, "ego_pose_token": ep_tok,
                    "calibrated_sensor_token": calib_by_channel[rec.channel], "timestamp": rec.timestamp_us,
                    "fileformat": "pcd" if rec.channel.startswith("LIDAR") else "jpg",
                    "is_key_frame": rec.is_key_frame, "height": rec.height, "width": rec.width,
                    "filename": rec.filename, "prev": "", "next": ""})
        for chain in chains.values():
            chain.sort(key=lambda d: d["timestamp"])
            for a, b in zip(chain[:-1], chain[1:]):
                a["next"], b["prev"] = b["token"], a["token"]
            tables["sample_data"].extend(chain)
        _annotations(seed, spec, samples, sample_toks, cat_tok, attr_tok, tables)

    log_tokens = [log["token"] for log in tables["log"]]
    tables["map"] = [{"token": token(seed, "map", LOCATION), "log_tokens": log_tokens, "category": "semantic_prior",
                      "filename": f"maps/{token(seed, 'map', LOCATION)}.png"}]
    return tables


def _annotations(seed: int, spec: SceneSpec, samples: list[SampleResult], sample_toks: list[str],
                 cat_tok: dict[str, str], attr_tok: dict[str, str], tables: dict[str, list[dict]]) -> None:
    per_instance: dict[int, list[dict]] = defaultdict(list)
    categories: dict[int, str] = {}
    for r, s_tok in zip(samples, sample_toks):
        for a in r.annotations:
            categories[a.instance] = a.category
            per_instance[a.instance].append({
                "token": token(seed, "sample_annotation", spec.name, r.sample_index, a.instance),
                "sample_token": s_tok, "instance_token": token(seed, "instance", spec.name, a.instance),
                "visibility_token": str(a.visibility),
                "attribute_tokens": [attr_tok[a.attribute]] if a.attribute else [],
                "translation": a.center, "size": a.size, "rotation": quaternion_wxyz(yaw_matrix(a.yaw)),
                "prev": "", "next": "", "num_lidar_pts": a.num_lidar_pts, "num_radar_pts": 0})
    for inst in sorted(per_instance):
        anns = per_instance[inst]
        for a, b in zip(anns[:-1], anns[1:]):
            a["next"], b["prev"] = b["token"], a["token"]
        tables["sample_annotation"].extend(anns)
        tables["instance"].append({"token": anns[0]["instance_token"], "category_token": cat_tok[categories[inst]],
                                   "nbr_annotations": len(anns), "first_annotation_token": anns[0]["token"],
                                   "last_annotation_token": anns[-1]["token"]})


def drivable_mask(roads: Sequence[RoadFootprint]) -> NDArray[np.uint8]:
    """A nuScenes ``semantic_prior`` map (255 = drivable) at `MAP_RESOLUTION_M`; row 0 is the map's top (max y)."""
    size = int(MAP_SIZE_M / MAP_RESOLUTION_M)
    mask = np.zeros((size, size), np.uint8)

    def fill(T: NDArray, x0: float, x1: float, y0: float, y1: float) -> None:
        corners = apply(T, np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]]))
        px = np.stack([corners[:, 0] / MAP_RESOLUTION_M, size - corners[:, 1] / MAP_RESOLUTION_M], 1)
        cv2.fillPoly(mask, [np.round(px).astype(np.int32)], 255)

    for road in roads:
        fill(road.T_global_scene, *road.x_extent, -road.road_half_width, road.road_half_width)
        if road.crossing_x is not None:
            fill(road.T_global_scene, road.crossing_x - road.crossing_half_width,
                 road.crossing_x + road.crossing_half_width, -150.0, 150.0)
    return mask


def write_dataset_tables(dataroot: Path, version: str, tables: dict[str, list[dict]],
                         splits: dict[str, list[str]], roads: Sequence[RoadFootprint]) -> None:
    """Write ``<dataroot>/<version>/*.json``, ``splits.json`` and the map PNG, each atomically."""
    for name, records in tables.items():
        atomic.write_json(dataroot / version / f"{name}.json", records)
    atomic.write_json(dataroot / version / "splits.json", splits)
    ok, png = cv2.imencode(".png", drivable_mask(roads), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding of the map mask failed")
    atomic.write_bytes(dataroot / tables["map"][0]["filename"], png.tobytes())
