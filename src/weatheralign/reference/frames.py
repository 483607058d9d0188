"""One reference frame with its camera's ray lengths: what the camera checks of `calibrate_fog` and `verify` read."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from weatheralign.camera.depth import camera_range_map
from weatheralign.data.errors import DataFormatError
from weatheralign.data.frame import Frame
from weatheralign.data.stf import CAMERA_CHANNEL
from weatheralign.reference.layout import ReferenceDataset


def reference_frame(ds: ReferenceDataset, sample_id: str) -> tuple[Frame, NDArray[np.uint8], NDArray[np.float32]]:
    """(frame, image (H, W, 3) uint8 sRGB, ray length (H, W) float32 [m], inf = sky) of one reference frame's
    stereo-left camera: the exact range map where the reference has one (synthetic), else dense depth from the
    frame's own scan (real Seeing Through Fog).

    Raises:
        DataFormatError: the frame has no stereo-left camera.
    """
    frame = ds.load_frame(sample_id)
    view = frame.cameras.get(CAMERA_CHANNEL)
    if view is None:
        raise DataFormatError(f"reference {ds.root}: frame {sample_id} has no {CAMERA_CHANNEL} image "
                              f"(expected {ds.camera_folder}/{sample_id}.png)")
    image = view.load_image()
    return frame, image, camera_range_map(view, frame.lidar, image)


__all__ = ["reference_frame"]
