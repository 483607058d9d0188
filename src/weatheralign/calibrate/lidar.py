"""ReDAM for the LiDAR: the (α, β) of the fog model whose simulated intensities best match a reference fog level.

Objective (the paper's): ``D_KS(α, β) = sup_x |F_sim(α,β)(x) - F_ref(x)|`` between the intensity ECDF of the
reference's **clear** scans fogged by `weatheralign.lidar.fog` with ``(α, β)`` and the ECDF of the reference's real
foggy scans of one level, both binned exactly (`weatheralign.calibrate.histograms`, 256 bins).

Simulation. The per-point intensity outcome of `weatheralign.lidar.fog.simulate_fog` depends only on each point's
range from its **beam origin** and its clear intensity (hard attenuation ``exp(-2 α R_0) i_0`` vs the fog echo), on
the scan's intensity scale, the pulse sensor and the detector **noise floor** (LOST returns are removed from the
cloud, so they leave the histogram). `fog_frames` therefore reduces the clear scans once to ``(R_0, i_0)`` per point
(origins from `weatheralign.lidar.beams.beam_origins`, as `simulate_fog` does) and `simulated_histograms` runs the
public `fog_intensities` on them, casts to float32 (the point-cloud dtype) and bins: the histograms are identical to
binning ``simulate_fog(scan, α, β, lidar=...).points[:, 3]`` with the same pulse and floor (tested). The fog model's
randomness is the detector's: the range jitter of fog echoes, which never changes an intensity, and the intensity noise
of each reading (`weatheralign.lidar.fog.fog_intensities`), whose normals are drawn once per point from its beam's noise
stream (`FogFrames.normals`, the same draws as `simulate_fog`): every ``(α, β)`` is evaluated on the same normals
(common random numbers), so the objective is a deterministic function of ``(α, β)`` and no seed enters the search. The
noise floor and pulse must be the reference LiDAR's (`weatheralign.reference.reference_lidar_model`), hence required
arguments, and so must its intensity noise (`fog_frames`' ``noise_std`` / ``noise_rel``).

Search (`calibrate_level`):
1. the paper's grid (`PAPER_ALPHAS` x `PAPER_BETA_FACTORS`, ``β = 0.023·factor/MOR``, ``MOR = ln 20 / α``), one
   `evaluate_cell` per cell (independent: the flow maps them as tasks) -> `GridResult` (8 x 6 table, best cell;
   ties go to the first cell in (α, factor) order);
2. `refine`: continuous refinement in ``(ln α, factor)``: ``ln α`` bounded by the neighbouring grid values of the
   best cell (clamped at the grid's ends), the factor by the grid's whole factor range. α and β trade off along a
   diagonal valley of D_KS (a larger α with a larger β): the best grid cell can sit at a β two grid steps from the
   optimum (measured: truth (0.03, 1.4), best cell (0.04, 1.8)), so bounding β to the best cell's neighbours would
   exclude it; the paper's factor range is the prior bound, and searching all of it costs a few evaluations. D_KS
   is piecewise constant (it changes when a point crosses a bin edge or the fog/hard decision flips; with ~10⁶
   points the steps are ~1e-6 but the surface is still rough and non-smooth at the sup's switches), so no gradient
   method applies. First a fine grid over the box (default 7 values of ``ln α``, the best cell's α and thirds of
   the grid steps on either side, x 11 factors in steps of 0.1; it cannot be trapped by steps finer than its
   spacing), then Nelder-Mead (scipy, bounded) from the best fine point with an initial simplex of one fine step:
   it only compares function values (robust to plateaus and kinks) and is deterministic - there is no seed to fix.
   Every evaluation is cached; the result is the best evaluated point, never worse than the grid's best cell (a
   fine-grid node);
3. D_KS at ``(α*, β*)`` with a frame-bootstrap interval (`bootstrap_ks`).

Cost: an evaluation is one `fog_intensities` pass and one binning over the reduced points (no scan is re-read or
re-simulated); a level takes 48 cells, 77 fine points, <= 60 Nelder-Mead steps and 1000 bootstrap resamples. β has no
effect where no point becomes a fog echo (light fog: at α = 0.005 fog only wins beyond ~140 m, past the sensor's range):
the KS surface is then flat along β and β* is not identified - `LevelCalibration.beta_identified` tells.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from weatheralign.calibrate.histograms import (
    NUM_BINS,
    IntensityHistograms,
    KsBootstrap,
    _as_generator,
    _check_bootstrap_args,
    bootstrap_ks,
    ks_statistic,
)
from weatheralign.data.frame import LidarScan
from weatheralign.lidar.beams import beam_origins, point_noise_keys, point_ranges
from weatheralign.lidar.fog import FogLabel, fog_intensities, intensity_normals, soft_target_response
from weatheralign.lidar.quantum import ReadingSpread, clear_readings, on_scale, scan_reading_spread
from weatheralign.medium.fog import LN20, PAPER_BETA_FACTORS, mor_from_alpha
from weatheralign.sensors import SYNTHETIC_INTENSITY, IntensityModel, PulseSensor, floor_scale

F64 = NDArray[np.float64]

PAPER_ALPHAS = (0.001, 0.005, 0.01, 0.02, 0.04, 0.06, 0.08, 0.1)
"""The paper's extinction grid [1/m]."""

