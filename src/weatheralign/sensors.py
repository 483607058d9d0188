"""Sensors as data: the LiDAR and camera models that travel with a dataset.

Every physics function that depends on a sensor fact (beam divergence, firing grid, maximum range, pulse, noise
floor, intensity calibration, exposure) takes a `LidarModel` or `CameraModel` explicitly; nothing falls back to a
default sensor. Where the models come from:

- the synthetic world: built from ``world.lidar`` / ``world.camera`` params (`lidar_model_from_params`,
  `camera_exposure_from_params`) and written into the dataset's manifest (`weatheralign.manifest`);
- real scans (nuScenes HDL-32E, Seeing Through Fog HDL-64, KITTI): estimated from the scans' ring / azimuth
  statistics (`estimate_lidar_model`: ring count, per-ring elevation, columns per ring, rotation direction), with the
  facts a point cloud cannot tell (divergence, pulse, intensity model) from the nearest known sensor and overridable
  in params (``world.sensor_overrides``).

Serialisation is plain JSON (`LidarModel.to_dict` / `from_dict`); the manifest's content digest covers it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.data.nuscenes import LIDAR_TOP_YAW, SWEEP_START_AZIMUTH, load_frame, load_lidar
from weatheralign.data.rings import HDL32E_ELEVATIONS_DEG

F64 = NDArray[np.float64]

SPEED_OF_LIGHT = 299_792_458.0
"""c [m/s]."""


class DetectorFloor(NamedTuple):
    """A sensor's detector floor as the numba kernels take it (`LidarModel.detector`): on the 0..255 scale the floor
    at reported range ``R`` is ``floor · R² g(R) / comp_ref`` (``g`` the `IntensityModel` gain of ``r_ref``,
    ``falloff``), or ``floor`` at every range when ``comp_ref`` is 0."""

    floor: float  # the floor at the reference range (0..255)
    r_ref: float  # the intensity model's range compensation: g(R) = min(1, (r_ref / R)^falloff)
    falloff: float
    comp_ref: float  # r_f² g(r_f) [m²] at the floor's reference range; 0: a constant floor


@dataclass(frozen=True)
class PulseSensor:
    """Pulse and optics parameters of a pulsed LiDAR.

    Attributes:
        tau_h: half-power pulse width τ_H [s] (the Velodyne HDL units: 10 ns, HDL-64 datasheet; Hahner's fog model
            used 20 ns).
        r1: range [m] where the receiver's field of view starts to overlap the beam (overlap ξ = 0 up to here).
        r2: range [m] from which the overlap is complete (ξ = 1); ξ rises linearly in between.
        gamma: hard-target reflectivity Γ of the reference target; ``beta_0 = Γ / π`` [1/sr].
        max_range: largest range the sensor reports [m].
        saturation: largest intensity the sensor reports, on the 0..255 scale.
    """

    tau_h: float = 20e-9
    r1: float = 0.9
    r2: float = 1.0
    gamma: float = 1e-6
    max_range: float = 120.0
    saturation: float = 255.0

    def __post_init__(self) -> None:
        checks = {
            "tau_h": (self.tau_h, 0.0 < self.tau_h < 1e-6, "0 < tau_h < 1e-6 s"),
            "r1": (self.r1, 0.0 < self.r1, "r1 > 0 m"),
            "r2": (self.r2, self.r1 < self.r2, f"r2 > r1 = {self.r1} m"),
            "gamma": (self.gamma, 0.0 < self.gamma, "gamma > 0"),
            "max_range": (self.max_range, self.r2 < self.max_range, f"max_range > r2 = {self.r2} m"),
            "saturation": (self.saturation, 0.0 < self.saturation <= 255.0, "0 < saturation <= 255"),
        }
        for name, (value, ok, allowed) in checks.items():
            if not (math.isfinite(value) and ok):
                raise ValueError(f"{type(self).__name__}.{name} = {value!r}; expected {allowed}")

    @property
    def beta_0(self) -> float:
        """Differential reflectivity ``Γ / π`` [1/sr] of the reference hard target."""
        return self.gamma / math.pi

    @property
    def pulse_length(self) -> float:
        """``c τ_H`` [m]: a hard target at ``R_0`` responds on ``R_0 <= R <= R_0 + c τ_H``, peaking at the middle."""
        return SPEED_OF_LIGHT * self.tau_h


@dataclass(frozen=True)
class IntensityModel:
    """How the sensor reports intensity: ``i = scale · ρ · cos θ · g(R)`` for a Lambertian target of reflectivity ρ
    covering the beam, with ``g(R) = min(1, (r_ref / R)^falloff)`` (see `weatheralign.lidar.particles`).

    Attributes:
        scale: intensity (0..255) of ρ = 1 at normal incidence where ``g = 1``.
        r_ref: range [m] up to which the sensor compensates the raw ``1/R²`` fall-off fully.
        falloff: exponent of the residual fall-off beyond ``r_ref`` (2 = raw power, 0 = calibrated reflectance).
    """

    scale: float = 255.0
    r_ref: float = 10.0
    falloff: float = 1.0

    def __post_init__(self) -> None:
        for name in ("scale", "r_ref"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"IntensityModel.{name} = {v!r}; expected a finite value > 0")
        if not (math.isfinite(self.falloff) and 0.0 <= self.falloff <= 4.0):
            raise ValueError(f"IntensityModel.falloff = {self.falloff!r}; expected 0 <= falloff <= 4")

    def gain(self, r: NDArray | float) -> F64:
        """``g(R)`` (any shape) for ranges ``r`` [m] (vectorised; the particle kernels' `_gain` is the same formula)."""
        r = np.maximum(np.asarray(r, dtype=np.float64), 1e-9)
        return np.minimum(1.0, (self.r_ref / r) ** self.falloff)

    def compensation(self, r: NDArray | float) -> F64:
        """``R² g(R)`` [m²] (any shape) at ranges ``r`` [m]: what turns a received raw power (falling as ``1 / R²``)
        into the reported value, up to the constant ``scale``; constant for a raw-reporting sensor (``r_ref = 1 m``,
        ``falloff = 2``, beyond 1 m)."""
        r = np.maximum(np.asarray(r, dtype=np.float64), 1e-9)
        return r * r * self.gain(r)

    def intensity(self, reflectivity: NDArray | float, r: NDArray | float, ratio: NDArray | float = 1.0) -> F64:
        """Reported intensity (0..255, unclipped) of a disk of ``reflectivity`` covering ``ratio`` of the beam at range
        ``r`` [m], in clear air."""
        return self.scale * np.asarray(reflectivity) * np.asarray(ratio) * self.gain(r)


SYNTHETIC_INTENSITY = IntensityModel(255.0, 10.0, 1.0)
"""The synthetic reference's HDL-64 (and the synthetic world's HDL-32E before it reported calibrated reflectivity):
``255 ρ cos θ min(1, 10 m / R)`` (`world.shading.lidar_intensity`)."""

HAHNER_INTENSITY = IntensityModel(255.0, 1.0, 2.0)
"""Hahner's published snow code: a particle reports ``255 ρ ratio / r²`` (raw power, calibrated at 1 m)."""

CALIBRATED_INTENSITY = IntensityModel(255.0, 1.0, 0.0)
"""A sensor reporting calibrated reflectance (KITTI's 0..1 reflectance): ``i = 255 ρ cos θ`` at any range."""

HDL_DIVERGENCE_RAD = 3e-3
"""Full beam divergence of the Velodyne HDL-32E / HDL-64E [rad] (datasheet order of magnitude)."""

HDL_PULSE_HALF_WIDTH_S = 10e-9
"""Half-power pulse width τ_H of the Velodyne HDL units [s] (HDL-64 datasheet, as in Hahner et al. 2022)."""

HDL32E_LASER_STEP_S = 1.152e-6
"""Delay between consecutive lasers of one HDL-32E firing column [s] (datasheet timing)."""


@dataclass(frozen=True)
class FiringPattern:
    """All beams of one sweep of a spinning LiDAR, in its own frame.

    Attributes:
        directions: (R*C, 3) unit beam directions; index = column * R + ring.
        ring: (R*C,) int16 ring index; column: (R*C,) int16 firing column 0..C-1.
        time_offsets: (R*C,) firing time relative to the sweep end [s], in [-period, 0).
        elevations_deg: (R,) elevation of each ring [deg].
        period: rotation period [s].
    """

    directions: F64
    ring: NDArray[np.int16]
    column: NDArray[np.int16]
    time_offsets: F64
    elevations_deg: F64
    period: float


@dataclass(frozen=True)
class LidarModel:
    """A spinning pulsed LiDAR.

    Attributes:
        elevations_deg: per ring index, the laser's elevation [deg] (the scan's ring convention).
        columns_per_ring: firings per ring and turn.
        rotation_hz: turns per second.
        clockwise: rotation seen from above (nuScenes: clockwise from the ego's left).
        start_azimuth_rad: azimuth where a sweep starts [rad, sensor frame].
        laser_step_s: delay between consecutive rings of one firing column [s].
        divergence_rad: full beam divergence [rad].
        max_range_m, min_range_m: reported range limits [m] (beams without return are ``max_range_m`` long).
        noise_floor: detector floor on the 0..255 scale: echoes below it are not reported. With ``floor_range_m``
            it is the floor at that range (`floor_at`).
        intensity_max: the intensity scale the scans are stored on (255 or 1).
        intensity: how the sensor turns received power into reported intensity (`IntensityModel`).
        pulse: pulse width, overlap and saturation (`PulseSensor`; its ``max_range`` is ``max_range_m``).
        firing_columns_stored: per-point firing columns are stored beside the scans (the synthetic world's extras),
            so beams without return come from the exact firing grid instead of a reconstruction.
        origin: ``params`` (declared) or ``estimated`` (from scans).
        intensity_noise_std, intensity_noise_rel: the detector's intensity noise on a new echo (0..255 scale):
            Gaussian of std ``sqrt(std² + (rel · peak)²)`` on the received peak, before the floor decides whether it
            is detected (0, 0: noise-free). Weak particle echoes near the floor are detected by chance through it.
        range_noise_std_m: Gaussian range noise of a new echo [m], clipped at ±2 σ.
        floor_range_m: None: the floor is ``noise_floor`` at every range, on the reported scale. A range [m]: the
            detector decides on the received raw power, as a real receiver does, and the reported value is that
            power times the range compensation ``R² g(R)`` at the reported range (`IntensityModel.compensation`), so
            on the reported scale the floor grows with range: ``floor(R) = noise_floor · R² g(R) / (r_f² g(r_f))``,
            ``noise_floor`` being what a target exactly at the floor reads at ``r_f = floor_range_m``. The constant
            part of a new echo's intensity noise is the receiver's and scales alike (`floor_scale`).
            ``docs/physics.md`` section 3.5.
    """

    elevations_deg: tuple[float, ...]
    columns_per_ring: int
    rotation_hz: float
    clockwise: bool
    start_azimuth_rad: float
    laser_step_s: float
    divergence_rad: float
    max_range_m: float
    min_range_m: float
    noise_floor: float
    intensity_max: float
    intensity: IntensityModel
    pulse: PulseSensor
    firing_columns_stored: bool = False
    origin: str = "params"
    intensity_noise_std: float = 0.0
    intensity_noise_rel: float = 0.0
    range_noise_std_m: float = 0.0
    floor_range_m: float | None = None

    def __post_init__(self) -> None:
        checks = {
            "floor_range_m": self.floor_range_m is None
            or (math.isfinite(self.floor_range_m) and 0.0 < self.floor_range_m <= 1000.0),
            "intensity_noise_std": math.isfinite(self.intensity_noise_std) and 0.0 <= self.intensity_noise_std <= 50.0,
            "intensity_noise_rel": math.isfinite(self.intensity_noise_rel) and 0.0 <= self.intensity_noise_rel <= 1.0,
            "range_noise_std_m": math.isfinite(self.range_noise_std_m) and 0.0 <= self.range_noise_std_m <= 1.0,
            "elevations_deg": len(self.elevations_deg) >= 1
            and all(math.isfinite(e) and -90.0 < e < 90.0 for e in self.elevations_deg),
            "columns_per_ring": 1 <= self.columns_per_ring <= 100_000,
            "rotation_hz": math.isfinite(self.rotation_hz) and 0.0 < self.rotation_hz <= 100.0,
            "divergence_rad": math.isfinite(self.divergence_rad) and 0.0 <= self.divergence_rad < 0.5,
            "max_range_m": math.isfinite(self.max_range_m) and self.max_range_m > self.min_range_m >= 0.0,
            "noise_floor": math.isfinite(self.noise_floor) and 0.0 <= self.noise_floor <= 255.0,
            "intensity_max": self.intensity_max in (1.0, 255.0),
            "laser_step_s": math.isfinite(self.laser_step_s) and 0.0 <= self.laser_step_s,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"LidarModel.{name} = {getattr(self, name)!r} is invalid")
        if self.pulse.max_range != self.max_range_m:
            raise ValueError(f"LidarModel: pulse.max_range {self.pulse.max_range} != max_range_m {self.max_range_m}")

    @property
    def num_rings(self) -> int:
        return len(self.elevations_deg)

    @property
    def period(self) -> float:
        """Rotation period [s]."""
        return 1.0 / self.rotation_hz

    def floor_scale(self, r: NDArray | float) -> F64:
        """(any shape) ``floor(R) / noise_floor`` at reported ranges ``r`` [m]: 1 without ``floor_range_m``, else
        ``R² g(R) / (r_f² g(r_f))``; the constant part of a new echo's intensity noise scales alike."""
        return floor_scale(r, self.intensity, self.floor_range_m)

    def floor_at(self, r: NDArray | float) -> F64:
        """(any shape) the detector floor on the 0..255 scale for echoes reported at ranges ``r`` [m]."""
        return self.noise_floor * self.floor_scale(r)

    def detector(self) -> DetectorFloor:
        """The floor as the numba kernels take it (`DetectorFloor`, `floor_factor`)."""
        comp = 0.0 if self.floor_range_m is None else float(self.intensity.compensation(self.floor_range_m))
        return DetectorFloor(float(self.noise_floor), float(self.intensity.r_ref), float(self.intensity.falloff),
                             comp)

    def firing_pattern(self) -> FiringPattern:
        """Every (ring, column) beam of one sweep: column c fires at azimuth ``start ∓ 2π (c + 1/2) / C`` (``-`` for
        clockwise) and time ``(c / C - 1) · period + ring · laser_step_s`` relative to the sweep's end."""
        elev = np.deg2rad(np.asarray(self.elevations_deg, dtype=np.float64))
        rings, columns = len(elev), self.columns_per_ring
        col = np.repeat(np.arange(columns), rings)
        ring = np.tile(np.arange(rings), columns)
        sign = -1.0 if self.clockwise else 1.0
        azimuth = self.start_azimuth_rad + sign * 2 * np.pi * (col + 0.5) / columns
        e = elev[ring]
        d = np.stack([np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.sin(e)], 1)
        t = (col / columns - 1.0) * self.period + ring * self.laser_step_s
        return FiringPattern(d, ring.astype(np.int16), col.astype(np.int16), t,
                             np.asarray(self.elevations_deg, dtype=np.float64), self.period)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON; ``floor_range_m`` only when set (a constant-floor sensor's dict is what it always was)."""
        d = asdict(self)
        d["elevations_deg"] = [float(e) for e in self.elevations_deg]
        if d["floor_range_m"] is None:
            del d["floor_range_m"]
        return d

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "lidar model") -> LidarModel:
        """Inverse of `to_dict`; raises ValueError naming ``where`` and the field on malformed input."""
        try:
            return LidarModel(**{**d, "elevations_deg": tuple(float(e) for e in d["elevations_deg"]),
                                 "intensity": IntensityModel(**d["intensity"]), "pulse": PulseSensor(**d["pulse"])})
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a valid LiDAR model ({exc})") from None


@dataclass(frozen=True)
class CameraModel:
    """A global-shutter camera: intrinsics ``K`` (3, 3) [px], ``width`` x ``height`` [px], ``exposure_s`` [s]."""

    channel: str
    K: tuple[tuple[float, float, float], ...]
    width: int
    height: int
    exposure_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.exposure_s) and 0.0 <= self.exposure_s <= 0.1):
            raise ValueError(f"CameraModel.exposure_s = {self.exposure_s!r}; expected 0..0.1 s")
        if self.width < 1 or self.height < 1:
            raise ValueError(f"CameraModel {self.channel}: size {self.width}x{self.height} is invalid")

    def to_dict(self) -> dict[str, Any]:
        return {"channel": self.channel, "K": [list(r) for r in self.K], "width": self.width, "height": self.height,
                "exposure_s": self.exposure_s}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "camera model") -> CameraModel:
        try:
            return CameraModel(d["channel"], tuple(tuple(float(v) for v in r) for r in d["K"]), int(d["width"]),
                               int(d["height"]), float(d["exposure_s"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a valid camera model ({exc})") from None


@dataclass(frozen=True)
class EgoBody:
    """The part of the ego vehicle that the cameras see (nuScenes: the rear of the roof at the bottom of CAM_BACK), in
    the ego frame (x forward, y left, z up; origin at the rear axle on the ground) [m]: the convex prism of width
    ``width`` over the side profile (front_x, roof_z) -> (rear_x, hatch_z) -> (rear_x, bottom_z) -> (front_x, bottom_z).

    The synthetic world renders exactly this solid into its cameras; the simulator gives its pixels the distance to
    it (`ray_distances`), so no weather is drawn on the ego (a real dataset's LiDAR never sees its own car)."""

    rear_x: float
    front_x: float
    roof_z: float
    hatch_z: float
    bottom_z: float
    width: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in asdict(self).values()):
            raise ValueError(f"ego body: every dimension must be finite, got {asdict(self)}")
        if not (self.rear_x < self.front_x and self.bottom_z < self.hatch_z <= self.roof_z and self.width > 0.0):
            raise ValueError(f"ego body {asdict(self)}: expected rear_x < front_x, bottom_z < hatch_z <= roof_z and "
                             f"width > 0 [m]")

    def corners(self) -> NDArray[np.float64]:
        """(8, 3) corners, ego frame [m]: the bottom ring, then the top ring, counter-clockwise from (rear, right)
        (`weatheralign.world.meshes.hexahedron` order)."""
        h = self.width / 2.0
        x0, x1 = self.rear_x, self.front_x
        z0 = self.bottom_z
        return np.array([[x0, -h, z0], [x1, -h, z0], [x1, h, z0], [x0, h, z0],
                         [x0, -h, self.hatch_z], [x1, -h, self.roof_z], [x1, h, self.roof_z], [x0, h, self.hatch_z]])

    def _planes(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Outward normals (6, 3) and offsets (6,): the solid is ``n · p <= d`` for all six planes."""
        h = self.width / 2.0
        slope = np.array([self.roof_z - self.hatch_z, 0.0, self.front_x - self.rear_x])  # up and back, outward
        slope /= np.linalg.norm(slope)
        normals = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0], [0, 0, -1.0], slope * [-1, 1, 1]])
        offsets = np.array([-self.rear_x, self.front_x, h, h, -self.bottom_z,
                            float(normals[5] @ [self.front_x, 0.0, self.roof_z])])
        return normals, offsets

    def ray_distances(self, origins: NDArray, directions: NDArray) -> NDArray[np.float64]:
        """(N,) distance [m] along each ray (origins (N, 3), unit directions (N, 3), ego frame) to where it enters the
        body; ``inf`` where it misses it or starts inside it (slab clipping against the six planes)."""
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        normals, offsets = self._planes()
        denom = d @ normals.T  # (N, 6)
        gap = offsets - o @ normals.T  # >= 0: the origin is inside that plane's half-space
        with np.errstate(divide="ignore", invalid="ignore"):
            t = gap / denom
        enter = np.where(denom < 0.0, t, -np.inf).max(axis=1)
        leave = np.where(denom > 0.0, t, np.inf).min(axis=1)
        parallel_out = ((denom == 0.0) & (gap < 0.0)).any(axis=1)
        hit = (enter <= leave) & (enter > 0.0) & ~parallel_out
        return np.where(hit, enter, np.inf)

    def camera_ranges(self, K: NDArray, T_ego_cam: NDArray, width: int, height: int) -> NDArray[np.float32]:
        """(H, W) float32 ray length [m] from a pinhole camera (intrinsics ``K`` (3, 3) for ``width`` x ``height``,
        OpenCV axes, pose ``T_ego_cam`` (4, 4)) to the body through each pixel centre; ``inf`` where its ray misses."""
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        dirs = rays @ np.asarray(T_ego_cam)[:3, :3].T
        origins = np.broadcast_to(np.asarray(T_ego_cam)[:3, 3], dirs.shape)
        return self.ray_distances(origins, dirs).reshape(height, width).astype(np.float32)

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "ego body") -> EgoBody:
        try:
            return EgoBody(**{k: float(v) for k, v in d.items()})
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{where}: not a valid ego body ({exc})") from None


@dataclass(frozen=True)
class SensorRig:
    """The sensors of one dataset: its LiDAR, its cameras by channel, and the ego body the cameras see (None: none)."""

    lidar: LidarModel
    cameras: dict[str, CameraModel]
    ego_body: EgoBody | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"lidar": self.lidar.to_dict(), "cameras": {k: v.to_dict() for k, v in sorted(self.cameras.items())},
                "ego_body": None if self.ego_body is None else self.ego_body.to_dict()}

    @staticmethod
    def from_dict(d: dict[str, Any], where: str = "sensors") -> SensorRig:
        if not isinstance(d, dict) or "lidar" not in d or not isinstance(d.get("cameras"), dict):
            raise ValueError(f"{where}: expected {{'lidar': {{...}}, 'cameras': {{channel: {{...}}}}, "
                             f"'ego_body': {{...}} or null}}")
        body = d.get("ego_body")
        return SensorRig(LidarModel.from_dict(d["lidar"], f"{where}.lidar"),
                         {k: CameraModel.from_dict(v, f"{where}.cameras.{k}") for k, v in d["cameras"].items()},
                         None if body is None else EgoBody.from_dict(body, f"{where}.ego_body"))


# ------------------------------------------------------------------------------------------------ from params


def sensor_start_azimuth(mount_yaw: float) -> float:
    """The nuScenes sweep start (`SWEEP_START_AZIMUTH`, an ego-frame azimuth) in the frame of a LiDAR mounted with
    ``mount_yaw`` [rad] about the ego's z (sensor azimuth = ego azimuth - mount yaw), in (-π, π]."""
    a = float(np.angle(np.exp(1j * (SWEEP_START_AZIMUTH - mount_yaw))))
    return math.pi if a == -math.pi else a


def mount_yaw_of(T_ego_lidar: NDArray) -> float:
    """Yaw [rad] of a LiDAR mounting ``T_ego_lidar`` (4, 4) about the ego's z axis."""
    R = np.asarray(T_ego_lidar, dtype=np.float64)[:3, :3]
    return float(math.atan2(R[1, 0], R[0, 0]))


def floor_scale(r: NDArray | float, intensity: IntensityModel, floor_range_m: float | None) -> F64:
    """(any shape) a detector floor's factor at reported ranges ``r`` [m] (`LidarModel.floor_scale`): 1 for a
    constant floor (``floor_range_m`` None), else ``R² g(R) / (r_f² g(r_f))`` with ``g`` the gain of ``intensity``."""
    r = np.asarray(r, dtype=np.float64)
    if floor_range_m is None:
        return np.ones(r.shape)
    return intensity.compensation(r) / float(intensity.compensation(floor_range_m))


@njit(nogil=True, cache=True, inline="always")
def compensation_at(r, r_ref, falloff):  # pragma: no cover
    """``R² g(R)`` [m²] at range ``r`` [m], ``g(R) = min(1, (r_ref / R)^falloff)``: the numba kernels' scalar form of
    `IntensityModel.compensation` (a raw power times it is the reported value, up to the sensor's scale)."""
    r = max(r, 1e-9)
    return r * r * min(1.0, (r_ref / r) ** falloff)


@njit(nogil=True, cache=True, inline="always")
def floor_factor(r, r_ref, falloff, comp_ref):  # pragma: no cover
    """``floor(R) / floor`` at reported range ``r`` [m] (the fields of a `DetectorFloor`): 1 for a constant floor
    (``comp_ref`` 0), else ``R² g(R) / comp_ref``: the numba kernels' scalar form of `floor_scale`."""
    if comp_ref <= 0.0:
        return 1.0
    return compensation_at(r, r_ref, falloff) / comp_ref


def lidar_model_from_params(cfg: Any, mount_yaw: float = LIDAR_TOP_YAW) -> LidarModel:
    """The synthetic world's HDL-32E-like LIDAR_TOP from ``world.lidar`` params (a `config.LidarConfig`), mounted like
    nuScenes' (``mount_yaw``: its firing grid starts at the nuScenes sweep start in the ego frame).

    Its detector decides on raw power (``floor_range_m``, `LidarModel.floor_range_m`), so the floor and the intensity
    noise both scale with ``R² g(R)``: the floor stays ``min_detectable_intensity / intensity_noise_std`` noise
    standard deviations above zero at every range, and new weather echoes are read with the renderer's noise.
    With a constant floor (``floor_range_m: null``) under the noise, a detector would report noise on every beam, so
    new weather echoes are then read noise-free."""
    raw_detector = cfg.floor_range_m is not None
    return LidarModel(
        elevations_deg=tuple(float(e) for e in HDL32E_ELEVATIONS_DEG), columns_per_ring=cfg.firings_per_ring,
        rotation_hz=cfg.frequency_hz, clockwise=True, start_azimuth_rad=sensor_start_azimuth(mount_yaw),
        laser_step_s=HDL32E_LASER_STEP_S, divergence_rad=cfg.beam_divergence_rad, max_range_m=cfg.max_range_m,
        min_range_m=cfg.min_range_m, noise_floor=cfg.min_detectable_intensity, intensity_max=255.0,
        range_noise_std_m=cfg.range_noise_std_m,
        intensity=IntensityModel(cfg.intensity_scale, cfg.intensity_r_ref_m, cfg.intensity_falloff),
        pulse=PulseSensor(tau_h=cfg.pulse_half_width_s, max_range=cfg.max_range_m),
        firing_columns_stored=True, origin="params", floor_range_m=cfg.floor_range_m,
        intensity_noise_std=cfg.intensity_noise_std if raw_detector else 0.0)


def ego_body_from_params(cfg: Any) -> EgoBody | None:
    """The `EgoBody` of ``world.ego_body`` params (a `config.EgoBodyConfig`, or None: no body in view)."""
    if cfg is None:
        return None
    return EgoBody(cfg.rear_x_m, cfg.front_x_m, cfg.roof_z_m, cfg.hatch_z_m, cfg.bottom_z_m, cfg.width_m)


# ------------------------------------------------------------------------------------------------ estimated


def _known_sensor(num_rings: int) -> tuple[float, float]:
    """(divergence [rad], pulse half width [s]) of the nearest known sensor by ring count (Velodyne HDL family)."""
    return HDL_DIVERGENCE_RAD, HDL_PULSE_HALF_WIDTH_S


class _RingSamples(NamedTuple):
    """Per scan, its points beyond 2 m from the sensor, as `estimate_lidar_model` reads them."""

    ring: list[NDArray[np.int64]]  # (N_s,) ring index
    elevation: list[F64]  # (N_s,) elevation seen from the sensor [deg]
    azimuth: list[F64]  # (N_s,) [rad]
    distance: list[F64]  # (N_s,) range from the sensor [m]
    time: list[F64 | None]  # (N_s,) per-point time offsets [s], or None
    intensity: list[F64]  # every point's intensity on 0..255 (all points, near ones included)


def _ring_samples(scans: list[LidarScan]) -> _RingSamples:
    """The `_RingSamples` of ``scans``."""
    rings_all, el_all, az_all, r_all, t_all, inten = [], [], [], [], [], []
    for scan in scans:
        p = scan.points[:, :3].astype(np.float64)
        r = np.linalg.norm(p, axis=1)
        ok = r > 2.0
        rings_all.append(scan.points[ok, 4].astype(np.int64))
        el_all.append(np.degrees(np.arcsin(np.clip(p[ok, 2] / r[ok], -1.0, 1.0))))
        az_all.append(np.arctan2(p[ok, 1], p[ok, 0]))
        r_all.append(r[ok])
        t_all.append(None if scan.time_offsets is None else scan.time_offsets[ok].astype(np.float64))
        inten.append(scan.intensity_255())
    return _RingSamples(rings_all, el_all, az_all, r_all, t_all, inten)


def _ring_elevations(ring: NDArray[np.int64], el: F64, num_rings: int, min_ring_points: int) -> list[float]:
    """Each ring's elevation [deg]: the median of its points' elevations ``el`` (N,) (``ring`` (N,) their rings)
    where it has at least ``min_ring_points``, else linear in the ring index (interpolated, or extrapolated from the
    two nearest rings)."""
    known = {k: float(np.median(el[ring == k])) for k in range(num_rings)
             if np.count_nonzero(ring == k) >= min_ring_points}
    if len(known) < 2:
        raise ValueError(f"estimate_lidar_model: only {len(known)} ring(s) with >= {min_ring_points} points; cannot "
                         f"estimate the elevations")
    ks = np.array(sorted(known), dtype=np.float64)
    es = np.array([known[int(k)] for k in ks])
    elevations = []
    for k in range(num_rings):  # rings without points (e.g. outside a cropped scan): linear in the ring index
        if k in known:
            elevations.append(known[k])
            continue
        lo, hi = (0, 1) if k < ks[0] else ((-2, -1) if k > ks[-1] else (None, None))
        if lo is None:
            elevations.append(float(np.interp(k, ks, es)))
        else:
            slope = (es[hi] - es[lo]) / (ks[hi] - ks[lo])
            elevations.append(float(es[lo] + slope * (k - ks[lo])))
    return elevations


def _azimuth_step_and_direction(seen: _RingSamples, min_ring_points: int) -> tuple[float, bool]:
    """The median azimuth step [rad] between neighbouring points of a ring (rings with at least ``min_ring_points``;
    the HDL-32E's 2π / 1085 without any) and whether the sensor turns clockwise (the sign of the azimuth's change
    with firing time where per-point times exist; clockwise otherwise)."""
    steps, corr = [], []
    for scan_ring, az, t in zip(seen.ring, seen.azimuth, seen.time):
        for k in np.unique(scan_ring):
            a = np.sort(az[scan_ring == k])
            if len(a) < min_ring_points:
                continue
            d = np.diff(a)
            steps.append(d[d > 1e-6])
            if t is not None:
                sel = scan_ring == k
                tk, ak = t[sel], np.unwrap(az[sel][np.argsort(t[sel])])
                if len(tk) > 2 and np.ptp(tk) > 0:
                    corr.append(float(np.sign(ak[-1] - ak[0])))
    step = float(np.median(np.concatenate(steps))) if steps else 2 * np.pi / 1085
    clockwise = bool(np.sum(corr) <= 0) if corr else True
    return step, clockwise


def _rotation_rate(scans: list[LidarScan], num_rings: int) -> float:
    """Rotation rate [Hz] from the scans' timestamps when they are consecutive sweeps (median interval 0.02..0.2 s),
    else 10 Hz for 64 rings, 20 Hz otherwise."""
    stamps = np.sort([s.timestamp for s in scans])
    dt = np.diff(stamps)
    return float(1.0 / np.median(dt)) if len(dt) and 0.02 <= np.median(dt) <= 0.2 else (
        10.0 if num_rings == 64 else 20.0)


DEFAULT_NOISE_FLOOR = 0.5
"""Detector floor (0..255), constant on the reported scale, of a real sensor whose scans do not show it. With the
``min(1, 10 m / R)`` intensity model it puts the snow share of a real scan in the band of WADS's labelled real snow,
and the snow echoes' ranges within 1.2x of theirs (``docs/physics.md`` section 3.5). A raw-power detector's floor is
set with ``sensor_overrides.noise_floor`` and ``floor_range_m``."""

CLAMP_SHARE = 0.01
"""Share of the points at exactly the smallest intensity above which that value is a clamp, not a floor."""


def estimate_noise_floor(intensity: NDArray, clamp_share: float = CLAMP_SHARE) -> float:
    """The detector floor (0..255) of real scans from their intensities (N,) on 0..255.

    The smallest reported intensity is the floor only when it is a tail: a sensor (or a dataset's conversion) that
    clamps weak returns to one value reports many points at exactly that value (Seeing Through Fog's HDL-64: 15 % of
    its points read exactly 24), and a floor of 0 (nuScenes, KITTI) is no floor at all (every particle echo,
    however faint, would be reported). In both cases, and when more than ``clamp_share`` of the points sit at the
    minimum, `DEFAULT_NOISE_FLOOR` is returned instead; otherwise the smallest intensity.
    """
    values = np.asarray(intensity, dtype=np.float64)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return DEFAULT_NOISE_FLOOR
    smallest = float(values.min())
    if smallest <= 0.0 or float(np.mean(values == smallest)) > clamp_share:
        return DEFAULT_NOISE_FLOOR
    return smallest


def estimate_lidar_model(scans: list[LidarScan], *, rotation_hz: float | None = None,
                         overrides: dict[str, Any] | None = None, min_ring_points: int = 16) -> LidarModel:
    """A `LidarModel` from real scans of one sensor (single sweeps, as stored).

    Estimated: the ring count (the scans' declared ``num_rings``, or the largest ring index + 1), each ring's
    elevation (median elevation of its points seen from the sensor, points beyond 2 m; rings without points
    interpolated, or extrapolated, linearly in the ring index), the columns
    per ring (2π / median azimuth step between neighbouring points of a ring), the rotation direction (sign of the
    correlation between firing time and azimuth where per-point times exist; clockwise otherwise, the nuScenes
    convention), the rotation rate (from consecutive scan timestamps when ``rotation_hz`` is None and the scans are
    consecutive sweeps; else 10 Hz for 64 rings, 20 Hz otherwise), the maximum range (the 99.9th percentile range
    rounded up to 10 m, at least 80 m), the noise floor (`estimate_noise_floor`) and the intensity scale. Not
    visible in a point cloud and taken from the Velodyne HDL family: divergence (3 mrad), pulse (τ_H = 10 ns) and a
    calibrated-reflectance intensity model for 0..1 data, ``min(1, (10 m / R))`` on 0..255.
    ``overrides``: any `LidarModel` field (plus ``pulse_half_width_s``) replacing the estimate.

    Raises:
        ValueError: no scans, no points, or an override naming no field.
    """
    if not scans or not any(len(s.points) for s in scans):
        raise ValueError("estimate_lidar_model: no LiDAR points to estimate a sensor from")
    seen = _ring_samples(scans)
    rings_all, r_all, inten = seen.ring, seen.distance, seen.intensity
    num_rings = max(max(int(s.num_rings) for s in scans), int(max(int(r.max()) for r in rings_all if len(r))) + 1)
    elevations = _ring_elevations(np.concatenate(rings_all), np.concatenate(seen.elevation), num_rings,
                                  min_ring_points)
    step, clockwise = _azimuth_step_and_direction(seen, min_ring_points)
    if rotation_hz is None:
        rotation_hz = _rotation_rate(scans, num_rings)
    max_range = max(80.0, float(math.ceil(np.percentile(np.concatenate(r_all), 99.9) / 10.0) * 10.0))
    imax = float(scans[0].intensity_max)
    divergence, tau = _known_sensor(num_rings)
    fields: dict[str, Any] = {
        "elevations_deg": tuple(elevations), "columns_per_ring": int(round(2 * np.pi / step)),
        "rotation_hz": rotation_hz, "clockwise": clockwise,
        "start_azimuth_rad": sensor_start_azimuth(mount_yaw_of(scans[0].T_ego_lidar)),
        "laser_step_s": 0.0, "divergence_rad": divergence, "max_range_m": max_range, "min_range_m": 1.0,
        "noise_floor": estimate_noise_floor(np.concatenate(inten)), "intensity_max": imax,
        "intensity": CALIBRATED_INTENSITY if imax == 1.0 else SYNTHETIC_INTENSITY,
        "firing_columns_stored": False, "origin": "estimated", "floor_range_m": None,
    }
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    tau = overrides.pop("pulse_half_width_s", tau)
    unknown = set(overrides) - set(fields)
    if unknown:
        raise ValueError(f"estimate_lidar_model: unknown override(s) {sorted(unknown)}; expected fields of "
                         f"LidarModel or pulse_half_width_s")
    fields.update(overrides)
    return LidarModel(**fields, pulse=PulseSensor(tau_h=tau, max_range=float(fields["max_range_m"])))


def with_overrides(model: LidarModel, overrides: dict[str, Any]) -> LidarModel:
    """``model`` with the non-None ``overrides`` applied (``pulse_half_width_s`` sets the pulse's τ_H)."""
    overrides = {k: v for k, v in overrides.items() if v is not None}
    pulse = model.pulse
    if "pulse_half_width_s" in overrides:
        pulse = replace(pulse, tau_h=overrides.pop("pulse_half_width_s"))
    if "max_range_m" in overrides:
        pulse = replace(pulse, max_range=overrides["max_range_m"])
    return replace(model, **overrides, pulse=pulse)


def camera_models(views: dict[str, Any], exposure_s: float) -> dict[str, CameraModel]:
    """`CameraModel` per channel from a frame's `CameraView`s (intrinsics and size as stored) and the exposure."""
    return {ch: CameraModel(ch, tuple(tuple(float(v) for v in row) for row in np.asarray(view.K)), int(view.width),
                            int(view.height), float(exposure_s)) for ch, view in sorted(views.items())}


__all__ = ["CALIBRATED_INTENSITY", "DEFAULT_NOISE_FLOOR", "HAHNER_INTENSITY", "SPEED_OF_LIGHT",
           "SYNTHETIC_INTENSITY", "CameraModel", "DetectorFloor", "FiringPattern", "IntensityModel", "LidarModel",
           "PulseSensor", "SensorRig", "camera_models", "compensation_at", "estimate_lidar_model",
           "estimate_noise_floor", "floor_factor", "floor_scale", "lidar_model_from_params", "with_overrides"]


ESTIMATION_SCANS = 8
"""Keyframe scans a real dataset's LiDAR model is estimated from (spread over the dataset)."""


def dataset_sensors(world: Any, nusc: Any) -> SensorRig:
    """The `SensorRig` of the dataset ``nusc`` (a devkit `NuScenes`) under ``world`` (a
    `weatheralign.config.WorldConfig`): the synthetic LiDAR from ``world.lidar`` when ``world.source`` is
    ``synthetic``, else a LiDAR estimated from `ESTIMATION_SCANS` keyframe scans spread over the dataset, corrected by
    ``world.sensor_overrides``; the cameras as calibrated in the tables with the exposure
    ``world.camera.exposure_s``; the ego body from ``world.ego_body``."""
    first = load_frame(nusc, nusc.sample[0]["token"])
    cameras = camera_models(first.cameras, world.camera.exposure_s)
    body = ego_body_from_params(world.ego_body)
    if world.source == "synthetic":
        return SensorRig(lidar_model_from_params(world.lidar), cameras, body)
    step = max(1, len(nusc.sample) // ESTIMATION_SCANS)
    scans = [load_lidar(nusc, s["data"]["LIDAR_TOP"]) for s in nusc.sample[::step][:ESTIMATION_SCANS]]
    return SensorRig(estimate_lidar_model(scans, overrides=world.sensor_overrides.as_dict()), cameras, body)
