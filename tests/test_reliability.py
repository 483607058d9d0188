"""Bad LiDAR values and broken files fail clearly (a `DataFormatError` naming the file, the field, the first bad row
and value, and the expected form), never silently; and property-based checks of the readers' validation and of the
LiDAR path of `simulate` (`observe_lidar`).

The nuScenes cases corrupt a copy of the session's tiny world (tables, LiDAR files and, where an image is corrupted,
the camera folders are copied; the rest is linked read-only); the STF / KITTI cases corrupt copies of the shared real
frames (skipped where ``../shared/data/real`` is absent) or small files written here.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from weatheralign.conditions import CONDITIONS
from weatheralign.config import params_from_dict
from weatheralign.data.errors import SCALE_CHECK_MIN_POINTS, DataFormatError, validate_scan
from weatheralign.data.frame import LidarScan
from weatheralign.data.kitti import load_kitti_frame, read_kitti_points
from weatheralign.data.nuscenes import load_frame, load_lidar, open_nuscenes
from weatheralign.data.stf import load_stf_frame, read_stf_points
from weatheralign.medium.conditions import field_spec
from weatheralign.simulate.media import SceneMedia, params_fog_levels
from weatheralign.simulate.observe import observe_lidar

from .conftest import SHARED_REAL, make_lidar

STF = SHARED_REAL / "stf"
KITTI = SHARED_REAL / "kitti"
STF_ID = "2019-09-11_19-13-44_00960"
PROPERTY = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real sample not available: {path}")
    return path


# ------------------------------------------------------------------------------------ corrupt copies of the world


def _copy_world(tiny_world, dest: Path, cameras: bool = False) -> Path:
    """A copy of the tiny world's dataroot under ``dest``: tables, maps and LiDAR files (and, with ``cameras``, the
    camera images) copied; the per-pixel range maps and (without ``cameras``) the camera folders linked."""
    src = tiny_world.dataroot
    root = dest / "world"
    linked: list[Path] = []

    def ignore(folder: str, names: list[str]) -> set[str]:
        rel = Path(folder).relative_to(src)
        skip = {".progress"} & set(names)
        link = set()
        if rel == Path("extras"):
            link |= {"range"} & set(names)
        if rel in (Path("samples"), Path("sweeps")) and not cameras:
            link |= {n for n in names if n.startswith("CAM_")}
        linked.extend(rel / n for n in link)
        return skip | link

    shutil.copytree(src, root, ignore=ignore)
    for rel in linked:
        os.symlink(src / rel, root / rel)
    return root


def _tables(root: Path, version: str, table: str) -> list[dict]:
    return json.loads((root / version / f"{table}.json").read_text())


def _edit(root: Path, version: str, table: str, edit) -> None:
    path = root / version / f"{table}.json"
    records = json.loads(path.read_text())
    edit(records)
    path.write_text(json.dumps(records))


def _key_record(root: Path, version: str, channel: str) -> tuple[str, dict]:
    """(first sample's token, its key-frame sample_data record of ``channel``)."""
    sample = _tables(root, version, "sample")[0]
    sensors = {s["token"]: s["channel"] for s in _tables(root, version, "sensor")}
    cs = {c["token"]: sensors[c["sensor_token"]] for c in _tables(root, version, "calibrated_sensor")}
    rec = next(sd for sd in _tables(root, version, "sample_data") if sd["sample_token"] == sample["token"]
               and sd["is_key_frame"] and cs[sd["calibrated_sensor_token"]] == channel)
    return sample["token"], rec


@pytest.fixture()
def world_copy(tiny_world, tmp_path):
    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path)
    sample_token, lidar = _key_record(root, version, "LIDAR_TOP")
    return root, version, sample_token, lidar


def _points(path: Path) -> np.ndarray:
    return np.fromfile(path, dtype="<f4").reshape(-1, 5).copy()


LIDAR_CASES = {
    # case: (corruption of the (N, 5) points, the message it must give)
    "nan_intensity": (lambda p: p.__setitem__((7, 3), np.nan),
                      r"1 NaN/inf intensities \(field 'intensity', column 4; first at row 7: nan\); expected a finite "
                      r"intensity on 0\.\.255"),
    "inf_intensity": (lambda p: p.__setitem__((7, 3), np.inf),
                      r"NaN/inf intensities \(field 'intensity', column 4; first at row 7: inf\)"),
    "intensity_above_scale": (lambda p: p.__setitem__((7, 3), 300.0),
                              r"1 intensities outside 0\.\.255 \(field 'intensity', column 4; first at row 7: "
                              r"300\.0\); expected intensity on 0\.\.255"),
    "negative_intensity": (lambda p: p.__setitem__((7, 3), -2.0),
                           r"intensities outside 0\.\.255 \(field 'intensity', column 4; first at row 7: -2\.0\)"),
    "unit_scale": (lambda p: p.__setitem__((slice(None), 3), p[:, 3] / 255.0),
                   r"every intensity of the \d+ points is <= 1\.0 \(field 'intensity', column 4; largest at row \d+: "
                   r"[0-9.]+\): a 0\.\.1 scan declared 0\.\.255; expected intensity on 0\.\.255"),
    "fractional_ring": (lambda p: p.__setitem__((7, 4), 3.5),
                        r"1 invalid rings \(field 'ring', column 5; first at row 7: 3\.5\); expected integers "
                        r"0\.\.31 in column 5"),
    "ring_out_of_range": (lambda p: p.__setitem__((7, 4), 32.0),
                          r"invalid rings \(field 'ring', column 5; first at row 7: 32\.0\); expected integers "
                          r"0\.\.31"),
    "nan_ring": (lambda p: p.__setitem__((7, 4), np.nan),
                 r"invalid rings \(field 'ring', column 5; first at row 7: nan\)"),
    "inf_coordinate": (lambda p: p.__setitem__((7, 2), -np.inf),
                       r"1 points with NaN/inf coordinates \(first at row 7, field 'z': .*\); expected finite x, y, z"),
}


@pytest.mark.parametrize("case", sorted(LIDAR_CASES))
def test_nuscenes_bad_keyframe_values(world_copy, case):
    """Before: only x, y, z were checked; NaN/inf or out-of-scale intensities, 0..1 scans and bad rings loaded."""
    root, version, sample_token, lidar = world_copy
    path = root / lidar["filename"]
    pts = _points(path)
    corrupt, match = LIDAR_CASES[case]
    corrupt(pts)
    pts.astype("<f4").tofile(path)
    nusc = open_nuscenes(root, version)
    with pytest.raises(DataFormatError, match=match) as err:
        load_frame(nusc, sample_token)
    assert str(err.value).startswith(f"{path}: ")