BETA_MOR_UNIT = 0.023
"""``β = BETA_MOR_UNIT · factor / MOR`` (the paper's β grid, `weatheralign.medium.fog.paper_beta_grid`)."""


BETA_SENSITIVITY_MIN = 1e-3
"""Smallest change of D_KS along β (at α*, over the grid's factor range) for β* to count as identified."""


def beta_from_factor(alpha: float, factor: float) -> float:
    """Backscatter [1/(m sr)] ``0.023 · factor / MOR`` with ``MOR = ln 20 / alpha`` (as `paper_beta_grid`)."""
    return BETA_MOR_UNIT * float(factor) * float(alpha) / LN20


# ----------------------------------------------------------------------------------------------- clear frames


@dataclass(frozen=True)
class FogFrames:
    """Clear scans reduced to what the fog's intensity outcome depends on (picklable; ~12 bytes per point, 20 with
    detector noise).

    Attributes:
        r0: (N,) float64 range of every point from its beam origin [m], all frames concatenated.
        i0: (N,) float32 clear intensity on ``0..intensity_max``.
        offsets: (F + 1,) int64 start of each frame in ``r0`` / ``i0`` (``offsets[-1] = N``).
        intensity_max: the scans' intensity scale (255.0 or 1.0).
        noise_std, noise_rel: the intensity noise of the detector that reads the fogged scans (0..255 scale; see
            `weatheralign.lidar.fog.fog_intensities`); 0, 0: noise-free.
        normals: (N,) float64 the standard normal of each point's reading (`intensity_normals` of its beam's noise
            stream, as `simulate_fog` draws it), or None when noise-free.
        spread: which ``i0`` the sensor rounded and where in its rounding interval each lies (each scan's
            `weatheralign.lidar.quantum.scan_reading_spread`, as `simulate_fog` finds it), or None where no scan was
            integer-quantised.
        intensity, floor_range_m: the reading sensor's `IntensityModel` and detector floor range
            (`weatheralign.sensors.LidarModel`): how a fog echo is reported and where the floor lies.
    """

    r0: F64
    i0: NDArray[np.float32]
    offsets: NDArray[np.int64]
    intensity_max: float
    noise_std: float = 0.0
    noise_rel: float = 0.0
    normals: F64 | None = None
    spread: ReadingSpread | None = None
    intensity: IntensityModel = SYNTHETIC_INTENSITY
    floor_range_m: float | None = None

    def __post_init__(self) -> None:
        n = len(self.r0)
        off = np.asarray(self.offsets)
        if self.r0.shape != (n,) or self.i0.shape != (n,):
            raise ValueError(f"FogFrames: r0 {self.r0.shape} and i0 {self.i0.shape} must be equal 1-D arrays")
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0.0 and math.isfinite(self.noise_rel)
                and self.noise_rel >= 0.0):
            raise ValueError(f"FogFrames: noise_std = {self.noise_std!r}, noise_rel = {self.noise_rel!r}; expected "
                             f"finite values >= 0")
        if (self.noise_std > 0.0 or self.noise_rel > 0.0) and (self.normals is None or self.normals.shape != (n,)):
            raise ValueError(f"FogFrames: a noisy detector needs normals of shape ({n},), got "
                             f"{None if self.normals is None else self.normals.shape}")
        if self.spread is not None and (self.spread.rounded.shape != (n,) or self.spread.uniforms.shape != (n,)):
            raise ValueError(f"FogFrames: spread must hold two arrays of shape ({n},), got "
                             f"{self.spread.rounded.shape}, {self.spread.uniforms.shape}")
        if off.ndim != 1 or len(off) < 2 or off[0] != 0 or off[-1] != n or (np.diff(off) < 0).any():
            raise ValueError(f"FogFrames: offsets must be non-decreasing from 0 to N = {n} with at least one frame")
        if self.intensity_max not in (1.0, 255.0):
            raise ValueError(f"FogFrames: intensity_max = {self.intensity_max!r}; expected 255.0 or 1.0")

    @property
    def num_frames(self) -> int:
        """Number of frames F."""
        return len(self.offsets) - 1

    @property
    def num_points(self) -> int:
        """Number of points N over all frames."""
        return len(self.r0)

    def clear_histograms(self) -> IntensityHistograms:
        """The clear intensities' per-frame histograms (the figure's context curve)."""
        hist = IntensityHistograms(self.intensity_max)
        for k in range(self.num_frames):
            hist.add_intensities(self.i0[self.offsets[k]:self.offsets[k + 1]])
        return hist


