"""One deterministic snow/rain particle field in world (global) coordinates, materialised on demand.

The field is static in a frame co-moving with the particle velocity ``D`` (terminal fall + wind) [m/s]: a particle
with co-moving position ``p'`` is, at time ``t``, at ``p' + D (t - t_ref)``, with z wrapped into the layer
``[z_min, z_max)`` (a particle leaving the bottom re-enters at the top, so the density is the same at every time).

Co-moving space is cut into a global grid of cells: ``cell_size`` wide in x and y (unbounded), and
``nz = round((z_max - z_min) / cell_size)`` cells over the layer in z (periodic). A cell's particles are a function
of ``(seed, cell index)`` alone, through a counter-based hash (SplitMix64), so any query, in any order, by any
sensor, gets the same particles:

- Each cell holds a Poisson process on the diameter axis with intensity ``V_cell N(D)``. It is generated largest
  particle first: with unit exponential increments ``E_1 < E_2 < ...`` (hashed from the cell key and the rank j),
  particle j has the diameter ``D_j`` at which the expected count of larger particles equals ``E_j``. The particles
  with ``D >= m`` are exactly the ranks with ``E_j <= V_cell n(D >= m)``: their count is Poisson with that mean and
  their diameters follow N(D) truncated to ``[m, d_max]``. So a query with ``min_diameter = m`` returns exactly the
  subset ``D >= m`` of the full field (same ids and positions), at the cost of only those particles; the extinction
  of the unresolved part ``D < m`` comes from the distribution (`ParticleField.unresolved_extinction`).
- Positions are uniform in the cell (three more hashed uniforms per rank).
- The id packs (cell, rank) into a non-negative int64: 20 bits each for ix and iy (|ix|, |iy| < 2^19 cells, i.e.
  ±1048 km of co-moving space with 2 m cells), 7 bits for the z cell (nz <= 128), 16 bits for the rank
  (< 65536 particles per cell). Ids are therefore stable, unique and invertible: `ParticleField.positions_at`
  propagates any id to any time without a query.

Keep ``t_ref`` near the times you query (e.g. the scene start): co-moving coordinates drift by ``D (t - t_ref)``.
Kernels are serial numba (``nogil``): callers parallelise across samples with threads.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from numpy.typing import NDArray

from weatheralign.medium.distributions import ExponentialSizeDistribution, SizeDistribution
from weatheralign.particle_ids import MAX_PER_CELL, MAX_Z_CELLS, RANK_BITS, XY_BITS, XY_OFFSET, Z_BITS, layer_cells

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_MASK64 = (1 << 64) - 1
_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 2.0**-53

U_RANK_BITS = np.uint64(RANK_BITS)
_U_Z_BITS = np.uint64(Z_BITS)
_U_XY_BITS = np.uint64(XY_BITS)
_U_RANK_MASK = np.uint64(MAX_PER_CELL - 1)
_U_Z_MASK = np.uint64(MAX_Z_CELLS - 1)
_U_XY_MASK = np.uint64((1 << XY_BITS) - 1)

DEFAULT_MAX_PARTICLES = 30_000_000
"""Refuse queries expected to return more particles than this (~1.2 GB); raise it explicitly if you mean it."""


# ----------------------------------------------------------------------------------------------------------- hashing
def splitmix64_py(z: int) -> int:
    """SplitMix64 finaliser on a Python int (64-bit wrap)."""
    z &= _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def field_seed_key(seed: int) -> np.uint64:
    return np.uint64(splitmix64_py(splitmix64_py(seed + 0x9E3779B97F4A7C15) ^ 0x5EED_F1E1D))


@njit(nogil=True, cache=True, inline="always")
def splitmix64(z: np.uint64) -> np.uint64:
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(nogil=True, cache=True, inline="always")
def stream_uniform(key: np.uint64, counter: np.uint64) -> float:
    """Uniform in [0, 1) from the ``counter``-th SplitMix64 output of stream ``key``."""
    h = splitmix64(key + (counter + np.uint64(1)) * _GAMMA)
    return float(h >> _S11) * _TWO_M53


@njit(nogil=True, cache=True, inline="always")
def normal_pair(key: np.uint64) -> tuple[float, float]:
    """Two independent standard normals (Box–Muller) from the first two outputs of the SplitMix64 stream ``key``: a
    LiDAR beam's detector noise (intensity, range) from its key (`weatheralign.lidar.beams.detector_noise_keys`)."""
    u1 = 1.0 - stream_uniform(key, np.uint64(0))  # (0, 1]
    u2 = stream_uniform(key, np.uint64(1))
    rad = math.sqrt(-2.0 * math.log(u1))
    return rad * math.cos(2.0 * math.pi * u2), rad * math.sin(2.0 * math.pi * u2)


