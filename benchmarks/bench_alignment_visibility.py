"""Can a camera show where the LiDAR's snow / rain particles are? The measurement behind verify's snow result.

verify's "unaligned" particle weather is the field's independent twin at the same rate: only the positions differ, so
a fused feature can tell aligned from unaligned only if the particles a LiDAR beam hits are visible in the image at
that beam's pixel. This benchmark measures that on the reference's clear frames through the fast simulator (the
`verify` stage's simulated frames, at the tuned rates of ``simulate.precipitation_rates``):

- the particle echoes (isolated returns within 20 m, `weatheralign.lidar.clutter.isolated_mask`) inside the camera's
  view per frame, their camera depth, and the projected diameter ``f D / z`` [px] of the particle behind each echo;
- the small-scale image contrast at their pixels (luma minus its Gaussian blur of σ = 3 px, positive part, maximum
  over 3 x 3 px), in the aligned and the unaligned image, for all echoes and for those nearer than 4 m, against random
  pixels.

Run from a repository whose pipeline has run (the reference and both calibrations):
``.venv/bin/python -m benchmarks.bench_alignment_visibility [--frames 8] [--conditions snow rain]``; results go to
``reports/benchmarks/alignment_visibility.json`` (one entry per condition).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter, maximum_filter

from benchmarks.common import REPO, merge_entries

OUT = REPO / "reports" / "benchmarks" / "alignment_visibility.json"
NEAR_M = 4.0
CONTRAST_SIGMA_PX = 3.0


def _contrast(image: np.ndarray) -> np.ndarray:
    """(H, W) small-scale contrast of an sRGB uint8 image: luma minus its blur, positive part, 3 x 3 maximum."""
    luma = image.astype(np.float64).mean(axis=2) / 255.0
    return maximum_filter(np.maximum(luma - gaussian_filter(luma, CONTRAST_SIGMA_PX), 0.0), 3)


def measure(condition_name: str, frames: int) -> dict[str, Any]:
    """The figures of the module docstring for one particle condition over the first ``frames`` clear frames."""
    from flows.verify import severity_of
    from weatheralign.camera.fog import estimate_airlight
    from weatheralign.conditions import CONDITIONS
    from weatheralign.config import load_params
    from weatheralign.data.stf import CAMERA_CHANNEL
    from weatheralign.lidar.clutter import isolated_mask
    from weatheralign.reference import configured_reference, reference_lidar_model
    from weatheralign.reference.frames import reference_frame
    from weatheralign.sensors import CameraModel, SensorRig
    from weatheralign.simulate.observe import ObserveOptions, observe
    from weatheralign.verify.frames import camera_from_lidar, scene_media

    params = load_params(REPO / "params.yaml")
    ds = configured_reference(params)
    lidar = reference_lidar_model(params, ds)
    severity, _ = severity_of(params)
    condition = CONDITIONS[condition_name]
    step = 2.0 * np.pi / lidar.columns_per_ring
    rng = np.random.default_rng(0)
    in_view, depth, size_px, near_count = [], [], [], []
    at = {True: [], False: []}
    at_near = {True: [], False: []}
    at_random = []
    t0 = time.process_time()
    for sid in ds.ids("clear")[:frames]:
        frame, image, range_map = reference_frame(ds, sid)
        view = frame.cameras[CAMERA_CHANNEL]
        camera = CameraModel(CAMERA_CHANNEL, tuple(tuple(float(v) for v in row) for row in view.K), view.width,
                             view.height, params.verify.exposure_s)
        rig = SensorRig(lidar=lidar, cameras={CAMERA_CHANNEL: camera})
        airlight = estimate_airlight([image], [range_map])
        images, ranges = {CAMERA_CHANNEL: image}, {CAMERA_CHANNEL: range_map}
        aligned = observe(frame, images, ranges, scene_media(condition, True, sid, severity, params.verify.seed),
                          rig, airlight, ObserveOptions())
        unaligned = observe(frame, images, ranges, scene_media(condition, False, sid, severity, params.verify.seed),
                            rig, airlight, ObserveOptions(), lidar=aligned.lidar)
        weather = aligned.lidar
        pts = weather.scan.points
        echo = isolated_mask(pts[:, :3].astype(np.float64), azimuth_step_rad=step)
        T = camera_from_lidar(frame)
        cam = pts[echo, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        uvw = cam @ np.asarray(view.K, dtype=np.float64).T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
        ok = (cam[:, 2] > 0.5) & (u >= 2) & (u < view.width - 2) & (v >= 2) & (v < view.height - 2)
        ui, vi, z = np.round(u[ok]).astype(int), np.round(v[ok]).astype(int), cam[ok, 2]
        in_view.append(int(ok.sum()))
        depth.append(z)
        near = z < NEAR_M
        near_count.append(int(near.sum()))
        # the particle behind each echo: its diameter from the field (ids of the scattered points)
        field = scene_media(condition, True, sid, severity, params.verify.seed).field.field()
        ids = weather.particle_id[echo][ok]
        pg = pts[echo][ok, :3].astype(np.float64) @ weather.scan.T_global_lidar[:3, :3].T \
            + weather.scan.T_global_lidar[:3, 3]
        if len(pg):
            box = field.materialize(pg.min(0) - 0.1, pg.max(0) + 0.1, weather.scan.timestamp, min_diameter=1e-4)
            diameter = dict(zip(box.ids.tolist(), box.diameters.tolist()))
            d = np.array([diameter.get(int(i), np.nan) for i in ids])
            size_px.append(d * float(view.K[0][0]) / z)
        for flag, result in ((True, aligned), (False, unaligned)):
            img = result.cameras[CAMERA_CHANNEL].image
            c = _contrast(image if img is None else img)
            at[flag].append(c[vi, ui])
            at_near[flag].append(c[vi[near], ui[near]])
            if flag:
                at_random.append(c[rng.integers(2, view.height - 2, 2000), rng.integers(2, view.width - 2, 2000)])
    z_all, px = np.concatenate(depth), np.concatenate(size_px) if size_px else np.zeros(0)

    def mean(parts: list[np.ndarray]) -> float | None:
        x = np.concatenate(parts) if parts else np.zeros(0)
        return float(x.mean()) if len(x) else None

    return {
        "workload": f"alignment_visibility_{condition_name}", "condition": condition_name, "frames": len(in_view),
        "rate_mm_h": severity.snow_rate_mm_h if condition.particles.kind == "snow" else severity.rain_rate_mm_h,
        "echoes_in_view_per_frame": float(np.mean(in_view)),
        "echoes_nearer_than_4m_per_frame": float(np.mean(near_count)),
        "echo_depth_m_percentiles_10_50_90": (np.percentile(z_all, [10, 50, 90]).round(2).tolist()
                                              if len(z_all) else None),
        "particle_diameter_px_percentiles_50_90_99": (np.nanpercentile(px, [50, 90, 99]).round(3).tolist()
                                                      if np.isfinite(px).any() else None),
        "share_at_least_1px": float(np.nanmean(px >= 1.0)) if len(px) else None,
        "share_at_least_2px": float(np.nanmean(px >= 2.0)) if len(px) else None,
        "share_at_least_one_fused_cell": (float(np.nanmean(px >= _cell_px(params))) if len(px) else None),
        "fused_cell_px": _cell_px(params),
        "contrast_at_echoes_aligned": mean(at[True]), "contrast_at_echoes_unaligned": mean(at[False]),
        "contrast_at_near_echoes_aligned": mean(at_near[True]),
        "contrast_at_near_echoes_unaligned": mean(at_near[False]),
        "contrast_at_random_pixels": mean(at_random),
        "cpu_seconds": round(time.process_time() - t0, 2),
    }


def _cell_px(params) -> float:
    """Width of one cell of verify's fused input in reference-image pixels."""
    from weatheralign.reference.synthetic import STF_FULL_SIZE

    width = STF_FULL_SIZE[0] * params.reference.camera.image_scale
    return float(width / params.verify.image_hw[1])


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--conditions", nargs="+", default=["snow", "rain"])
    args = parser.parse_args(argv)
    entries = []
    for name in args.conditions:
        entry = measure(name, args.frames)
        entries.append(entry)
        print(json.dumps(entry))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(merge_entries(OUT, entries), indent=2) + "\n")
    print(f"wrote {OUT}")
    return entries


if __name__ == "__main__":
    main()
