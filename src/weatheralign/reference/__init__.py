"""The fog reference of ReDAM: a Seeing Through Fog root (real, or the embedded synthetic one) read per fog level.

- `layout`: `open_reference` / `ReferenceDataset` (split files, frames as `weatheralign.data.frame.Frame`, exact range
  maps where the reference has them), `check_reference`.
- `synthetic`: the embedded synthetic reference (other scenes than the world, HDL-64-like LiDAR, stereo-left camera,
  hidden fog levels in ``<paths.data>/reference/sealed_truth.json``).
- `lidar_exact`, `camera_exact`: its exact fog processes (full pulse integral per beam; per-pixel integration).

`configured_reference(params)` opens the reference that ``params.reference`` names.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from weatheralign.data.errors import DataFormatError
from weatheralign.reference.layout import (LEVELS, ReferenceDataset, ReferenceSplit, SplitSummary, check_reference,
                                           open_reference, split_files_of)

if TYPE_CHECKING:
    from weatheralign.config import Params

__all__ = ["LEVELS", "ReferenceDataset", "ReferenceSplit", "SplitSummary", "check_reference", "configured_reference",
           "open_reference", "reference_root", "split_files_of"]


def reference_root(params: "Params") -> Path:
    """The reference root of ``params.reference``: ``stf_root`` for ``source: stf``, else the synthetic reference
    under ``<paths.data>/reference/synthetic``."""
    cfg = params.reference
    if cfg.source == "stf":
        assert cfg.stf_root is not None  # checked by the config
        return Path(cfg.stf_root)
    from weatheralign.reference.synthetic import synthetic_root

    return synthetic_root(params.paths.data)


def configured_reference(params: "Params") -> ReferenceDataset:
    """`open_reference` of the reference ``params.reference`` describes (root, split files, declared scale).

    Raises:
        DataFormatError: the synthetic reference has not been rendered yet, or see `open_reference`.
    """
    cfg = params.reference
    root = reference_root(params)
    if cfg.source == "synthetic" and not root.is_dir():
        raise DataFormatError(f"reference root {root} does not exist: render the synthetic reference first "
                              f"(python -m flows.reference)")
    return open_reference(root, split_files_of(cfg.split_files), cfg.intensity_max)
