"""Every condition on the shared real frames: clean vs each weather, side by side, and what a reviewer would check.

``.venv/bin/python -m benchmarks.bench_real_weather [--data data]`` renders the real Seeing Through Fog and KITTI
frames of ``../shared/data/real`` (dense depth from their own scans: what a user's real data gets) through every
condition of `weatheralign.conditions.CONDITIONS`, aligned, at the tuned fog levels and precipitation rates of the
last pipeline run (``<data>/calibrate_fog/fog_levels.json``, ``<data>/calibrate_precipitation/rates.json``; the
params' values where those are absent). The real snowy STF frame stands beside the simulated snow as the real
reference. Figures: ``reports/benchmarks/real_weather_<frame>.png`` (clean, then one tile per condition). Numbers
per frame and condition, in ``reports/benchmarks/real_weather.json``: the share of the top quarter clipped at 255
(white sky), the mean sRGB change over sky and over structure, the contrast left over structure (fog must grey
structure with depth, not paint it white), particles drawn and scattered LiDAR echoes, re-projection error, CPU
and wall seconds.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from benchmarks.common import REAL, REPO, real_frames
from weatheralign.atomic import write_json

OUT = REPO / "reports" / "benchmarks"
STF_SNOW = "cam_stereo_left_lut_2018-02-12_15-39-23_00100_snow.png"


def _levels_and_rates(params: Any, data: Path) -> tuple[Any, Any, str]:
    """(FogLevels, PrecipitationRates, where they came from): the last run's tuned values, else the params'."""
    from weatheralign.manifest import FOG_LEVELS_FILE, PRECIPITATION_RATES_FILE
    from weatheralign.simulate.media import (
        configured_fog_levels,
        configured_precipitation_rates,
        params_fog_levels,
        params_precipitation_rates,
    )
    levels = (configured_fog_levels(params.simulate, data) if (data / FOG_LEVELS_FILE).is_file()
              else params_fog_levels(params.simulate))
    rates = (configured_precipitation_rates(params.simulate, params.particles, data)
             if (data / PRECIPITATION_RATES_FILE).is_file() else params_precipitation_rates(params.particles))
    return levels, rates, f"fog: {levels.source}, rates: {rates.source}"


def frame_media(params: Any, condition: str, scene: str, t_ref: float, levels: Any, rates: Any) -> Any:
    """`SceneMedia` of ``condition`` (aligned) over a one-frame ``scene``, as the media stage resolves it (tuned fog
    level and its airlight gain drawn for the scene, particle field at the tuned rate)."""
    from weatheralign.conditions import CONDITIONS
    from weatheralign.medium.conditions import field_spec
    from weatheralign.simulate.media import resolve_media

    fields = {kind: [field_spec(params.particles, kind, scene, t_ref)] for kind in ("snow", "rain")}
    media = resolve_media(CONDITIONS[condition], params.simulate, [scene], levels, fields, rates)
    return media.for_scene(scene, True, params.simulate.rain_appearance)


def image_stats(clean: np.ndarray, out: np.ndarray, rng: np.ndarray) -> dict[str, float]:
    """Clipping of the top quarter, mean sRGB change over sky / structure, and the structure's remaining contrast
    (std of luminance over structure, weather / clean)."""
    top = out[: max(1, out.shape[0] // 4)]
    sky = ~np.isfinite(rng)
    lum_c = clean.astype(np.float64).mean(axis=2)
    lum_o = out.astype(np.float64).mean(axis=2)
    d = lum_o - lum_c
    struct = ~sky
    return {"top_quarter_clipped": float((top.max(axis=2) >= 255).mean()),
            "top_quarter_clipped_clean": float((clean[: top.shape[0]].max(axis=2) >= 255).mean()),
            "mean_change_sky": float(d[sky].mean()) if sky.any() else None,
            "mean_change_structure": float(d[struct].mean()),
            "structure_contrast_ratio": float(lum_o[struct].std() / max(lum_c[struct].std(), 1e-6))}


def label(img: np.ndarray, text: str) -> np.ndarray:
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    draw.rectangle([0, 0, 8 * len(text) + 10, 22], fill=(0, 0, 0))
    draw.text((5, 5), text, fill=(255, 255, 255))
    return np.asarray(pil)


def grid(tiles: list[np.ndarray], cols: int, width: int) -> np.ndarray:
    """Tiles resized to ``width`` and laid out ``cols`` per row (white gaps)."""
    h = int(round(tiles[0].shape[0] * width / tiles[0].shape[1]))
    rs = [np.asarray(Image.fromarray(t).resize((width, h), Image.BILINEAR)) for t in tiles]
    while len(rs) % cols:
        rs.append(np.full_like(rs[0], 255))
    rows = [np.concatenate([np.pad(r, ((2, 2), (2, 2), (0, 0)), constant_values=255) for r in rs[i:i + cols]], 1)
            for i in range(0, len(rs), cols)]
    return np.concatenate(rows, 0)


def run_frame(params: Any, name: str, frame: Any, levels: Any, rates: Any
              ) -> tuple[list[dict[str, Any]], list[np.ndarray]]:
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.fog import estimate_airlight
    from weatheralign.conditions import CONDITIONS
    from weatheralign.sensors import SensorRig, camera_models, estimate_lidar_model
    from weatheralign.simulate.observe import ObserveOptions, observe

    channel, view = next(iter(frame.cameras.items()))
    image = view.load_image()
    t0 = time.process_time()
    rng = camera_range_map(view, frame.lidar, image)
    depth_cpu = time.process_time() - t0
    sensors = SensorRig(estimate_lidar_model([frame.lidar], rotation_hz=10.0),
                        camera_models(frame.cameras, params.world.camera.exposure_s))
    airlight = estimate_airlight([image], [rng])
    rows: list[dict[str, Any]] = []
    tiles = [label(image, f"{name}: clean")]
    for condition in CONDITIONS:
        media = frame_media(params, condition, f"real-{name}", frame.lidar.timestamp, levels, rates)
        t0, w0 = time.process_time(), time.perf_counter()
        fw = observe(frame, {channel: image}, {channel: rng}, media, sensors, airlight, ObserveOptions(threads=1))
        cpu, wall = time.process_time() - t0, time.perf_counter() - w0
        out = fw.cameras[channel].image
        out = image if out is None else out
        e = fw.reprojection_px
        row = {"frame": name, "condition": condition, "cpu_s": cpu, "wall_s": wall, "depth_cpu_s": depth_cpu,
               "camera_alpha": media.camera_alpha, "rate_mm_h": None if media.field is None else media.field.rate_mm_h,
               "particles_drawn": fw.cameras[channel].drawn, "lidar_scattered": fw.lidar.counts["SCATTERED"],
               "reprojection_mean_px": float(e.mean()) if e.size else None,
               "reprojection_max_px": float(e.max()) if e.size else None, **image_stats(image, out, rng)}
        rows.append(row)
        text = condition + (f" a={media.camera_alpha:.4f}" if media.camera_alpha else "") + \
            (f" {media.field.rate_mm_h:.1f} mm/h" if media.field is not None else "")
        tiles.append(label(out, text))
    return rows, tiles


def main(argv: list[str] | None = None) -> dict[str, Any]:
    from weatheralign.config import params_from_dict

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO / "data", help="the pipeline's data folder (tuned levels)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    frames = real_frames()
    if not frames:
        print(f"{REAL}: no real frames, nothing to render")
        return {}
    params = params_from_dict({})
    levels, rates, source = _levels_and_rates(params, args.data)
    result: dict[str, Any] = {"source": source, "frames": []}
    for name, load in frames.items():
        rows, tiles = run_frame(params, name, load(), levels, rates)
        result["frames"] += rows
        if name == "stf" and (REAL / "stf" / STF_SNOW).is_file():
            tiles.append(label(np.asarray(Image.open(REAL / "stf" / STF_SNOW).convert("RGB")),
                               "REAL snow (another STF recording)"))
        args.out.mkdir(parents=True, exist_ok=True)
        Image.fromarray(grid(tiles, 2, 600)).save(args.out / f"real_weather_{name}.png", optimize=True)
        for r in rows:
            print(f"{name:6s} {r['condition']:10s} clipped top {r['top_quarter_clipped']:.3f} "
                  f"(clean {r['top_quarter_clipped_clean']:.3f})  d sky {r['mean_change_sky']}  "
                  f"d struct {r['mean_change_structure']:.1f}  contrast {r['structure_contrast_ratio']:.2f}  "
                  f"drawn {r['particles_drawn']}  scattered {r['lidar_scattered']}  {r['cpu_s']:.2f} CPU-s "
                  f"{r['wall_s']:.2f} s")
    write_json(args.out / "real_weather.json", result, indent=2)
    return result


if __name__ == "__main__":
    main()