@pytest.mark.parametrize("case", ["nan_intensity", "unit_scale", "fractional_ring", "empty"])
def test_nuscenes_bad_sweep_values(world_copy, case):
    """Every aggregated sweep is validated too, and the error names the sweep's file."""
    root, version, sample_token, lidar = world_copy
    nusc = open_nuscenes(root, version)
    sweep = nusc.get("sample_data", lidar["prev"])
    path = root / sweep["filename"]
    if case == "empty":
        path.write_bytes(b"")
        match = r"empty scan \(0 points\); expected at least one point \(x, y, z, intensity, ring per record\)"
    else:
        pts = _points(path)
        corrupt, match = LIDAR_CASES[case]
        corrupt(pts)
        pts.astype("<f4").tofile(path)
    load_lidar(nusc, lidar["token"], nsweeps=1)  # the key frame alone is fine
    with pytest.raises(DataFormatError, match=match) as err:
        load_lidar(nusc, lidar["token"], nsweeps=2)
    assert str(err.value).startswith(f"{path}: ")


def test_nuscenes_empty_keyframe(world_copy):
    root, version, sample_token, lidar = world_copy
    path = root / lidar["filename"]
    path.write_bytes(b"")
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: empty scan (0 points)")):
        load_frame(open_nuscenes(root, version), sample_token)


def test_nuscenes_bad_extras_time_offsets(world_copy):
    root, version, sample_token, lidar = world_copy
    extras = root / "extras" / "LIDAR_TOP" / (Path(lidar["filename"]).name.split(".")[0] + ".npy")
    rec = np.load(extras)
    rec["time_offset"][3] = np.nan
    np.save(extras, rec)
    with pytest.raises(DataFormatError, match=r"1 NaN/inf time offsets \(field 'time_offset', first at row 3: nan\)"):
        load_frame(open_nuscenes(root, version), sample_token)
    extras.write_bytes(extras.read_bytes()[:200])
    with pytest.raises(DataFormatError, match=r"LIDAR_TOP/.*\.npy: not a valid per-point records file"):
        load_frame(open_nuscenes(root, version), sample_token)


@pytest.mark.parametrize("case", ["truncated", "not_an_image"])
def test_nuscenes_broken_camera_image(tiny_world, tmp_path, case):
    """Before: ``OSError: image file is truncated`` from Pillow, naming neither file nor camera."""
    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path, cameras=True)
    sample_token, cam = _key_record(root, version, "CAM_FRONT")
    path = root / cam["filename"]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if case == "truncated" else b"not a JPEG at all\n" * 10)
    frame = load_frame(open_nuscenes(root, version), sample_token)  # images are decoded when read
    detail = "OSError: image file is truncated" if case == "truncated" else "UnidentifiedImageError"
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: CAM_FRONT image is truncated or not a valid "
                                                        f"JPEG/PNG image ({detail}")):
        frame.cameras["CAM_FRONT"].load_image()
    assert frame.cameras["CAM_BACK"].load_image().shape == (cam["height"], cam["width"], 3)


def test_nuscenes_invalid_table_json(world_copy):
    """Before: ``JSONDecodeError`` from the devkit, naming no table."""
    root, version, *_ = world_copy
    path = root / version / "sample_data.json"
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: not valid JSON: ") +
                       r".* at line \d+ column \d+ \(char \d+\); expected a JSON list of sample_data records"):
        open_nuscenes(root, version)


TABLE_CASES = {
    # case: (table, edit of its records, message) -- problems the devkit trips over while indexing
    "top_level_not_a_list": ("ego_pose", None,
                             r"ego_pose\.json: the top level is a JSON dict; expected a JSON list of ego_pose records"),
    "record_without_token": ("sensor", lambda recs: recs[0].pop("token"),
                             r"sensor\.json: sensor record 0: missing field 'token'"),
    "sample_data_without_calibrated_sensor": (
        "sample_data", lambda recs: recs[0].pop("calibrated_sensor_token"),
        r"sample_data\.json: sample_data [0-9a-f]+: missing field 'calibrated_sensor_token'"),
    "dangling_category": ("instance", lambda recs: recs[0].update(category_token="nope"),
                          r"instance\.json: instance [0-9a-f]+: category_token 'nope' matches no record of "
                          r"category\.json"),
}


@pytest.mark.parametrize("case", sorted(TABLE_CASES))
def test_nuscenes_structurally_wrong_tables(world_copy, case):
    """Before: ``KeyError`` / ``TypeError`` from inside the devkit's indexing."""
    root, version, *_ = world_copy
    table, edit, match = TABLE_CASES[case]
    if edit is None:
        path = root / version / f"{table}.json"
        path.write_text(json.dumps({"records": json.loads(path.read_text())}))
    else:
        _edit(root, version, table, edit)
    with pytest.raises(DataFormatError, match=match):
        open_nuscenes(root, version)


def _drop(key):
    return lambda rec: rec.pop(key)


FRAME_CASES = {
    # case: (channel of the key-frame sample_data edited, or a table, the edit, message)
    "no_lidar_top": ("LIDAR_TOP", lambda rec: rec.update(is_key_frame=False),
                     r"sample\.json: sample {sample}: no LIDAR_TOP sample_data \(no key-frame record of "
                     r".*sample_data\.json with this sample_token on a LIDAR_TOP sensor; channels: \["),
    "no_camera": ("CAM_BACK", lambda rec: rec.update(is_key_frame=False),
                  r"sample\.json: sample {sample}: no CAM_BACK sample_data"),
    "lidar_without_filename": ("LIDAR_TOP", _drop("filename"),
                               r"sample_data\.json: sample_data {token}: missing field 'filename'"),
    "camera_without_filename": ("CAM_FRONT", _drop("filename"),
                                r"sample_data\.json: sample_data {token}: missing field 'filename'"),
    "lidar_without_ego_pose": ("LIDAR_TOP", _drop("ego_pose_token"),
                               r"sample_data\.json: sample_data {token}: missing field 'ego_pose_token'"),
    "dangling_ego_pose": ("LIDAR_TOP", lambda rec: rec.update(ego_pose_token="nope"),
                          r"ego_pose\.json: no ego_pose record with token 'nope' \(referenced by sample_data "
                          r"{token}\.ego_pose_token\)"),
    "camera_without_width": ("CAM_FRONT", _drop("width"),
                             r"sample_data\.json: sample_data {token}: missing field 'width'"),
    "timestamp_not_a_number": ("LIDAR_TOP", lambda rec: rec.update(timestamp="soon"),
                               r"sample_data\.json: sample_data {token}: field 'timestamp' = 'soon'; expected a "
                               r"finite timestamp"),
}


