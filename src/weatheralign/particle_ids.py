"""How a particle field's ids pack (cell, rank) and how many cells its layer may hold
(`weatheralign.medium.field.ParticleField`): plain numbers without dependencies, so that params validation
(`weatheralign.config`) checks a cell size against the layer without importing the medium.

An id packs 20 bits each for the co-moving cell's x and y index (|ix|, |iy| < `XY_OFFSET`), `Z_BITS` for its z
index over the layer (at most `MAX_Z_CELLS` cells) and `RANK_BITS` for the particle's rank in its cell (fewer than
`MAX_PER_CELL` particles per cell).
"""

from __future__ import annotations

XY_BITS = 20
Z_BITS = 7
RANK_BITS = 16
XY_OFFSET = 1 << (XY_BITS - 1)
MAX_Z_CELLS = 1 << Z_BITS
MAX_PER_CELL = 1 << RANK_BITS


def layer_cells(height_m: float, cell_size_m: float) -> int:
    """Cells a field of ``cell_size_m`` [m] cuts a layer ``height_m`` [m] high into (in z): at least one; at most
    `MAX_Z_CELLS` fit an id."""
    return max(1, round(height_m / cell_size_m))


__all__ = ["MAX_PER_CELL", "MAX_Z_CELLS", "RANK_BITS", "XY_BITS", "XY_OFFSET", "Z_BITS", "layer_cells"]
