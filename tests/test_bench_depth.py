"""The depth benchmark's own measures (`benchmarks.bench_depth`) on images whose answer is known."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_depth import DepthSums, SkySums, depth_edges, halo_widths, seam_pairs


def test_halo_width_is_the_extent_of_the_difference_beside_an_edge():
    t = np.full((60, 80), 0.8, np.float32)
    t[:, 40:] = 0.1  # a transmission edge between columns 39 and 40
    exact = np.full((60, 80, 3), 100, np.uint8)
    est = exact.copy()
    est[:, 40:47] += 30  # the near surface's fog bled 7 px into the far side
    est[:, 70:] += 30  # a difference not connected to the edge: no halo
    w = halo_widths(est, exact, t, codes=8)
    assert len(w) == 2 * 60  # both pixels of each row's jump are edge pixels
    # columns 40..46 differ: 6 px beyond the far side's edge pixel (column 40), none beside the near one (39)
    assert sorted(set(w.tolist())) == [0.0, 6.0] and np.sum(w == 6.0) == 60
    assert np.all(halo_widths(exact, exact, t, codes=8) == 0)


def test_depth_and_sky_sums():
    g = np.array([[10.0, 20.0, np.inf, np.inf]], np.float32)
    e = np.array([[11.0, 20.0, np.inf, 30.0]], np.float32)
    d = DepthSums()
    d.add(e, g, np.ones(g.shape, bool))
    r = d.result()
    assert r["pixels"] == 2 and abs(r["abs_rel"] - 0.05) < 1e-9 and r["delta_1.25"] == 1.0
    s = SkySums()
    s.add(e, g, near_m=60.0)
    r = s.result()
    assert r["precision"] == 1.0 and r["recall"] == 0.5 and r["exact_sky_given_finite"] == 0.5
    assert depth_edges(g)[0].tolist() == [True, True, True, False]


def test_seam_pairs_map_a_direction_to_the_same_direction():
    from dataclasses import dataclass

    @dataclass
    class View:
        K: np.ndarray
        width: int
        height: int
        T_global_cam: np.ndarray

    K = np.array([[100.0, 0, 100], [0, 100.0, 50], [0, 0, 1]])
    a = View(K, 200, 100, np.eye(4))
    yaw = np.radians(30.0)
    R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    T = np.eye(4)
    T[:3, :3] = R
    b = View(K, 200, 100, T)
    va, ua, vb, ub = seam_pairs(a, b, stride=2)
    assert len(va) > 100
    da = np.linalg.solve(K, np.stack([ua, va, np.ones(len(ua))]).astype(float))
    db = R @ np.linalg.solve(K, np.stack([ub, vb, np.ones(len(ub))]).astype(float))
    cos = (da * db).sum(0) / np.linalg.norm(da, axis=0) / np.linalg.norm(db, axis=0)
    assert np.all(cos > np.cos(np.radians(1.0)))
