"""A small BEVFusion-style LiDAR-camera detector in plain PyTorch (trainable on CPU), its nuScenes-format data
pipeline and the nuScenes detection metrics (see docs/architecture.md)."""