def fog_frames(scans: Iterable[LidarScan], *, noise_std: float = 0.0, noise_rel: float = 0.0,
               intensity: IntensityModel = SYNTHETIC_INTENSITY, floor_range_m: float | None = None) -> FogFrames:
    """Reduce clear scans (a sequence or any iterable, consumed once) to `FogFrames`, read through a detector of
    intensity noise ``noise_std`` (0..255 scale) and ``noise_rel`` (the sensor's ``intensity_noise_std`` /
    ``intensity_noise_rel``), intensity model ``intensity`` and floor range ``floor_range_m``.

    Each point's range is taken from its own beam origin (`weatheralign.lidar.beams.beam_origins`: a moving ego's sensor
    moves during the sweep; None -> the frame origin), exactly as `simulate_fog` computes it, and so are its noise
    (`weatheralign.lidar.beams.point_noise_keys`) and, for an integer-quantised scan, where each rounded reading lies
    in its rounding interval (`weatheralign.lidar.quantum.scan_reading_spread`).

    Raises:
        ValueError: no scans, or scans of different intensity scales.
    """
    r0s: list[F64] = []
    i0s: list[NDArray[np.float32]] = []
    normals: list[F64] = []
    spreads: list[ReadingSpread | None] = []
    noisy = noise_std > 0.0 or noise_rel > 0.0
    scale: float | None = None
    for k, scan in enumerate(scans):
        if scale is None:
            scale = float(scan.intensity_max)
        elif float(scan.intensity_max) != scale:
            raise ValueError(f"fog_frames: scan {k} has intensity_max = {scan.intensity_max}, the first {scale}; "
                             f"expected one scale")
        origins = beam_origins(scan, "scan")
        r0s.append(point_ranges(scan.points, origins))
        i0s.append(np.ascontiguousarray(scan.points[:, 3], dtype=np.float32))
        if noisy:
            normals.append(intensity_normals(point_noise_keys(scan)))
        spreads.append(scan_reading_spread(scan))
    if scale is None:
        raise ValueError("fog_frames: no scans; expected at least one clear LidarScan")
    frames = replace(fog_frames_from_arrays(r0s, i0s, scale), intensity=intensity, floor_range_m=floor_range_m)
    if any(p is not None for p in spreads):
        none = [ReadingSpread(np.zeros(len(i), dtype=bool), np.zeros(len(i))) for i in i0s]
        joined = [n if p is None else p for n, p in zip(none, spreads)]
        frames = replace(frames, spread=ReadingSpread(np.concatenate([p.rounded for p in joined]),
                                                      np.concatenate([p.uniforms for p in joined])))
    if not noisy:
        return frames
    return replace(frames, noise_std=float(noise_std), noise_rel=float(noise_rel), normals=np.concatenate(normals))


def fog_frames_from_arrays(
    ranges: Sequence[ArrayLike], intensities: Sequence[ArrayLike], intensity_max: float
) -> FogFrames:
    """`FogFrames` from per-frame ranges [m] (N_k,) and clear intensities (N_k,) on ``0..intensity_max``."""
    if len(ranges) != len(intensities) or not ranges:
        raise ValueError(f"fog_frames_from_arrays: {len(ranges)} range arrays for {len(intensities)} intensity "
                         f"arrays; expected equal, non-zero numbers")
    r = [np.asarray(x, dtype=np.float64).ravel() for x in ranges]
    i = [np.asarray(x, dtype=np.float32).ravel() for x in intensities]
    for k, (a, b) in enumerate(zip(r, i)):
        if a.shape != b.shape:
            raise ValueError(f"fog_frames_from_arrays: frame {k} has {len(a)} ranges and {len(b)} intensities")
        if a.size and not (np.isfinite(a).all() and a.min() >= 0.0):
            raise ValueError(f"fog_frames_from_arrays: frame {k} has a negative or non-finite range")
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in r])]).astype(np.int64)
    return FogFrames(r0=np.concatenate(r), i0=np.concatenate(i), offsets=offsets,
                     intensity_max=float(intensity_max))


# --------------------------------------------------------------------------------------------- one (α, β)


