"""The library's entry point without the pipeline: a weather copy of any nuScenes-format dataset in one call.

`simulate_weather` does in one process what the pipeline's stages do for one condition (sensors from the dataset,
one particle field per scene, the condition's media, every sample observed by every sensor, the copy completed with
hard links), with the fog levels and precipitation rates of ``params`` (the pipeline tunes them to a real reference
first: `calibrate_fog`, `calibrate_precipitation`). No Prefect, DVC or MLflow; same params and seed, same bytes; an
interrupted call resumes the samples it finished.

    from weatheralign.api import simulate_weather
    simulate_weather("/data/nuscenes", "snow", "/data/nuscenes-snow", version="v1.0-mini")
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from tqdm import tqdm

from weatheralign.conditions import condition_named
from weatheralign.config import Params
from weatheralign.data.nuscenes import open_nuscenes
from weatheralign.manifest import dataset_digest
from weatheralign.medium.conditions import PRECIPITATION, FieldSpec, field_spec
from weatheralign.sensors import dataset_sensors
from weatheralign.simulate.media import params_fog_levels, params_precipitation_rates, resolve_media
from weatheralign.simulate.observe import ObserveOptions
from weatheralign.simulate.plan import plan_jobs
from weatheralign.simulate.weather_copy import copy_outputs, finalize_copy, run_sample, summarise


def scene_fields(nusc, params: Params) -> dict[str, list[FieldSpec]]:
    """One snow and one rain field per scene of ``nusc``, anchored at the scene's first keyframe (its time [s])."""
    anchors = []
    for scene in nusc.scene:
        sample = nusc.get("sample", scene["first_sample_token"])
        anchors.append((scene["name"], sample["timestamp"] * 1e-6))
    return {kind: [field_spec(params.particles, kind, name, t0) for name, t0 in anchors] for kind in PRECIPITATION}


def _run_digest(params: Params, digest: str, condition: str, aligned: bool) -> str:
    """What makes a finished sample reusable: the dataset, the condition and every parameter the weather reads."""
    key = {"dataset": digest, "condition": condition, "aligned": aligned,
           "simulate": params.simulate.model_dump(mode="json"), "particles": params.particles.model_dump(mode="json"),
           "world": params.world.model_dump(mode="json")}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


def simulate_weather(dataroot: str | Path, condition: str, out: str | Path, *, version: str = "v1.0-mini",
                     aligned: bool = True, params: Params | None = None, show_progress: bool = True) -> dict:
    """Write a weather copy of the nuScenes-format dataset at ``dataroot`` to ``out`` for ``condition`` (a key of
    `weatheralign.conditions.CONDITIONS`: ``fog_light``, ``fog_dense``, ``snow``, ``rain``, ``fog_snow``).

    ``aligned=False`` gives the cameras the condition's independent twin media (the unaligned ablation).
    ``params`` (default: the defaults of params.yaml's schema, `weatheralign.config.Params`) sets the fog levels
    (``simulate.fog_alpha_*``), the rates (``particles.*.rate_mm_h``), the seeds and the rendering; its ``world``
    section describes the dataset (``world.source: nuscenes`` estimates the LiDAR model from the scans).
    The input is never modified. Returns the copy's summary (points per label, particles drawn, re-projection error).

    Raises:
        ValueError: an unknown condition, or ``out`` inside ``dataroot`` (or the reverse).
        weatheralign.data.errors.DataFormatError: the dataset cannot be read (names the file and field).
    """
    src_root, out_root = Path(dataroot).resolve(), Path(out).resolve()
    if out_root == src_root or src_root in out_root.parents or out_root in src_root.parents:
        raise ValueError(f"simulate_weather: out {out_root} must lie outside the dataset {src_root} (and not hold it)")
    cond = condition_named(condition)
    params = params or Params.model_validate(
        {"world": {"source": "nuscenes", "nuscenes_dataroot": str(src_root), "version": version}})
    nusc = open_nuscenes(src_root, version)
    sensors = dataset_sensors(params.world, nusc)
    media = resolve_media(cond, params.simulate, [s["name"] for s in nusc.scene], params_fog_levels(params.simulate),
                          scene_fields(nusc, params), params_precipitation_rates(params.particles))
    jobs = plan_jobs(nusc, media, aligned, params.simulate.rain_appearance, params.simulate.max_samples)
    options = ObserveOptions(params.simulate.near_clip_m, params.simulate.refine_transmission)
    digest = _run_digest(params, dataset_digest(src_root, version), cond.name, aligned)
    records = [run_sample(nusc, src_root, out_root, job, sensors, options, digest, params.simulate.jpeg_quality,
                          params.simulate.sweeps)[0]
               for job in tqdm(jobs, desc=f"{condition} ({'aligned' if aligned else 'unaligned'})", unit="sample",
                               disable=not show_progress)]
    finalize_copy(nusc, src_root, out_root, version, copy_outputs(nusc, [j.sample_token for j in jobs],
                                                                  params.simulate.sweeps))
    return summarise(records)

