"""The float32 <-> binary16 conversions (weatheralign.data.float16) against numpy's own, bit for bit."""

from __future__ import annotations

import numpy as np

from weatheralign.data.float16 import from_float16, to_float16


def test_every_half_widens_to_numpys_float32_bits() -> None:
    halves = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16).reshape(256, 256)
    with np.errstate(invalid="ignore"):
        expected = halves.astype(np.float32)
    got = from_float16(halves)
    assert got.dtype == np.float32 and got.shape == (256, 256)
    assert np.array_equal(got.view(np.uint32), expected.view(np.uint32))


def test_narrowing_matches_numpy_and_round_trips() -> None:
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(0.0, 1e3, 100_000), rng.uniform(-7e-5, 7e-5, 10_000),
                             [np.inf, -np.inf, np.nan, 0.0, -0.0, 65504.0, 65520.0, 1e-8]]).astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        expected = values.astype(np.float16)
    narrowed = to_float16(values)
    assert np.array_equal(narrowed.view(np.uint16), expected.view(np.uint16))
    assert np.array_equal(from_float16(narrowed), narrowed.astype(np.float32), equal_nan=True)
