"""A clear reading's rounding interval: what an integer intensity stood for before the sensor rounded it.

A sensor that reports integer intensities (nuScenes-format bytes, the synthetic world, the reference's detector)
reports ``q`` for every measured value in ``[q - ½, q + ½)`` that passed its floor, i.e. for values in
``[max(q - ½, floor), q + ½)``: a reading of 1 at a floor of 1 stood for a value in ``[1, 1.5)``. A weather that
weakens it by a factor ``k < 1`` pushes the true value below the floor only when ``k x < floor``; taking the reading
as exactly ``q`` instead loses every reading at the floor under any attenuation (`docs/physics.md` section 3.4). The
lost tests of the fog (`weatheralign.lidar.fog`), the particles (`weatheralign.lidar.particles`) and the wet ground
(`weatheralign.ground.wet`) therefore attenuate `clear_readings`: each rounded reading spread uniformly over its
rounding interval, at the position of a uniform draw from the beam's own detector-noise stream (its third draw,
after `weatheralign.medium.field.normal_pair`'s two), so the same scan gives the same bytes.

Which readings were rounded is read from the data (`rounded_readings`): a scan is integer-quantised when its
readings are whole numbers on the 0..255 scale; after a weather edit (the wet ground's spread readings) the
readings it did not change still are, and only those are spread again.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from weatheralign.data.frame import LidarScan
from weatheralign.lidar.beams import point_noise_keys
from weatheralign.medium.field import splitmix64_py, stream_uniform

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

QUANTUM = 1.0
"""The rounding quantum of an integer-quantised scan on the 0..255 scale."""

QUANTISED_MIN_SHARE = 0.1
"""A scan is integer-quantised when at least this share of its readings strictly between 0 and 255 are whole numbers
on the 0..255 scale: a sensor's integers all are, and a ground edit leaves the readings off the wet or snowy ground
whole; unrounded float32 readings are whole about once in 10^5. (The shared Seeing Through Fog scan: 45 % whole, all
of them below 40, its floor 24; finer steps above.)"""

WHOLE_TOLERANCE = 1e-4
"""A reading on the 0..255 scale within this of an integer is a whole one: a 0..1 scan's ``q / 255`` stored as
float32 comes back as ``q`` within 2e-5."""

DITHER_COUNTER = 2
"""The draw of a beam's detector-noise stream (`stream_uniform` counter) that places its clear reading in the
rounding interval: `normal_pair` takes draws 0 and 1 (intensity and range noise)."""


def rounded_readings(intensity_255: ArrayLike) -> Mask:
    """(N,) which of a scan's clear readings (N,) on the 0..255 scale the sensor rounded to integers: the whole numbers
    in (0, 255) of an integer-quantised scan (at least `QUANTISED_MIN_SHARE` of its readings in (0, 255) whole); all
    False otherwise (unrounded or finer-quantised readings, an empty scan)."""
    values = np.asarray(intensity_255, dtype=np.float64).ravel()
    inside = (values > 0.0) & (values < 255.0)
    whole = inside & (np.abs(values - np.rint(values)) <= WHOLE_TOLERANCE)
    n_inside = int(np.count_nonzero(inside))
    if n_inside == 0 or np.count_nonzero(whole) < QUANTISED_MIN_SHARE * n_inside:
        return np.zeros(len(values), dtype=bool)
    return whole


@njit(cache=True, nogil=True)
def _uniforms_kernel(keys, counter, out):  # pragma: no cover
    for n in range(len(keys)):
        out[n] = stream_uniform(keys[n], counter)


def reading_uniforms(noise_keys: ArrayLike, counter: int = DITHER_COUNTER) -> F64:
    """(N,) uniform in [0, 1) per beam: the ``counter``-th draw (default `DITHER_COUNTER`) of each beam's
    detector-noise stream ``noise_keys`` (N,) (`weatheralign.lidar.beams.detector_noise_keys`)."""
    keys = np.ascontiguousarray(noise_keys, dtype=np.uint64).ravel()
    out = np.empty(len(keys))
    _uniforms_kernel(keys, np.uint64(counter), out)
    return out


def reading_uniforms_naive(noise_keys: ArrayLike, counter: int = DITHER_COUNTER) -> F64:
    """`reading_uniforms` in Python integers: draw ``c`` of stream ``k`` is the top 53 bits of SplitMix64's finaliser
    (`splitmix64_py`) of ``k + (c + 1) γ``, γ = 0x9E3779B97F4A7C15 (the golden-ratio increment): the oracle of its
    kernel."""
    gamma = 0x9E3779B97F4A7C15
    out = [(splitmix64_py(int(k) + (counter + 1) * gamma) >> 11) * 2.0 ** -53
           for k in np.asarray(noise_keys, dtype=np.uint64).ravel()]
    return np.asarray(out, dtype=np.float64)


def rounding_interval(i0_255: ArrayLike, noise_floor: ArrayLike | None) -> tuple[F64, F64]:
    """``(lo, hi)`` (N,) each: the values a whole reading ``i0_255`` (N,) (0..255 scale; ``q`` its nearest integer)
    stood for, ``[max(q - ½, floor, 0), q + ½)`` (``floor`` the detector's, a scalar or (N,) the floor at each
    reading's range; None: none); empty (``hi <= lo``) for a reading under the floor, which the sensor reported
    nevertheless."""
    q = np.rint(np.asarray(i0_255, dtype=np.float64))
    lo = np.maximum(q - 0.5 * QUANTUM, 0.0 if noise_floor is None else np.maximum(np.asarray(noise_floor, float), 0.0))
    return lo, q + 0.5 * QUANTUM


def clear_readings(i0_255: ArrayLike, rounded: ArrayLike, noise_floor: ArrayLike | None, uniforms: ArrayLike) -> F64:
    """(N,) the value each clear reading ``i0_255`` (N,) (0..255 scale) stood for before rounding: for a ``rounded``
    (N,) one, ``lo + u (hi - lo)`` on its `rounding_interval` with ``u`` (N,) in [0, 1) (`reading_uniforms` of its
    beam); the reading itself where it was not rounded or its interval is empty."""
    i0 = np.asarray(i0_255, dtype=np.float64)
    lo, hi = rounding_interval(i0, noise_floor)
    spread = np.asarray(rounded, dtype=bool) & (hi > lo)
    return np.where(spread, lo + np.asarray(uniforms, dtype=np.float64) * (hi - lo), i0)


class ReadingSpread(NamedTuple):
    """Which of a scan's N readings the sensor rounded, and where in its rounding interval each lies."""

    rounded: Mask  # (N,) `rounded_readings`
    uniforms: F64  # (N,) in [0, 1): `reading_uniforms` of each point's beam (0 where not rounded)


def scan_reading_spread(scan: LidarScan, keys: NDArray[np.uint64] | None = None) -> ReadingSpread | None:
    """``scan``'s `ReadingSpread`, its uniforms drawn from each point's beam stream (``keys`` (N,), the scan's
    `point_noise_keys` where the caller has them: the stream of its detector noise), or None where the sensor rounded
    none of its readings."""
    rounded = rounded_readings(scan.intensity_255())
    if not rounded.any():
        return None
    uniforms = np.zeros(len(rounded))
    uniforms[rounded] = reading_uniforms((point_noise_keys(scan) if keys is None else keys)[rounded])
    return ReadingSpread(rounded, uniforms)


def scan_clear_readings(scan: LidarScan, noise_floor: ArrayLike | None, keys: NDArray[np.uint64] | None = None
                        ) -> F64 | None:
    """(N,) `clear_readings` of ``scan``'s points on the 0..255 scale (`scan_reading_spread`, ``keys`` its
    `point_noise_keys` where known), or None where the sensor rounded none of them."""
    spread = scan_reading_spread(scan, keys)
    if spread is None:
        return None
    return clear_readings(scan.intensity_255(), spread.rounded, noise_floor, spread.uniforms)


def on_scale(clear_255: ArrayLike, i0: ArrayLike, intensity_max: float) -> F64:
    """(N,) clear values ``clear_255`` (0..255) on the scale ``0..intensity_max`` of the readings ``i0`` (N,) they
    stand for: ``i0`` itself, bit for bit, where the reading was not spread."""
    own = np.asarray(i0, dtype=np.float64)
    x = np.asarray(clear_255, dtype=np.float64)
    as_255 = (np.asarray(i0, dtype=np.float32) * np.float32(255.0 / intensity_max)).astype(np.float64)
    return np.where(x != as_255, x * (intensity_max / 255.0), own)


def attenuated_reading(reading: ArrayLike, i0: ArrayLike, clear: ArrayLike, transmission: ArrayLike) -> F64:
    """The weather's reading (N,) of a clear reading ``clear`` (N,) instead of ``i0`` (N,): ``reading`` (N,), the
    reading of ``i0`` through ``transmission`` (N,) (the share of the clear echo that comes back), plus the
    transmitted difference ``(clear - i0) · transmission``. Exactly ``reading`` where ``clear == i0``."""
    return (np.asarray(reading, dtype=np.float64)
            + (np.asarray(clear, dtype=np.float64) - np.asarray(i0, dtype=np.float64))
            * np.asarray(transmission, dtype=np.float64))


__all__ = ["DITHER_COUNTER", "QUANTISED_MIN_SHARE", "QUANTUM", "WHOLE_TOLERANCE", "ReadingSpread", "attenuated_reading",
           "clear_readings", "on_scale", "reading_uniforms", "reading_uniforms_naive", "rounded_readings",
           "rounding_interval", "scan_clear_readings", "scan_reading_spread"]
