"""The overcast light of snow and rain beside clear, on the shared real frames and a synthetic reference frame.

``.venv/bin/python -m benchmarks.bench_overcast_real`` relights the real Seeing Through Fog and KITTI frames of
``../shared/data/real`` (dense depth from their own scans; a metering camera: `Exposure.AUTO`) and a clear frame of
the embedded synthetic reference (its exact range map; the reference's fixed exposure) with the operator of
`weatheralign.camera.overcast` at the params' light (``simulate.overcast_*``); beside the synthetic frame the same
scene rendered by the reference itself under its hidden snow light (`weatheralign.reference.overcast`, without the
snowfall and lying snow), and last the real snowy STF frame. Figure: ``reports/benchmarks/overcast_real.png``
(clear left, overcast right); numbers (the sky's blue over red, the share of saturated pixels, the surfaces' median
chromaticity and, on the real frames, the share of visibly blue pixels above the horizon, clear and overcast) in
``reports/benchmarks/overcast_real.json``; the real snowy frame's road chromaticity beside them.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from benchmarks.bench_real_weather import STF_SNOW, grid, label
from benchmarks.common import REAL, REPO, real_frames
from weatheralign.atomic import write_json

OUT = REPO / "reports" / "benchmarks"


def light_stats(image: np.ndarray, sky: np.ndarray, above: np.ndarray | None = None) -> dict[str, float | None]:
    """Blue over red of the mean sky pixel (linear sRGB; None without sky), the share of pixels with a channel at
    255 of ``image`` (H, W, 3) uint8, the median per-pixel red over green and blue over green of its surfaces (not
    ``sky``, luminance above 0.01), and with ``above`` (H, W; above the horizon) the share of those pixels that are
    visibly blue (blue over red above 1.5, luminance above 0.05)."""
    from weatheralign.camera.fog import decode_srgb_u8
    from weatheralign.camera.overcast import luminance

    lin = decode_srgb_u8(image)
    blue_red = float(lin[sky][:, 2].mean() / max(lin[sky][:, 0].mean(), 1e-6)) if sky.any() else None
    y = luminance(lin)
    px = lin[~sky & (y > 0.01)]
    chroma = np.median(px / np.maximum(px[:, 1:2], 1e-4), axis=0)
    row: dict[str, float | None] = {"sky_blue_over_red": blue_red,
                                    "saturated_share": float((image.max(axis=2) >= 255).mean()),
                                    "surface_red_over_green": float(chroma[0]),
                                    "surface_blue_over_green": float(chroma[2])}
    if above is not None:
        blue = (lin[..., 2] > 1.5 * np.maximum(lin[..., 0], 1e-4)) & (y > 0.05)
        row["blue_share_above_horizon"] = float(blue[above].mean())
    return row


def real_tiles(name: str, frame: Any, light: Any) -> tuple[list[np.ndarray], dict[str, Any]]:
    """(clear, overcast) tiles and the numbers of one real frame (a metering camera)."""
    from weatheralign.camera.depth import camera_range_map
    from weatheralign.camera.overcast import Exposure, overcast_image, pixel_sin_elevation, up_in_camera

    view = next(iter(frame.cameras.values()))
    image = view.load_image()
    rng = camera_range_map(view, frame.lidar, image)
    out = overcast_image(image, rng, view.K, view.T_global_cam, light, Exposure.AUTO)
    sky = ~np.isfinite(rng)
    h, w = sky.shape
    above = pixel_sin_elevation(view.K, w, h, up_in_camera(view.T_global_cam)) > 0.0
    row = {"frame": name, "clear": light_stats(image, sky, above), "overcast": light_stats(out, sky, above)}
    return [label(image, f"{name}: clear"), label(out, f"{name}: overcast (operator, metering camera)")], row


def synthetic_tiles(params: Any) -> tuple[list[np.ndarray], dict[str, Any]]:
    """A clear synthetic reference frame, the operator's overcast of it (fixed exposure), and the same scene as the
    reference renders it under its hidden snow light (no snowfall, no lying snow)."""
    from weatheralign.camera.overcast import Exposure, overcast_image
    from weatheralign.reference.synthetic import (
        CLEAR,
        EGO_SPEED_RANGE,
        SCENE_DURATION_S,
        frame_specs,
        render_frame,
        stereo_left_camera,
    )
    from weatheralign.world.layout import generate_layout

    cfg = params.reference.model_copy(update={
        "lidar": params.reference.lidar.model_copy(update={"firings_per_ring": 90}),
        "camera": params.reference.camera.model_copy(update={"image_scale": 0.4}),
        "precipitation": params.reference.precipitation.model_copy(update={"ground": False})})
    spec = next(s for s in frame_specs(cfg.model_copy(update={"frames_per_split": 3})) if s.level == "clear"
                and s.index == 2)
    clear = render_frame(spec, cfg, CLEAR)
    truth = render_frame(dataclasses.replace(spec, level="snow"), cfg, CLEAR)
    cam = stereo_left_camera(cfg.camera.image_scale)
    layout = generate_layout(spec.recording, spec.scene_seed, spec.t_start, SCENE_DURATION_S, EGO_SPEED_RANGE,
                             np.array(spec.origin), spec.heading)
    T_global_cam = layout.T_global_ego(spec.time) @ cam.T_ego_cam
    light = overcast_light(params)
    out = overcast_image(clear.image, clear.range, cam.K, T_global_cam, light, Exposure.FIXED)
    sky = ~np.isfinite(clear.range)
    row = {"frame": "synthetic", "clear": light_stats(clear.image, sky), "overcast": light_stats(out, sky),
           "reference_overcast": light_stats(truth.image, sky)}
    return [label(clear.image, "synthetic reference: clear"), label(out, "synthetic: overcast (operator)"),
            label(truth.image, "synthetic: the reference's own overcast render")], row


def overcast_light(params: Any) -> Any:
    """The operator's light of the params (``simulate.overcast_*``)."""
    from weatheralign.camera.overcast import Overcast

    s = params.simulate
    return Overcast(s.overcast_sun_transmittance, s.overcast_zenith_luminance, s.overcast_diffuse_gain,
                    s.overcast_zenith_over_surface)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    from weatheralign.config import params_from_dict

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    params = params_from_dict({})
    tiles: list[np.ndarray] = []
    rows: list[dict[str, Any]] = []
    for name, load in real_frames().items():
        t, row = real_tiles(name, load(), overcast_light(params))
        tiles += t
        rows.append(row)
    t, row = synthetic_tiles(params)
    tiles += t
    rows.append(row)
    if (REAL / "stf" / STF_SNOW).is_file():
        snow = np.asarray(Image.open(REAL / "stf" / STF_SNOW).convert("RGB"))
        tiles.append(label(snow, "REAL snow (another STF recording)"))
        h, w = snow.shape[:2]
        road = np.ones(snow.shape[:2], bool)
        road[int(0.72 * h):int(0.9 * h), int(0.22 * w):int(0.78 * w)] = False  # its road, as a "not sky" region
        rows.append({"frame": "stf_snow_road", "real_snow": light_stats(snow, road)})
    args.out.mkdir(parents=True, exist_ok=True)
    Image.fromarray(grid(tiles, 2, 600)).save(args.out / "overcast_real.png", optimize=True)
    result = {"light": overcast_light(params).to_dict(), "frames": rows}
    write_json(args.out / "overcast_real.json", result, indent=2)
    for r in rows:
        print(r)
    return result


if __name__ == "__main__":
    main()