@njit(nogil=True, cache=True, inline="always")
def packed_cell(ix: np.int64, iy: np.int64, iz: np.int64) -> np.uint64:
    ux = np.uint64(ix + XY_OFFSET)
    uy = np.uint64(iy + XY_OFFSET)
    return (((ux << _U_XY_BITS) | uy) << _U_Z_BITS) | np.uint64(iz)


@njit(nogil=True, cache=True, inline="always")
def cell_key(seed_key: np.uint64, packed: np.uint64) -> np.uint64:
    return splitmix64(seed_key ^ splitmix64(packed + _GAMMA))


# ----------------------------------------------------------------------------------------------------------- kernels
@njit(nogil=True, cache=True)
def _count_kernel(seed_key: np.uint64, cells: NDArray, c_max: float, counts: NDArray) -> bool:
    """Per cell, the number of ranks j with E_j <= c_max; False if a cell would exceed the rank bits."""
    for k in range(cells.shape[0]):
        key = cell_key(seed_key, packed_cell(cells[k, 0], cells[k, 1], cells[k, 2]))
        e = 0.0
        j = 0
        while True:
            e -= math.log(1.0 - stream_uniform(key, np.uint64(4 * j)))
            if e > c_max:
                break
            j += 1
            if j >= MAX_PER_CELL:
                return False
        counts[k] = j
    return True


@njit(nogil=True, cache=True, inline="always")
def wrap_height(z: float, height: float) -> float:
    """``z`` mod ``height`` in [0, height) (Python float modulo: exact fmod, shifted into [0, height) for z < 0;
    the same expression wherever a position is computed)."""
    r = z % height
    if r >= height:  # a tiny negative z rounds up to the period
        r = 0.0
    return r


@njit(nogil=True, cache=True)
def _fill_kernel(seed_key: np.uint64, cells: NDArray, counts: NDArray, cell_size: float, cell_z: float,
                 lam: float, exp_lam_dmax: float, scale: float, d_floor: float, d_max: float, shift: NDArray,
                 z_min: float, height: float, lo: NDArray, hi: NDArray, positions: NDArray, diameters: NDArray,
                 ids: NDArray) -> int:
    """World positions (N, 3), diameters and ids of the counted particles of ``cells`` that lie in the closed box
    ``[lo, hi]``, cell by cell, largest first; returns how many were written.

    A particle's world position is its co-moving position plus ``shift = D (t - t_ref)``, z wrapped into the layer.
    """
    n = 0
    for k in range(cells.shape[0]):
        ix, iy, iz = cells[k, 0], cells[k, 1], cells[k, 2]
        packed = packed_cell(ix, iy, iz)
        key = cell_key(seed_key, packed)
        id_base = np.int64(packed << U_RANK_BITS)
        e = 0.0
        for j in range(counts[k]):
            c = np.uint64(4 * j)
            e -= math.log(1.0 - stream_uniform(key, c))
            x = (ix + stream_uniform(key, c + np.uint64(1))) * cell_size + shift[0]
            y = (iy + stream_uniform(key, c + np.uint64(2))) * cell_size + shift[1]
            z = z_min + wrap_height((iz + stream_uniform(key, c + np.uint64(3))) * cell_z + shift[2], height)
            if x < lo[0] or x > hi[0] or y < lo[1] or y > hi[1] or z < lo[2] or z > hi[2]:
                continue
            d = -math.log(exp_lam_dmax + e / scale) / lam
            positions[n, 0] = x
            positions[n, 1] = y
            positions[n, 2] = z
            diameters[n] = min(max(d, d_floor), d_max)
            ids[n] = id_base + j
            n += 1
    return n