@pytest.mark.parametrize("case", sorted(FRAME_CASES))
def test_nuscenes_missing_records_and_fields(world_copy, case):
    """Before: ``KeyError: 'LIDAR_TOP'``, ``KeyError: 'filename'``, ``TypeError`` from `load_frame`."""
    root, version, sample_token, _ = world_copy
    channel, edit, match = FRAME_CASES[case]
    _, rec = _key_record(root, version, channel)
    _edit(root, version, "sample_data", lambda recs: [edit(r) for r in recs if r["token"] == rec["token"]])
    with pytest.raises(DataFormatError, match=match.format(sample=sample_token, token=rec["token"])):
        load_frame(open_nuscenes(root, version), sample_token)


@pytest.mark.parametrize("field", ["size", "translation", "instance_token"])
def test_nuscenes_bad_annotation(world_copy, field):
    root, version, sample_token, _ = world_copy
    anns = [a for a in _tables(root, version, "sample_annotation") if a["sample_token"] == sample_token]
    assert anns
    token = anns[0]["token"]
    if field == "translation":
        edit, match = (lambda a: a.update(translation=[1.0, 2.0]),
                       r"field 'translation' = \[1\.0, 2\.0\]; expected 3 finite numbers")
    elif field == "instance_token":
        edit, match = (lambda a: a.update(instance_token="nope"), r"instance_token 'nope' matches no record")
    else:
        edit, match = (lambda a: a.pop(field), f"missing field '{field}'")
    _edit(root, version, "sample_annotation", lambda recs: [edit(a) for a in recs if a["token"] == token])
    with pytest.raises(DataFormatError, match=r"sample_annotation(\.json)?.*" + match) as err:
        load_frame(open_nuscenes(root, version), sample_token)
    assert token in str(err.value)


def test_nuscenes_calibration_without_rotation(world_copy):
    root, version, sample_token, lidar = world_copy
    _edit(root, version, "calibrated_sensor", lambda recs: [r.pop("rotation") for r in recs
                                                           if r["token"] == lidar["calibrated_sensor_token"]])
    with pytest.raises(DataFormatError, match=r"calibrated_sensor of samples/LIDAR_TOP/.*calibrated_sensor\.json, "
                                              r"token [0-9a-f]+\): missing field 'rotation'"):
        load_frame(open_nuscenes(root, version), sample_token)


def test_valid_copy_loads_exactly_as_the_world(tiny_world, world_copy):
    """The validation changes nothing for valid data: the copy's frame equals the world's, sweeps included."""
    root, version, sample_token, _ = world_copy
    a = load_frame(open_nuscenes(tiny_world.dataroot, version), sample_token, nsweeps=3)
    b = load_frame(open_nuscenes(root, version), sample_token, nsweeps=3)
    np.testing.assert_array_equal(a.lidar.points, b.lidar.points)
    np.testing.assert_array_equal(a.lidar.time_offsets, b.lidar.time_offsets)
    assert [x.token for x in a.boxes] == [x.token for x in b.boxes]
    for ch in a.cameras:
        np.testing.assert_array_equal(a.cameras[ch].K, b.cameras[ch].K)


# ------------------------------------------------------------------------------- STF / KITTI, real frames copied


@pytest.fixture()
def stf_copy(tmp_path):
    src = _need(STF)
    for name in (f"lidar_hdl64_strongest_{STF_ID}.bin", f"cam_stereo_left_lut_{STF_ID}.png",
                 "calib_cam_stereo_left.json", "calib_tf_tree_full.json"):
        shutil.copy(src / name, tmp_path / name)
    return tmp_path, tmp_path / f"lidar_hdl64_strongest_{STF_ID}.bin"


def test_stf_unit_scale_declared_255(stf_copy):
    """Before: a 0..1 copy of the scan loaded as 0..255 (every point ~255x too dark)."""
    root, path = stf_copy
    pts = _points(path)
    pts[:, 3] /= 255.0
    pts.tofile(path)
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: every intensity of the {len(pts)} points is <= 1.0 "
                                                        f"(field 'intensity', column 4; largest at row")):
        load_stf_frame(root, STF_ID)
    frame = load_stf_frame(root, STF_ID, intensity_max=1.0, camera_folder=None)  # declared as what it is: fine
    assert frame.lidar.intensity_max == 1.0 and frame.lidar.points[:, 3].max() <= 1.0


@pytest.mark.parametrize("case", ["empty", "nan_intensity", "fractional_channel"])
def test_stf_bad_scan(stf_copy, case):
    root, path = stf_copy
    pts = _points(path)
    if case == "empty":
        path.write_bytes(b"")
        match = r"empty scan \(0 points\)"
    elif case == "nan_intensity":
        pts[11, 3] = np.nan
        pts.tofile(path)
        match = r"1 NaN/inf intensities \(field 'intensity', column 4; first at row 11: nan\)"
    else:
        pts[11, 4] = 7.25
        pts.tofile(path)
        match = r"1 invalid channels \(field 'channel', column 5; first at row 11: 7\.25\); expected integers 0\.\.63"
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: ") + match):
        load_stf_frame(root, STF_ID, camera_folder=None)


def test_stf_truncated_image(stf_copy):
    """Before: the frame loaded (header only) and ``OSError: image file is truncated`` came from `load_image`."""
    root, _ = stf_copy
    png = root / f"cam_stereo_left_lut_{STF_ID}.png"
    png.write_bytes(png.read_bytes()[:100_000])
    with pytest.raises(DataFormatError, match=re.escape(f"{png}: STF stereo-left image is truncated or not a valid "
                                                        f"JPEG/PNG image (OSError")):
        load_stf_frame(root, STF_ID)


@pytest.fixture()
def kitti_copy(tmp_path):
    src = _need(KITTI)
    for name in ("000008.bin", "000008.png", "calib.json"):
        shutil.copy(src / name, tmp_path / name)
    return tmp_path


