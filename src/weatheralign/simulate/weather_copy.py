"""The weather copy of a nuScenes-format dataroot: per-sample inputs, outputs, resume records; no physics.

`run_sample` loads one sample's inputs (the frame, decoded images, each camera's ray-length map:
`weatheralign.simulate.plan.sample_range_maps`), runs the pure core `weatheralign.simulate.observe.observe` on the
keyframe and the ``sweeps`` LiDAR sweeps nearest before it (each at its own time through the same media: the sweeps a
multi-sweep detector aggregates) and writes the files; `run_chunk` does it for consecutive samples of one scene (one
task: the per-task overhead of the engine is paid once per chunk); `finalize_copy` completes the copy.

The copy is lean. Every file the weather did not change (the older sweeps, cameras a condition leaves clear, the
tables and maps, the input's per-point extras of unchanged scans) is a **hard link** to the input's file (a copy only
where the file system refuses links), so it costs no space; weather scans get a new ``.pcd.bin`` at the input's
relative path, their per-point records re-indexed to the new points as a compressed
``extras/LIDAR_TOP/<stem>.npz`` (`compressed_extras_relpath`; weather points get ``instance`` 0 and ``material``
`WEATHER_MATERIAL`, clutter ``column`` -1) and their weather record ``extras/weather/LIDAR_TOP/<stem>.npz``
(`weather_relpath`): per point ``label`` (`WeatherLabel`, uint8), ``particle_id`` (-1 if none) and ``source_index``
(input row, -1 for clutter), each in the smallest integer dtype that holds its values exactly. A scan without a
weather record is unchanged (`read_weather_record` gives its identity record). Weather images are JPEGs at the
params' quality with 4:2:0 chroma subsampling, like nuScenes' own. Camera range maps are not copied. Because links
share the input's bytes, edit neither dataset in place.

Every file is written atomically; a finished sample leaves a record in ``<out parent>/.progress/<copy name>/``
(beside the copy: a finished copy holds only data) with the size and SHA-256 of every file it wrote, tagged with the
run's fingerprint (`copy_fingerprint`: the stage's declared code and params, the scene's media, the sensors, the input
dataset's digest) plus the stamps of its input files, so a rerun skips it.
"""
from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PIL import Image

from weatheralign import atomic
from weatheralign.data.errors import DataFormatError, read_float32_records
from weatheralign.data.frame import Frame, LidarScan
from weatheralign.data.nuscenes import (
    compressed_extras_relpath,
    extras_relpath,
    load_frame,
    load_lidar,
    open_nuscenes_cached,
    read_point_extras,
    read_record_file,
)
from weatheralign.lidar.labels import WeatherLabel
from weatheralign.provenance import file_stamps, files_intact, read_record_json, read_resume_record, write_resume_record
from weatheralign.sensors import SensorRig
from weatheralign.simulate.media import SceneMedia
from weatheralign.simulate.observe import (
    COUNT_KEYS,
    FrameWeather,
    LidarWeather,
    ObserveOptions,
    observe,
    observe_lidar_scans,
)
from weatheralign.simulate.plan import SampleJob, sample_range_maps

WEATHER_MATERIAL = 255
"""``material`` of a point that is a weather echo (scattered or clutter) in the copied per-point extras."""
PROGRESS_DIR = ".progress"
JPEG_SUBSAMPLING = "4:2:0"
"""Chroma subsampling of the weather JPEGs: nuScenes' own (and the synthetic world's)."""


def weather_relpath(filename: str) -> str:
    """``extras/weather/<channel>/<stem>.npz``: per-point labels, particle ids and source rows of a weather scan."""
    parts = Path(filename).parts
    return f"extras/weather/{parts[1]}/{parts[-1].split('.')[0]}.npz"