@njit(nogil=True, cache=True)
def _positions_from_ids_kernel(seed_key: np.uint64, ids: NDArray, cell_size: float, cell_z: float,
                               shifts: NDArray, z_min: float, height: float, positions: NDArray) -> None:
    """World positions (N, 3) of particles given by id, each with its own shift (N, 3) (same expressions as
    `_fill_kernel`)."""
    for n in range(ids.shape[0]):
        u = np.uint64(ids[n])
        j = u & _U_RANK_MASK
        packed = u >> U_RANK_BITS
        iz = np.int64(packed & _U_Z_MASK)
        iy = np.int64((packed >> _U_Z_BITS) & _U_XY_MASK) - XY_OFFSET
        ix = np.int64((packed >> (_U_Z_BITS + _U_XY_BITS)) & _U_XY_MASK) - XY_OFFSET
        key = cell_key(seed_key, packed)
        c = np.uint64(4) * j
        positions[n, 0] = (ix + stream_uniform(key, c + np.uint64(1))) * cell_size + shifts[n, 0]
        positions[n, 1] = (iy + stream_uniform(key, c + np.uint64(2))) * cell_size + shifts[n, 1]
        z_cell = (iz + stream_uniform(key, c + np.uint64(3))) * cell_z + shifts[n, 2]
        positions[n, 2] = z_min + wrap_height(z_cell, height)


# ------------------------------------------------------------------------------------------------------------- types
@dataclass(frozen=True, eq=False)
class Particles:
    """Particles of a field at one time.

    Attributes:
        positions: (N, 3) float64 world positions [m] at time ``t``.
        diameters: (N,) float64 [m], all >= ``min_diameter``.
        ids: (N,) int64 stable particle ids (sorted ascending in a query result).
        t: time [s] of ``positions``.
        min_diameter: smallest diameter [m] that was materialised; smaller particles of the medium are not listed
            (their extinction is `ParticleField.unresolved_extinction(min_diameter)`).
    """

    positions: F64
    diameters: F64
    ids: I64
    t: float
    min_diameter: float

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def select(self, mask: NDArray) -> Particles:
        """The particles where ``mask`` (N,) bool (or an index array) selects."""
        return Particles(self.positions[mask], self.diameters[mask], self.ids[mask], self.t, self.min_diameter)


def fall_velocity(terminal_velocity: float, wind: Sequence[float] = (0.0, 0.0)) -> tuple[float, float, float]:
    """Particle velocity ``D`` [m/s] (3,): horizontal ``wind`` (wx, wy) plus the fall ``(0, 0, -terminal_velocity)``."""
    v = float(terminal_velocity)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"terminal_velocity = {terminal_velocity!r} [m/s] is invalid: must be finite and >= 0")
    w = [float(x) for x in wind]
    if len(w) != 2 or not all(math.isfinite(x) for x in w):
        raise ValueError(f"wind = {wind!r} [m/s] is invalid: expected two finite numbers (wx, wy)")
    return (w[0], w[1], -v)