@njit(cache=True, nogil=True)
def _bin_frames(intensity, labels, offsets, scale, lost, out):  # pragma: no cover
    """Per-frame 256-bin counts of the float32-cast ``intensity`` of every non-LOST point into ``out`` (F, 256)."""
    for f in range(len(offsets) - 1):
        for n in range(offsets[f], offsets[f + 1]):
            if labels[n] == lost:
                continue
            code = np.float64(np.float32(intensity[n])) * scale
            k = int(math.floor(code + 0.5))
            if k > 255:
                k = 255
            elif k < 0:
                k = 0
            out[f, k] += 1


def frame_clear_values(frames: FogFrames, noise_floor: float | None) -> F64 | None:
    """(N,) the clear value each of ``frames``' intensities stood for before the sensor rounded it, on their scale,
    under a detector floor ``noise_floor`` (0..255; `weatheralign.lidar.quantum.clear_readings`), or None where none
    was rounded."""
    if frames.spread is None:
        return None
    i0_255 = frames.i0 * np.float32(255.0 / frames.intensity_max)
    floor = None if noise_floor is None else noise_floor * floor_scale(frames.r0, frames.intensity,
                                                                        frames.floor_range_m)
    x = clear_readings(i0_255, frames.spread.rounded, floor, frames.spread.uniforms)
    return on_scale(x, frames.i0, frames.intensity_max)


def simulated_histograms(
    frames: FogFrames,
    alpha: float,
    beta: float,
    *,
    noise_floor: float | None,
    sensor: PulseSensor,
) -> IntensityHistograms:
    """Per-frame intensity histograms of the clear ``frames`` fogged with ``(alpha, beta)``.

    Equal to binning ``simulate_fog(scan, alpha, beta, lidar=<pulse sensor, floor noise_floor, the frames' intensity
    noise>).points[:, 3]`` of every scan (any range noise). Releases the GIL (numba), so cells run in parallel
    threads.

    Args:
        frames: clear scans (`fog_frames`).
        alpha: extinction [1/m] (>= 0); beta: backscatter [1/(m sr)] (>= 0).
        noise_floor: detector floor on the 0..255 scale (the reference LiDAR's), or None.
        sensor: the pulse sensor of the simulation.
    """
    res = fog_intensities(frames.r0, frames.i0, alpha, beta, intensity_max=frames.intensity_max, sensor=sensor,
                          noise_floor=noise_floor, response=soft_target_response(alpha, sensor),
                          noise_std=frames.noise_std, noise_rel=frames.noise_rel, noise_normals=frames.normals,
                          clear_values=frame_clear_values(frames, noise_floor), intensity=frames.intensity,
                          floor_range_m=frames.floor_range_m)
    counts = np.zeros((frames.num_frames, NUM_BINS), dtype=np.int64)
    _bin_frames(res.intensity, res.labels, frames.offsets, 255.0 / frames.intensity_max, np.uint8(FogLabel.LOST),
                counts)
    return IntensityHistograms(frames.intensity_max, counts)


@dataclass(frozen=True)
class CellResult:
    """D_KS of one ``(alpha, beta_factor)``: ``beta = 0.023 · beta_factor / MOR`` [1/(m sr)]."""

    alpha: float
    beta_factor: float
    beta: float
    ks: float


def evaluate_cell(
    frames: FogFrames,
    reference: IntensityHistograms,
    alpha: float,
    beta_factor: float,
    *,
    noise_floor: float | None,
    sensor: PulseSensor,
) -> CellResult:
    """D_KS between ``frames`` fogged with ``(alpha, beta_from_factor(alpha, beta_factor))`` and ``reference``
    (one fog level's real scans). The unit of work the flow maps over the grid."""
    if not (math.isfinite(alpha) and alpha > 0.0):
        raise ValueError(f"evaluate_cell: alpha = {alpha!r}; expected a finite extinction > 0 [1/m]")
    if not (math.isfinite(beta_factor) and beta_factor >= 0.0):
        raise ValueError(f"evaluate_cell: beta_factor = {beta_factor!r}; expected a finite factor >= 0")
    beta = beta_from_factor(alpha, beta_factor)
    sim = simulated_histograms(frames, alpha, beta, noise_floor=noise_floor, sensor=sensor)
    return CellResult(alpha=float(alpha), beta_factor=float(beta_factor), beta=beta, ks=ks_statistic(sim, reference))


# ----------------------------------------------------------------------------------------------------- grid


def _check_axis(values: Sequence[float], name: str, positive: bool) -> F64:
    a = np.asarray(values, dtype=np.float64)
    lo_ok = (a > 0.0) if positive else (a >= 0.0)
    if a.ndim != 1 or len(a) == 0 or not (np.isfinite(a).all() and lo_ok.all()) or (np.diff(a) <= 0).any():
        raise ValueError(f"{name} = {values!r}; expected a non-empty, strictly increasing list of finite "
                         f"{'positive' if positive else 'non-negative'} values")
    return a


