"""Typed configuration: `params.yaml` validated into frozen pydantic models.

`load_params(path, overrides)` is the only entry point. Errors name the offending key and the allowed form, e.g.
``params.yaml: world.ego_speed_max = 30.0 is invalid: Input should be less than or equal to 12``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class ConfigError(ValueError):
    """Invalid params: the message names the file, the key, the bad value and the allowed form."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PathsConfig(_Section):
    """Every generated file lives under one of these two folders (relative to the repository root)."""

    data: Path = Path("data")
    reports: Path = Path("reports")


class RunConfig(_Section):
    """How per-frame work is executed."""

    max_workers: Annotated[int, Field(ge=1, le=64)] = 2
    dask_address: str | None = None
    torch_threads: Annotated[int, Field(ge=1, le=64)] = 2
    show_progress: bool = True


class TrackingConfig(_Section):
    """MLflow tracking: a local sqlite store inside the repository unless a URI is given."""

    mlflow_uri: str | None = None
    experiment: str = "weatheralign"
    enabled: bool = True


class LidarConfig(_Section):
    """The synthetic LIDAR_TOP, modelled on a Velodyne HDL-32E."""

    frequency_hz: Annotated[float, Field(gt=1.0, le=50.0)] = 20.0
    firings_per_ring: Annotated[int, Field(ge=90, le=4000)] = 1085
    max_range_m: Annotated[float, Field(gt=10.0, le=300.0)] = 100.0
    min_range_m: Annotated[float, Field(ge=0.0, le=5.0)] = 1.0
    range_noise_std_m: Annotated[float, Field(ge=0.0, le=0.1)] = 0.008
    intensity_noise_std: Annotated[float, Field(ge=0.0, le=20.0)] = 1.5
    min_detectable_intensity: Annotated[float, Field(ge=0.0, le=50.0)] = 0.5
    beam_divergence_rad: Annotated[float, Field(gt=0.0, le=0.02)] = 0.003


class CameraConfig(_Section):
    """The six nuScenes-like cameras."""

    image_scale: Annotated[float, Field(gt=0.02, le=1.0)] = 1.0
    jpeg_quality: Annotated[int, Field(ge=50, le=100)] = 92
    noise_std: Annotated[float, Field(ge=0.0, le=0.1)] = 0.012
    shadows: bool = True


class WorldConfig(_Section):
    """The `world` stage: the synthetic nuScenes-format dataset (or a real nuScenes dataroot)."""

    source: Literal["synthetic", "nuscenes"] = "synthetic"
    nuscenes_dataroot: Path | None = None
    version: str = "v1.0-mini"
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 2026
    num_train_scenes: Annotated[int, Field(ge=1, le=200)] = 8
    num_val_scenes: Annotated[int, Field(ge=1, le=200)] = 2
    samples_per_scene: Annotated[int, Field(ge=2, le=80)] = 6
    sweeps_per_sample: Annotated[int, Field(ge=0, le=9)] = 9
    ego_speed_min: Annotated[float, Field(ge=5.0, le=12.0)] = 5.0
    ego_speed_max: Annotated[float, Field(ge=5.0, le=12.0)] = 12.0
    lidar: LidarConfig = LidarConfig()
    camera: CameraConfig = CameraConfig()

    @model_validator(mode="after")
    def _check(self) -> "WorldConfig":
        if self.ego_speed_min > self.ego_speed_max:
            raise ValueError(
                f"ego_speed_min ({self.ego_speed_min}) must not exceed ego_speed_max ({self.ego_speed_max})"
            )
        if self.source == "nuscenes" and self.nuscenes_dataroot is None:
            raise ValueError("source 'nuscenes' needs nuscenes_dataroot (a folder holding <version>/*.json)")
        return self


class SnowConfig(_Section):
    """Snowfall (Hahner 2022): water-equivalent rate, terminal velocity, size distribution, wind."""

    rate_mm_h: Annotated[float, Field(gt=0.0, le=20.0)] = 2.0
    terminal_velocity_m_s: Annotated[float, Field(ge=0.2, le=5.0)] = 1.5
    size_distribution: Literal["gunn_marshall", "sekhon_srivastava"] = "gunn_marshall"
    wind_m_s: tuple[float, float] = (0.0, 0.0)
    cell_size_m: Annotated[float, Field(ge=0.5, le=10.0)] = 2.0


class RainConfig(_Section):
    """Rain (LISA): Marshall-Palmer drops from the rain rate, one fall velocity for the field, wind."""

    rate_mm_h: Annotated[float, Field(gt=0.0, le=300.0)] = 50.0
    terminal_velocity_m_s: Annotated[float, Field(ge=0.5, le=12.0)] = 2.0
    wind_m_s: tuple[float, float] = (0.0, 0.0)
    min_diameter_m: Annotated[float, Field(ge=1e-5, le=1e-3)] = 5e-5
    cell_size_m: Annotated[float, Field(ge=0.25, le=10.0)] = 1.0


