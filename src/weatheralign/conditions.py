"""Weather conditions as data: one typed `Condition` per named condition, kept in the plain dict `CONDITIONS`.

A condition says which media exist (a fog medium at a tuned level, a particle field of a kind, or both), how each
sensor sees them (the LiDAR reflectivity of the particles, the cameras' particle appearance) and what "unaligned"
means for it. Everything that enumerates conditions — the DVC matrix (a test keeps ``dvc.yaml`` equal to this dict),
the flows, the simulate core, the reports — reads this dict; nothing dispatches on condition-name strings.

Composition. Media combine without a code path per sensor: the LiDAR sees every medium in one pulse response
(fog extinction added to the particles' bulk extinction, particle echoes, then the fog's backscatter competing with
the strongest echo, `weatheralign.simulate.observe.observe_lidar`); the cameras see one transmission (the fog's
Koschmieder term times the unresolved particles') and the resolvable particles pre-fogged by the same fog.

Unaligned. Each medium defines its own independent twin, misaligned in severity and (for particles) position, as
sensor-dedicated simulators that each pick their own parameters would be: a fog's cameras see an extinction drawn
uniformly between the light and dense levels once per scene (`FogPart.camera_alpha`), a particle field's cameras see
the field's twin of another seed (`weatheralign.medium.conditions.FieldSpec.field`) at a rate drawn log-uniformly
within ``simulate.unaligned_rate_factor`` of the LiDAR's, once per scene (`ParticlePart.camera_rate`; factor 1: the
positions alone differ). The LiDAR always sees the condition's own media; a mixed condition's unaligned variant twins
every medium.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from typing import Literal

from weatheralign.config import CONDITION_NAMES
from weatheralign.medium.distributions import RAIN_REFLECTIVITY, SNOW_REFLECTIVITY

FogLevel = Literal["light", "dense"]
PrecipitationKind = Literal["snow", "rain"]
ALIGNMENTS: tuple[str, ...] = ("aligned", "unaligned")
RAIN_APPEARANCES: tuple[str, ...] = ("rain", "rain_weather_edit")
"""The values of ``simulate.rain_appearance``: names of `weatheralign.camera.splat.APPEARANCES` (``rain``: opaque
refracting drops, radiance from their environment; ``rain_weather_edit``: Weather-edit's translucent grey drops)."""


@dataclass(frozen=True)
class FogPart:
    """A homogeneous fog at one of the tuned levels (its (α, β) come from the calibrate_fog stage or params).

    Unaligned: the cameras' extinction is drawn uniformly in ``[α_light, α_dense]``, once per scene
    (`camera_alpha`), independently of the LiDAR's level. The fog's airlight (its brightness relative to the clear
    sky) is drawn once per scene from the level's calibrated spread (`airlight_gain`), the same for both.
    """

    level: FogLevel

    @staticmethod
    def camera_alpha(aligned: bool, lidar_alpha: float, alpha_light: float, alpha_dense: float, seed: int,
                     condition: str, scene: str) -> float:
        """The cameras' extinction [1/m]: ``lidar_alpha`` when aligned, else ``U[alpha_light, alpha_dense]`` from a
        hash of (``seed``, ``condition``, ``scene``)."""
        if aligned:
            return lidar_alpha
        digest = hashlib.sha256(f"{seed}/{condition}/{scene}/camera".encode()).digest()
        u = int.from_bytes(digest[:8], "little") / 2.0**64
        return alpha_light + u * (alpha_dense - alpha_light)

    @staticmethod
    def airlight_gain(gains: tuple[float, ...], seed: int, condition: str, scene: str) -> float:
        """The fog's airlight relative to the scene's clear sky: one of the level's calibrated ``gains``
        (`weatheralign.camera.fog.airlight_gains`), picked uniformly by a hash of (``seed``, ``condition``,
        ``scene``). Aligned and unaligned cameras get the same one: it is the day's light, not the fog's severity."""
        if not gains:
            raise ValueError("airlight_gain: no gains; expected at least one (1.0: the clear sky's airlight)")
        digest = hashlib.sha256(f"{seed}/{condition}/{scene}/airlight".encode()).digest()
        return float(gains[int.from_bytes(digest[:8], "little") % len(gains)])


@dataclass(frozen=True)
class ParticlePart:
    """A falling-particle field of one kind (its physical parameters: ``particles.<kind>`` in params).

    Attributes:
        kind: ``snow`` or ``rain``.
        lidar_reflectivity: the particles' reflectivity at the LiDAR wavelength.
        camera_appearance: how the cameras draw them: a name of `weatheralign.camera.splat.APPEARANCES`
            (``snow``, ``rain``, ``rain_weather_edit``).

    Unaligned: the cameras observe the field's independent twin (another seed) at a rate of their own, drawn
    log-uniformly within a factor of the LiDAR's once per scene (`camera_rate`): sensor-dedicated simulators each
    set their own severity, as the fog's unaligned cameras do.
    """

    kind: PrecipitationKind
    lidar_reflectivity: float
    camera_appearance: str

    @staticmethod
    def camera_rate(aligned: bool, rate_mm_h: float, factor: float, field_seed: int) -> float:
        """The cameras' rate [mm/h]: ``rate_mm_h`` when aligned (or ``factor`` 1), else ``rate_mm_h ·
        factor^u`` with ``u ~ U[-1, 1]`` from a hash of the scene's ``field_seed``."""
        if aligned or factor == 1.0:
            return rate_mm_h
        digest = hashlib.sha256(f"{field_seed}/camera_rate".encode()).digest()
        u = int.from_bytes(digest[:8], "little") / 2.0**64
        return rate_mm_h * factor ** (2.0 * u - 1.0)


@dataclass(frozen=True)
class GroundPart:
    """What the condition leaves on the ground (`weatheralign.ground`): ``wet`` (a water film and puddles) or
    ``snow`` (lying snow with wheel tracks); its amount (film or snow depth) and fields come from ``simulate.ground``.

    Unaligned: the cameras see the ground's twin: its fields from another seed and its amount drawn log-uniformly
    within ``simulate.unaligned_rate_factor`` of the LiDAR's, once per scene (`camera_amount`), as a camera-only
    background edit picks its own.
    """

    kind: Literal["wet", "snow"]

    @staticmethod
    def camera_amount(aligned: bool, amount_m: float, factor: float, seed: int) -> float:
        """The cameras' film or snow depth [m]: ``amount_m`` when aligned (or ``factor`` 1), else ``amount_m ·
        factor^u`` with ``u ~ U[-1, 1]`` from a hash of the scene's ground ``seed``."""
        if aligned or factor == 1.0:
            return amount_m
        digest = hashlib.sha256(f"{seed}/camera_ground".encode()).digest()
        u = int.from_bytes(digest[:8], "little") / 2.0**64
        return amount_m * factor ** (2.0 * u - 1.0)


@dataclass(frozen=True)
class SkyPart:
    """The light the condition falls under: the overcast sky of snowfall or rain (`weatheralign.camera.overcast`),
    its parameters those calibrated on the reference's ``split`` (``snow`` or ``rain``) or ``simulate.overcast_*``;
    ``simulate.overcast`` switches it off.

    Aligned and unaligned cameras see the same light: it is the day's, global to the scene, not a medium that a
    per-sensor simulator could place elsewhere (the LiDAR, its own light source, does not see it)."""

    split: PrecipitationKind


@dataclass(frozen=True)
class Condition:
    """One named weather condition: its media (``fog``, ``particles``, or both) and a one-line description."""

    name: str
    description: str
    fog: FogPart | None = None
    particles: ParticlePart | None = None
    ground: GroundPart | None = None
    sky: SkyPart | None = None

    def __post_init__(self) -> None:
        if self.fog is None and self.particles is None:
            raise ValueError(f"condition {self.name!r} has no medium")

    @property
    def media(self) -> tuple[str, ...]:
        """The inputs this condition uses: ``fog_levels`` and/or ``fields``."""
        return tuple(m for m, part in (("fog_levels", self.fog), ("fields", self.particles)) if part is not None)

    def with_rain_appearance(self, appearance: str) -> Condition:
        """The condition with rain drawn as ``appearance`` (one of `RAIN_APPEARANCES`), unchanged for any other
        particle kind."""
        if self.particles is None or self.particles.kind != "rain":
            return self
        if appearance not in RAIN_APPEARANCES:
            raise ValueError(f"simulate.rain_appearance = {appearance!r} is invalid: expected one of "
                             f"{list(RAIN_APPEARANCES)}")
        return replace(self, particles=replace(self.particles, camera_appearance=appearance))


SNOW_PART = ParticlePart("snow", SNOW_REFLECTIVITY, "snow")
RAIN_PART = ParticlePart("rain", RAIN_REFLECTIVITY, "rain")

CONDITIONS: dict[str, Condition] = {
    "fog_light": Condition("fog_light", "light fog (the tuned light level)", fog=FogPart("light")),
    "fog_dense": Condition("fog_dense", "dense fog (the tuned dense level)", fog=FogPart("dense")),
    "snow": Condition("snow", "snowfall on snow-covered ground under an overcast sky (particles.snow)",
                      particles=SNOW_PART, ground=GroundPart("snow"), sky=SkyPart("snow")),
    "rain": Condition("rain", "rain on a wet road under an overcast sky (particles.rain)", particles=RAIN_PART,
                      ground=GroundPart("wet"), sky=SkyPart("rain")),
    "fog_snow": Condition("fog_snow", "light fog and snowfall together, snow-covered ground, overcast",
                          fog=FogPart("light"), particles=SNOW_PART, ground=GroundPart("snow"), sky=SkyPart("snow")),
}
"""Every named condition; the `simulate` DVC matrix runs each, aligned and unaligned."""
if tuple(CONDITIONS) != CONDITION_NAMES:
    raise RuntimeError(f"weatheralign.config.CONDITION_NAMES {CONDITION_NAMES} must list CONDITIONS' keys in order, "
                       f"{tuple(CONDITIONS)}")


def condition_named(name: str) -> Condition:
    """``CONDITIONS[name]``, or a ValueError naming the params key and the known conditions."""
    if name not in CONDITIONS:
        raise ValueError(f"simulate.condition = {name!r} is invalid: expected one of {list(CONDITIONS)}")
    return CONDITIONS[name]


def variant_name(condition: str, aligned: bool) -> str:
    """``<condition>-aligned`` or ``<condition>-unaligned``: the name of a simulate stage and its weather copy."""
    return f"{condition}-{ALIGNMENTS[0] if aligned else ALIGNMENTS[1]}"


def severity_label(name: str, snow_rate_mm_h: float, rain_rate_mm_h: float) -> str:
    """Condition ``name``'s severity in words: its fog level and / or its particle rate (``light``, ``2 mm/h``,
    ``light + 2 mm/h``), from the rates of ``particles.snow`` / ``particles.rain``."""
    c = condition_named(name)
    parts = [c.fog.level] if c.fog is not None else []
    if c.particles is not None:
        parts.append(f"{snow_rate_mm_h if c.particles.kind == 'snow' else rain_rate_mm_h:g} mm/h")
    return " + ".join(parts)


def condition_tags(name: str, aligned: bool | None, snow_rate_mm_h: float, rain_rate_mm_h: float) -> dict[str, str]:
    """The ``weather``, ``alignment`` (``none`` for None) and ``severity`` tags of condition ``name``'s runs."""
    alignment = "none" if aligned is None else variant_name(name, aligned).rsplit("-", 1)[1]
    return {"weather": name, "alignment": alignment,
            "severity": severity_label(name, snow_rate_mm_h, rain_rate_mm_h)}


__all__ = ["ALIGNMENTS", "CONDITIONS", "RAIN_APPEARANCES", "Condition", "FogPart", "GroundPart", "ParticlePart",
           "SkyPart", "condition_named",
           "condition_tags", "severity_label", "variant_name"]