def unaligned_seed(seed: int) -> int:
    """An independent field seed with the same statistics, for the "unaligned" ablation.

    Derived deterministically (numpy ``SeedSequence(seed).spawn(1)``), in [0, 2^63), never equal to ``seed``.
    """
    s = _check_seed(seed)
    child = np.random.SeedSequence(s).spawn(1)[0]
    out = int(child.generate_state(1, np.uint64)[0]) >> 1
    return out if out != s else (out + 1) % (1 << 63)


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise ValueError(f"seed = {seed!r} is invalid: must be an integer in [0, 2^63)")
    return int(seed)


def _finite(name: str, value: float, unit: str) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} = {value!r} [{unit}] is invalid: must be finite")
    return v


def _vec3(name: str, value: NDArray | Sequence[float], unit: str = "m") -> F64:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} = {value!r} is invalid: expected 3 finite numbers (x, y, z) [{unit}]")
    return v


# ------------------------------------------------------------------------------------------------------------- field
@dataclass(frozen=True)
class ParticleField:
    """A deterministic snow or rain field (see the module docstring).

    Attributes:
        seed: field seed, integer in [0, 2^63).
        distribution: size distribution (`SnowSizeDistribution`, `RainSizeDistribution` or an
            `ExponentialSizeDistribution`); its number density sets the particle density.
        velocity: particle velocity D (3,) [m/s], e.g. ``fall_velocity(1.5, wind=(2, 0))`` = (2, 0, -1.5).
        t_ref: time [s] at which co-moving and world coordinates coincide.
        z_min, z_max: the vertical layer [m] (world z) that holds particles; periodic in z.
        cell_size: horizontal cell size [m]; the layer is cut into ``round((z_max - z_min) / cell_size)`` cells.
    """

    seed: int
    distribution: SizeDistribution
    velocity: tuple[float, float, float] = (0.0, 0.0, -1.5)
    t_ref: float = 0.0
    z_min: float = -2.0
    z_max: float = 30.0
    cell_size: float = 2.0
    _spec: ExponentialSizeDistribution = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "seed", _check_seed(self.seed))
        spec = getattr(self.distribution, "spectrum", None)
        if spec is None:
            raise ValueError(f"distribution = {self.distribution!r} is invalid: expected a size distribution "
                             "(SnowSizeDistribution, RainSizeDistribution or ExponentialSizeDistribution)")
        object.__setattr__(self, "_spec", spec())
        object.__setattr__(self, "velocity", tuple(float(x) for x in _vec3("velocity", self.velocity, "m/s")))
        object.__setattr__(self, "t_ref", _finite("t_ref", self.t_ref, "s"))
        z0, z1 = _finite("z_min", self.z_min, "m"), _finite("z_max", self.z_max, "m")
        if not z1 > z0:
            raise ValueError(f"z_max = {self.z_max!r} [m] is invalid: must exceed z_min = {self.z_min!r}")
        object.__setattr__(self, "z_min", z0)
        object.__setattr__(self, "z_max", z1)
        cs = _finite("cell_size", self.cell_size, "m")
        if not 0.05 <= cs <= 100.0:
            raise ValueError(f"cell_size = {self.cell_size!r} [m] is invalid: must be in [0.05, 100]")
        object.__setattr__(self, "cell_size", cs)
        if self.nz > MAX_Z_CELLS:
            raise ValueError(f"cell_size = {cs} [m] is invalid for a {z1 - z0} m layer: at most {MAX_Z_CELLS} cells "
                             f"over the layer, i.e. cell_size >= {(z1 - z0) / (MAX_Z_CELLS - 0.5):.3g} m")
        mean = self._spec.number_density() * self.cell_volume
        if mean + 12.0 * math.sqrt(mean) + 16.0 >= MAX_PER_CELL:
            cs_max = (0.8 * MAX_PER_CELL / self._spec.number_density()) ** (1.0 / 3.0)
            raise ValueError(f"cell_size = {cs} [m] is invalid for this density ({self._spec.number_density():.4g} "
                             f"per m³, {mean:.0f} per cell): ids hold < {MAX_PER_CELL} particles per cell; "
                             f"use cell_size <= {cs_max:.2f} m")

    # ------------------------------------------------------------------------------------------------ geometry
    @property
    def nz(self) -> int:
        """Number of cells over the layer height."""
        return layer_cells(self.z_max - self.z_min, self.cell_size)

    @property
    def cell_z(self) -> float:
        """Cell height [m] (the layer height divided by `nz`)."""
        return (self.z_max - self.z_min) / self.nz

    @property
    def cell_volume(self) -> float:
        """Volume of one cell [m³]."""
        return self.cell_size * self.cell_size * self.cell_z

    @property
    def velocity_array(self) -> F64:
        """D (3,) [m/s]."""
        return np.asarray(self.velocity, dtype=np.float64)

    @property
    def spectrum(self) -> ExponentialSizeDistribution:
        """The size spectrum N(D) of the field."""
        return self._spec

    # ------------------------------------------------------------------------------------------------ statistics
    def _floor(self, min_diameter: float) -> float:
        m = float(min_diameter)
        if not (math.isfinite(m) and m >= 0.0):
            raise ValueError(f"min_diameter = {min_diameter!r} [m] is invalid: must be finite and >= 0")
        return max(m, self._spec.d_min)

    def number_density(self, min_diameter: float = 0.0) -> float:
        """Particles per m³ inside the layer with diameter >= ``min_diameter`` [m]."""
        return self._spec.number_density(self._floor(min_diameter))

    def extinction(self) -> float:
        """Bulk extinction [1/m] of all particles (Q_ext = 2)."""
        return self._spec.extinction()

    def unresolved_extinction(self, min_diameter: float) -> float:
        """Extinction [1/m] of the particles smaller than ``min_diameter`` [m], which a query with that threshold
        leaves out: fold it into the bulk attenuation so the resolved + unresolved total stays `extinction`."""
        return self._spec.extinction(d_hi=self._floor(min_diameter))

    def expected_count(self, bounds_min: NDArray | Sequence[float], bounds_max: NDArray | Sequence[float],
                       min_diameter: float = 0.0) -> float:
        """Expected number of particles (D >= ``min_diameter``) in an axis-aligned box [m] (its part in the layer)."""
        lo, hi = _vec3("bounds_min", bounds_min), _vec3("bounds_max", bounds_max)
        z_lo, z_hi = max(lo[2], self.z_min), min(hi[2], self.z_max)
        volume = max(hi[0] - lo[0], 0.0) * max(hi[1] - lo[1], 0.0) * max(z_hi - z_lo, 0.0)
        return volume * self.number_density(min_diameter)

    # ------------------------------------------------------------------------------------------------ positions
    def _shift(self, t: float) -> F64:
        """``D (t - t_ref)`` (3,) [m]: world minus co-moving position at time ``t`` (before the z wrap)."""
        return self.velocity_array * (float(t) - self.t_ref)

    def positions_at(self, particles: Particles | NDArray, t: float) -> F64:
        """World positions (N, 3) [m] at time ``t`` [s] of particles of this field, given as `Particles` or ids (N,).

        Exactly the positions a query at ``t`` returns for the same ids.
        """
        t = _finite("t", t, "s")
        ids = particles.ids if isinstance(particles, Particles) else np.asarray(particles)
        return self._positions(ids, np.tile(self._shift(t), (len(ids), 1)))

    def positions_at_times(self, ids: NDArray, times: NDArray) -> F64:
        """World positions (N, 3) [m] of particles ``ids`` (N,), each at its own time ``times`` (N,) [s]: row ``n``
        equals ``positions_at(ids[n:n + 1], times[n])`` exactly."""
        ids, times = np.asarray(ids), np.asarray(times, dtype=np.float64)
        if times.shape != ids.shape or not np.isfinite(times).all():
            raise ValueError(f"times: expected {ids.shape} finite times [s], got {times.shape}")
        return self._positions(ids, self.velocity_array[None, :] * (times - self.t_ref)[:, None])

    def _positions(self, ids: NDArray, shifts: F64) -> F64:
        if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer) or (ids.size and ids.min() < 0):
            raise ValueError("ids must be a 1-D array of non-negative integers (ids of this field)")
        out = np.empty((ids.shape[0], 3))
        _positions_from_ids_kernel(field_seed_key(self.seed), np.ascontiguousarray(ids, dtype=np.int64), self.cell_size,
                                   self.cell_z, np.ascontiguousarray(shifts, dtype=np.float64), self.z_min,
                                   self.z_max - self.z_min, out)
        return out

    def cell_indices(self, points: NDArray, t: float) -> I64:
        """Co-moving cells (N, 3) int64 (ix, iy, iz) holding world ``points`` (N, 3) [m] at time ``t`` [s].

        z is taken periodically over the layer (points outside ``[z_min, z_max)`` map to the cell of their
        periodic image: clip them first if that is not wanted). Use with `materialize_cells`, e.g. for the cells
        along LiDAR beams.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tau = _finite("t", t, "s") - self.t_ref
        d = self.velocity_array
        out = np.empty((p.shape[0], 3), dtype=np.int64)
        out[:, 0] = np.floor((p[:, 0] - d[0] * tau) / self.cell_size)
        out[:, 1] = np.floor((p[:, 1] - d[1] * tau) / self.cell_size)
        zc = np.floor(np.mod(p[:, 2] - self.z_min - d[2] * tau, self.z_max - self.z_min) / self.cell_z)
        out[:, 2] = np.minimum(zc, self.nz - 1)
        return out

    # ------------------------------------------------------------------------------------------------ queries
    def _check_cells(self, cells: I64) -> None:
        if cells.size and (np.abs(cells[:, :2]).max() >= XY_OFFSET - 1):
            raise ValueError(f"query reaches co-moving cell |index| >= {XY_OFFSET - 1} "
                             f"(> {XY_OFFSET * self.cell_size / 1e3:.0f} km from the origin at t_ref): "
                             "set t_ref near the query times")
        if cells.size and (cells[:, 2].min() < 0 or cells[:, 2].max() >= self.nz):
            raise ValueError(f"cell z index out of range [0, {self.nz})")

    def materialize_cells(self, cells: NDArray, t: float, min_diameter: float = 0.0,
                          max_particles: int = DEFAULT_MAX_PARTICLES) -> Particles:
        """Every particle (D >= ``min_diameter`` [m]) of the co-moving ``cells`` (M, 3) int (ix, iy, iz) at time
        ``t`` [s]. Cells should be unique (a repeated cell returns its particles twice)."""
        c = np.ascontiguousarray(np.asarray(cells, dtype=np.int64).reshape(-1, 3))
        self._check_cells(c)
        everywhere = np.full(3, np.inf)
        return self._generate(c, _finite("t", t, "s"), self._floor(min_diameter), max_particles, -everywhere,
                              everywhere)

    def materialize(self, bounds_min: NDArray | Sequence[float], bounds_max: NDArray | Sequence[float], t: float,
                    min_diameter: float = 0.0, max_particles: int = DEFAULT_MAX_PARTICLES) -> Particles:
        """Every particle inside the closed world box ``[bounds_min, bounds_max]`` (3,) [m] at time ``t`` [s] with
        diameter >= ``min_diameter`` [m].

        The same particle has the same id and position whichever box asks; results are sorted by id.

        Raises:
            ValueError: bad box, or more than ``max_particles`` particles expected (raise ``min_diameter`` or
                shrink the box: a full 80 m LiDAR range of light snow holds ~10^8 flakes).
        """
        lo, hi = _vec3("bounds_min", bounds_min), _vec3("bounds_max", bounds_max)
        if np.any(hi < lo):
            raise ValueError(f"bounds_max = {hi.tolist()} is invalid: must be >= bounds_min = {lo.tolist()}")
        t = _finite("t", t, "s")
        m = self._floor(min_diameter)
        cells = self._cells_in_box(lo, hi, t)
        return self._generate(cells, t, m, max_particles, lo, hi)

    def _cells_in_box(self, lo: F64, hi: F64, t: float) -> I64:
        """Co-moving cells (M, 3) that can hold particles inside the world box at ``t``, sorted by id order."""
        tau = t - self.t_ref
        d = self.velocity_array
        eps = 1e-6
        z_lo, z_hi = max(lo[2], self.z_min), min(hi[2], self.z_max)
        if z_hi < z_lo:
            return np.zeros((0, 3), dtype=np.int64)
        ranges = []
        for k in range(2):
            a = math.floor((lo[k] - d[k] * tau - eps) / self.cell_size)
            b = math.floor((hi[k] - d[k] * tau + eps) / self.cell_size)
            ranges.append(np.arange(a, b + 1, dtype=np.int64))
        s_lo = z_lo - self.z_min - d[2] * tau - eps
        s_hi = z_hi - self.z_min - d[2] * tau + eps
        a, b = math.floor(s_lo / self.cell_z), math.floor(s_hi / self.cell_z)
        iz = np.arange(self.nz) if b - a + 1 >= self.nz else np.unique(np.mod(np.arange(a, b + 1), self.nz))
        n_cells = len(ranges[0]) * len(ranges[1]) * len(iz)
        if n_cells > 50_000_000:
            raise ValueError(f"query box spans {n_cells} cells (> 5e7): shrink the box or use a larger cell_size")
        gx, gy, gz = np.meshgrid(ranges[0], ranges[1], iz.astype(np.int64), indexing="ij")
        cells = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
        self._check_cells(cells)
        return cells

    def _generate(self, cells: I64, t: float, m: float, max_particles: int, lo: F64, hi: F64) -> Particles:
        """Particles (D >= m) of ``cells`` inside the closed box ``[lo, hi]`` at time ``t``."""
        spec = self._spec
        scale = spec.n0 * self.cell_volume / spec.lam  # expected count per cell above D is scale (e^-λD - e^-λb)
        exp_lam_dmax = math.exp(-spec.lam * spec.d_max)
        c_max = scale * (math.exp(-spec.lam * m) - exp_lam_dmax)
        expected = c_max * cells.shape[0]
        if expected > max_particles:
            raise ValueError(f"query expects {expected:.3g} particles in its cells (> max_particles = "
                             f"{max_particles}): raise min_diameter (now {m} m) or shrink the region")
        seed_key = field_seed_key(self.seed)
        counts = np.zeros(cells.shape[0], dtype=np.int64)
        if not _count_kernel(seed_key, cells, c_max, counts):
            raise ValueError(f"a cell exceeds {MAX_PER_CELL} particles: use a smaller cell_size")
        n_max = int(counts.sum())
        if n_max > max_particles:
            raise ValueError(f"query holds {n_max} particles in its cells (> max_particles = {max_particles})")
        positions = np.empty((n_max, 3))
        diameters = np.empty(n_max)
        ids = np.empty(n_max, dtype=np.int64)
        n = _fill_kernel(seed_key, cells, counts, self.cell_size, self.cell_z, spec.lam, exp_lam_dmax, scale, m,
                         spec.d_max, self._shift(t), self.z_min, self.z_max - self.z_min,
                         np.ascontiguousarray(lo, dtype=np.float64), np.ascontiguousarray(hi, dtype=np.float64),
                         positions, diameters, ids)
        positions, diameters, ids = positions[:n], diameters[:n], ids[:n]
        if n < 0.75 * n_max:  # copy so a large discarded tail is freed
            positions, diameters, ids = positions.copy(), diameters.copy(), ids.copy()
        return Particles(positions, diameters, ids, t, m)