def smallest_int_dtype(values: NDArray) -> np.dtype:
    """The smallest integer dtype holding every value of ``values`` exactly (int8 for an empty array)."""
    if values.size == 0:
        return np.dtype(np.int8)
    dtype = np.promote_types(np.min_scalar_type(int(values.min())), np.min_scalar_type(int(values.max())))
    # a negative minimum with a maximum beyond int32 promotes (int8, uint64) to float64, which would round ids above
    # 2**53: int64 holds every value of an int64 array exactly
    return dtype if dtype.kind in "iu" else np.dtype(np.int64)


def read_weather_record(root: Path, filename: str, num_points: int) -> NDArray:
    """The weather record of the scan ``filename`` of a weather copy at ``root``: (N,) structured ``label``,
    ``particle_id``, ``source_index`` (as stored); the identity record (all unchanged, no particle, row i from row i)
    for a scan the weather left clear (no record).

    Raises:
        DataFormatError: a record that is not a valid ``.npz`` or whose length differs from ``num_points``.
    """
    path = Path(root) / weather_relpath(filename)
    if not path.is_file():
        rec = np.zeros(num_points, dtype=[("label", "u1"), ("particle_id", "i1"), ("source_index", "<i8")])
        rec["particle_id"], rec["source_index"] = -1, np.arange(num_points)
        return rec
    try:
        rec = read_record_file(path)
    except (OSError, ValueError, EOFError, KeyError, TypeError) as exc:
        raise DataFormatError(f"{path}: not a valid weather record ({type(exc).__name__}: {exc}); expected an .npz "
                              f"with label, particle_id and source_index per point of {filename}") from None
    if len(rec) != num_points or set(rec.dtype.names or ()) != {"label", "particle_id", "source_index"}:
        raise DataFormatError(f"{path}: fields {rec.dtype.names} with {len(rec)} rows; expected label, particle_id "
                              f"and source_index for each of the {num_points} points of {filename}")
    return rec