def test_kitti_real_unit_reflectance_is_not_a_scale_error(kitti_copy):
    """KITTI's reflectance is 0..1 by declaration: every value <= 1.0 is right there, not the 0..1-in-0..255 error."""
    frame = load_kitti_frame(kitti_copy / "000008.bin", None, kitti_copy / "calib.json")
    assert len(frame.lidar.points) > SCALE_CHECK_MIN_POINTS and frame.lidar.points[:, 3].max() <= 1.0


@pytest.mark.parametrize("case", ["scale_255", "nan_reflectance", "empty"])
def test_kitti_bad_scan(kitti_copy, case):
    path = kitti_copy / "000008.bin"
    raw = np.fromfile(path, dtype="<f4").reshape(-1, 4).copy()
    if case == "scale_255":
        raw[:, 3] *= 255.0
        match = r"\d+ reflectances outside 0\.\.1 \(field 'reflectance', column 4; first at row \d+: [0-9.]+\); " \
                r"expected reflectance on 0\.\.1"
    elif case == "nan_reflectance":
        raw[5, 3] = np.nan
        match = r"1 NaN/inf reflectances \(field 'reflectance', column 4; first at row 5: nan\)"
    else:
        raw = raw[:0]
        match = r"empty scan \(0 points\); expected at least one point \(x, y, z, reflectance per record\)"
    raw.tofile(path)
    with pytest.raises(DataFormatError, match=re.escape(f"{path}: ") + match):
        load_kitti_frame(path, kitti_copy / "000008.png", kitti_copy / "calib.json")


def test_kitti_truncated_image(kitti_copy):
    png = kitti_copy / "000008.png"
    png.write_bytes(png.read_bytes()[:5000])
    with pytest.raises(DataFormatError, match=re.escape(f"{png}: KITTI image_2 is truncated or not a valid JPEG/PNG "
                                                        f"image (OSError")):
        load_kitti_frame(kitti_copy / "000008.bin", png, kitti_copy / "calib.json")


def test_scale_check_needs_more_than_100_points():
    """A 0..255 scan whose every intensity is <= 1.0 is a scale error only with more than 100 points (a handful of
    dark returns is plausible); a scan declared 0..1 is never one."""
    pts = np.zeros((SCALE_CHECK_MIN_POINTS, 5), np.float32)
    pts[:, 0] = 5.0
    pts[:, 3] = 0.5
    validate_scan(pts, "small.bin", intensity_max=255.0, num_rings=32)
    more = np.concatenate([pts, pts[:1]])
    with pytest.raises(DataFormatError, match=r"small\.bin: every intensity of the 101 points is <= 1\.0"):
        validate_scan(more, "small.bin", intensity_max=255.0, num_rings=32)
    validate_scan(more, "small.bin", intensity_max=1.0, num_rings=32)
    more[3, 3] = 1.5  # one return above 1.0: a dark 0..255 scan, not a 0..1 one
    validate_scan(more, "small.bin", intensity_max=255.0, num_rings=32)


# ------------------------------------------------------------------------- property: the readers' validation

_BAD_VALUES = (np.nan, np.inf, -np.inf, -0.5, 1.5, 256.0, 1e6, 3.5, 31.5, 32.0, 63.0, 64.0, -1.0)


def _valid(points: np.ndarray, intensity_max: float, num_rings: int | None) -> bool:
    """The oracle: what `validate_scan` must accept."""
    if len(points) == 0 or not np.isfinite(points).all():
        return False
    i = points[:, 3]
    if i.min() < 0 or i.max() > intensity_max:
        return False
    if intensity_max == 255.0 and len(points) > SCALE_CHECK_MIN_POINTS and i.max() <= 1.0:
        return False
    if num_rings is not None:
        r = points[:, 4]
        if r.min() < 0 or r.max() > num_rings - 1 or not np.all(r == np.round(r)):
            return False
    return True


@st.composite
def raw_scans(draw) -> tuple[np.ndarray, float]:
    """(N, 5) float32 scans: finite ones on a 0..255 or 0..1 scale with integer rings 0..31, with random corrupted
    cells (NaN, inf, out-of-range and fractional values) dropped in."""
    n = draw(st.integers(0, 400))
    seed = draw(st.integers(0, 2**32 - 1))
    scale = draw(st.sampled_from([255.0, 1.0]))
    rng = np.random.default_rng(seed)
    pts = np.empty((n, 5), np.float32)
    pts[:, :3] = rng.uniform(-100, 100, (n, 3))
    pts[:, 3] = np.round(rng.uniform(0, 255, n)) * np.float32(scale / 255.0)
    pts[:, 4] = rng.integers(0, 32, n)
    if n:
        cells = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 4), st.sampled_from(_BAD_VALUES)),
                              max_size=3))
        for row, col, value in cells:
            pts[row, col] = value
    return pts, scale


@pytest.fixture(scope="module")
def property_world(tiny_world, tmp_path_factory):
    """A world copy whose first key-frame scan each example overwrites (its extras removed: any length is fine)."""
    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path_factory.mktemp("property_world"))
    _, lidar = _key_record(root, version, "LIDAR_TOP")
    (root / "extras" / "LIDAR_TOP" / (Path(lidar["filename"]).name.split(".")[0] + ".npy")).unlink()
    return open_nuscenes(root, version), lidar, root / lidar["filename"]


@PROPERTY
@given(scan=raw_scans(), declared=st.sampled_from([255.0, 1.0]))
def test_property_readers_accept_exactly_the_valid_scans(property_world, tmp_path_factory, scan, declared):
    """nuScenes, STF and KITTI readers over random scans written to files: a scan is accepted iff it is valid
    (never a non-finite value), an accepted scan comes back as stored, and every rejection names the file."""
    pts, _ = scan
    nusc, lidar, nus_path = property_world
    folder = tmp_path_factory.getbasetemp() / "property_scans"
    folder.mkdir(exist_ok=True)
    stf_path, kitti_path = folder / "rec_00001.bin", folder / "000001.bin"
    pts.tofile(nus_path)
    pts.tofile(stf_path)
    pts[:, :4].tofile(kitti_path)
    readers = [
        ("nuscenes", nus_path, lambda: load_lidar(nusc, lidar["token"]).points, _valid(pts, 255.0, 32)),
        ("stf", stf_path, lambda: read_stf_points(stf_path, 64, declared), _valid(pts, declared, 64)),
        ("kitti", kitti_path, lambda: read_kitti_points(kitti_path), _valid(pts[:, :4], 1.0, None)),
    ]
    for name, path, read, valid in readers:
        try:
            out = read()
        except DataFormatError as err:
            event(f"{name}: rejected")
            assert not valid, f"{name} rejected a valid scan: {err}"
            assert str(err).startswith(f"{path}: "), (name, str(err))
            continue
        event(f"{name}: accepted")
        assert valid, f"{name} accepted an invalid scan"
        assert np.isfinite(out).all(), name
        np.testing.assert_array_equal(out[:, :4], pts[:, :4], err_msg=name)
    # the shared function agrees with the oracle on the array itself
    try:
        validate_scan(pts, "array", intensity_max=declared, num_rings=32)
        assert _valid(pts, declared, 32)
    except DataFormatError as err:
        assert not _valid(pts, declared, 32) and str(err).startswith("array: ")


