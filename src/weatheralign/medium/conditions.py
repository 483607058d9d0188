"""Precipitation conditions as concrete, reproducible particle fields: one field per (scene, condition).

A `FieldSpec` is everything needed to rebuild a `ParticleField` exactly (seed, size distribution parameters,
velocity, reference time, layer, cell size). The `particles` stage writes them to JSON; the `simulate` stage rebuilds
the same fields from that file, so a change of rate or seed reruns exactly the stages it must. The "unaligned"
ablation gives the cameras ``unaligned_seed(seed)``: a field of identical statistics with independent particles.

Fall speed. A field has one velocity, set here once for every sensor. Snow falls at its configured speed; rain at
its configured speed, or by default (``terminal_velocity_m_s: None``) at the terminal speed of the Marshall-Palmer
median-volume drop at the field's own rate (`weatheralign.medium.distributions.rain_field_fall_speed`), so a rate
replaced by the calibration (the media stage) falls at its own speed. In that default each drop's camera streak is
drawn at its own diameter's terminal speed (`FieldSpec.drop_velocities`); its position, which every sensor shares,
moves with the field.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from weatheralign.config import ParticlesConfig
from weatheralign.medium.distributions import (
    RainSizeDistribution,
    SnowSizeDistribution,
    rain_field_fall_speed,
    rain_terminal_velocity,
)
from weatheralign.medium.field import ParticleField, fall_velocity, unaligned_seed

Precipitation = Literal["snow", "rain"]
PRECIPITATION: tuple[Precipitation, ...] = ("snow", "rain")


@dataclass(frozen=True)
class FieldSpec:
    """A reproducible particle field of one scene and condition (JSON-serialisable).

    Attributes:
        condition: ``snow`` or ``rain``; scene: scene name; seed: the field seed (the LiDAR's and, when aligned,
        the cameras'); rate_mm_h: snowfall (water equivalent) or rain rate; terminal_velocity_m_s: fall speed
        [m/s], or None (rain only) for the median-volume drop's at ``rate_mm_h`` (`fall_speed_m_s`);
        size_distribution: ``gunn_marshall``/``sekhon_srivastava`` (snow) or ``marshall_palmer`` (rain);
        wind_m_s: (2,) horizontal wind; t_ref: field reference time [s]; layer (z_min, z_max) [m]; cell_size [m];
        min_diameter_m: smallest drop (rain) or 0 (snow).
    """

    condition: str
    scene: str
    seed: int
    rate_mm_h: float
    terminal_velocity_m_s: float | None
    size_distribution: str
    wind_m_s: tuple[float, float]
    t_ref: float
    z_min: float
    z_max: float
    cell_size: float
    min_diameter_m: float = 0.0

    @property
    def fall_speed_m_s(self) -> float:
        """The field's fall speed [m/s]: ``terminal_velocity_m_s``, or for rain with None the terminal speed of the
        median-volume drop at ``rate_mm_h`` (`rain_field_fall_speed`)."""
        if self.terminal_velocity_m_s is not None:
            return float(self.terminal_velocity_m_s)
        if self.condition != "rain":
            raise ValueError(f"{self.condition} field of scene {self.scene!r}: terminal_velocity_m_s = None is "
                             f"invalid: only rain derives its fall speed from drop size")
        return rain_field_fall_speed(self.rate_mm_h)

    @property
    def per_drop_fall(self) -> bool:
        """Rain whose fall speed comes from drop size (``terminal_velocity_m_s`` None): the field moves at the
        median-volume drop's speed, and within a camera's exposure each drop falls at its own (`drop_velocities`)."""
        return self.condition == "rain" and self.terminal_velocity_m_s is None

    def drop_velocities(self, diameters: NDArray) -> NDArray[np.float64]:
        """(N, 3) velocity [m/s] of particles of ``diameters`` (N,) [m] within a camera's exposure (their streaks):
        with `per_drop_fall` the horizontal wind and each drop's own terminal fall speed (`rain_terminal_velocity`,
        the fall-speed law the field's speed comes from), else the field's one velocity. Positions stay the field's,
        shared by every sensor: a drop's own speed only shapes its streak."""
        d = np.asarray(diameters, dtype=np.float64)
        if d.ndim != 1 or not np.all(np.isfinite(d)) or (d < 0).any():
            raise ValueError(f"diameters must be (N,) finite and >= 0 [m], got shape {d.shape}")
        if not self.per_drop_fall:
            return np.tile(np.asarray(fall_velocity(self.fall_speed_m_s, self.wind_m_s)), (len(d), 1))
        out = np.empty((len(d), 3))
        out[:, 0], out[:, 1] = self.wind_m_s
        out[:, 2] = -rain_terminal_velocity(d)
        return out

    def field(self, aligned: bool = True) -> ParticleField:
        """The field; ``aligned=False`` gives the independent twin of identical statistics."""
        if self.condition == "snow":
            dist = SnowSizeDistribution(self.rate_mm_h, self.fall_speed_m_s, model=self.size_distribution)
        elif self.condition == "rain":
            dist = RainSizeDistribution(self.rate_mm_h, d_min=self.min_diameter_m)
        else:
            raise ValueError(f"condition = {self.condition!r} is invalid: expected 'snow' or 'rain'")
        return ParticleField(seed=self.seed if aligned else unaligned_seed(self.seed), distribution=dist,
                             velocity=fall_velocity(self.fall_speed_m_s, self.wind_m_s), t_ref=self.t_ref,
                             z_min=self.z_min, z_max=self.z_max, cell_size=self.cell_size)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> FieldSpec:
        return FieldSpec(**{**d, "wind_m_s": tuple(d["wind_m_s"])})


def field_seed(base_seed: int, condition: str, scene: str) -> int:
    """A deterministic per-(scene, condition) seed derived from the stage seed."""
    digest = hashlib.sha256(f"{base_seed}/{condition}/{scene}".encode()).digest()
    return int.from_bytes(digest[:7], "little")


def field_spec(cfg: ParticlesConfig, condition: Precipitation, scene: str, t_ref: float) -> FieldSpec:
    """The field of ``condition`` over ``scene`` (reference time ``t_ref`` [s], e.g. the scene's first sample)."""
    c = cfg.snow if condition == "snow" else cfg.rain
    return FieldSpec(
        condition=condition, scene=scene, seed=field_seed(cfg.seed, condition, scene), rate_mm_h=c.rate_mm_h,
        terminal_velocity_m_s=c.terminal_velocity_m_s,
        size_distribution=cfg.snow.size_distribution if condition == "snow" else "marshall_palmer",
        wind_m_s=tuple(float(w) for w in c.wind_m_s), t_ref=t_ref, z_min=cfg.layer_bottom_m, z_max=cfg.layer_top_m,
        cell_size=c.cell_size_m, min_diameter_m=cfg.rain.min_diameter_m if condition == "rain" else 0.0)