def copy_fingerprint(run_digest: str, media: SceneMedia, sensors: SensorRig, airlight: tuple[float, ...]) -> str:
    """16 hex digits over what changes a scene's weather files: ``run_digest`` (the stage's declared code and params
    and the input dataset's digest, `weatheralign.provenance.stage_fingerprint`), the scene's media, the sensors
    and the airlight."""
    blob = json.dumps({"run": run_digest, "condition": media.condition.name, "aligned": media.aligned,
                       "appearance": None if media.condition.particles is None
                       else media.condition.particles.camera_appearance,
                       "fog": [media.lidar_alpha, media.lidar_beta, media.camera_alpha],
                       "field": None if media.field is None else media.field.to_dict(),
                       "camera_rate": media.camera_rate_mm_h,
                       "ground": None if media.ground is None else media.ground.to_dict(),
                       "sensors": sensors.to_dict(), "airlight": list(airlight)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def lidar_fingerprint(run_digest: str, media: SceneMedia, sensors: SensorRig) -> str:
    """16 hex digits over what changes a scene's LiDAR weather files: ``run_digest``, the media the LiDAR sees (the
    condition, its fog level, the field the LiDAR observes, the particles' reflectivity) and the LiDAR model. Equal for
    a condition's aligned and unaligned copies (the LiDAR sees the condition's own media in both), which is what lets
    the unaligned copy take its twin's LiDAR files (`reusable_lidar`)."""
    particles = media.condition.particles
    blob = json.dumps({"run": run_digest, "condition": media.condition.name,
                       "fog": [media.lidar_alpha, media.lidar_beta],
                       "field": None if media.field is None else media.field.to_dict(),
                       "reflectivity": None if particles is None else particles.lidar_reflectivity,
                       "ground": None if media.ground is None else [media.ground.kind, media.ground.amount_m,
                                                                    media.ground.seed, media.ground.puddle_share],
                       "lidar": sensors.lidar.to_dict()}, sort_keys=True)
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


def weather_sweeps(nusc, sample_token: str, sweeps: int) -> list[dict]:
    """The ``sweeps`` LiDAR sweeps nearest before the sample's keyframe (oldest first): those the weather reaches."""
    return sweep_records(nusc, sample_token)[-sweeps:] if sweeps > 0 else []


def _weather_scans(nusc, sample_token: str, sweeps: int) -> list[str]:
    """The scans the weather reaches: the keyframe's, then the ``sweeps`` nearest sweeps (oldest first)."""
    lidar, _ = _sample_files(nusc, sample_token)
    return [lidar] + [sd["filename"] for sd in weather_sweeps(nusc, sample_token, sweeps)]


def _lidar_outputs(nusc, sample_token: str, sweeps: int = 0) -> list[str]:
    """Per weather scan: the ``.pcd.bin``, its compressed per-point extras and its weather record."""
    return [rel for f in _weather_scans(nusc, sample_token, sweeps)
            for rel in (f, compressed_extras_relpath(f), weather_relpath(f))]


def _outputs(nusc, sample_token: str, sweeps: int = 0) -> list[str]:
    return _lidar_outputs(nusc, sample_token, sweeps) + _sample_files(nusc, sample_token)[1]


def progress_dir(out_root: Path) -> Path:
    """Where a copy's resume records live: ``<parent>/.progress/<copy name>/``, beside the copy, not in it (a
    finished copy holds only data)."""
    out_root = Path(out_root)
    return out_root.parent / PROGRESS_DIR / out_root.name


def _progress_file(out_root: Path, sample_token: str) -> Path:
    return progress_dir(out_root) / f"{sample_token}.json"


def link_or_copy(src: Path, dst: Path) -> bool:
    """``dst`` as a hard link to ``src`` (atomically: linked beside it, then renamed), or a copy where the file
    system refuses links (another device, no link support). Returns True if it copied."""
    with atomic.atomic_path(dst) as tmp:
        tmp.unlink()
        try:
            os.link(src, tmp)
            return False
        except OSError as exc:
            if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EACCES):
                raise
            shutil.copyfile(src, tmp)
            return True


def _new_extras(src_root: Path, rel: str, lw: LidarWeather, scan_timestamp: float) -> NDArray | None:
    """The input's per-point records re-indexed to the weather points (None if the input has none)."""
    ex = read_point_extras(src_root, rel)
    if ex is None:
        return None
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
    extras = _new_extras(Path(src_root), rel, lw, timestamp)
    if extras is None:  # no input extras: per-point firing times alone, so the reader gets exact times
        extras = np.zeros(len(lw.labels), dtype=[("time_offset", "<f4")])
        extras["time_offset"] = (lw.times - timestamp).astype(np.float32)
    atomic.save_npz(out_root / compressed_extras_relpath(rel), {n: extras[n] for n in extras.dtype.names},
                    compress=True)
    atomic.save_npz(out_root / weather_relpath(rel), {
        "label": lw.labels.astype(np.uint8),
        "particle_id": lw.particle_id.astype(smallest_int_dtype(lw.particle_id)),
        "source_index": lw.source_index.astype(smallest_int_dtype(lw.source_index))}, compress=True)


def reusable_lidar(twin_root: Path, sample_token: str, fingerprint: str, relpaths: list[str]) -> dict | None:
    """The resume record of ``sample_token`` in the weather copy at ``twin_root`` (the aligned twin of an unaligned
    copy) if its LiDAR files were made with the LiDAR ``fingerprint`` (`lidar_fingerprint` + input stamps) and every
    one of ``relpaths`` is there with its recorded size and SHA-256; None otherwise (the LiDAR is then computed)."""
    record = read_record_json(_progress_file(twin_root, sample_token))
    if record is None or record.get("lidar_fingerprint") != fingerprint:
        return None
    files = record.get("files")
    if not isinstance(files, dict) or any(rel not in files for rel in relpaths):
        return None
    return record if files_intact(twin_root, {rel: files[rel] for rel in relpaths}) else None


def read_lidar_weather(root: Path, rel: str, scan: LidarScan, counts: dict[str, int]) -> LidarWeather:
    """The weather scan ``rel`` of the copy at ``root`` as `LidarWeather` (points, labels, particle ids, source rows
    and the stored firing-time offsets), ``scan`` being its clear input (timestamp, poses) and ``counts`` its
    record's."""
    path = Path(root) / rel
    points = read_float32_records(path, 5, "weather scan")
    record = read_weather_record(root, rel, len(points))
    extras = read_point_extras(root, rel)
    if extras is None or "time_offset" not in (extras.dtype.names or ()) or len(extras) != len(points):
        raise DataFormatError(f"{Path(root) / compressed_extras_relpath(rel)}: expected a time_offset per point of "
                              f"{path}")
    offsets = np.ascontiguousarray(extras["time_offset"], dtype=np.float32)
    weather_scan = replace(scan, points=points, time_offsets=offsets if scan.time_offsets is not None else None,
                           sweep_index=None if scan.sweep_index is None else np.zeros(len(points), np.int16))
    return LidarWeather(weather_scan, record["label"].astype(np.uint8), record["particle_id"].astype(np.int64),
                        record["source_index"].astype(np.int64), scan.timestamp + offsets.astype(np.float64),
                        {k: int(counts.get(k, 0)) for k in COUNT_KEYS}, stored_offsets=offsets)


def write_sample(src_root: Path, out_root: Path, nusc, sample_token: str, fw: FrameWeather, frame: Frame,
                 jpeg_quality: int, lidar_written: bool = False) -> None:
    """Write one sample's weather files (atomically) at the input's relative paths (the keyframe scan unless
    ``lidar_written``)."""
    lidar_rel, _ = _sample_files(nusc, sample_token)
    if not lidar_written:
        write_scan(src_root, out_root, lidar_rel, fw.lidar, frame.lidar.timestamp)
    sample = nusc.get("sample", sample_token)
    for ch, view in frame.cameras.items():
        rel = nusc.get("sample_data", sample["data"][ch])["filename"]
        cw = fw.cameras[ch]
        if cw.image is None:
            link_or_copy(view.image_path, out_root / rel)
        else:
            buf = io.BytesIO()
            Image.fromarray(cw.image).save(buf, format="JPEG", quality=jpeg_quality, subsampling=JPEG_SUBSAMPLING)
            atomic.write_bytes(out_root / rel, buf.getvalue())


def run_sample(nusc, src_root: Path, out_root: Path, job: SampleJob, sensors: SensorRig, options: ObserveOptions,
               run_digest: str, jpeg_quality: int = 92, sweeps: int = 0,
               lidar_twin: Path | None = None) -> tuple[dict, bool]:
    """Simulate and write one sample (its keyframe, cameras and the ``sweeps`` nearest sweeps) unless an identical
    earlier run finished it. Returns (record, done_now).

    ``lidar_twin``: for an unaligned copy, its aligned twin's root. The LiDAR sees the condition's own media in both
    copies, so where the twin finished this sample with the same LiDAR fingerprint (`reusable_lidar`), its LiDAR files
    are hard-linked instead of computed again (byte-identical to computing them; the cameras are rendered as always).

    The record holds the LiDAR counts (keyframe and sweeps apart), the particles rendered, the re-projection errors,
    the bytes written, the wall and CPU seconds taken and the LiDAR fingerprint.
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
    t0, cpu0 = time.time(), time.process_time()
    lidar_files = _lidar_outputs(nusc, token, sweeps)
    lidar_fp = lidar_fingerprint(run_digest, job.media, sensors) + file_stamps(src_root, lidar_files)
    twin = None
    if lidar_twin is not None and not job.media.aligned:
        twin = reusable_lidar(Path(lidar_twin), token, lidar_fp, lidar_files)
    frame = load_frame(nusc, token)
    images = {ch: v.load_image() for ch, v in frame.cameras.items()}
    ranges = sample_range_maps(nusc, frame, images, sensors.ego_body)
    sweep_list = weather_sweeps(nusc, token, sweeps)
    if twin is not None:
        keyframe = read_lidar_weather(Path(lidar_twin), _sample_files(nusc, token)[0], frame.lidar, twin["counts"])
        for rel in lidar_files:  # an earlier run's file there is replaced atomically
            link_or_copy(Path(lidar_twin) / rel, out_root / rel)
        fw = observe(frame, images, ranges, job.media, sensors, np.asarray(job.airlight), options, lidar=keyframe)
        write_sample(src_root, out_root, nusc, token, fw, frame, jpeg_quality, lidar_written=True)
        sweep_counts = {k: int(twin["sweep_counts"].get(k, 0)) for k in COUNT_KEYS}
    else:  # the keyframe and the sweeps through the same media at their own times, in one LiDAR run
        sweep_scans = [load_lidar(nusc, sd["token"]) for sd in sweep_list]
        keyframe, *sweep_weather = observe_lidar_scans([frame.lidar, *sweep_scans], job.media, sensors.lidar)
        fw = observe(frame, images, ranges, job.media, sensors, np.asarray(job.airlight), options, lidar=keyframe)
        write_sample(src_root, out_root, nusc, token, fw, frame, jpeg_quality)
        sweep_counts = {k: 0 for k in COUNT_KEYS}
        for sd, scan, lw in zip(sweep_list, sweep_scans, sweep_weather):
            write_scan(src_root, out_root, sd["filename"], lw, scan.timestamp)
            for k, v in lw.counts.items():
                sweep_counts[k] += v
    outputs = _outputs(nusc, token, sweeps)
    record = write_resume_record(_progress_file(out_root, token), digest, out_root, outputs, {
        "sample": token, "lidar_fingerprint": lidar_fp, "lidar_from_twin": twin is not None,
        "counts": fw.lidar.counts, "sweep_counts": sweep_counts,
        "sweeps_simulated": len(sweep_list), "particles_rendered": fw.particles_rendered,
        "reprojection_px": [float(e) for e in fw.reprojection_px],
        "reprojection_channels": list(fw.reprojection_channels), "ground_iou": dict(fw.ground_iou),
        "bytes_written": _bytes_written(out_root, outputs),
        "seconds": round(time.time() - t0, 3), "cpu_seconds": round(time.process_time() - cpu0, 3)})
    return record, True


def _bytes_written(out_root: Path, outputs: list[str]) -> int:
    """Bytes of the outputs that are files of their own (hard links to the input cost nothing)."""
    total = 0
    for rel in outputs:
        st = (out_root / rel).stat()
        total += st.st_size if st.st_nlink == 1 else 0
    return total


@dataclass(frozen=True)
class DatasetRef:
    """What a worker process needs to open the input dataset itself (`open_nuscenes_cached`): ``dataroot``,
    ``version`` and the manifest's ``content_digest``."""

    dataroot: str
    version: str
    content_digest: str


def run_chunk(dataset: DatasetRef, out_root: Path, jobs: list[SampleJob], sensors: SensorRig,
              options: ObserveOptions, run_digest: str, jpeg_quality: int = 92, sweeps: int = 0,
              lidar_twin: Path | None = None) -> list[tuple[dict, bool]]:
    """`run_sample` for consecutive samples, the dataset opened once per process. Returns one (record, done_now)
    per job, in order."""
    nusc = open_nuscenes_cached(dataset.dataroot, dataset.version, dataset.content_digest)
    return [run_sample(nusc, Path(dataset.dataroot), out_root, job, sensors, options, run_digest, jpeg_quality,
                       sweeps, lidar_twin) for job in jobs]


def copy_outputs(nusc, sample_tokens: list[str], sweeps: int) -> set[str]:
    """Relative paths of every file the weather writes for these samples (scans, their records, cameras)."""
    return {rel for token in sample_tokens for rel in _outputs(nusc, token, sweeps)}


def written_list_path(out_root: Path) -> Path:
    """``<parent>/.progress/<copy name>.written.json``: the relative path of every file the stage placed in the copy
    (weather files, links and copies of the input's), beside the copy like its resume records."""
    out_root = Path(out_root)
    return out_root.parent / PROGRESS_DIR / f"{out_root.name}.written.json"


def _inside(rel: str) -> bool:
    """Whether ``rel`` is a relative path that stays inside the copy (a tampered record must not reach out)."""
    parts = Path(rel).parts
    return bool(parts) and not Path(rel).is_absolute() and ".." not in parts


def files_written_before(out_root: Path) -> set[str]:
    """Relative paths of the files earlier runs placed in the copy at ``out_root``: those of its written list
    (`written_list_path`) and those its per-sample resume records name (empty for a new copy). Only these may be
    removed: any other file in the copy is the user's."""
    out_root = Path(out_root)
    records = [read_record_json(written_list_path(out_root))]
    records += [read_record_json(p) for p in sorted(progress_dir(out_root).glob("*.json"))]
    found: set[str] = set()
    for record in records:
        files = (record or {}).get("files")
        if isinstance(files, (list, dict)):
            found |= {rel for rel in files if isinstance(rel, str) and _inside(rel)}
    return found


def _record_written(out_root: Path, relpaths: set[str]) -> None:
    atomic.write_json(written_list_path(out_root), {"files": sorted(relpaths)})


def _completion_plan(nusc, src_root: Path, version: str, written: set[str]) -> tuple[list[str], list[str]]:
    """(files to complete from the input, in order: every sensor file the weather did not write with its per-point
    extras, then ``maps/`` and the ``<version>/`` tables last; stale weather records to remove: those of the scans
    the weather left clear this time)."""
    complete, stale = [], []
    for sd in nusc.sample_data:
        rel = sd["filename"]
        if rel in written:
            continue
        if sd["sensor_modality"] == "lidar":
            stale.append(weather_relpath(rel))
            complete += [extras_relpath(rel), compressed_extras_relpath(rel)]
        complete.append(rel)
    for top in ("maps", version):
        complete += [str(src.relative_to(src_root)) for src in sorted((src_root / top).rglob("*")) if src.is_file()]
    return complete, stale


def _remove_temporaries(out_root: Path, ours: set[str]) -> int:
    """Remove the `atomic.atomic_path` temporaries a killed run never renamed, of files in ``ours``; returns how
    many."""
    removed = 0
    for leftover in out_root.rglob(".*.tmp"):
        target = atomic.temporary_target(leftover)
        if leftover.is_file() and target is not None and str(target.relative_to(out_root)) in ours:
            leftover.unlink()
            removed += 1
    return removed


def finalize_copy(nusc, src_root: Path, out_root: Path, version: str, written: set[str]) -> dict[str, int]:
    """Complete the weather copy around the files the weather ``written`` (`copy_outputs`): every other sensor file
    and its per-point extras a hard link to the input's (`link_or_copy`; a stale weather file of an earlier run with
    more sweeps or samples is replaced, its weather record removed), then the ``<version>/`` tables and ``maps/`` the
    same way (last, so the copy loads only once complete). Scans left clear have no weather record
    (`read_weather_record` gives their identity record).

    Only files the stage can prove it placed are replaced or removed: those at the paths the input's tables name,
    and those an earlier run recorded (`files_written_before`): files of an earlier input that no table lists any more
    are removed, while anything else in the copy (a user's notes, a folder of their own images) is left as it is.
    Every file placed is recorded in `written_list_path` (before it is placed, so a killed run's files stay known).

    Returns ``{"linked": n, "copied": m, "removed": k}``: files completed now (copied where links were refused) and
    stale files removed.
    """
    src_root, out_root = Path(src_root), Path(out_root)
    to_complete, stale = _completion_plan(nusc, src_root, version, written)
    expected = set(written) | set(to_complete)
    before = files_written_before(out_root)
    _record_written(out_root, before | expected)
    _remove_temporaries(out_root, before | expected)
    done = {"linked": 0, "copied": 0, "removed": 0}

    def remove(rel: str) -> None:
        if (out_root / rel).is_file():
            (out_root / rel).unlink()
            done["removed"] += 1

    def complete(rel: str) -> None:
        src, dst = src_root / rel, out_root / rel
        if not src.is_file():
            remove(rel)
            return
        if dst.is_file() and os.path.samefile(src, dst):
            return
        if dst.is_file() and rel not in written:
            dst.unlink()  # a weather file of an earlier run, or a copy made where links were refused
        done["copied" if link_or_copy(src, dst) else "linked"] += 1

    for rel in stale:
        remove(rel)
    for rel in to_complete:
        complete(rel)
    for rel in sorted(before - expected):  # the stage's own files of an earlier input that no table lists any more
        remove(rel)
    _record_written(out_root, expected)
    return done


def summarise(records: list[dict]) -> dict:
    """Stage metrics from the per-sample records."""
    counts = {k: sum(r["counts"].get(k, 0) for r in records) for k in COUNT_KEYS}
    errors = np.array([e for r in records for e in r["reprojection_px"]], dtype=np.float64)
    ious = [v for r in records for v in r.get("ground_iou", {}).values()]
    return {
        "points_unchanged": counts["UNCHANGED"], "points_attenuated": counts["ATTENUATED"],
        "points_scattered": counts["SCATTERED"] + counts["CLUTTER"], "points_clutter": counts["CLUTTER"],
        "points_lost": counts["LOST"], "points_ground": counts["GROUND"], "points_ground_lost": counts["GROUND_LOST"],
        "points_ground_added": counts["GROUND_ADDED"],
        "ground_iou_mean": float(np.mean(ious)) if ious else None,
        "particles_rendered": sum(r["particles_rendered"] for r in records),
        "reprojection_mean_px": float(errors.mean()) if errors.size else None,
        "reprojection_max_px": float(errors.max()) if errors.size else None,
        "reprojection_p99_px": float(np.percentile(errors, 99)) if errors.size else None,
        "reprojection_pairs": int(errors.size), "num_samples": len(records),
        "sweep_points_scattered": sum(r.get("sweep_counts", {}).get("SCATTERED", 0)
                                      + r.get("sweep_counts", {}).get("CLUTTER", 0) for r in records),
        "sweep_points_lost": sum(r.get("sweep_counts", {}).get("LOST", 0) for r in records),
        "sweeps_simulated": max((r.get("sweeps_simulated", 0) for r in records), default=0),
        "lidar_samples_from_twin": sum(1 for r in records if r.get("lidar_from_twin")),
        "seconds_per_sample": round(float(np.mean([r["seconds"] for r in records])), 3) if records else None,
        "cpu_seconds_per_sample": round(float(np.mean([r.get("cpu_seconds", np.nan) for r in records])), 3)
        if records else None,
        "bytes_written_per_sample": round(float(np.mean([r.get("bytes_written", 0) for r in records]))) if records
        else None,
    }


__all__ = ["JPEG_SUBSAMPLING", "WEATHER_MATERIAL", "DatasetRef", "copy_fingerprint", "copy_outputs",
           "files_written_before", "finalize_copy", "lidar_fingerprint", "link_or_copy", "read_lidar_weather",
           "read_weather_record", "reusable_lidar", "run_chunk", "run_sample", "smallest_int_dtype", "summarise",
           "sweep_records", "weather_relpath", "weather_sweeps", "write_sample", "write_scan", "written_list_path"]
