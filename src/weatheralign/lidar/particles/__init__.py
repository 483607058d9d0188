"""LiDAR snow and rain: every beam of a scan through one 3-D particle field (Hahner et al. 2022, generalised).

Physics (``docs/physics.md`` sections 1 and 3, 3.4 for the beam model). Each beam is a cone from the sensor position
at its own firing time, of radius ``w(s) = s tan(θ/2)`` at axial distance ``s`` (θ: full divergence, ~3 mrad), up to
its measured range ``R_0`` (or the maximum range for beams without return). A particle (a sphere of diameter D, at
``P(t) = P(t_ref) + v (t - t_ref)`` at the beam's firing time t) intersects the beam if its centre lies in front of
the target and closer to the axis than ``w(s) + D/2``. Its occlusion ratio is the share of the beam cross-section it
covers — the circle–circle overlap of its disk with the beam disk in the plane at its range, over ``π w²`` — nearest
particle first: a disk overlapping no nearer disk inside the beam gets the closed form, otherwise its still uncovered
part is counted on a 48 x 48 grid over its box. The target keeps the rest; the ratios sum to 1.

Received signal: the sum of closed-form hard-target pulses (`weatheralign.lidar.pulse`: ``sin²(π (R - r_k) / (c τ_H))``
on ``[r_k, r_k + c τ_H]``), one per particle at its range and one for the target with its remaining ratio, all
attenuated by the bulk extinction of the unresolved particles (below). Between consecutive pulse starts/ends the sum
is a constant plus one sinusoid of period ``c τ_H``, so its maximum is found exactly (no receiver grid); the measured
range is the peak position minus ``c τ_H / 2`` (as in Hahner's code). A peak within ``keep_tolerance`` (0.2 m) of
``R_0`` keeps the point where it is with the peak intensity (ATTENUATED, or UNCHANGED if its float32 intensity is
bit-identical; a detector with intensity noise reads it again: its clear intensity's noise scaled with the signal
lacks ``σ_0² (1 - k²)`` of the reading's variance at transmission ``k``, added as in the fog model); otherwise the point
moves along its beam to the measured range (SCATTERED, with the id of the particle contributing most at the peak). A
particle echo below the detector noise floor is not detected: the target's own echo then decides, and a return the
weather pushed below the floor is LOST (points that were below the floor in clear weather were detected nevertheless and
are kept, as in the fog model), decided on the value an integer clear reading stood for before the sensor rounded it
(`weatheralign.lidar.quantum`) and, with intensity noise, on the noisy reading (as the fog model decides). Beams
without return can return a particle: SCATTERED clutter with ``source_index`` -1 (the reference code never simulates
those beams). Echoes measured nearer than the sensor's minimum range are not reported.

The unresolved particles (below) return light too: a smooth waveform peaking a few metres out
(`api.unresolved_continuum`, tabulated once per run over the beam length). The receiver compares the summed waveform at
the pulse sum's crest and at the continuum's; where the continuum's is stronger it is read like a particle echo
(SCATTERED without particle id if detected). Far below the floor, it still hides fainter far echoes from a
strongest-return receiver. Likewise a short run of beams without return between two returns of a surface at the detector
floor is taken to hit that surface under the floor (`weatheralign.lidar.beams.with_faint_surfaces`), and a beam without
return still open that points below the horizon hits the scan's fitted ground plane under the floor
(`weatheralign.lidar.beams.with_ground_plane`: a dark or wet road): its undetectable echo outshines weaker weather
echoes, it ends the beam, and the beam reports nothing unless the weather puts a detectable echo in front of it.

Particle echo vs target echo (the calibration choice, `weatheralign.sensors.IntensityModel`, part of the sensor's
`LidarModel`). A clear measurement ``i_0`` at ``R_0`` fixes only the product of the system constant and the target's
(unknown) reflectivity; a particle's echo needs the system constant alone. We calibrate it from the sensor's intensity
model: a Lambertian target of reflectivity ρ filling the beam at normal incidence reports ``i = scale ρ g(R)``, ``g(R) =
min(1, (r_ref / R)^falloff)`` being the range compensation the sensor applies to the raw ``1/R²`` power. In raw units
(``i / (R² g(R))``) a particle — a disk of reflectivity ρ_p covering ``ratio`` of the footprint at range r — gives
``scale ρ_p ratio ξ(r) / r²``, the target ``i_0 ratio_t / (R_0² g(R_0))``, and the detector reports ``P* R² g(R)`` at
the measured range R, so a clear target comes back as ``i_0`` exactly. The synthetic reference's renderer is exactly
``scale = 255, r_ref = 10 m, falloff = 1`` (`weatheralign.sensors.SYNTHETIC_INTENSITY`), the synthetic world's HDL-32E
``scale = 100, falloff = 0`` (a calibrated reflectivity, configs/world_rig.yaml): there a flake filling the beam
reports what a 0.9-reflectivity wall would. Every floor test reads the floor at the echo's reported range (a
raw-power detector's grows as ``R² g(R)``, `weatheralign.sensors.LidarModel.floor_range_m`). Hahner's published code
is the case ``r_ref = 1 m, falloff = 2`` (`weatheralign.sensors.HAHNER_INTENSITY`: a flake reports ``0.9 · 255 ·
ratio / r²`` while the target is normalised at its own range), and a reflectance-calibrated sensor (KITTI) is
``falloff = 0`` (`weatheralign.sensors.CALIBRATED_INTENSITY`).

Dense fields. Physical densities (~166 flakes/m³ at 2 mm/h, ~4000 drops/m³ at 50 mm/h: ~10^8 particles within the
sensor's reach) cannot all be tested against every beam. A particle that would cover less than ``ratio_threshold``
of a beam even when centred on it is folded into the bulk extinction: space is cut into range shells ``[s_0, s_1)``
around the sensor path (``0, 1 m, then x1.25``) with thresholds ``D_k = 2 w(s_0) sqrt(ratio_threshold)``; the field
cells that some beam can reach (an angular reach map of beam lengths, widened by the sensor's motion, the beam and
the particle radius) are materialised once each, with the threshold of the shell of the cell's nearest point (the
field's nested ``min_diameter`` queries return exactly the particles ``D >= D_k`` of the one field; the kernel
generates them with the field's own hash streams cell by cell and never stores them), and a particle counts as
resolved iff ``D >= D_k`` of the shell holding its centre. The unresolved rest of shell k attenuates every
echo by ``exp(-2 · factor · ∫ field.unresolved_extinction(D_k) ds)``; ``factor = 1/4`` (default) is their geometric
shadow counted once, exactly how a resolved particle's ratio acts on the target (Q_ext = 2 counts diffraction too,
which the 3 mrad beam keeps; a monostatic beam is hidden where it is shadowed), which makes the results independent
of the threshold (measured in the benchmark). The particles of a cell are matched to the beams together: the time
slices of the sweep (each with its own reference origin and time) that the cell can reach, then per slice the
particles inside its azimuth wedge whose elevation window holds a beam (fine bins of the z-component: a LiDAR's rings),
then per particle the beams of those bins within its window (sorted by the projection on the slice's tangent) and its
cone; the windows are widened by the slices' origin and time spread, the beam radius and the particle radius, so
every candidate pair is then tested exactly at the beam's firing time, with the same expressions whatever the index.
Kernels are serial numba (``nogil``): run frames in parallel threads.

Labels: `weatheralign.lidar.labels.WeatherLabel` (``ParticleLabel`` here, ``FogLabel`` in the fog model): UNCHANGED,
ATTENUATED, SCATTERED, LOST per point, and NO_ECHO for a beam without return that stays empty.

Modules: `api` (this package's public names: `ParticleResult`, `simulate_particles` (with the optional fog),
`simulate_particle_list`, `simulate_particle_scans`: several scans of one sensor through the field at once, each
cell generated once for all of them), `beam_index` (beam geometry set up once per scan: time slices, sorted beams, reach
map; range shells, reachable field cells; the drivers of the hit kernels), `kernels` (the numba kernels that index the
beams and find the hits), `response` (the numba kernel of the per-beam response) and `records` (the typed records the
kernels take).
"""

from weatheralign.lidar.labels import POINT_LABELS, WeatherLabel
from weatheralign.lidar.particles.api import (
    DEFAULT_RATIO_THRESHOLD,
    FIRST_SHELL,
    KEEP_TOLERANCE,
    MAX_AUTO_RATIO_THRESHOLD,
    RAIN_REFLECTIVITY,
    SAMPLE_GRID,
    SHELL_RATIO,
    SNOW_REFLECTIVITY,
    BeamHits,
    ParticleLabel,
    ParticleResult,
    auto_ratio_threshold,
    simulate_particle_list,
    simulate_particle_scans,
    simulate_particles,
)

__all__ = [
    "DEFAULT_RATIO_THRESHOLD",
    "FIRST_SHELL",
    "KEEP_TOLERANCE",
    "MAX_AUTO_RATIO_THRESHOLD",
    "POINT_LABELS",
    "RAIN_REFLECTIVITY",
    "SAMPLE_GRID",
    "SHELL_RATIO",
    "SNOW_REFLECTIVITY",
    "BeamHits",
    "ParticleLabel",
    "ParticleResult",
    "WeatherLabel",
    "auto_ratio_threshold",
    "simulate_particle_list",
    "simulate_particle_scans",
    "simulate_particles",
]