@dataclass(frozen=True)
class GridResult:
    """D_KS over the (α, β-factor) grid of one fog level.

    Attributes:
        alphas: (A,) extinctions [1/m]; beta_factors: (B,) factors (``β = 0.023 · factor / MOR``).
        ks: (A, B) D_KS per cell.
    """

    alphas: F64
    beta_factors: F64
    ks: F64

    def __post_init__(self) -> None:
        if self.ks.shape != (len(self.alphas), len(self.beta_factors)):
            raise ValueError(f"GridResult: ks {self.ks.shape} != ({len(self.alphas)}, {len(self.beta_factors)})")

    @classmethod
    def from_cells(cls, cells: Iterable[CellResult], alphas: Sequence[float] = PAPER_ALPHAS,
                   beta_factors: Sequence[float] = PAPER_BETA_FACTORS) -> GridResult:
        """Assemble mapped `evaluate_cell` results (any order); every grid cell must be present exactly once."""
        a = _check_axis(alphas, "alphas", True)
        b = _check_axis(beta_factors, "beta_factors", False)
        ks = np.full((len(a), len(b)), np.nan)
        for cell in cells:
            i = np.flatnonzero(np.isclose(a, cell.alpha, rtol=1e-12, atol=0.0))
            j = np.flatnonzero(np.isclose(b, cell.beta_factor, rtol=1e-12, atol=1e-15))
            if len(i) != 1 or len(j) != 1:
                raise ValueError(f"GridResult.from_cells: cell (alpha={cell.alpha}, factor={cell.beta_factor}) is "
                                 f"not on the grid")
            if not np.isnan(ks[i[0], j[0]]):
                raise ValueError(f"GridResult.from_cells: cell (alpha={cell.alpha}, factor={cell.beta_factor}) twice")
            ks[i[0], j[0]] = cell.ks
        if np.isnan(ks).any():
            missing = [(float(a[i]), float(b[j])) for i, j in zip(*np.nonzero(np.isnan(ks)))]
            raise ValueError(f"GridResult.from_cells: missing cells {missing[:5]}{'...' if len(missing) > 5 else ''}")
        return cls(alphas=a, beta_factors=b, ks=ks)

    @property
    def best_index(self) -> tuple[int, int]:
        """(i, j) of the smallest D_KS (first in (α, factor) order on ties)."""
        i, j = np.unravel_index(int(np.argmin(self.ks)), self.ks.shape)
        return int(i), int(j)

    @property
    def best_alpha(self) -> float:
        return float(self.alphas[self.best_index[0]])

    @property
    def best_beta_factor(self) -> float:
        return float(self.beta_factors[self.best_index[1]])

    @property
    def best_ks(self) -> float:
        return float(self.ks[self.best_index])

    def table(self) -> list[dict[str, float]]:
        """Rows ``{"alpha", "beta_factor", "beta", "mor", "ks"}`` of every cell (for a CSV / MLflow table)."""
        return [{"alpha": float(a), "beta_factor": float(f), "beta": beta_from_factor(a, f),
                 "mor": mor_from_alpha(float(a)), "ks": float(self.ks[i, j])}
                for i, a in enumerate(self.alphas) for j, f in enumerate(self.beta_factors)]


def grid_cells(alphas: Sequence[float] = PAPER_ALPHAS,
               beta_factors: Sequence[float] = PAPER_BETA_FACTORS) -> list[tuple[float, float]]:
    """The ``(alpha, beta_factor)`` pairs of the grid, α-major (what the flow maps `evaluate_cell` over)."""
    a = _check_axis(alphas, "alphas", True)
    b = _check_axis(beta_factors, "beta_factors", False)
    return [(float(x), float(y)) for x in a for y in b]


def grid_search(
    frames: FogFrames,
    reference: IntensityHistograms,
    *,
    noise_floor: float | None,
    alphas: Sequence[float] = PAPER_ALPHAS,
    beta_factors: Sequence[float] = PAPER_BETA_FACTORS,
    sensor: PulseSensor,
) -> GridResult:
    """Every grid cell in turn (the flow maps `evaluate_cell` instead and calls `GridResult.from_cells`)."""
    cells = [evaluate_cell(frames, reference, a, f, noise_floor=noise_floor, sensor=sensor)
             for a, f in grid_cells(alphas, beta_factors)]
    return GridResult.from_cells(cells, alphas, beta_factors)


# ----------------------------------------------------------------------------------------------- refinement


