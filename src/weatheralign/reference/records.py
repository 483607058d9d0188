"""Typed records passed to the numba kernels of the synthetic reference (`weatheralign.reference.lidar_exact`,
`.lidar_particles_exact`, `.camera_particles_exact`).

Each record is a `typing.NamedTuple` of arrays and scalars: numba compiles them in nopython mode as typed tuples
(``cache=True`` works because the classes are importable), so a kernel takes a handful of named records instead of
dozens of positional arrays (the model: `weatheralign.lidar.particles.records`). Lengths: N beams or pixels,
B beams, P particles, K sub-rays per beam, E = K + 1 events per beam, M + 1 receiver-grid nodes ``m step``,
T table entries ``j h``. Lengths in metres, angles in radians, intensities on the 0..255 scale.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# ---------------------------------------------------------------------------------------------- the LiDAR sensor


class SensorOptics(NamedTuple):
    """The reference LiDAR as its kernels read it (`lidar_exact.ExactSensor`, `lidar_exact.sensor_optics`)."""

    length: float  # c τ_H, the pulse's extent on the receiver axis [m]
    listen_end: float  # last receiver-axis position whose peak is reported [m]
    r1: float  # bi-static overlap ξ = 0 up to r1 [m] ...
    r2: float  # ... and 1 from r2 [m]
    kappa: float  # receiver field-of-view radius over beam radius (disc-overlap model)
    beta0: float  # backscatter of the reference hard target Γ / π [1/sr]


# ---------------------------------------------------------------------------------------------- fog (lidar_exact)


class FogMedium(NamedTuple):
    """A homogeneous fog."""

    alpha: float  # extinction [1/m]
    beta: float  # backscatter [1/(m sr)]


class FogGrid(NamedTuple):
    """The tables of one extinction on the grid ``r_j = r_start + j step`` (`lidar_exact.FogTables`)."""

    r_start: float  # [m] (the overlap's r1)
    step: float  # [m]
    h0: F64  # (T,) running integral of h = ξ exp(-2 α r) / r² from r_start to r_j
    hc: F64  # (T,) the same of h cos ωr (ω = 2π / (c τ_H))
    hs: F64  # (T,) the same of h sin ωr
    gmax: F64  # (T,) prefix maximum of the unobstructed soft response G over R <= r_j [s/m²]
    gmax_at: F64  # (T,) where that maximum is reached [m]
    g_peak: float  # maximum of G over the listening window [s/m²]
    r_peak: float  # its position [m]


class FogPeaks(NamedTuple):
    """Per-beam output of the fog kernel: the strongest peak of the received power."""

    power: F64  # (N,) peak power in intensity units (C times the response)
    r_peak: F64  # (N,) its position on the receiver axis [m]
    source: NDArray[np.uint8]  # (N,) `lidar_exact.TARGET`, `FOG`, or 0: nothing received


# ---------------------------------------------------------------------------------------------- snow and rain
# (lidar_particles_exact)


class ExactBeams(NamedTuple):
    """The beams of one scan, all fired from one origin."""

    origin: F64  # (3,) sensor origin [m]
    dirs: F64  # (B, 3) unit beam directions
    r0: F64  # (B,) target range [m], inf where there is none
    i0: F64  # (B,) clear intensity of each target (full overlap), 0 where r0 is inf
    phi: F64  # (B,) rotation of each beam's sub-ray pattern [rad] (`lidar_particles_exact.beam_rotations`)


class BeamParticles(NamedTuple):
    """The resolved particles and, per beam, those whose sphere touches its cone (CSR by beam)."""

    pos: F64  # (P, 3) centres [m]
    diam: F64  # (P,) diameters [m]
    pair_start: I64  # (B+1,) the candidates of beam b are pair_part[pair_start[b]:pair_start[b+1]]
    pair_part: I64  # (pair_start[B],) particle rows


class SubrayPattern(NamedTuple):
    """The unrotated sunflower pattern of a beam's sub-rays (`lidar_particles_exact._pattern`)."""

    px: F64  # (K,) offset along e1 on the disc of radius tan_a at unit distance
    py: F64  # (K,) offset along e2
    pn: F64  # (K,) 1 / sqrt(1 + px² + py²): each sub-ray's normalisation
    tan_a: float  # tan(θ/2), θ the full beam divergence


class EchoGain(NamedTuple):
    """How strong an echo is (raw units of the `IntensityModel`)."""

    w_part: float  # scale x particle reflectivity: a particle's echo weight
    r_ref: float  # intensity gain g(R) = min(1, (r_ref / R)^falloff) [m]
    falloff: float