class ParticlesConfig(_Section):
    """The `particles` stage: one shared particle field per scene and precipitation condition."""

    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 11
    layer_bottom_m: Annotated[float, Field(ge=-50.0, le=0.0)] = -2.0
    layer_top_m: Annotated[float, Field(ge=5.0, le=200.0)] = 30.0
    validation_regions: Annotated[int, Field(ge=1, le=50)] = 4
    validation_max_particles: Annotated[int, Field(ge=10_000, le=5_000_000)] = 400_000
    snow: SnowConfig = SnowConfig()
    rain: RainConfig = RainConfig()


class SimulateConfig(_Section):
    """The `simulate` stage: one weather condition (aligned or unaligned) applied to a copy of the clean dataset.

    Fog levels are the literature values (``alpha`` [1/m], ``beta = fog_beta_mor / MOR``) until the calibration stage
    overrides them through these keys. ``fog_beta_light`` / ``fog_beta_dense`` (None: from ``fog_beta_mor``) set beta
    directly. Unaligned fog: the cameras' alpha is drawn uniformly in ``[fog_alpha_light, fog_alpha_dense]``, once per
    scene (seed ``fog_seed``), independently of the LiDAR's level.
    """

    condition: Literal["fog_light", "fog_dense", "snow", "rain"] = "snow"
    aligned: bool = True
    fog_alpha_light: Annotated[float, Field(gt=0.0, le=0.5)] = 0.01
    fog_alpha_dense: Annotated[float, Field(gt=0.0, le=0.5)] = 0.04
    fog_beta_mor: Annotated[float, Field(ge=0.0, le=1.0)] = 0.046
    fog_beta_light: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    fog_beta_dense: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    fog_seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 7
    noise_floor: Annotated[float, Field(ge=0.0, le=50.0)] = 0.5
    rain_appearance: Literal["rain", "rain_opaque_drops"] = "rain"
    exposure_s: Annotated[float, Field(ge=0.0, le=0.1)] = 0.005
    near_clip_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    refine_transmission: bool = True
    max_samples: Annotated[int, Field(ge=0)] = 0
    sweeps: bool = False

    @field_validator("aligned", mode="before")
    @classmethod
    def _alignment_word(cls, v: Any) -> Any:
        """Also accept the DVC matrix words ``aligned`` / ``unaligned``."""
        return {"aligned": True, "unaligned": False}.get(v, v) if isinstance(v, str) else v

    @model_validator(mode="after")
    def _check(self) -> "SimulateConfig":
        if self.fog_alpha_light > self.fog_alpha_dense:
            raise ValueError(f"fog_alpha_light ({self.fog_alpha_light}) must not exceed fog_alpha_dense "
                             f"({self.fog_alpha_dense})")
        return self


class Params(_Section):
    """The whole of params.yaml."""

    paths: PathsConfig = PathsConfig()
    run: RunConfig = RunConfig()
    tracking: TrackingConfig = TrackingConfig()
    world: WorldConfig = WorldConfig()
    particles: ParticlesConfig = ParticlesConfig()
    simulate: SimulateConfig = SimulateConfig()


def apply_override(tree: dict[str, Any], assignment: str) -> None:
    """Apply one ``dotted.key=value`` override in place; the value is parsed as YAML (numbers, bools, lists)."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment!r}: expected the form key.sub=value")
    key, raw = assignment.split("=", 1)
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"--set {assignment!r}: empty key component in {key!r}")
    node = tree
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"--set {assignment!r}: {part!r} is a value, not a section")
        node = child
    node[parts[-1]] = yaml.safe_load(raw) if raw.strip() else None


def _format_error(source: str, tree: dict[str, Any], err: ValidationError) -> str:
    lines = []
    for item in err.errors():
        loc = ".".join(str(p) for p in item["loc"])
        value: Any = tree
        for part in item["loc"]:
            value = value.get(part, "<missing>") if isinstance(value, dict) else "<missing>"
        msg = item["msg"]
        if item["type"] == "extra_forbidden":
            msg = "unknown key (check the spelling against params.yaml)"
        shown = "" if isinstance(value, dict) else f" = {value!r}"
        lines.append(f"{source}: {loc}{shown} is invalid: {msg}")
    return "\n".join(lines)


def params_from_dict(tree: dict[str, Any], source: str = "params") -> Params:
    """Validate a nested dict into `Params`; raise `ConfigError` naming each bad key."""
    try:
        return Params.model_validate(tree)
    except ValidationError as err:
        raise ConfigError(_format_error(source, tree, err)) from None


def load_params(path: str | Path = "params.yaml", overrides: list[str] | tuple[str, ...] = ()) -> Params:
    """Read a params YAML file, apply ``key=value`` overrides, validate.

    Raises:
        ConfigError: missing/unparsable file, or a key with a value outside its allowed range.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: params file not found")
    try:
        tree = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at top level, got {type(tree).__name__}")
    for assignment in overrides:
        apply_override(tree, assignment)
    return params_from_dict(tree, source=str(path))