@dataclass(frozen=True)
class Refinement:
    """The continuous refinement around the grid's best cell.

    Attributes:
        alpha, beta_factor, beta, ks: the best evaluated point.
        alpha_bounds, factor_bounds: the search box (α: neighbouring grid values of the best cell; factor: the
            grid's range).
        evaluations: (M, 3) every evaluated ``(alpha, beta_factor, ks)`` in order (fine grid, then Nelder-Mead).
        num_fine: how many of them are the fine grid.
    """

    alpha: float
    beta_factor: float
    beta: float
    ks: float
    alpha_bounds: tuple[float, float]
    factor_bounds: tuple[float, float]
    evaluations: F64
    num_fine: int


def _neighbour_bounds(axis: F64, index: int) -> tuple[float, float]:
    return float(axis[max(index - 1, 0)]), float(axis[min(index + 1, len(axis) - 1)])


def refine(
    frames: FogFrames,
    reference: IntensityHistograms,
    grid: GridResult,
    *,
    noise_floor: float | None,
    sensor: PulseSensor,
    fine_points: int | tuple[int, int] = (7, 11),
    max_nelder_mead: int = 60,
) -> Refinement:
    """Refine the grid's best cell in ``(ln α, factor)`` (module docstring: α between the best cell's grid
    neighbours, the factor over the grid's range).

    Args:
        frames, reference, noise_floor, sensor: as for `evaluate_cell`.
        grid: the level's `GridResult`.
        fine_points: (n_α, n_factor) nodes of the fine grid over the box (each >= 2; an int n means (n, n)).
        max_nelder_mead: function evaluations allowed to Nelder-Mead (0: fine grid only).
    """
    n_a, n_f = (int(fine_points),) * 2 if isinstance(fine_points, (int, np.integer)) else map(int, fine_points)
    if n_a < 2 or n_f < 2:
        raise ValueError(f"refine: fine_points = {fine_points!r}; expected (n_alpha, n_factor), each >= 2")
    i, _ = grid.best_index
    a_lo, a_hi = _neighbour_bounds(grid.alphas, i)
    f_lo, f_hi = float(grid.beta_factors[0]), float(grid.beta_factors[-1])
    u_lo, u_hi = math.log(a_lo), math.log(a_hi)
    cache: dict[tuple[float, float], float] = {}
    order: list[tuple[float, float, float]] = []

    def point(s: float, t: float) -> tuple[float, float]:
        s, t = min(max(s, 0.0), 1.0), min(max(t, 0.0), 1.0)
        alpha = math.exp(u_lo + s * (u_hi - u_lo)) if u_hi > u_lo else a_lo
        return alpha, f_lo + t * (f_hi - f_lo)

    def objective(x: NDArray) -> float:
        alpha, factor = point(float(x[0]), float(x[1]))
        key = (alpha, factor)
        if key not in cache:
            cache[key] = evaluate_cell(frames, reference, alpha, factor, noise_floor=noise_floor, sensor=sensor).ks
            order.append((alpha, factor, cache[key]))
        return cache[key]

    # fine ln-alpha nodes: (n_a - 1) / 2 equal steps on each side of the best cell's alpha (a node itself)
    s_best = (math.log(grid.best_alpha) - u_lo) / (u_hi - u_lo) if u_hi > u_lo else 0.0
    half = max(1, (n_a - 1) // 2)
    s_nodes = np.unique(np.concatenate([np.linspace(0.0, s_best, half + 1), np.linspace(s_best, 1.0, half + 1)]))
    t_nodes = np.linspace(0.0, 1.0, n_f)
    best_x, best_ks = np.zeros(2), math.inf
    for s in s_nodes:
        for t in t_nodes:
            ks = objective(np.array([s, t]))
            if ks < best_ks:
                best_x, best_ks = np.array([s, t]), ks
    num_fine = len(order)
    if max_nelder_mead > 0:
        ds, dt = float(np.diff(s_nodes).min()) if len(s_nodes) > 1 else 0.1, 1.0 / (n_f - 1)
        simplex = np.array([best_x, best_x + [ds if best_x[0] + ds <= 1 else -ds, 0.0],
                            best_x + [0.0, dt if best_x[1] + dt <= 1 else -dt]])
        minimize(objective, best_x, method="Nelder-Mead", bounds=[(0.0, 1.0), (0.0, 1.0)],
                 options={"initial_simplex": simplex, "maxfev": int(max_nelder_mead), "xatol": 1e-3,
                          "fatol": 1e-6})
    evals = np.array(order, dtype=np.float64)
    k = int(np.argmin(evals[:, 2]))  # first of equal minima: the fine grid's order, then Nelder-Mead's
    alpha, factor, ks = (float(v) for v in evals[k])
    if grid.best_ks < ks:  # only by float rounding of the factor nodes (the best cell's alpha is a node)
        alpha, factor, ks = grid.best_alpha, grid.best_beta_factor, grid.best_ks
    return Refinement(alpha=alpha, beta_factor=factor, beta=beta_from_factor(alpha, factor), ks=ks,
                      alpha_bounds=(a_lo, a_hi), factor_bounds=(f_lo, f_hi), evaluations=evals, num_fine=num_fine)


# ---------------------------------------------------------------------------------------------------- level


@dataclass(frozen=True)
class LevelCalibration:
    """ReDAM's LiDAR result for one fog level.

    Attributes:
        alpha [1/m], beta [1/(m sr)], beta_factor, mor [m]: the tuned medium (``MOR = ln 20 / α``).
        ks, ks_ci_low, ks_ci_high, confidence: D_KS at the tuned medium with its frame-bootstrap interval.
        alpha_ci_low, alpha_ci_high: frame-bootstrap interval of α* itself (`bootstrap_alpha`, at ``beta_factor``).
        grid: the grid table; refinement: the continuous refinement.
        simulated: per-frame histograms of the clear frames fogged with the tuned medium (for the figure).
        clear: per-frame histograms of the clear frames.
        beta_sensitivity: ``max - min`` of D_KS at α* over the grid's smallest and largest factor and β*: ~0 where
            no point becomes a fog echo (β is then arbitrary; see `beta_identified`).
    """

    alpha: float
    beta: float
    beta_factor: float
    mor: float
    ks: float
    ks_ci_low: float
    ks_ci_high: float
    confidence: float
    alpha_ci_low: float
    alpha_ci_high: float
    grid: GridResult
    refinement: Refinement
    simulated: IntensityHistograms
    clear: IntensityHistograms
    beta_sensitivity: float
    num_reference_frames: int = 0
    num_reference_points: int = 0

    @property
    def beta_identified(self) -> bool:
        """Whether β matters at α*: D_KS changes by more than `BETA_SENSITIVITY_MIN` across the grid's factors."""
        return self.beta_sensitivity > BETA_SENSITIVITY_MIN

    def metrics(self) -> dict[str, float]:
        """Flat numbers for details.json / MLflow."""
        return {
            "alpha": self.alpha, "beta": self.beta, "beta_factor": self.beta_factor, "mor": self.mor,
            "ks": self.ks, "ks_ci_low": self.ks_ci_low, "ks_ci_high": self.ks_ci_high,
            "alpha_ci_low": self.alpha_ci_low, "alpha_ci_high": self.alpha_ci_high,
            "grid_alpha": self.grid.best_alpha, "grid_beta_factor": self.grid.best_beta_factor,
            "grid_ks": self.grid.best_ks, "beta_sensitivity": self.beta_sensitivity,
            "clear_frames": float(self.clear.num_frames), "clear_points": float(self.clear.num_points),
            "reference_frames": float(self.num_reference_frames),
            "reference_points": float(self.num_reference_points),
        }


def bootstrap_alpha(
    frames: FogFrames,
    reference: IntensityHistograms,
    alpha: float,
    beta_factor: float,
    *,
    noise_floor: float | None,
    sensor: PulseSensor,
    num_resamples: int = 1000,
    confidence: float = 0.95,
    rng: np.random.Generator | int = 0,
    span: float = 1.5,
    points: int = 61,
) -> tuple[float, float]:
    """Frame-bootstrap percentile interval of the tuned extinction [1/m]: how far α* would move with other frames.

    Each resample draws the clear frames and the reference frames with replacement (independently, as
    `bootstrap_ks`) and takes the α minimising D_KS on a log grid of ``points`` values in ``[α / span, α span]``
    (β from ``beta_factor``: β barely moves D_KS where it is identified at all, `beta_identified`). The per-frame
    histograms of every grid α are computed once, so a resample costs a weighted sum. The resolution is the grid's
    step (``2 ln(span) / (points - 1)`` in ln α: 1.4 % by default): an interval narrower than that collapses onto
    α*; an interval end at the grid's edge means "at least this far" (widen ``span``).

    Raises:
        ValueError: bad ``span`` / ``points`` or bootstrap arguments.
    """
    if not (span > 1.0 and points >= 3):
        raise ValueError(f"bootstrap_alpha: span = {span!r}, points = {points!r}; expected span > 1, points >= 3")
    _check_bootstrap_args(num_resamples, confidence)
    grid = alpha * np.exp(np.linspace(-math.log(span), math.log(span), int(points)))
    sims = np.stack([simulated_histograms(frames, a, beta_from_factor(a, beta_factor), noise_floor=noise_floor,
                                          sensor=sensor).counts for a in grid]).astype(np.float64)  # (A, F, 256)
    ref = reference.counts.astype(np.float64)
    gen = _as_generator(rng)
    best = np.empty(num_resamples)
    for b in range(num_resamples):
        w_sim = np.bincount(gen.integers(0, sims.shape[1], sims.shape[1]), minlength=sims.shape[1])
        w_ref = np.bincount(gen.integers(0, len(ref), len(ref)), minlength=len(ref))
        s = np.einsum("afk,f->ak", sims, w_sim.astype(np.float64))
        r = w_ref.astype(np.float64) @ ref
        cdf_s = np.cumsum(s, axis=1) / np.maximum(s.sum(axis=1, keepdims=True), 1.0)
        cdf_r = np.cumsum(r) / max(float(r.sum()), 1.0)
        best[b] = grid[int(np.argmin(np.abs(cdf_s - cdf_r).max(axis=1)))]
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.percentile(best, [tail, 100.0 - tail])
    return float(lo), float(hi)


def finish_level(
    frames: FogFrames,
    reference: IntensityHistograms,
    grid: GridResult,
    *,
    noise_floor: float | None,
    sensor: PulseSensor,
    fine_points: int | tuple[int, int] = (7, 11),
    max_nelder_mead: int = 60,
    num_bootstrap: int = 1000,
    confidence: float = 0.95,
    seed: int = 0,
) -> LevelCalibration:
    """Refinement + bootstrap after the grid (the flow's step after its mapped `evaluate_cell` tasks)."""
    ref = refine(frames, reference, grid, noise_floor=noise_floor, sensor=sensor, fine_points=fine_points,
                 max_nelder_mead=max_nelder_mead)
    sim = simulated_histograms(frames, ref.alpha, ref.beta, noise_floor=noise_floor, sensor=sensor)
    boot: KsBootstrap = bootstrap_ks(sim, reference, num_resamples=num_bootstrap, confidence=confidence, rng=seed)
    alpha_ci = bootstrap_alpha(frames, reference, ref.alpha, ref.beta_factor, noise_floor=noise_floor, sensor=sensor,
                               num_resamples=num_bootstrap, confidence=confidence, rng=seed)
    # does β matter at α*? D_KS at the grid's extreme factors vs the tuned one
    along_beta = [ref.ks] + [evaluate_cell(frames, reference, ref.alpha, f, noise_floor=noise_floor,
                                           sensor=sensor).ks
                             for f in (float(grid.beta_factors[0]), float(grid.beta_factors[-1]))]
    return LevelCalibration(
        alpha=ref.alpha, beta=ref.beta, beta_factor=ref.beta_factor, mor=mor_from_alpha(ref.alpha),
        ks=boot.statistic, ks_ci_low=boot.ci_low, ks_ci_high=boot.ci_high, confidence=boot.confidence,
        alpha_ci_low=alpha_ci[0], alpha_ci_high=alpha_ci[1],
        grid=grid, refinement=ref, simulated=sim, clear=frames.clear_histograms(),
        beta_sensitivity=float(max(along_beta) - min(along_beta)),
        num_reference_frames=reference.num_frames, num_reference_points=reference.num_points,
    )


def calibrate_level(
    frames: FogFrames,
    reference: IntensityHistograms,
    *,
    noise_floor: float | None,
    alphas: Sequence[float] = PAPER_ALPHAS,
    beta_factors: Sequence[float] = PAPER_BETA_FACTORS,
    sensor: PulseSensor,
    fine_points: int | tuple[int, int] = (7, 11),
    max_nelder_mead: int = 60,
    num_bootstrap: int = 1000,
    confidence: float = 0.95,
    seed: int = 0,
) -> LevelCalibration:
    """The whole LiDAR ReDAM of one fog level, sequentially: grid, refinement, bootstrap.

    Args:
        frames: the reference's clear scans (`fog_frames`).
        reference: the level's real foggy scans (`IntensityHistograms.from_scans`), same intensity scale.
        noise_floor: the simulate stage's detector floor (0..255 scale) or None.
        alphas, beta_factors: the grid (default: the paper's).
        sensor: pulse sensor of the simulation.
        fine_points, max_nelder_mead: refinement effort (see `refine`).
        num_bootstrap, confidence, seed: the D_KS interval (`bootstrap_ks`).
    """
    if frames.intensity_max != reference.intensity_max:
        raise ValueError(f"calibrate_level: clear frames are on 0..{frames.intensity_max:g}, the reference on "
                         f"0..{reference.intensity_max:g}; expected one scale (same sensor)")
    grid = grid_search(frames, reference, noise_floor=noise_floor, alphas=alphas, beta_factors=beta_factors,
                       sensor=sensor)
    return finish_level(frames, reference, grid, noise_floor=noise_floor, sensor=sensor, fine_points=fine_points,
                        max_nelder_mead=max_nelder_mead, num_bootstrap=num_bootstrap, confidence=confidence,
                        seed=seed)