# ------------------------------------------------------------------------- property: the LiDAR path of simulate

_PARAMS = params_from_dict({})
_LEVELS = params_fog_levels(_PARAMS.simulate)
_GRID_COLUMNS = 180  # a coarse firing grid keeps the examples fast (32 x 180 beams)
_LIDAR = make_lidar(columns_per_ring=_GRID_COLUMNS)
_SNOW = field_spec(_PARAMS.particles, "snow", "scene-property", 0.0)
_RANGE_TOLERANCE_M = 1e-3


def _fog_media(level: str, with_snow: bool) -> SceneMedia:
    name = "fog_snow" if with_snow else f"fog_{level}"
    return SceneMedia(CONDITIONS[name], True, "scene-property", lidar_alpha=_LEVELS.alpha[level],
                      lidar_beta=_LEVELS.beta[level], camera_alpha=_LEVELS.alpha[level],
                      field=_SNOW if with_snow else None)


@st.composite
def finite_scans(draw) -> tuple[np.ndarray, np.ndarray | None]:
    """A static scan of random finite points 1..100 m from the sensor, intensities 0..255, rings 0..31: either on
    the sensor's firing grid (with per-point columns, as the synthetic world stores them) or anywhere on the rings'
    elevations (no columns: the beams without return are reconstructed). Returns (points, columns or None)."""
    n = draw(st.integers(1, 1000))
    seed = draw(st.integers(0, 2**32 - 1))
    on_grid = draw(st.booleans())
    rng = np.random.default_rng(seed)
    pattern = _LIDAR.firing_pattern()
    r = rng.uniform(1.0, 100.0, n)
    if on_grid:
        cells = rng.choice(len(pattern.ring), size=n, replace=False)
        d = pattern.directions[cells]
        ring, columns = pattern.ring[cells].astype(np.float32), pattern.column[cells].astype(np.int16)
    else:
        ring_i = rng.integers(0, _LIDAR.num_rings, n)
        el = np.deg2rad(np.asarray(_LIDAR.elevations_deg))[ring_i] + rng.normal(0.0, 0.002, n)
        az = rng.uniform(-np.pi, np.pi, n)
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
        ring, columns = ring_i.astype(np.float32), None
    pts = np.empty((n, 5), np.float32)
    pts[:, :3] = d * r[:, None]
    pts[:, 3] = np.round(rng.uniform(0, 255, n))
    pts[:, 4] = ring
    return pts, columns


def _scan(pts: np.ndarray, columns: np.ndarray | None, folder: Path) -> LidarScan:
    path = None
    if columns is not None:  # where `synthetic_columns` finds them: <root>/extras/LIDAR_TOP/<stem>.npy
        (folder / "samples" / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
        (folder / "extras" / "LIDAR_TOP").mkdir(parents=True, exist_ok=True)
        path = folder / "samples" / "LIDAR_TOP" / "scan.pcd.bin"
        rec = np.zeros(len(pts), dtype=[("time_offset", "<f4"), ("column", "<i2")])
        rec["column"] = columns
        np.save(folder / "extras" / "LIDAR_TOP" / "scan.npy", rec)
    return LidarScan(points=pts, timestamp=0.0, T_ego_lidar=np.eye(4), T_global_ego=np.eye(4), path=path)


def _check_weather(pts: np.ndarray, columns: np.ndarray | None, out) -> None:
    q = out.scan.points
    assert q.dtype == np.float32 and q.ndim == 2 and q.shape[1] == 5
    assert np.isfinite(q).all(), "non-finite output"
    rng = np.linalg.norm(q[:, :3].astype(np.float64), axis=1)  # static pose: the sensor is at the origin
    assert np.all(rng <= _LIDAR.max_range_m + _RANGE_TOLERANCE_M), f"beyond max range: {rng.max()}"
    src = out.source_index
    assert src.shape == (len(q),) and np.all(src < len(pts))
    kept = src >= 0
    along = np.einsum("ij,ij->i", q[kept, :3].astype(np.float64), pts[src[kept], :3].astype(np.float64))
    assert np.all(along >= 0.0), "a point behind the sensor along its beam"
    grid = _LIDAR.num_rings * _LIDAR.columns_per_ring
    no_return = grid - len(pts) if columns is not None else grid
    assert out.counts["CLUTTER"] == int(np.sum(~kept)) <= no_return
    assert len(q) <= len(pts) + no_return
    assert np.all((q[:, 3] >= 0) & (q[:, 3] <= 255.0))
    assert np.all((q[:, 4] >= 0) & (q[:, 4] <= 31) & (q[:, 4] == np.round(q[:, 4])))


@PROPERTY
@given(scan=finite_scans(), level=st.sampled_from(["light", "dense"]))
def test_property_observe_lidar_fog(tmp_path_factory, scan, level):
    pts, columns = scan
    out = observe_lidar(_scan(pts, columns, tmp_path_factory.getbasetemp() / "fog_scans"), _fog_media(level, False),
                        _LIDAR)
    event("grid" if columns is not None else "reconstructed")
    _check_weather(pts, columns, out)
    assert len(out.scan.points) <= len(pts)  # fog adds no points on beams without a return


@PROPERTY
@given(scan=finite_scans(), with_fog=st.booleans())
def test_property_observe_lidar_snow(tmp_path_factory, scan, with_fog):
    pts, columns = scan
    media = _fog_media("light", True) if with_fog else SceneMedia(CONDITIONS["snow"], True, "scene-property",
                                                                  field=_SNOW)
    out = observe_lidar(_scan(pts, columns, tmp_path_factory.getbasetemp() / "snow_scans"), media, _LIDAR)
    event("grid" if columns is not None else "reconstructed")
    event("clutter" if out.counts["CLUTTER"] else "no clutter")
    _check_weather(pts, columns, out)


# ------------------------------------------------------------------------------------------------ the whole dataset
def test_world_checks_a_users_dataset_up_front_and_reports_every_bad_file(tiny_world, tmp_path):
    """world.source=nuscenes reads everything later stages read before anything is written, and one error lists
    every bad file (a truncated image, an empty sweep, a NaN keyframe intensity), not just the first."""
    from flows.world import _summarise_real

    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path, cameras=True)
    records = _tables(root, version, "sample_data")
    image = next(r for r in records if "/CAM_BACK/" in r["filename"])
    (root / image["filename"]).write_bytes((root / image["filename"]).read_bytes()[:5000])
    sweep = next(r for r in records if r["filename"].startswith("sweeps/LIDAR_TOP"))
    (root / sweep["filename"]).write_bytes(b"")
    key = next(r for r in records if r["filename"].startswith("samples/LIDAR_TOP"))
    pts = np.fromfile(root / key["filename"], dtype="<f4").reshape(-1, 5)
    pts[3, 3] = np.nan
    pts.tofile(root / key["filename"])
    params = params_from_dict({"world": {"source": "nuscenes", "nuscenes_dataroot": str(root), "version": version}})
    with pytest.raises(DataFormatError) as err:
        _summarise_real(params)
    msg = str(err.value)
    assert "problem(s) in the dataset" in msg
    for bad in (image["filename"], sweep["filename"], key["filename"]):
        assert Path(bad).name in msg, (bad, msg[:2000])
    # the intact dataset passes and says what it read
    good = _copy_world(tiny_world, tmp_path / "good", cameras=True)
    params = params_from_dict({"world": {"source": "nuscenes", "nuscenes_dataroot": str(good), "version": version}})
    _, summary = _summarise_real(params)
    assert summary["images_checked"] == 6 * summary["num_samples"]
    assert summary["lidar_files_checked"] == summary["num_samples"] + summary["num_sweeps"]


