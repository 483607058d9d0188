"""The weather copy of a nuScenes-format dataroot: per-sample inputs, outputs, resume records; no physics.

`run_sample` loads one sample's inputs (the frame, decoded images, each camera's ray-length map from
`weatheralign.camera.depth.camera_range_map` with `DEPTH_SWEEPS` aggregated sweeps where the dataset has no exact
map), runs the pure core `weatheralign.simulate.observe.observe` and writes the files; `finalize_copy` completes
the copy. The copy holds the input's tables and maps byte-for-byte (tokens, ``num_lidar_pts`` untouched), new
keyframe LiDAR files and camera JPEGs at the same relative paths, ``extras/LIDAR_TOP/<stem>.npy`` (the input's
per-point records re-indexed to the new points: weather points get ``instance`` 0 and ``material``
`WEATHER_MATERIAL`; clutter ``column`` -1) and ``extras/weather/LIDAR_TOP/<stem>.npy`` (per point ``label``
(`WeatherLabel`), ``particle_id`` (-1 if none), ``source_index`` (input row, -1 for clutter)). LiDAR sweeps are copied
unchanged (identity labels) unless ``simulate.sweeps``, which runs every sweep through the same media (LiDAR only);
the ``points_*`` metrics count keyframe scans, ``sweep_points_*`` the sweeps. Camera range maps are not copied.
Every file is written atomically; a finished sample leaves a record in ``<out parent>/.progress/<copy name>/``
(beside the copy: a finished copy holds only data) with the size and SHA-256 of every file it wrote, tagged with the
run's fingerprint (`copy_fingerprint`: the stage's declared code and params, the scene's media, the sensors, the input
dataset's digest) plus the stamps of its input files, so a rerun skips it.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from weatheralign import atomic
from weatheralign.camera.depth import camera_range_map
from weatheralign.data.frame import Frame
from weatheralign.data.nuscenes import extras_relpath, load_frame, load_lidar
from weatheralign.lidar.labels import WeatherLabel
from weatheralign.provenance import file_stamps, read_resume_record, write_resume_record
from weatheralign.sensors import SensorRig
from weatheralign.simulate.media import SceneMedia
from weatheralign.simulate.observe import COUNT_KEYS, FrameWeather, LidarWeather, ObserveOptions, observe, observe_lidar
from weatheralign.simulate.plan import SampleJob

WEATHER_MATERIAL = 255
"""``material`` of a point that is a weather echo (scattered or clutter) in the copied per-point extras."""
WEATHER_DTYPE = np.dtype([("label", "u1"), ("particle_id", "<i8"), ("source_index", "<i8")])
PROGRESS_DIR = ".progress"
DEPTH_SWEEPS = 3
"""LiDAR sweeps aggregated for a real camera's dense depth (nuScenes: 3 HDL-32E sweeps cover ~2 % of an image)."""


def weather_relpath(filename: str) -> str:
    """``extras/weather/<channel>/<stem>.npy``: per-point labels and particle ids of a weather scan."""
    parts = Path(filename).parts
    return f"extras/weather/{parts[1]}/{parts[-1].split('.')[0]}.npy"


