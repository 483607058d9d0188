"""`media` stage: every condition's media resolved once, one file per condition.

``python -m flows.media`` reads the world's manifest (its scenes), the calibrate_fog stage's tuned fog levels
(``simulate.fog_levels: calibrated``; ``params`` uses the literature levels), the particles stage's fields and the
calibrate_precipitation stage's tuned snow and rain rates (``simulate.precipitation_rates: calibrated``; ``params``
keeps the particles params' rates), and
writes ``<paths.data>/media/<condition>.json`` for every condition of `weatheralign.conditions.CONDITIONS`
(`weatheralign.simulate.media.resolve_media`): the fog's (α, β) and the cameras' unaligned α per scene, and/or the
particle field of every scene. ``simulate@<condition>-*`` depends on its condition's file alone, so a new fog
calibration reruns the fog conditions and nothing else (the other files are rewritten with the same bytes).
"""

from __future__ import annotations

from prefect import flow

from flows.common import parse_stage_args, run_stage
from tasks.tracking import StageTracker
from weatheralign import atomic
from weatheralign.conditions import CONDITIONS, condition_tags
from weatheralign.config import Params
from weatheralign.manifest import FIELDS_FILE, manifest_path, read_manifest
from weatheralign.simulate.media import (
    PrecipitationRates,
    configured_fog_levels,
    configured_precipitation_rates,
    load_fields,
    media_path,
    resolve_media,
)

FOG_HEADLINE = ("fog_light", "fog_dense")
"""The fog levels whose extinction the headline gives (fog_snow's fog is fog_light's)."""


def headline(details: dict) -> dict:
    """The weather in force, calibrated or from params: the precipitation rates and the `FOG_HEADLINE` levels'
    extinction (the Prefect table artifact; the rest, backscatter and ground depths included, in details.json and the
    MLflow child run of each condition). No DVC metrics: the calibrations' metrics or the params columns of
    ``dvc exp show`` give the same figures."""
    rates = details["precipitation_rates"] or {}
    conditions = details["conditions"]
    return {"rate_mm_h": {k: v["rate_mm_h"] for k, v in rates.items()},
            "fog": {name: {"alpha": conditions[name]["fog_alpha"]} for name in FOG_HEADLINE
                    if (conditions.get(name) or {}).get("fog_alpha") is not None}}


def ground_source(kind: str, rates: PrecipitationRates | None) -> str:
    """Where the depth of a ``kind`` (``wet`` / ``snow``) ground came from: ``calibrated`` or ``params``."""
    calibrated = rates is not None and ("rain" if kind == "wet" else "snow") in rates.ground_depth_m
    return "calibrated" if calibrated else "params"


@flow(name="media", log_prints=True)
def media_flow(params: Params) -> dict:
    """Write every condition's media file; returns the metrics (per condition: fog level, α, β, fields)."""
    cfg = params.simulate
    with StageTracker(params, "media") as tracker:
        world = read_manifest(manifest_path(params.paths.data, "world"))
        tracker.log_dataset("world", world.content_digest, world.dataroot, "source")
        scenes = list(world.scenes)
        needs = {m for c in CONDITIONS.values() for m in c.media}
        fog_levels = configured_fog_levels(cfg, params.paths.data) if "fog_levels" in needs else None
        fields = load_fields(params.paths.data / FIELDS_FILE) if "fields" in needs else None
        rates = configured_precipitation_rates(cfg, params.particles, params.paths.data) if fields else None
        metrics: dict = {"fog_levels": None if fog_levels is None else fog_levels.source,
                         "precipitation_rates": None if rates is None else {
                             k: {"rate_mm_h": rates.rate_mm_h[k], "source": rates.source[k]} for k in rates.rate_mm_h},
                         "conditions": {}}
        for name, condition in CONDITIONS.items():
            media = resolve_media(condition, cfg, scenes, fog_levels, fields, rates)
            atomic.write_json(media_path(params.paths.data, name), media.to_dict(), indent=1)
            ground = next(iter(media.ground.values())) if media.ground else None
            metrics["conditions"][name] = {
                "fog_alpha": None if media.fog is None else media.fog["alpha"],
                "fog_beta": None if media.fog is None else media.fog["beta"],
                "fields": 0 if media.fields is None else len(media.fields),
                "ground": None if ground is None else ground.kind,
                "ground_depth_m": None if ground is None else ground.amount_m,
                "ground_source": None if ground is None else ground_source(ground.kind, rates)}
        snow_rain = (params.particles.snow.rate_mm_h, params.particles.rain.rate_mm_h) if rates is None else \
            (rates.rate_mm_h["snow"], rates.rate_mm_h["rain"])
        tracker.finish(metrics, headline(metrics), logged={}, metrics_file=False, children={
            name: (condition_tags(name, None, *snow_rain), values) for name, values in metrics["conditions"].items()})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    return run_stage(media_flow, parse_stage_args("media", argv), runner=None)


if __name__ == "__main__":
    main()
