"""The synthetic multi-sensor world: procedural scenes, ray-cast LiDAR and cameras, nuScenes-format output."""