def test_reconstruction_is_bounded_for_near_duplicate_points():
    """Returns a few µrad apart dominating the median azimuth step made a 48-point scan reconstruct ~100,000 beams
    without return (a million for denser clusters); the step is now floored at a physical firing rate."""
    from weatheralign.lidar.beams import reconstruct_no_return_beams

    az = np.concatenate([np.linspace(-0.5, 0.5, 16), 0.1 + 1e-5 * np.arange(32)])
    pts = np.zeros((len(az), 5), dtype=np.float32)
    pts[:, 0], pts[:, 1], pts[:, 2] = 10 * np.cos(az), 10 * np.sin(az), -1.0
    scan = LidarScan(pts, 0.0, np.eye(4), np.eye(4))
    assert len(reconstruct_no_return_beams(scan, min_ring_points=16)) <= 10_000


@pytest.mark.flow
def test_a_stage_failing_on_bad_input_prints_one_clear_line(tmp_path, prefect_home):
    """A stage that stops on a data error says so first and once, without Prefect's ~75-line traceback (which
    WEATHERALIGN_VERBOSE=1 brings back)."""
    import subprocess
    import sys

    from .conftest import REPO

    args = [sys.executable, "-m", "flows.media", "--set", f"paths.data={tmp_path / 'data'}",
            "--set", f"paths.reports={tmp_path / 'reports'}", "--set", "tracking.enabled=false"]
    env = {**{k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}, "PYTHONPATH": str(REPO),
           "PREFECT_HOME": str(prefect_home), "PREFECT_LOGGING_LEVEL": "WARNING"}
    run = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 2
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert lines[0].startswith("error: ") and "manifests/world.json: missing" in lines[0], run.stderr[-2000:]
    assert "Traceback" not in run.stderr and len(lines) <= 2, run.stderr[-2000:]
    verbose = subprocess.run(args, cwd=REPO, env={**env, "WEATHERALIGN_VERBOSE": "1"}, capture_output=True,
                             text=True, timeout=300)
    assert verbose.returncode != 0 and "Traceback" in verbose.stderr


# ------------------------------------------------------------------------------- a rerun keeps the user's files
def test_a_rerun_of_simulate_keeps_the_users_files_in_the_weather_copy(tiny_world, tmp_path):
    """Before: `finalize_copy` removed every file no table lists, so a rerun silently deleted a user's notes and a
    folder of their own images inside a weather copy. Now it removes only files the stage recorded as its own."""
    from weatheralign.simulate.weather_copy import finalize_copy, written_list_path

    version = tiny_world.params.world.version
    nusc = open_nuscenes(tiny_world.dataroot, version)
    out = tmp_path / "simulate" / "fog_dense-aligned"
    finalize_copy(nusc, tiny_world.dataroot, out, version, set())
    placed = json.loads(written_list_path(out).read_text())["files"]
    assert placed and all((out / rel).is_file() for rel in placed if (tiny_world.dataroot / rel).is_file())
    users = {"notes.txt": b"which run was this?\n", "my_images/crop_001.png": b"\x89PNG\r\n\x1a\n" + b"\0" * 64,
             "samples/CAM_FRONT/my_own_frame.jpg": b"\xff\xd8\xff" + b"\0" * 64, ".draft.tmp": b"half a note"}
    for rel, data in users.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)
    done = finalize_copy(nusc, tiny_world.dataroot, out, version, set())  # the rerun
    assert done["removed"] == 0
    for rel, data in users.items():
        assert (out / rel).read_bytes() == data, rel
    assert nusc.sample_data[0]["filename"] in json.loads(written_list_path(out).read_text())["files"]
    assert "notes.txt" not in json.loads(written_list_path(out).read_text())["files"]


