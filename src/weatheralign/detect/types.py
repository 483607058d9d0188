"""The contracts between the detector's data pipeline, model and evaluation: class and attribute vocabularies, a
batch, and one sample's detections. Every geometric quantity is in the keyframe's LiDAR frame (the sensor frame of
LIDAR_TOP at the keyframe's timestamp), whatever way the LiDAR is mounted.

Box rows are ``(x, y, z, w, l, h, yaw, vx, vy)``: centre [m], nuScenes size order width, length, height [m], yaw
[rad] of the box's length axis about the LiDAR z axis measured from the LiDAR x axis, velocity [m/s] in the LiDAR
x/y axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from numpy.typing import NDArray

#: the ten nuScenes detection classes, in nuscenes-devkit's order (``DETECTION_NAMES``)
DETECTION_CLASSES: tuple[str, ...] = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
                                      "motorcycle", "bicycle", "traffic_cone", "barrier")
#: the eight nuScenes attributes, in nuscenes-devkit's order (``ATTRIBUTE_NAMES``); index -1 means none
ATTRIBUTES: tuple[str, ...] = ("pedestrian.moving", "pedestrian.sitting_lying_down", "pedestrian.standing",
                               "cycle.with_rider", "cycle.without_rider", "vehicle.moving", "vehicle.parked",
                               "vehicle.stopped")
BOX_DIM = 9
POINT_DIM = 6  # batch index, x, y, z [m], intensity / 255, time lag of its sweep behind the keyframe [s] (>= 0)


@dataclass
class DetectionBatch:
    """B samples, collated.

    Attributes:
        points: (P, 6) float32 ``batch index, x, y, z, intensity / 255, time lag [s]`` of all samples' aggregated
            sweeps (ego-motion compensated into the keyframe LiDAR frame).
        images: (B, C, 3, H, W) float32 RGB in [0, 1] of the C cameras, resized (and cropped).
        features_s8, features_s16: (B, C, 40, H/8, W/8) and (B, C, 112, H/16, W/16) float32 frozen image features
            of ``images`` (`weatheralign.detect.image_features`), what the camera branch reads.
        intrinsics: (B, C, 3, 3) float32 pinhole matrices of ``images`` (after resize / crop) [px].
        cam_to_lidar: (B, C, 4, 4) float32 camera frame (at the camera's own timestamp) -> keyframe LiDAR frame.
        boxes: B tensors (M_b, 9) float32 ground-truth boxes (see the module docstring).
        labels: B tensors (M_b,) int64 indices into `DETECTION_CLASSES`.
        attributes: B tensors (M_b,) int64 indices into `ATTRIBUTES` (-1: none).
        tokens: B sample tokens.
        T_global_lidar: (B, 4, 4) float64 keyframe LiDAR frame -> global frame (for evaluation).
    """

    points: torch.Tensor
    images: torch.Tensor
    features_s8: torch.Tensor
    features_s16: torch.Tensor
    intrinsics: torch.Tensor
    cam_to_lidar: torch.Tensor
    boxes: list[torch.Tensor]
    labels: list[torch.Tensor]
    attributes: list[torch.Tensor]
    tokens: list[str]
    T_global_lidar: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 4, 4, dtype=torch.float64))

    @property
    def batch_size(self) -> int:
        return len(self.tokens)

    def to(self, device: torch.device | str) -> DetectionBatch:
        """The same batch with every tensor on ``device`` (``T_global_lidar`` stays on the CPU)."""
        return replace(self, points=self.points.to(device), images=self.images.to(device),
                       features_s8=self.features_s8.to(device), features_s16=self.features_s16.to(device),
                       intrinsics=self.intrinsics.to(device), cam_to_lidar=self.cam_to_lidar.to(device),
                       boxes=[b.to(device) for b in self.boxes], labels=[x.to(device) for x in self.labels],
                       attributes=[a.to(device) for a in self.attributes])


@dataclass(frozen=True)
class SampleDetections:
    """One sample's detections in its keyframe LiDAR frame.

    Attributes:
        boxes: (K, 9) float64 box rows; scores: (K,) float64 in [0, 1]; labels: (K,) int64 into `DETECTION_CLASSES`;
        attributes: (K,) int64 into `ATTRIBUTES` (-1: none).
    """

    token: str
    boxes: NDArray[np.float64]
    scores: NDArray[np.float64]
    labels: NDArray[np.int64]
    attributes: NDArray[np.int64]


__all__ = ["ATTRIBUTES", "BOX_DIM", "DETECTION_CLASSES", "DetectionBatch", "POINT_DIM", "SampleDetections"]
