"""Readers and writers of sensor data (nuScenes format, Seeing Through Fog, KITTI) and the `Frame` type."""