# ------------------------------------------------------------------------------------------ image sizes up front
def _resize_front_image(root: Path, version: str) -> tuple[dict, Path]:
    """Halve the first sample's CAM_FRONT image in place; returns its sample_data record and path."""
    from PIL import Image

    _, cam = _key_record(root, version, "CAM_FRONT")
    path = root / cam["filename"]
    with Image.open(path) as im:
        im.resize((im.width // 2, im.height // 2)).save(path, quality=90)
    return cam, path


def test_world_check_names_an_image_whose_size_differs_from_its_table(tiny_world, tmp_path):
    """Before: the dataset check decoded each image and dropped its size, so a resized image passed and `simulate`
    failed midway through a half-written copy. Now the check names the file, its size and the table's."""
    from weatheralign.data.check import check_dataset

    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path, cameras=True)
    cam, path = _resize_front_image(root, version)
    check = check_dataset(open_nuscenes(root, version))
    assert check.errors == (f"{path}: CAM_FRONT image is {cam['width'] // 2}x{cam['height'] // 2}, its sample_data "
                            f"record {cam['token']} says {cam['width']}x{cam['height']}; expected the image's own "
                            f"size there",)
    with pytest.raises(DataFormatError, match="1 problem"):
        check.raise_if_bad(root)


def test_world_check_names_intrinsics_that_do_not_fit_a_resized_image(tiny_world, tmp_path):
    """An image resized with its table's width / height but not its calibrated intrinsics: the principal point
    still sits at the centre of the full-size image, which the check names beside the image's size."""
    from weatheralign.data.check import check_dataset

    version = tiny_world.params.world.version
    root = _copy_world(tiny_world, tmp_path, cameras=True)
    cam, path = _resize_front_image(root, version)
    w, h = cam["width"] // 2, cam["height"] // 2

    def shrink(records: list[dict]) -> None:
        rec = next(r for r in records if r["token"] == cam["token"])
        rec["width"], rec["height"] = w, h

    _edit(root, version, "sample_data", shrink)
    K = next(c["camera_intrinsic"] for c in _tables(root, version, "calibrated_sensor")
             if c["token"] == cam["calibrated_sensor_token"])
    (error,) = check_dataset(open_nuscenes(root, version)).errors
    assert error.startswith(f"{path}: CAM_FRONT image is {w}x{h} as its sample_data record says, but its "
                            f"calibrated_sensor {cam['calibrated_sensor_token']} camera_intrinsic does not fit it: "
                            f"the principal point ({K[0][2]:.1f}, {K[1][2]:.1f}) px is the centre of a "
                            f"{2 * K[0][2]:.0f}x{2 * K[1][2]:.0f} image"), error
    assert error.endswith("rescale camera_intrinsic with the image") and "\n" not in error


# ------------------------------------------------------------------------------------------- the tracking store
def _store_error(db: Path, tmp_path: Path) -> str:
    """The message a stage start gives for the sqlite store ``db`` (`StageTracker.__enter__`)."""
    from tasks.tracking import StageTracker
    from weatheralign.config import ConfigError

    params = params_from_dict({"paths": {"reports": str(tmp_path / "reports")},
                               "tracking": {"mlflow_uri": f"sqlite:///{db}"}})
    with pytest.raises(ConfigError) as err, StageTracker(params, "world", repo=tmp_path):
        pass
    return str(err.value)


def test_a_corrupt_tracking_store_fails_at_stage_start_in_one_line(tmp_path):
    """Before: an SQLAlchemy traceback naming neither the file nor the params key. Now one line names both."""
    db = tmp_path / "mlflow.db"
    db.write_bytes(b"this was an MLflow store once\n" * 100)
    msg = _store_error(db, tmp_path)
    assert msg.startswith(f"{db}: the MLflow tracking store is not a valid SQLite database (file is not a database)")
    assert "tracking.mlflow_uri" in msg and "\n" not in msg


def test_a_tracking_store_under_a_file_fails_at_stage_start_in_one_line(tmp_path):
    """A store whose folder is a file (a typo in tracking.mlflow_uri): refused by name, whoever runs it."""
    (tmp_path / "notes").write_text("a file, not a folder\n")
    db = tmp_path / "notes" / "mlflow.db"
    msg = _store_error(db, tmp_path)
    assert msg.startswith(f"{db}: the MLflow tracking store cannot be created (Not a directory: {db.parent}); its "
                          f"folder {db.parent} must be a writable folder"), msg
    assert "tracking.mlflow_uri" in msg and "\n" not in msg


NOBODY = 65534
"""The unprivileged user the read-only cases run as when the tests run as root (root writes anything)."""


def _store_check_message(uri: str) -> str:
    """`check_tracking_store`'s message for ``uri`` ("" when it passes)."""
    from tasks.tracking import check_tracking_store
    from weatheralign.config import ConfigError

    try:
        check_tracking_store(uri)
    except ConfigError as err:
        return str(err)
    return ""


def _unprivileged_store_check(uri: str) -> str:
    """`_store_check_message` as the user running the tests or, for root, in a forked child that became `NOBODY`."""
    if os.geteuid() != 0:
        return _store_check_message(uri)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: drop root, check, report through the pipe, exit without pytest's teardown
        try:
            os.close(read)
            os.setgroups([])
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            os.write(write, _store_check_message(uri).encode())
        except BaseException as exc:  # noqa: BLE001 - reported to the parent instead
            os.write(write, f"child failed: {exc!r}".encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read) as pipe:
        message = pipe.read()
    os.waitpid(pid, 0)
    return message


@pytest.mark.parametrize("read_only", ["file", "folder"])
def test_a_read_only_tracking_store_fails_at_stage_start_in_one_line(read_only):
    """Before: ~100 s of MLflow retries, then a 354-line traceback. Now a real write to the store (not a permission
    check, which root passes) fails at once, in one line naming the file and tracking.mlflow_uri. As root, the check
    runs as an unprivileged user on a store it may read but not write."""
    import sqlite3
    import tempfile

    with tempfile.TemporaryDirectory(dir="/tmp") as base:  # pytest's folders are private to their owner
        folder = Path(base) / "tracking"
        folder.mkdir()
        db = folder / "mlflow.db"
        with sqlite3.connect(db) as con:
            con.execute("CREATE TABLE experiments (name TEXT)")
        con.close()
        os.chmod(base, 0o755)
        os.chmod(db, 0o444 if read_only == "file" else 0o666)
        os.chmod(folder, 0o555 if read_only == "folder" else 0o777)
        try:
            msg = _unprivileged_store_check(f"sqlite:///{db}")
        finally:
            os.chmod(folder, 0o755)
    assert msg.startswith(f"{db}: the MLflow tracking store cannot be written ("), msg
    assert "tracking.mlflow_uri" in msg and "\n" not in msg


def test_a_writable_tracking_store_passes_and_is_unchanged(tmp_path):
    """The check's write is rolled back: the store's bytes stay as they were; a new store's folder is made."""
    import sqlite3

    from tasks.tracking import check_tracking_store

    db = tmp_path / "mlflow.db"
    with sqlite3.connect(db) as con:
        con.execute("CREATE TABLE experiments (name TEXT)")
    con.close()
    before = db.read_bytes()
    check_tracking_store(f"sqlite:///{db}")
    assert db.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["mlflow.db"]
    check_tracking_store(f"sqlite:///{tmp_path / 'new' / 'mlflow.db'}")
    assert (tmp_path / "new").is_dir() and not (tmp_path / "new" / "mlflow.db").exists()
    check_tracking_store("http://127.0.0.1:5000")  # a server: MLflow's to check


# ------------------------------------------------------------------------------------------- one line, not a trace
def test_a_full_disk_names_the_file_and_the_space_left(tmp_path):
    """Before: ``OSError: [Errno 28] No space left on device`` with no path. Now every atomic write names the file
    it was writing and the free space, and the stage prints it as one line (`DiskFullError` is an expected error)."""
    import pickle

    from flows.common import EXPECTED_ERRORS
    from weatheralign.atomic import DiskFullError, atomic_path

    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    target = tmp_path / "out" / "scan.pcd.bin"
    with pytest.raises(DiskFullError) as err, atomic_path(target) as tmp, open("/dev/full", "wb") as full:
        full.write(b"\0" * 4096)  # the kernel answers ENOSPC, as a full disk does
    msg = str(err.value)
    assert re.fullmatch(rf"{re.escape(str(target))}: no space left on the device while writing it \([0-9.]+ MiB "
                        rf"free on {re.escape(str(target.parent))}'s file system\); free some space there and rerun",
                        msg), msg
    assert not tmp.exists() and not target.exists() and err.value.errno == 28
    assert str(pickle.loads(pickle.dumps(err.value))) == msg  # as a worker process sends it back
    assert isinstance(err.value, EXPECTED_ERRORS)


def test_an_unknown_finetune_condition_fails_at_params_load(tmp_path):
    """Before: the detect stage started its Prefect server and then failed blaming ``simulate.condition``. Now the
    params do not load, naming ``detect.finetune_conditions``."""
    from weatheralign.config import ConfigError, load_params

    from .conftest import REPO, write_params_file

    path = write_params_file(tmp_path / "params.yaml", {"detect": {"finetune_conditions": ["fog_dense", "hail"]}})
    with pytest.raises(ConfigError) as err:
        load_params(path)
    assert str(err.value) == (f"{path}: detect.finetune_conditions = ['fog_dense', 'hail'] is invalid: unknown "
                              f"condition 'hail': expected names from {list(CONDITIONS)}")
    with pytest.raises(ConfigError, match=r"^--set detect.finetune_conditions=\[snow, sn0w\]: "
                                          r"detect.finetune_conditions = \['snow', 'sn0w'\] is invalid: unknown "
                                          r"condition 'sn0w'"):
        load_params(REPO / "params.yaml", ["detect.finetune_conditions=[snow, sn0w]"])
    assert params_from_dict({"detect": {"finetune_conditions": list(CONDITIONS)}}).detect.finetune_conditions


def test_a_particle_cell_size_that_does_not_fit_the_layer_fails_at_params_load():
    """Before: params passed and the particles stage failed in a worker (``cell_size = 0.5 [m] is invalid for a 102.0
    m layer``). Now the params do not load, naming the cell size and both layer keys; the smallest cell size the
    message gives builds the field."""
    from weatheralign.config import ConfigError

    tree = {"particles": {"layer_top_m": 100.0, "rain": {"cell_size_m": 0.5}}}
    with pytest.raises(ConfigError) as err:
        params_from_dict(tree)
    msg = str(err.value)
    assert msg.startswith("params: particles is invalid: particles.rain.cell_size_m = 0.5 m cuts the 102 m layer "
                          "(particles.layer_bottom_m = -2.0 to particles.layer_top_m = 100.0) into 204 cells; a "
                          "particle field holds at most 128 cells over the layer: use cell_size_m >= "), msg
    spec = field_spec(params_from_dict({}).particles, "rain", "scene", 0.0)
    with pytest.raises(ValueError, match="at most 128 cells"):  # what the particles stage met
        replace(spec, z_max=100.0, cell_size=0.5).field()
    smallest = float(re.search(r">= ([0-9.]+) m", msg)[1])
    tree["particles"]["rain"]["cell_size_m"] = smallest
    assert field_spec(params_from_dict(tree).particles, "rain", "scene", 0.0).field().nz == 128


WORKER_FAILURE = """
from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import gather, run_stage
from weatheralign.config import params_from_dict
from weatheralign.data.errors import DataFormatError


@task(name="read-scan", cache_policy=NO_CACHE, retries=0)
def read_scan(i: int) -> int:
    if i == 1:
        raise DataFormatError("/data/scan_1.pcd.bin: 3 NaN/inf intensities; expected finite intensity on 0..255")
    return i


@flow(name="worker-failure")
def worker_failure(params) -> list:
    return gather([read_scan.submit(i) for i in range(3)], "scans", False)


run_stage(worker_failure, params_from_dict({"tracking": {"enabled": False}}))
"""


@pytest.mark.flow
def test_a_worker_task_failing_on_bad_data_prints_one_clear_line(tmp_path, prefect_home):
    """Before: a task on a Dask worker process that raised a `DataFormatError` printed the worker's Prefect traceback
    (and a 'Finished in state Failed' line) before the stage's one line. Now each worker preloads the same console
    filter (`flows.common.dask_setup`); ``WEATHERALIGN_VERBOSE=1`` brings the traceback back."""
    import subprocess
    import sys

    from .conftest import REPO

    env = {**{k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "WEATHERALIGN_VERBOSE")},
           "PYTHONPATH": str(REPO), "PREFECT_HOME": str(prefect_home), "PREFECT_LOGGING_LEVEL": "WARNING"}
    args = [sys.executable, "-c", WORKER_FAILURE]
    run = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 2, run.stderr[-3000:]
    errors = [ln for ln in run.stderr.splitlines() if "scan_1.pcd.bin" in ln]
    assert errors == ["error: /data/scan_1.pcd.bin: 3 NaN/inf intensities; expected finite intensity on 0..255"], \
        run.stderr[-3000:]
    assert "Traceback" not in run.stderr and "DataFormatError" not in run.stderr, run.stderr[-3000:]
    verbose = subprocess.run(args, cwd=tmp_path, env={**env, "WEATHERALIGN_VERBOSE": "1"}, capture_output=True,
                             text=True, timeout=600)
    assert verbose.returncode != 0 and "Traceback" in verbose.stderr and "DataFormatError" in verbose.stderr
