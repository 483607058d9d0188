"""float32 <-> IEEE binary16 conversions with numpy's exact results at a fraction of its cost (numpy converts
element by element in C without the hardware's help): the world stores its exact range maps as float16, and every
stage that reads one widens it back."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray


@njit(nogil=True, cache=True)
def _half_bits(bits: NDArray, out: NDArray) -> None:
    """IEEE binary16 bit patterns (round to nearest, ties to even; numpy's own conversion, step by step) of the
    float32 bit patterns ``bits`` (N,) uint32."""
    for i in range(len(bits)):
        f = np.uint32(bits[i])
        sign = np.uint16((f & np.uint32(0x80000000)) >> np.uint32(16))
        exp = f & np.uint32(0x7F800000)
        if exp >= np.uint32(0x47800000):  # inf, nan or too large: inf (nan keeps a payload bit)
            sig = f & np.uint32(0x007FFFFF)
            if exp == np.uint32(0x7F800000) and sig != 0:
                h = np.uint16(0x7C00) + np.uint16(sig >> np.uint32(13))
                out[i] = sign + (h + np.uint16(1) if h == np.uint16(0x7C00) else h)
            else:
                out[i] = sign + np.uint16(0x7C00)
        elif exp <= np.uint32(0x38000000):  # subnormal or zero
            if exp < np.uint32(0x33000000):
                out[i] = sign
            else:
                sig = (np.uint32(0x00800000) + (f & np.uint32(0x007FFFFF))) >> (np.uint32(113) - (exp >> np.uint32(23)))
                if (sig & np.uint32(0x3FFF)) != np.uint32(0x1000) or (f & np.uint32(0x7FF)) != 0:
                    sig += np.uint32(0x1000)  # (the shift above may drop up to 11 bits: they count for the tie)
                out[i] = sign + np.uint16(sig >> np.uint32(13))
        else:
            sig = f & np.uint32(0x007FFFFF)
            if (sig & np.uint32(0x3FFF)) != np.uint32(0x1000):
                sig += np.uint32(0x1000)
            out[i] = sign + np.uint16((sig >> np.uint32(13)) + ((exp - np.uint32(0x38000000)) >> np.uint32(13)))


def to_float16(values: NDArray[np.float32]) -> NDArray[np.float16]:
    """``values.astype(np.float16)`` (the same bits) at a fraction of numpy's cost."""
    values = np.ascontiguousarray(values, np.float32)
    out = np.empty(values.shape, np.uint16)
    _half_bits(values.reshape(-1).view(np.uint32), out.reshape(-1))
    return out.view(np.float16)


@njit(nogil=True, cache=True)
def _float_bits(halves: NDArray, out: NDArray) -> None:
    """float32 bit patterns (exact: every binary16 value is a float32) of the binary16 bit patterns ``halves`` (N,)
    uint16, into ``out`` (N,) uint32."""
    for i in range(len(halves)):
        h = np.uint32(halves[i])
        sign = (h & np.uint32(0x8000)) << np.uint32(16)
        exp = (h >> np.uint32(10)) & np.uint32(0x1F)
        sig = h & np.uint32(0x3FF)
        if exp == np.uint32(0x1F):  # inf or nan (payload kept)
            out[i] = sign | np.uint32(0x7F800000) | (sig << np.uint32(13))
        elif exp != 0:
            out[i] = sign | ((exp + np.uint32(112)) << np.uint32(23)) | (sig << np.uint32(13))
        elif sig == 0:
            out[i] = sign
        else:  # subnormal: normalise the significand
            e = np.uint32(113)
            while (sig & np.uint32(0x400)) == 0:
                sig <<= np.uint32(1)
                e -= np.uint32(1)
            out[i] = sign | (e << np.uint32(23)) | ((sig & np.uint32(0x3FF)) << np.uint32(13))


def from_float16(values: NDArray[np.float16]) -> NDArray[np.float32]:
    """``values.astype(np.float32)`` (the same bits) at a fraction of numpy's cost."""
    values = np.ascontiguousarray(values, np.float16)
    out = np.empty(values.shape, np.uint32)
    _float_bits(values.reshape(-1).view(np.uint16), out.reshape(-1))
    return out.view(np.float32)
