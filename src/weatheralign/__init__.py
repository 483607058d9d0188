"""weatheralign: aligned weather simulation for LiDAR + multi-camera driving data."""

__version__ = "0.1.0"
