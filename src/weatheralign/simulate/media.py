"""The media of a condition, resolved once per dataset: tuned fog levels and per-scene particle fields.

`resolve_media` (the `media` stage) turns a `weatheralign.conditions.Condition` into `ConditionMedia`: the fog's
(α, β) at its level (from the calibrate_fog stage's ``fog_levels.json`` or the literature values in params), the
cameras' unaligned fog extinction per scene, and the particle field of every scene (from the particles stage's
``fields.json``). It is written to ``<paths.data>/media/<condition>.json``, the only weather input of
``simulate@<condition>-*``, so a simulate stage depends on exactly the inputs its condition uses.
`ConditionMedia.for_scene` gives the `SceneMedia` that the observation core consumes.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from weatheralign.camera.overcast import Overcast
from weatheralign.conditions import CONDITIONS, Condition, FogPart, GroundPart, ParticlePart
from weatheralign.config import ParticlesConfig, SimulateConfig
from weatheralign.data.errors import DataFormatError, read_json_file
from weatheralign.ground.edit import GroundState
from weatheralign.ground.snow import SnowCover, TireTracks
from weatheralign.ground.wet import WetRoad
from weatheralign.manifest import FOG_LEVELS_FILE, PRECIPITATION_RATES_FILE
from weatheralign.medium.conditions import FieldSpec
from weatheralign.medium.field import ParticleField
from weatheralign.medium.fog import mor_from_alpha


@dataclass(frozen=True)
class FogLevels:
    """(α [1/m], β [1/(m sr)]) of the light and dense levels, each level's airlight gains (the fog's airlight over the
    clear sky's, `weatheralign.camera.fog.airlight_gains`; ``(1.0,)``: the clear sky's own) and where they came
    from."""

    alpha: dict[str, float]
    beta: dict[str, float]
    source: str
    airlight_gains: dict[str, tuple[float, ...]] = field(
        default_factory=lambda: {"light": (1.0,), "dense": (1.0,)})


def params_fog_levels(cfg: SimulateConfig) -> FogLevels:
    """The literature levels of params: ``beta = fog_beta_mor / MOR`` unless ``fog_beta_<level>`` is set."""
    alpha = {"light": cfg.fog_alpha_light, "dense": cfg.fog_alpha_dense}
    explicit = {"light": cfg.fog_beta_light, "dense": cfg.fog_beta_dense}
    beta = {k: cfg.fog_beta_mor / mor_from_alpha(a) if explicit[k] is None else explicit[k] for k, a in alpha.items()}
    return FogLevels(alpha, beta, "params")


def calibrated_fog_levels(path: Path) -> FogLevels:
    """The tuned levels in ``path`` (`FOG_LEVELS_FILE`); a level without ``airlight_gains`` keeps the clear sky's
    airlight (``(1.0,)``).

    Raises:
        DataFormatError: missing or unreadable file, a missing level or key, a non-positive alpha, a negative beta,
            airlight gains that are not a non-empty list of positive numbers, or a light level denser than the dense
            one.
    """
    path = Path(path)
    levels = read_json_file(path, "run the calibrate_fog stage first (dvc repro calibrate_fog) or set "
                                  "simulate.fog_levels=params to use the literature levels")
    alpha, beta, gains = {}, {}, {}
    for level in ("light", "dense"):
        entry = levels.get(level) if isinstance(levels, dict) else None
        gains[level] = _airlight_gains(entry.get("airlight_gains", [1.0]) if isinstance(entry, dict) else [1.0],
                                       f"{path}: {level}.airlight_gains")
        for key, out in (("alpha", alpha), ("beta", beta)):
            v = entry.get(key) if isinstance(entry, dict) else None
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise DataFormatError(f"{path}: {level}.{key} = {v!r}; expected a finite number")
            out[level] = float(v)
        if alpha[level] <= 0.0 or beta[level] < 0.0:
            raise DataFormatError(f"{path}: {level} must have alpha > 0 and beta >= 0, got {alpha[level]}, "
                                  f"{beta[level]}")
    if alpha["light"] > alpha["dense"]:
        raise DataFormatError(f"{path}: light.alpha {alpha['light']} exceeds dense.alpha {alpha['dense']}")
    return FogLevels(alpha, beta, "calibrated", gains)


def _airlight_gains(value: Any, where: str) -> tuple[float, ...]:
    if not isinstance(value, list) or not value or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0.0 for v in value):
        raise DataFormatError(f"{where} = {value!r}; expected a non-empty list of positive numbers")
    return tuple(float(v) for v in value)


def configured_fog_levels(cfg: SimulateConfig, data: Path) -> FogLevels:
    """The fog levels ``simulate.fog_levels`` selects (``calibrated``: `FOG_LEVELS_FILE` under ``data``)."""
    return calibrated_fog_levels(Path(data) / FOG_LEVELS_FILE) if cfg.fog_levels == "calibrated" else \
        params_fog_levels(cfg)


@dataclass(frozen=True)
class PrecipitationRates:
    """The snow and rain rates [mm/h] of the particle fields and where each came from (``calibrated`` or
    ``params``); the ground each leaves, where calibrated (``ground_depth_m``: ``rain`` the mean film depth,
    ``snow`` the snow depth [m]; a kind absent keeps ``simulate.wet_film_depth_m`` / ``snow_depth_m``)."""

    rate_mm_h: dict[str, float]
    source: dict[str, str]
    ground_depth_m: dict[str, float] = field(default_factory=dict)
    overcast: dict[str, CalibratedLight] = field(default_factory=dict)
    """Per split (``snow`` / ``rain``) the calibrated overcast light; a split absent keeps ``simulate.overcast_*``."""


@dataclass(frozen=True)
class CalibratedLight:
    """One split's calibrated overcast (``rates.json["overcast"][split]``, `weatheralign.calibrate.overcast`): the
    zenith luminance L_z, ζ, and the diffuse gain Q at each sun transmittance of ``sun_grid``; ``sun_transmittance``
    where the reference identified it, else None (the simulation's ``simulate.overcast_sun_transmittance`` is used
    and Q read off the curve)."""

    zenith_luminance: float
    zenith_over_surface: float
    sun_grid: tuple[float, ...]
    diffuse_gains: tuple[float, ...]
    sun_transmittance: float | None = None

    @classmethod
    def of(cls, light: Overcast) -> CalibratedLight:
        """A fully known light (``T`` given, Q the same at every T)."""
        return cls(light.zenith_luminance, light.zenith_over_surface, (light.sun_transmittance,),
                   (light.diffuse_gain,), light.sun_transmittance)

    def light(self, configured_sun: float) -> Overcast:
        """The operator's light: this split's T (``configured_sun`` where not identified), Q at that T (interpolated
        on ``sun_grid``, clamped to its ends)."""
        t = configured_sun if self.sun_transmittance is None else self.sun_transmittance
        return Overcast(t, self.zenith_luminance, float(np.interp(t, self.sun_grid, self.diffuse_gains)),
                        self.zenith_over_surface)


def params_precipitation_rates(particles: ParticlesConfig) -> PrecipitationRates:
    """The rates of ``particles.<kind>.rate_mm_h``."""
    return PrecipitationRates({k: getattr(particles, k).rate_mm_h for k in ("snow", "rain")},
                              {"snow": "params", "rain": "params"})


def _positive(path: Path, where: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0.0:
        raise DataFormatError(f"{path}: {where} = {value!r}; expected a positive number")
    return float(value)


def calibrated_precipitation_rates(path: Path, particles: ParticlesConfig) -> PrecipitationRates:
    """The tuned rates in ``path`` (`PRECIPITATION_RATES_FILE`) and the tuned ground depths (its ``ground`` entry);
    a kind the file lacks (a reference without that split) keeps its params rate, and its source says so.

    Raises:
        DataFormatError: missing or unreadable file, or a rate that is not a positive number.
    """
    path = Path(path)
    tuned = read_json_file(path, "run the calibrate_precipitation stage first (dvc repro calibrate_precipitation) "
                                 "or set simulate.precipitation_rates=params to use the particles params")
    out = params_precipitation_rates(particles)
    for kind in ("snow", "rain"):
        entry = tuned.get(kind) if isinstance(tuned, dict) else None
        if entry is None:
            out.source[kind] = f"params (no {kind} split in the reference)"
            continue
        v = entry.get("rate_mm_h") if isinstance(entry, dict) else None
        out.rate_mm_h[kind], out.source[kind] = _positive(path, f"{kind}.rate_mm_h", v), "calibrated"
    ground = tuned.get("ground") if isinstance(tuned, dict) else None
    for kind, entry in (ground or {}).items():
        if kind in ("snow", "rain"):
            depth = entry.get("depth_m") if isinstance(entry, dict) else None
            out.ground_depth_m[kind] = _positive(path, f"ground.{kind}.depth_m", depth)
    for kind, entry in (tuned.get("overcast") or {} if isinstance(tuned, dict) else {}).items():
        if kind in ("snow", "rain"):
            out.overcast[kind] = _calibrated_light(path, kind, entry if isinstance(entry, dict) else {})
    return out


def _calibrated_light(path: Path, kind: str, entry: dict) -> CalibratedLight:
    """`CalibratedLight` of ``rates.json["overcast"][kind]`` (``sun_transmittance`` null: not identified).

    Raises:
        DataFormatError: a value missing or not positive, or a Q curve that does not match its T grid.
    """
    where = f"overcast.{kind}"
    grid = entry.get("sun_grid")
    gains = entry.get("diffuse_gain_by_sun")
    if not isinstance(grid, list) or not isinstance(gains, list) or len(grid) != len(gains) or not grid:
        raise DataFormatError(f"{path}: {where}: sun_grid and diffuse_gain_by_sun must be lists of one length, got "
                              f"{grid!r} and {gains!r}")
    sun = entry.get("sun_transmittance")
    try:
        light = CalibratedLight(_positive(path, f"{where}.zenith_luminance", entry.get("zenith_luminance")),
                                _positive(path, f"{where}.zenith_over_surface", entry.get("zenith_over_surface")),
                                tuple(float(t) for t in grid),
                                tuple(_positive(path, f"{where}.diffuse_gain_by_sun", q) for q in gains),
                                None if sun is None else _positive(path, f"{where}.sun_transmittance", sun))
        light.light(0.0)
    except (TypeError, ValueError) as exc:
        raise DataFormatError(f"{path}: {where}: {exc}") from None
    return light


def configured_precipitation_rates(cfg: SimulateConfig, particles: ParticlesConfig, data: Path
                                   ) -> PrecipitationRates:
    """The rates ``simulate.precipitation_rates`` selects (``calibrated``: `PRECIPITATION_RATES_FILE` under
    ``data``)."""
    if cfg.precipitation_rates == "calibrated":
        return calibrated_precipitation_rates(Path(data) / PRECIPITATION_RATES_FILE, particles)
    return params_precipitation_rates(particles)


def load_fields(path: Path) -> dict[str, list[FieldSpec]]:
    """``{kind: [FieldSpec, ...]}`` from the particles stage's file.

    Raises:
        DataFormatError: missing or malformed file.
    """
    raw = read_json_file(path, "run the particles stage first (python -m flows.particles)")
    try:
        return {kind: [FieldSpec.from_dict(d) for d in specs] for kind, specs in raw.items()}
    except (TypeError, KeyError, AttributeError) as exc:
        raise DataFormatError(f"{path}: expected {{kind: [field spec, ...]}} ({exc})") from None


# ------------------------------------------------------------------------------------------------ resolved media


@dataclass(frozen=True)
class SceneGround:
    """A scene's ground under a condition: ``kind`` (``wet`` or ``snow``), the LiDAR's film or snow depth
    ``amount_m`` and field ``seed``, the cameras' (``camera_amount_m``, ``camera_seed``: the LiDAR's when aligned,
    the twin's when not), the puddles' share of a wet road."""

    kind: str
    amount_m: float
    seed: int
    camera_amount_m: float
    camera_seed: int
    puddle_share: float = 0.0

    def state(self, camera: bool, tracks: TireTracks | None) -> GroundState:
        """The `GroundState` the LiDAR (``camera`` False) or the cameras see; snow pressed down in ``tracks``."""
        amount, seed = (self.camera_amount_m, self.camera_seed) if camera else (self.amount_m, self.seed)
        if self.kind == "wet":
            return GroundState(road=WetRoad(film_depth_m=amount, puddle_share=self.puddle_share), seed=seed)
        return GroundState(cover=SnowCover(depth_m=amount), tracks=tracks, seed=seed)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "amount_m": self.amount_m, "seed": self.seed,
                "camera_amount_m": self.camera_amount_m, "camera_seed": self.camera_seed,
                "puddle_share": self.puddle_share}


def ground_seed(seed: int, condition: str, scene: str, camera: bool) -> int:
    """The ground field's seed of ``scene`` (the cameras' twin's with ``camera``): a hash of (``seed``,
    ``condition``, ``scene``)."""
    digest = hashlib.sha256(f"{seed}/{condition}/{scene}/ground{'/camera' if camera else ''}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


@dataclass(frozen=True)
class SceneMedia:
    """A condition over one scene, as each sensor sees it.

    Attributes:
        condition: the `Condition`; aligned: whether the cameras see the LiDAR's media; scene: scene name.
        lidar_alpha, lidar_beta: the LiDAR's fog [1/m], [1/(m sr)] (0 without fog).
        camera_alpha: the cameras' fog extinction [1/m] (aligned: ``lidar_alpha``; 0 without fog).
        field: the scene's `FieldSpec` (the LiDAR's field; the cameras see `camera_field`), or None.
        camera_rate_mm_h: the unaligned cameras' precipitation rate [mm/h] (`ParticlePart.camera_rate`); None: the
            field's own.
        airlight_gain: the fog's airlight over the scene's clear-sky airlight (`FogPart.airlight_gain`; 1 without
            fog).
        ground: the scene's ground (`SceneGround`) or None (the air alone).
        overcast: the light the cameras see the scene under (`weatheralign.camera.overcast.Overcast`), or None (the
            clear day's).
    """

    condition: Condition
    aligned: bool
    scene: str
    lidar_alpha: float = 0.0
    lidar_beta: float = 0.0
    camera_alpha: float = 0.0
    field: FieldSpec | None = None
    camera_rate_mm_h: float | None = None
    airlight_gain: float = 1.0
    ground: SceneGround | None = None
    overcast: Overcast | None = None

    @property
    def has_particles(self) -> bool:
        """A particle field of positive rate exists."""
        return self.field is not None and self.field.rate_mm_h > 0.0

    def camera_field(self) -> ParticleField | None:
        """The particle field the cameras see: the LiDAR's when aligned, else its twin (another seed) at
        ``camera_rate_mm_h``; None without particles."""
        if not self.has_particles:
            return None
        if self.aligned:
            return self.field.field()
        rate = self.field.rate_mm_h if self.camera_rate_mm_h is None else self.camera_rate_mm_h
        return replace(self.field, rate_mm_h=rate).field(aligned=False)


@dataclass(frozen=True)
class ConditionMedia:
    """The resolved media of one condition over every scene of a dataset (JSON: `to_dict` / `from_dict`).

    Attributes:
        condition: the condition's name (a key of `CONDITIONS`).
        fog: ``{"level", "alpha", "beta", "source", "camera_alpha_unaligned": {scene: α}, "airlight_gain":
            {scene: gain}}`` or None (media without ``airlight_gain``: 1, the clear sky's airlight).
        fields: ``{scene: FieldSpec}`` or None.
        camera_rate_unaligned: ``{scene: rate [mm/h]}`` the unaligned cameras' rate (with ``fields``).
        ground: ``{scene: SceneGround}`` as the unaligned copy sees it (the aligned copy's cameras see the LiDAR's
            ground), or None.
        overcast: the overcast light of every scene (`Overcast.to_dict`; aligned and unaligned alike), or None.
    """

    condition: str
    fog: dict[str, Any] | None
    fields: dict[str, FieldSpec] | None
    camera_rate_unaligned: dict[str, float] | None = None
    ground: dict[str, SceneGround] | None = None
    overcast: dict[str, float] | None = None

    def for_scene(self, scene: str, aligned: bool, rain_appearance: str = "rain") -> SceneMedia:
        """`SceneMedia` of ``scene``.

        Raises:
            DataFormatError: the media hold no field or fog extinction for ``scene``.
        """
        condition = CONDITIONS[self.condition].with_rain_appearance(rain_appearance)
        kw: dict[str, Any] = {}
        if self.fog is not None:
            unaligned = self.fog["camera_alpha_unaligned"]
            if scene not in unaligned:
                raise DataFormatError(f"media of {self.condition}: no fog for scene {scene!r}; rerun the media stage")
            kw.update(lidar_alpha=self.fog["alpha"], lidar_beta=self.fog["beta"],
                      camera_alpha=self.fog["alpha"] if aligned else unaligned[scene],
                      airlight_gain=float(self.fog.get("airlight_gain", {}).get(scene, 1.0)))
        if self.fields is not None:
            if scene not in self.fields:
                raise DataFormatError(f"media of {self.condition}: no particle field for scene {scene!r} (has "
                                      f"{sorted(self.fields)}); rerun the particles and media stages")
            kw["field"] = self.fields[scene]
            if not aligned:
                if not self.camera_rate_unaligned or scene not in self.camera_rate_unaligned:
                    raise DataFormatError(f"media of {self.condition}: no unaligned camera rate for scene {scene!r}; "
                                          f"rerun the media stage")
                kw["camera_rate_mm_h"] = self.camera_rate_unaligned[scene]
        if self.ground is not None:
            if scene not in self.ground:
                raise DataFormatError(f"media of {self.condition}: no ground for scene {scene!r}; rerun the media "
                                      f"stage")
            g = self.ground[scene]
            kw["ground"] = g if not aligned else replace(g, camera_amount_m=g.amount_m, camera_seed=g.seed)
        if self.overcast is not None:
            kw["overcast"] = Overcast(**self.overcast)
        return SceneMedia(condition, aligned, scene, **kw)

    def rates(self, particles: ParticlesConfig) -> tuple[float, float]:
        """(snow, rain) [mm/h] for run tags: the fields' rate (tuned or params, as resolved) for the condition's own
        kind, the ``particles`` params' for the other."""
        rates = {"snow": particles.snow.rate_mm_h, "rain": particles.rain.rate_mm_h}
        if self.fields:
            spec = next(iter(self.fields.values()))
            rates[spec.condition] = spec.rate_mm_h
        return rates["snow"], rates["rain"]

    def to_dict(self) -> dict[str, Any]:
        return {"condition": self.condition, "fog": self.fog,
                "fields": None if self.fields is None else {k: v.to_dict() for k, v in sorted(self.fields.items())},
                "camera_rate_unaligned": None if self.camera_rate_unaligned is None
                else dict(sorted(self.camera_rate_unaligned.items())),
                "ground": None if self.ground is None else {k: v.to_dict() for k, v in sorted(self.ground.items())},
                "overcast": self.overcast}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "media") -> ConditionMedia:
        try:
            if d["condition"] not in CONDITIONS:
                raise ValueError(f"unknown condition {d['condition']!r}")
            fields = None if d["fields"] is None else {k: FieldSpec.from_dict(v) for k, v in d["fields"].items()}
            rates = d.get("camera_rate_unaligned")
            rates = None if rates is None else {k: float(v) for k, v in rates.items()}
            ground = d.get("ground")
            ground = None if ground is None else {k: SceneGround(**v) for k, v in ground.items()}
            overcast = d.get("overcast")
            if overcast is not None:
                overcast = Overcast(**overcast).to_dict()
            return ConditionMedia(d["condition"], d["fog"], fields, rates, ground, overcast)
        except (KeyError, TypeError, ValueError) as exc:
            raise DataFormatError(f"{where}: not a valid media file ({exc})") from None


def resolve_media(condition: Condition, cfg: SimulateConfig, scenes: list[str], fog_levels: FogLevels | None,
                  fields: dict[str, list[FieldSpec]] | None, rates: PrecipitationRates | None = None
                  ) -> ConditionMedia:
    """The media of ``condition`` over ``scenes`` (``fog_levels`` needed with fog, ``fields`` with particles; the
    fields' rates replaced by ``rates`` where given).

    Raises:
        DataFormatError: a needed input is missing or lacks a scene.
    """
    fog = None
    if condition.fog is not None:
        if fog_levels is None:
            raise DataFormatError(f"condition {condition.name} needs fog levels")
        level = condition.fog.level
        alpha = fog_levels.alpha[level]
        fog = {"level": level, "alpha": alpha, "beta": fog_levels.beta[level], "source": fog_levels.source,
               "camera_alpha_unaligned": {
                   s: FogPart.camera_alpha(False, alpha, fog_levels.alpha["light"], fog_levels.alpha["dense"],
                                           cfg.fog_seed, condition.name, s) for s in scenes},
               "airlight_gain": {s: FogPart.airlight_gain(fog_levels.airlight_gains[level], cfg.fog_seed,
                                                          condition.name, s) for s in scenes}}
    per_scene = None
    if condition.particles is not None:
        kind = condition.particles.kind
        if not fields or kind not in fields:
            raise DataFormatError(f"condition {condition.name} needs {kind} fields (run the particles stage)")
        by_scene = {spec.scene: spec for spec in fields[kind]}
        missing = [s for s in scenes if s not in by_scene]
        if missing:
            raise DataFormatError(f"the particles stage's {kind} fields lack scenes {missing}; rerun it")
        per_scene = {s: by_scene[s] if rates is None else replace(by_scene[s], rate_mm_h=rates.rate_mm_h[kind])
                     for s in scenes}
        camera_rates = {s: ParticlePart.camera_rate(False, spec.rate_mm_h, cfg.unaligned_rate_factor, spec.seed)
                        for s, spec in per_scene.items()}
        return ConditionMedia(condition.name, fog, per_scene, camera_rates, resolve_ground(
            condition, cfg, scenes, None if rates is None else rates.ground_depth_m),
            resolve_overcast(condition, cfg, rates))
    return ConditionMedia(condition.name, fog, per_scene, ground=resolve_ground(
        condition, cfg, scenes, None if rates is None else rates.ground_depth_m),
        overcast=resolve_overcast(condition, cfg, rates))


def resolve_overcast(condition: Condition, cfg: SimulateConfig, rates: PrecipitationRates | None = None
                     ) -> dict[str, float] | None:
    """The light of ``condition`` (`Overcast.to_dict`; None without a `SkyPart` or with ``simulate.overcast``
    off): the calibrated light of its split where ``rates`` has one (``simulate.overcast_sun_transmittance`` where
    its T was not identified), else ``simulate.overcast_*``."""
    if condition.sky is None or not cfg.overcast:
        return None
    calibrated = (rates.overcast if rates is not None else {}).get(condition.sky.split)
    if calibrated is not None:
        return calibrated.light(cfg.overcast_sun_transmittance).to_dict()
    return Overcast(cfg.overcast_sun_transmittance, cfg.overcast_zenith_luminance, cfg.overcast_diffuse_gain,
                    cfg.overcast_zenith_over_surface).to_dict()


def resolve_ground(condition: Condition, cfg: SimulateConfig, scenes: list[str],
                   depths_m: dict[str, float] | None = None) -> dict[str, SceneGround] | None:
    """The ground of ``condition`` per scene as an unaligned copy sees it (None without one or with
    ``simulate.ground`` off): the film or snow depth of ``depths_m`` (``rain`` / ``snow``, the calibrated ones)
    where it has one, else ``simulate.wet_film_depth_m`` / ``snow_depth_m``."""
    if condition.ground is None or not cfg.ground:
        return None
    wet = condition.ground.kind == "wet"
    amount = (depths_m or {}).get("rain" if wet else "snow", cfg.wet_film_depth_m if wet else cfg.snow_depth_m)
    out = {}
    for scene in scenes:
        seed = ground_seed(cfg.ground_seed, condition.name, scene, camera=False)
        out[scene] = SceneGround(condition.ground.kind, amount, seed,
                                 GroundPart.camera_amount(False, amount, cfg.unaligned_rate_factor, seed),
                                 ground_seed(cfg.ground_seed, condition.name, scene, camera=True),
                                 cfg.wet_puddle_share if wet else 0.0)
    return out


def media_path(data: Path, condition: str) -> Path:
    """``<data>/media/<condition>.json``."""
    return Path(data) / "media" / f"{condition}.json"


def read_media(path: Path) -> ConditionMedia:
    """The media file written by the media stage.

    Raises:
        DataFormatError: missing or malformed.
    """
    raw = read_json_file(path, "run the media stage first (python -m flows.media)")
    return ConditionMedia.from_dict(raw, str(path))
