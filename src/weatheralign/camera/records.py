"""Typed records passed to the numba kernels of the particle splatting (`weatheralign.camera.splat`).

Each record is a `typing.NamedTuple` of arrays and scalars: numba compiles them in nopython mode as typed tuples
(``cache=True`` works because the classes are importable), so a kernel takes a handful of named records instead of
dozens of positional arrays (the model: `weatheralign.lidar.particles.records`). Lengths: N particles; images are
H x W pixels, pixel (u, v) is column u, row v at its centre.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]


class PinholeView(NamedTuple):
    """A camera at one instant."""

    R: F64  # (3, 3) global -> camera rotation (OpenCV axes)
    tr: F64  # (3,) global -> camera translation [m]
    K: F64  # (3, 3) intrinsics [px] (a skew K[0, 1] allowed)
    width: int  # [px]
    height: int  # [px]


class FootprintRules(NamedTuple):
    """How a particle's footprint is projected and bounded."""

    near_clip: float  # particles at a smaller ray length, or with z < near_clip / 4, are skipped [m]
    cap_var: float  # largest variance of a footprint axis [px²]: (max_footprint_px / 3)²
    dilation: float  # EWA low-pass dilation added to every projected covariance [px²]
    keep_area: bool  # the opacity keeps the energy of the undilated footprint (`ParticleAppearance`)
    centroid_q: float  # smallest Mahalanobis² bound of the centroid window


class Gaussians(NamedTuple):
    """The particles as 3-D Gaussians (global frame)."""

    pos: F64  # (N, 3) centres at the middle of the exposure [m]
    cov: F64  # (N, 3, 3) covariances [m²]
    opacity: F64  # (N,) opacity of the still particle
    streak: F64  # (N, 3) motion relative to the camera during the exposure [m]


class Footprints(NamedTuple):
    """Each particle's projected footprint: output of `splat._prepare_kernel`, input of `splat._splat_kernel`."""

    u0: F64  # (N,) projected centre: column [px]
    v0: F64  # (N,) row [px]
    ca: F64  # (N,) conic of the streaked, dilated and capped Σ'2D⁻¹: q = ca dx² + 2 cb dx dy + cc dy² [1/px²]
    cb: F64  # (N,)
    cc: F64  # (N,)
    opac: F64  # (N,) opacity after the streak (and the dilation with keep_area); nan where near-clipped
    qmax: F64  # (N,) Mahalanobis² at which alpha falls to 1/255
    qwin: F64  # (N,) Mahalanobis² bound of the centroid window: max(qmax, centroid_q)
    ell: F64  # (N,) ray length from the camera centre [m]
    rx: F64  # (N,) half extent of the centroid window along u [px]
    ry: F64  # (N,) along v [px]
    status: NDArray[np.int8]  # (N,) ok, near-clipped, too faint or off screen (`splat._OK` ...)
    capped: NDArray[np.bool_]  # (N,) the footprint was shrunk to cap_var
    in_frame: NDArray[np.bool_]  # (N,) the whole centroid window lies inside the image


class Canvas(NamedTuple):
    """The image the particles are composited into, front to back."""

    rng: F32  # (H, W) the scene's ray length [m], inf = sky
    bg: F32  # (H, W, 3) linear RGB background
    out: F32  # (H, W, 3) the running composite C + T bg (starts as a copy of bg)
    acc_t: F32  # (H, W) transmittance T left after the particles composited so far


class FootprintSums(NamedTuple):
    """What the compositing saw of each particle (pixels of its centroid window in front of the scene)."""

    sum_a: F64  # (N,) sum of alpha >= 1/255 [px²]
    sum_w: F64  # (N,) sum of the centroid weights alpha (any size)
    sum_wu: F64  # (N,) sum of alpha u
    sum_wv: F64  # (N,) sum of alpha v
    max_a: F64  # (N,) largest alpha >= 1/255
    occluded: NDArray[np.bool_]  # (N,) some pixel of the window lies behind the scene
