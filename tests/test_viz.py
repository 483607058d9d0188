"""Figure helpers: the BEV's axes are the LiDAR's own, and its forward arrow follows the LiDAR's mounting."""

from __future__ import annotations

import numpy as np
import pytest

from weatheralign.viz import ego_forward_in_lidar


def test_ego_forward_follows_the_lidar_mounting() -> None:
    assert ego_forward_in_lidar(np.eye(4)) == pytest.approx([1.0, 0.0])
    nuscenes_top = np.eye(4)  # real nuScenes LIDAR_TOP: x right, y forward (LiDAR y is the ego's x)
    nuscenes_top[:3, :3] = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    assert ego_forward_in_lidar(nuscenes_top) == pytest.approx([0.0, 1.0], abs=1e-12)
    yawed = np.eye(4)  # a LiDAR turned by +30 deg about z sees the ego's forward at -30 deg
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    yawed[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    assert ego_forward_in_lidar(yawed) == pytest.approx([c, -s])