def copy_fingerprint(run_digest: str, media: SceneMedia, sensors: SensorRig, airlight: tuple[float, ...]) -> str:
    """16 hex digits over what changes a scene's weather files: ``run_digest`` (the stage's declared code and params
    and the input dataset's digest, `weatheralign.provenance.stage_fingerprint`), the scene's media, the sensors
    and the airlight."""
    blob = json.dumps({"run": run_digest, "condition": media.condition.name, "aligned": media.aligned,
                       "appearance": None if media.condition.particles is None
                       else media.condition.particles.camera_appearance,
                       "fog": [media.lidar_alpha, media.lidar_beta, media.camera_alpha],
                       "field": None if media.field is None else media.field.to_dict(),
                       "sensors": sensors.to_dict(), "airlight": list(airlight)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _sample_files(nusc, sample_token: str) -> tuple[str, list[str]]:
    sample = nusc.get("sample", sample_token)
    lidar = nusc.get("sample_data", sample["data"]["LIDAR_TOP"])["filename"]
    cams = [nusc.get("sample_data", tok)["filename"] for ch, tok in sorted(sample["data"].items())
            if ch.startswith("CAM")]
    return lidar, cams


def sweep_records(nusc, sample_token: str) -> list[dict]:
    """The LiDAR sweeps (non-keyframe sample_data) between the previous keyframe and this sample's, oldest first."""
    sd = nusc.get("sample_data", nusc.get("sample", sample_token)["data"]["LIDAR_TOP"])
    out = []
    while sd["prev"]:
        sd = nusc.get("sample_data", sd["prev"])
        if sd["is_key_frame"]:
            break
        out.append(sd)
    return out[::-1]


def _outputs(nusc, sample_token: str, sweeps: bool = False) -> list[str]:
    lidar, cams = _sample_files(nusc, sample_token)
    scans = [lidar] + ([sd["filename"] for sd in sweep_records(nusc, sample_token)] if sweeps else [])
    return [rel for f in scans for rel in (f, extras_relpath(f), weather_relpath(f))] + cams


def progress_dir(out_root: Path) -> Path:
    """Where a copy's resume records live: ``<parent>/.progress/<copy name>/``, beside the copy, not in it (a
    finished copy holds only data)."""
    out_root = Path(out_root)
    return out_root.parent / PROGRESS_DIR / out_root.name


def _progress_file(out_root: Path, sample_token: str) -> Path:
    return progress_dir(out_root) / f"{sample_token}.json"


def _copy_file(src: Path, dst: Path) -> None:
    with atomic.atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def _new_extras(src_extras: Path, lw: LidarWeather, scan_timestamp: float) -> NDArray | None:
    """The input's per-point records re-indexed to the weather points (None if the input has none)."""
    if not src_extras.is_file():
        return None
    ex = np.load(src_extras)
    src = lw.source_index
    out = np.zeros(len(src), dtype=ex.dtype)
    kept = src >= 0
    out[kept] = ex[src[kept]]
    out["time_offset"] = (lw.times - scan_timestamp).astype(np.float32)
    out["time_offset"][kept] = ex["time_offset"][src[kept]]
    if "column" in ex.dtype.names:
        out["column"][~kept] = -1
    weather_pt = lw.labels == WeatherLabel.SCATTERED
    if "instance" in ex.dtype.names:
        out["instance"][weather_pt] = 0
    if "material" in ex.dtype.names:
        out["material"][weather_pt] = WEATHER_MATERIAL
    return out


def write_scan(src_root: Path, out_root: Path, rel: str, lw: LidarWeather, timestamp: float) -> None:
    """A weather scan at ``rel``: the points, the re-indexed per-point extras and the weather labels (atomically)."""
    atomic.write_bytes(out_root / rel, lw.scan.points.astype("<f4").tobytes())
    extras = _new_extras(Path(src_root) / extras_relpath(rel), lw, timestamp)
    if extras is None:  # no input extras: per-point firing times alone, so the reader gets exact times
        extras = np.zeros(len(lw.labels), dtype=[("time_offset", "<f4")])
        extras["time_offset"] = (lw.times - timestamp).astype(np.float32)
    atomic.save_npy(out_root / extras_relpath(rel), extras)
    rec = np.zeros(len(lw.labels), dtype=WEATHER_DTYPE)
    rec["label"], rec["particle_id"], rec["source_index"] = lw.labels, lw.particle_id, lw.source_index
    atomic.save_npy(out_root / weather_relpath(rel), rec)


def write_sample(src_root: Path, out_root: Path, nusc, sample_token: str, fw: FrameWeather, frame: Frame,
                 jpeg_quality: int) -> None:
    """Write one sample's weather files (atomically) at the input's relative paths."""
    lidar_rel, _ = _sample_files(nusc, sample_token)
    write_scan(src_root, out_root, lidar_rel, fw.lidar, frame.lidar.timestamp)
    sample = nusc.get("sample", sample_token)
    for ch, view in frame.cameras.items():
        rel = nusc.get("sample_data", sample["data"][ch])["filename"]
        cw = fw.cameras[ch]
        if cw.image is None:
            _copy_file(view.image_path, out_root / rel)
        else:
            buf = io.BytesIO()
            Image.fromarray(cw.image).save(buf, format="JPEG", quality=jpeg_quality, subsampling=0)
            atomic.write_bytes(out_root / rel, buf.getvalue())


def run_sample(nusc, src_root: Path, out_root: Path, job: SampleJob, sensors: SensorRig, options: ObserveOptions,
               run_digest: str, jpeg_quality: int = 92, sweeps: bool = False) -> tuple[dict, bool]:
    """Simulate and write one sample unless an identical earlier run finished it. Returns (record, done_now).

    The record holds the LiDAR counts, the particles rendered, the re-projection errors and the seconds taken.
    """
    src_root, out_root = Path(src_root), Path(out_root)
    if src_root.resolve() == out_root.resolve():
        raise ValueError(f"the weather copy must not overwrite its input {src_root}")
    token = job.sample_token
    digest = copy_fingerprint(run_digest, job.media, sensors, job.airlight) + file_stamps(
        src_root, _outputs(nusc, token, sweeps))
    done = read_resume_record(_progress_file(out_root, token), digest, out_root)
    if done is not None:
        return done, False
    t0 = time.time()
    frame = load_frame(nusc, token)
    exact = all(v.range_path is not None for v in frame.cameras.values())
    depth_lidar = frame.lidar if exact else load_lidar(nusc, nusc.get("sample", token)["data"]["LIDAR_TOP"],
                                                       DEPTH_SWEEPS)
    images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    ranges = {ch: camera_range_map(v, depth_lidar, images[ch]) for ch, v in frame.cameras.items()}
    fw = observe(frame, images, ranges, job.media, sensors, np.asarray(job.airlight), options)
    write_sample(src_root, out_root, nusc, token, fw, frame, jpeg_quality)
    sweep_counts = {k: 0 for k in COUNT_KEYS}
    if sweeps:  # the same media through every sweep of the sample (LiDAR only)
        for sd in sweep_records(nusc, token):
            scan = load_lidar(nusc, sd["token"])
            lw = observe_lidar(scan, job.media, sensors.lidar)
            write_scan(src_root, out_root, sd["filename"], lw, scan.timestamp)
            for k, v in lw.counts.items():
                sweep_counts[k] += v
    record = write_resume_record(_progress_file(out_root, token), digest, out_root, _outputs(nusc, token, sweeps), {
        "sample": token, "counts": fw.lidar.counts, "sweep_counts": sweep_counts,
        "particles_rendered": fw.particles_rendered, "reprojection_px": [float(e) for e in fw.reprojection_px],
        "reprojection_channels": list(fw.reprojection_channels), "seconds": round(time.time() - t0, 3)})
    return record, True


def finalize_copy(nusc, src_root: Path, out_root: Path, version: str) -> int:
    """Complete the weather copy: every sensor file not simulated (sweeps) copied unchanged with its LiDAR extras,
    identity labels for keyframe scans left clear, then the ``<version>/`` tables and ``maps/`` byte-for-byte
    (last, so the copy loads only once complete).
    Returns the number of files copied now."""
    src_root, out_root = Path(src_root), Path(out_root)
    for leftover in out_root.rglob(".*.tmp"):  # temporaries of writes a killed run never renamed
        if leftover.is_file():
            leftover.unlink()
    copied = 0
    for sd in nusc.sample_data:
        rels = [sd["filename"]]
        if not sd["filename"].split("/")[1].startswith("CAM"):
            rels.append(extras_relpath(sd["filename"]))
        for rel in rels:
            src, dst = src_root / rel, out_root / rel
            if src.is_file() and not dst.is_file():
                _copy_file(src, dst)
                copied += 1
        label_file = out_root / weather_relpath(sd["filename"])
        if sd["sensor_modality"] == "lidar" and not label_file.is_file():
            # a scan left clear (sweeps by default, samples beyond ``max_samples``): identity labels, so every
            # scan of the copy has its record
            n = (out_root / sd["filename"]).stat().st_size // 20
            rec = np.zeros(n, dtype=WEATHER_DTYPE)
            rec["particle_id"], rec["source_index"] = -1, np.arange(n)
            atomic.save_npy(label_file, rec)
    for top in ("maps", version):
        for src in sorted((src_root / top).rglob("*")):
            if src.is_file():
                dst = out_root / src.relative_to(src_root)
                if not (dst.is_file() and dst.read_bytes() == src.read_bytes()):
                    _copy_file(src, dst)
                    copied += 1
    return copied


def summarise(records: list[dict]) -> dict:
    """Stage metrics from the per-sample records."""
    counts = {k: sum(r["counts"].get(k, 0) for r in records) for k in COUNT_KEYS}
    errors = np.array([e for r in records for e in r["reprojection_px"]], dtype=np.float64)
    return {
        "points_unchanged": counts["UNCHANGED"], "points_attenuated": counts["ATTENUATED"],
        "points_scattered": counts["SCATTERED"] + counts["CLUTTER"], "points_clutter": counts["CLUTTER"],
        "points_lost": counts["LOST"], "particles_rendered": sum(r["particles_rendered"] for r in records),
        "reprojection_mean_px": float(errors.mean()) if errors.size else None,
        "reprojection_max_px": float(errors.max()) if errors.size else None,
        "reprojection_p99_px": float(np.percentile(errors, 99)) if errors.size else None,
        "reprojection_pairs": int(errors.size), "num_samples": len(records),
        "sweep_points_scattered": sum(r.get("sweep_counts", {}).get("SCATTERED", 0)
                                      + r.get("sweep_counts", {}).get("CLUTTER", 0) for r in records),
        "sweep_points_lost": sum(r.get("sweep_counts", {}).get("LOST", 0) for r in records),
        "seconds_per_sample": round(float(np.mean([r["seconds"] for r in records])), 3) if records else None,
    }


__all__ = ["DEPTH_SWEEPS", "WEATHER_DTYPE", "WEATHER_MATERIAL", "copy_fingerprint", "finalize_copy", "run_sample",
           "summarise", "sweep_records", "weather_relpath", "write_sample", "write_scan"]
