"""Alignment metrics between the sensors' observations of the shared weather."""

from weatheralign.metrics.reprojection import CameraParticles, ReprojectionResult, lidar_particles, reprojection_check

__all__ = ["CameraParticles", "ReprojectionResult", "lidar_particles", "reprojection_check"]