class Shadow(NamedTuple):
    """The unresolved particles' extinction on range shells (`lidar_particles_exact.Unresolved`)."""

    edges: F64  # (S,) inner edge of each shell [m]
    area: F64  # (S,) geometric cross-section per m³ a_u in the shell [1/m]
    tau: F64  # (S+1,) one-way optical depth at each edge


class ContinuumIntegrals(NamedTuple):
    """The unresolved continuum's running integrals on the fine grid ``j h``: of ``f = scale ρ a_u ξ T / r²`` times
    1, cos ωr, sin ωr (ω = 2π / (c τ_H))."""

    has_cont: bool  # False: no continuum (the tables are all zero)
    h: float  # grid step [m]
    H0: F64  # (T,)
    Hc: F64  # (T,)
    Hs: F64  # (T,)


class ContinuumNodes(NamedTuple):
    """The continuum's tables on the receiver grid ``R_m = m step`` (`lidar_particles_exact._tables`)."""

    step: float  # receiver-grid step [m]
    H0n: F64  # (M+1,) H0 at R_m
    Hcn: F64  # (M+1,)
    Hsn: F64  # (M+1,)
    H0l: F64  # (M+1,) H0 at R_m - c τ_H (lagged)
    Hcl: F64  # (M+1,)
    Hsl: F64  # (M+1,)
    cosn: F64  # (M+1,) cos ωR_m
    sinn: F64  # (M+1,) sin ωR_m
    G: F64  # (M+1,) the continuum's response with nothing in front
    sp: I64  # (L, M+1) sparse table of range argmax of G (level l: windows of 2^l nodes)


class SubrayScratch(NamedTuple):
    """Per-beam scratch of the sub-ray tracing."""

    rays: F64  # (K, 3) sub-ray directions
    best_s: F64  # (K,) nearest hit along each sub-ray [m]
    best_p: I64  # (K,) particle row of that hit, -1: the target


class BeamEvents(NamedTuple):
    """A beam's events sorted by range (`lidar_particles_exact._events`; the first n_ev rows are valid)."""

    s: F64  # (E,) range of the event [m]
    amp: F64  # (E,) echo amplitude (n/K) w ξ T / r²
    q: F64  # (E,) share of the sub-rays it stops
    p: I64  # (E,) particle row, -1: the target
    cs: F64  # (E,) amp cos ωs
    sn: F64  # (E,) amp sin ωs
    h0: F64  # (E,) the continuum's running integrals at s (`ContinuumIntegrals`)
    hc: F64  # (E,)
    hs: F64  # (E,)


class ParticlePeaks(NamedTuple):
    """Per-beam output of the snow / rain kernel."""

    power: F64  # (B,) peak intensity before the detector
    r_peak: F64  # (B,) its position on the receiver axis [m]
    source: NDArray[np.uint8]  # (B,) `TARGET`, `FOG` (the continuum) or `PARTICLE`, 0: nothing received
    dominant: I64  # (B,) particle row contributing most to a `PARTICLE` peak, else -1
    hits: NDArray[np.int32]  # (B,) sub-rays stopped by particles
    target_power: F64  # (B,) where the peak is not the target's: the waveform at the target's own echo crest
    target_r: F64  # (B,) that crest's receiver-axis position [m] (0 where target_power is 0)


# ---------------------------------------------------------------------------------------------- camera
# (camera_particles_exact)


class PixelRays(NamedTuple):
    """The pixel-centre rays of a pinhole camera (no skew), pixels row-major."""

    R: F64  # (3, 3) camera -> world rotation
    origin_z: float  # world height of the camera centre [m]
    fx: float  # [px]
    fy: float
    cx: float
    cy: float
    width: int  # pixels per row


class PixelScene(NamedTuple):
    """What each pixel (row-major, N = H W) sees without the unresolved medium, and its sample hits."""

    J: F64  # (N, 3) clear linear radiance
    behind: F64  # (N, 3) clear radiance behind a sky pixel's path
    ray_len: F64  # (N,) distance to the scene [m], inf for sky
    counts: I64  # (N,) samples that met a resolved particle
    samples: int  # samples per pixel S
    radiance: F64  # (3,) linear radiance L of a particle and of the medium's veil
    sky_distance: float  # length of a sky pixel's path through the medium [m]


class CameraMedium(NamedTuple):
    """The unresolved particles as a camera's medium (`camera_particles_exact.UnresolvedMedium`)."""

    n0: float  # spectrum N(D) = n0 exp(-lam D) on [d_min, d_max] [1/m⁴]
    lam: float  # [1/m]
    d_min: float  # [m]
    d_max: float  # [m]
    k: float  # D_res(s) = k s [m of diameter per m of distance]
    max_distance: float  # beyond this distance every particle is unresolved [m]
    alpha_total: float  # the field's bulk extinction, as the camera counts it [1/m]
    z_min: float  # the layer (world z) that holds the medium [m]
    z_max: float
