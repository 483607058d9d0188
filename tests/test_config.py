import re
import shutil
from pathlib import Path

import pytest
import yaml

from weatheralign.config import (
    SECTIONS,
    SETUP_FILES,
    ConfigError,
    apply_override,
    load_params,
    params_from_dict,
    params_tree,
)

from .conftest import REPO


def _params_file(tmp_path: Path, old: str = "", new: str = "", name: str = "p.yaml", section: str = "") -> Path:
    """The repository's params.yaml (every section present, as `load_params` requires) with one text edit (the
    first ``old`` of ``section`` when given, else the only one), beside a copy of the setup files it names."""
    shutil.copytree(REPO / "configs", tmp_path / "configs", dirs_exist_ok=True)
    text = (REPO / "params.yaml").read_text()
    if old:
        start = text.index(f"\n{section}:") if section else 0
        assert old in text[start:] and (section or text.count(old) == 1), old
        i = text.index(old, start)
        text = text[:i] + new + text[i + len(old):]
    f = tmp_path / name
    f.write_text(text)
    return f


def test_repository_params_load_with_defaults():
    p = load_params(REPO / "params.yaml")
    assert p.world.num_train_scenes == 8 and p.world.num_val_scenes == 2
    assert p.world.lidar.firings_per_ring == 1085
    assert p.paths.data == Path("data")


def test_out_of_range_value_names_key_and_range(tmp_path):
    f = _params_file(tmp_path, "  ego_speed_max: 12.0\n", "  ego_speed_max: 30\n")
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value) == f"{f}: world.ego_speed_max = 30 is invalid: Input should be less than or equal to 12"


def test_unknown_key_is_refused():
    with pytest.raises(ConfigError, match=r"world.num_scenes .*unknown key"):
        params_from_dict({"world": {"num_scenes": 3}})


def test_cross_field_check():
    with pytest.raises(ConfigError, match="ego_speed_min"):
        params_from_dict({"world": {"ego_speed_min": 11, "ego_speed_max": 6}})


def test_set_overrides_parse_yaml_values(tmp_path):
    f = _params_file(tmp_path, "  seed: 2026\n", "  seed: 1\n")
    p = load_params(f, ["world.seed=7", "world.camera.shadows=false", "run.dask_address=tcp://127.0.0.1:8786"])
    assert p.world.seed == 7 and p.world.camera.shadows is False
    assert p.run.dask_address == "tcp://127.0.0.1:8786"


def test_bad_override_syntax():
    with pytest.raises(ConfigError, match="key.sub=value"):
        apply_override({}, "world.seed")
    with pytest.raises(ConfigError, match="is a value"):
        apply_override({"world": 3}, "world.seed=1")


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("world: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params(bad)


def test_nuscenes_source_needs_dataroot():
    with pytest.raises(ConfigError, match="nuscenes_dataroot"):
        params_from_dict({"world": {"source": "nuscenes"}})


def test_reference_section_defaults_and_ranges():
    p = load_params(REPO / "params.yaml")
    ref = p.reference
    assert ref.source == "synthetic" and ref.intensity_max == 255.0 and ref.frames_per_split >= 1
    assert ref.split_files.clear and ref.alpha_light[1] <= ref.alpha_dense[0]
    with pytest.raises(ConfigError, match=r"reference.lidar.firings_per_ring = 50 is invalid: .*greater than or equal "
                                          r"to 90"):
        params_from_dict({"reference": {"lidar": {"firings_per_ring": 50}}})
    with pytest.raises(ConfigError, match=r"reference.intensity_max = 100 is invalid"):
        params_from_dict({"reference": {"intensity_max": 100}})
    with pytest.raises(ConfigError, match="source 'stf' needs stf_root"):
        params_from_dict({"reference": {"source": "stf"}})
    with pytest.raises(ConfigError, match=r"synthetic reference is written on the 0\.\.255 scale"):
        params_from_dict({"reference": {"intensity_max": 1.0}})
    with pytest.raises(ConfigError, match=r"alpha_dense = \[0\.07, 0\.03\] must satisfy"):
        params_from_dict({"reference": {"alpha_dense": [0.07, 0.03]}})
    stf = params_from_dict({"reference": {"source": "stf", "stf_root": "/x", "intensity_max": 1}})
    assert stf.reference.intensity_max == 1.0


def test_every_params_key_is_read_by_some_code() -> None:
    """Each leaf key of params.yaml is accessed as an attribute somewhere outside config.py (a key nothing reads is a
    lie to the user). Keys read by name in a loop are listed with the place that reads them."""
    import re

    repo = Path(__file__).resolve().parents[1]
    dynamic = {"reference.split_files.clear", "reference.split_files.light", "reference.split_files.dense",
               "world.rig", "reference.setup"}
    # ^ read per level by weatheralign.reference.layout.split_files_of (getattr over LEVELS); the setup files' paths
    # by the loader (config.py) and by dvc.yaml's deps

    def leaves(d: dict, prefix: tuple = ()):
        for k, v in d.items():
            yield from (leaves(v, prefix + (k,)) if isinstance(v, dict) else [prefix + (k,)])

    code = "\n".join(p.read_text() for d in ("src", "flows", "tasks") for p in (repo / d).rglob("*.py")
                     if p.name != "config.py")
    tree = params_tree(repo / "params.yaml")  # params.yaml and its setup files (configs/)
    unread = [".".join(k) for k in leaves(tree)
              if ".".join(k) not in dynamic and not re.search(r"\." + re.escape(k[-1]) + r"\b", code)]
    assert not unread, f"params keys no code reads: {unread}"


# --- strict loading: wrong params fail at once, naming the file (or the --set), the key and the expected form ---


def test_repository_params_has_every_section_and_loads():
    tree = yaml.safe_load((REPO / "params.yaml").read_text())
    assert set(SECTIONS) <= set(tree), f"params.yaml lacks {sorted(set(SECTIONS) - set(tree))}"
    p = load_params(REPO / "params.yaml")
    assert p.run.dask_address is None and p.tracking.mlflow_uri is None and p.calibrate_fog.device == "cpu"
    assert p.particles.snow.wind_m_s == (0.0, 0.0)


def test_empty_file_or_missing_section_is_refused(tmp_path):
    for text in ("", "# only a comment\n"):
        empty = tmp_path / "empty.yaml"
        empty.write_text(text)
        with pytest.raises(ConfigError, match=rf"^{empty}: the params file is empty; it must hold the sections "
                                              r"paths, run, tracking, world, particles, simulate, reference, "
                                              r"calibrate_fog, calibrate_precipitation, detect, verify"):
            load_params(empty)
    partial = tmp_path / "partial.yaml"
    partial.write_text("world:\n  seed: 1\n")
    with pytest.raises(ConfigError) as err:
        load_params(partial)
    msg = str(err.value)
    assert msg.startswith(f"{partial}: missing sections paths, run, tracking, particles, simulate, reference, "
                          f"calibrate_fog, calibrate_precipitation, detect, verify: "
                          f"a params file must hold every section")
    # one section short: named alone; --set cannot stand in for it (overrides are for keys)
    f = _params_file(tmp_path, "calibrate_fog:", "calibrate_fog_old:")
    for overrides in ([], ["calibrate_fog.device=cpu"]):
        with pytest.raises(ConfigError, match=rf"^{f}: missing section calibrate_fog: .*--set overrides keys, it "
                                              r"cannot replace a missing section"):
            load_params(f, overrides)
    # only the file loader is strict: params built from partial dicts still take defaults
    assert params_from_dict({"world": {"seed": 1}}).calibrate_fog.device == "cpu"
    assert params_from_dict({}).world.seed == 2026


def test_duplicate_key_is_refused_with_path_and_line(tmp_path):
    f = _params_file(tmp_path, "  seed: 2026\n", "  seed: 2026\n  num_train_scenes: 8\n  seed: 7\n")
    line = next(i for i, t in enumerate(f.read_text().splitlines(), 1) if t == "  seed: 7")
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value).startswith(f"{f}: duplicate key world.seed at line {line} (first given at line {line - 2}")
    nested = _params_file(tmp_path, "    rate_mm_h: 2.0 ", "    rate_mm_h: 9.0\n    rate_mm_h: 2.0 ")
    with pytest.raises(ConfigError, match=rf"^{nested}: duplicate key particles\.snow\.rate_mm_h at line \d+"):
        load_params(nested)
    top = tmp_path / "top.yaml"
    top.write_text((REPO / "params.yaml").read_text() + "\nrun:\n  max_workers: 4\n")
    with pytest.raises(ConfigError, match=rf"^{top}: duplicate key run at line \d+"):
        load_params(top)
    with pytest.raises(ConfigError, match=r"--set 'world.seed=\{a: 1, a: 2\}': the value is not valid YAML: "
                                          r"duplicate key a"):
        apply_override({}, "world.seed={a: 1, a: 2}")


def test_nan_infinite_and_absurd_values_are_refused(tmp_path):
    base = _params_file(tmp_path)
    for raw, expected in ((".nan", "nan is invalid: Input should be a finite number"),
                          ("1e30", "'1e30' is invalid: Input should be less than or equal to 50"),
                          ("-51.0", "-51.0 is invalid: Input should be greater than or equal to -50")):
        for section in ("snow", "rain"):
            override = f"particles.{section}.wind_m_s=[{raw},0]"
            with pytest.raises(ConfigError) as err:
                load_params(base, [override])
            assert str(err.value) == f"--set {override}: particles.{section}.wind_m_s[0] = {expected}"
    assert load_params(base, ["particles.rain.wind_m_s=[-50,12.5]"]).particles.rain.wind_m_s == (-50.0, 12.5)
    # in the file: blamed on the file; every float of every section must be finite, tuples and optionals included
    f = _params_file(tmp_path, "  ego_speed_max: 12.0\n", "  ego_speed_max: .inf\n")
    with pytest.raises(ConfigError, match=rf"^{f}: world.ego_speed_max = inf is invalid: Input should be a finite "
                                          r"number"):
        load_params(f)
    for tree, key in (({"reference": {"alpha_light": [float("nan"), 0.01]}}, r"reference.alpha_light\[0\] = nan"),
                      ({"simulate": {"fog_beta_light": float("nan")}}, r"simulate.fog_beta_light = nan"),
                      ({"world": {"camera": {"exposure_s": "nan"}}}, r"world.camera.exposure_s = 'nan'")):
        with pytest.raises(ConfigError, match=rf"{key} is invalid: Input should be a finite number"):
            params_from_dict(tree)
    with pytest.raises(ConfigError, match=r"simulate.max_samples = 100000000 is invalid: Input should be less than "
                                          r"or equal to 10000000"):
        params_from_dict({"simulate": {"max_samples": 10**8}})


@pytest.mark.parametrize("key, good, bad, form", [
    ("run.dask_address", ["tcp://10.0.0.5:8786", "tls://scheduler.internal:8786", "tcp://[::1]:1", "tcp://h:65535"],
     ["10.0.0.5:8786", "tcp://h:0", "tcp://h:65536", "tcp://:8786", "inproc://x", "tcp://h", ""],
     "expected a Dask scheduler address tcp://host:port or tls://host:port with port 1..65535"),
    ("tracking.mlflow_uri", ["sqlite:///tmp/m.db", "file:/tmp/mlruns", "http://h:5000", "https://mlflow.example",
                             "postgresql://u@h/db", "postgresql+psycopg2://u@h/db", "mysql://u@h/db", "databricks",
                             "databricks://profile"],
     ["mlruns", "/tmp/mlruns", "sqlite:/x.db", "ftp://h", "http://", "databricksx", ""],
     "expected an MLflow tracking URI: sqlite:///<path>, file:<path>, http(s)://<host>[:port], postgresql://..., "
     "mysql://..., databricks[://<profile>]"),
    ("calibrate_fog.device", ["cpu", "cuda", "cuda:0", "cuda:12", "mps"],
     ["gpu", "CUDA", "cuda:", "cuda:x", "cuda0", "tpu", ""],
     "expected a torch device: cpu, cuda, cuda:N (N = GPU index) or mps"),
    ("detect.device", ["cpu", "cuda", "cuda:1", "mps"], ["gpu", "cuda:", ""],
     "expected a torch device: cpu, cuda, cuda:N (N = GPU index) or mps"),
])
def test_addresses_uris_and_devices_are_checked_by_form(tmp_path, key, good, bad, form):
    section, name = key.split(".")
    for value in good:
        assert getattr(getattr(load_params(_params_file(tmp_path), [f"{key}={value}"]), section), name) == value
    for value in bad:
        with pytest.raises(ConfigError) as err:
            params_from_dict({section: {name: value}})
        assert str(err.value).startswith(f"params: {key} = {value!r} is invalid: {form}"), str(err.value)
    # in the file that holds it (params.yaml or the section's setup file): the file and the key are named
    old, new = f"{name}: {'null' if name != 'device' else 'cpu'}", f"{name}: {bad[0]}"
    setup = [k for (s, k), fields in SETUP_FILES.items() if s == section and name in fields]
    f = _params_file(tmp_path, *(() if setup else (old, new)), section=section)
    where, named = f, key
    if setup:
        where = tmp_path / load_params(f).model_dump()[section][setup[0]]
        where.write_text(where.read_text().replace(old, new, 1))
        named = name
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value).startswith(f"{where}: {named} = {bad[0]!r} is invalid: {form}"), str(err.value)


def test_errors_from_set_overrides_name_the_set(tmp_path):
    f = _params_file(tmp_path)
    cases = {
        "simulate.exposure=3": "--set simulate.exposure=3: simulate.exposure = 3 is invalid: unknown key",
        "world.ego_speed_max=30": "--set world.ego_speed_max=30: world.ego_speed_max = 30 is invalid: Input should be "
                                  "less than or equal to 12",
        "run.dask_address=foo:8786": "--set run.dask_address=foo:8786: run.dask_address = 'foo:8786' is invalid: "
                                     "expected a Dask scheduler address",
        "world={seed: -1}": "--set world={seed: -1}: world.rig is missing: the path of the YAML file holding world's "
                            "lidar",  # the --set replaced the whole section, the setup file's path included
        "world={seed: -1, rig: configs/world_rig.yaml}": "--set world={seed: -1, rig: configs/world_rig.yaml}: "
                                                         "world.seed = -1 is invalid: Input should be greater than or "
                                                         "equal to 0",
    }
    for override, expected in cases.items():
        with pytest.raises(ConfigError) as err:
            load_params(f, [override])
        assert str(err.value).startswith(expected), str(err.value)
        assert str(f) not in str(err.value)
    # the file's own bad value stays the file's, next to a harmless --set
    bad = _params_file(tmp_path, "  ego_speed_max: 12.0\n", "  ego_speed_max: 30\n", name="bad.yaml")
    with pytest.raises(ConfigError, match=rf"^{bad}: world.ego_speed_max = 30 is invalid"):
        load_params(bad, ["world.seed=3"])
    # a later --set of the whole section replaces an earlier --set of one of its keys
    with pytest.raises(ConfigError, match=r"^--set world=\{seed: -1, rig: configs/world_rig.yaml\}: world.seed = -1"):
        load_params(f, ["world.seed=5", "world={seed: -1, rig: configs/world_rig.yaml}"])
    # a check over a whole section names the --set keys involved
    with pytest.raises(ConfigError) as err:
        load_params(f, ["world.ego_speed_min=11", "world.ego_speed_max=6"])
    assert str(err.value) == (f"{f}: world is invalid: ego_speed_min (11.0) must not exceed ego_speed_max (6.0) "
                              f"(with --set world.ego_speed_min=11, --set world.ego_speed_max=6)")
    # a value that is not YAML is blamed on its --set, not a traceback
    with pytest.raises(ConfigError, match=r"^--set 'world.seed=\[1': the value is not valid YAML"):
        load_params(f, ["world.seed=[1"])


def test_rain_fall_speed_from_drop_size_by_default_with_the_paper_preset(tmp_path):
    """``particles.rain.terminal_velocity_m_s``: null (the repository's and the default) derives the speed from drop
    size; a number fixes it (the paper's 2.0 m/s); out of range names the key and the range."""
    base = _params_file(tmp_path)
    assert load_params(base).particles.rain.terminal_velocity_m_s is None
    assert params_from_dict({}).particles.rain.terminal_velocity_m_s is None
    assert load_params(base, ["particles.rain.terminal_velocity_m_s=2.0"]).particles.rain.terminal_velocity_m_s == 2.0
    assert load_params(base, ["particles.rain.terminal_velocity_m_s=null"]).particles.rain.terminal_velocity_m_s is None
    with pytest.raises(ConfigError) as err:
        load_params(base, ["particles.rain.terminal_velocity_m_s=20"])
    assert str(err.value) == ("--set particles.rain.terminal_velocity_m_s=20: particles.rain.terminal_velocity_m_s = "
                              "20 is invalid: Input should be less than or equal to 12")


def test_rain_appearance_names_the_presets(tmp_path):
    base = _params_file(tmp_path)
    assert load_params(base).simulate.rain_appearance == "rain"
    assert load_params(base, ["simulate.rain_appearance=rain_weather_edit"]).simulate.rain_appearance == \
        "rain_weather_edit"
    with pytest.raises(ConfigError, match=r"simulate.rain_appearance = 'rain_opaque_drops' is invalid: Input should "
                                          r"be 'rain' or 'rain_weather_edit'"):
        load_params(base, ["simulate.rain_appearance=rain_opaque_drops"])


# --- the setup files params.yaml names (configs/): the same typed records, errors naming file, field and form ---

def test_setup_files_fill_the_typed_records():
    """The sensors and the reference's hidden truth come from configs/, not params.yaml, into the same records."""
    raw = yaml.safe_load((REPO / "params.yaml").read_text())
    for (section, key), fields in SETUP_FILES.items():
        assert raw[section][key].startswith("configs/") and not set(fields) & set(raw[section]), (section, fields)
    p = load_params(REPO / "params.yaml")
    assert p.world.rig == Path("configs/world_rig.yaml") and p.reference.setup == Path("configs/reference.yaml")
    assert p.world.lidar.firings_per_ring == 1085 and p.world.ego_body is not None
    assert p.reference.lidar.firings_per_ring == 1800 and p.reference.alpha_dense == (0.03, 0.07)
    assert p.reference.split_files.snow == "splits/snow.txt" and p.reference.intensity_max == 255.0
    tree = params_tree(REPO / "params.yaml")
    assert tree["world"]["camera"]["image_scale"] == 1.0 and tree["reference"]["precipitation"]["ground"] is True


def test_params_yaml_and_set_override_a_setup_file_key(tmp_path):
    """A key of a setup file given in params.yaml (what ``dvc exp run -S +world.camera.image_scale=0.5`` writes) or
    by ``--set`` wins over the file, the file's other keys stay; ``--set world.rig=...`` reads another file."""
    f = _params_file(tmp_path, "  rig: configs/world_rig.yaml", "  camera:\n    image_scale: 0.5\n"
                                                                "  rig: configs/world_rig.yaml")
    p = load_params(f, ["world.lidar.max_range_m=80"])
    assert p.world.camera.image_scale == 0.5 and p.world.camera.jpeg_quality == 92
    assert p.world.lidar.max_range_m == 80.0 and p.world.lidar.firings_per_ring == 1085
    other = tmp_path / "configs" / "other_rig.yaml"
    other.write_text((REPO / "configs" / "world_rig.yaml").read_text().replace("firings_per_ring: 1085",
                                                                               "firings_per_ring: 2000"))
    assert load_params(f, ["world.rig=configs/other_rig.yaml"]).world.lidar.firings_per_ring == 2000
    assert load_params(f, [f"world.rig={other}"]).world.lidar.firings_per_ring == 2000  # absolute


def _rig(tmp_path: Path, old: str, new: str, name: str = "world_rig.yaml") -> Path:
    """The copied setup file ``name`` with one text edit."""
    rig = tmp_path / "configs" / name
    text = rig.read_text()
    assert text.count(old) == 1, old
    rig.write_text(text.replace(old, new))
    return rig


def test_a_missing_or_malformed_setup_file_names_the_file_the_field_and_the_form(tmp_path):
    f = _params_file(tmp_path)
    rig = tmp_path / "configs" / "world_rig.yaml"
    holds = "a YAML file holding world's lidar, camera, ego_body, sensor_overrides (start from the repository's " \
            "configs/world_rig.yaml)"
    with pytest.raises(ConfigError) as err:
        load_params(f, ["world.rig=configs/nope.yaml"])
    assert str(err.value) == (f"{f}: world.rig = 'configs/nope.yaml': no such file {tmp_path}/configs/nope.yaml; "
                              f"expected {holds}")
    with pytest.raises(ConfigError, match=rf"^{f}: world.rig = 5 is invalid: expected the path of a YAML file"):
        load_params(f, ["world.rig=5"])
    no_key = _params_file(tmp_path, "  rig: configs/world_rig.yaml", "", name="no_key.yaml")
    with pytest.raises(ConfigError, match=rf"^{no_key}: world.rig is missing: the path of the YAML file holding "
                                          r"world's lidar, camera, ego_body, sensor_overrides"):
        load_params(no_key)
    original = rig.read_text()
    for text, expected in (("", "expected a mapping of lidar, camera, ego_body, sensor_overrides, got an empty file"),
                           ("- lidar\n", "expected a mapping of lidar, camera, ego_body, sensor_overrides, got a list"),
                           ("lidar: [unclosed\n", "not valid YAML")):
        rig.write_text(text)
        with pytest.raises(ConfigError, match=rf"^{rig}.*{re.escape(expected)}"):
            load_params(f)
    rig.write_text(original)
    _rig(tmp_path, "  max_range_m: 100.0\n", "  max_range_m: 100.0\n  max_range_m: 90.0\n")
    with pytest.raises(ConfigError, match=rf"^{rig}: duplicate key lidar.max_range_m at line \d+"):
        load_params(f)
    rig.write_text(original)
    _rig(tmp_path, "camera:\n", "kamera:\n")
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value) == (f"{rig}: unknown key kamera: the file world.rig names holds lidar, camera, ego_body, "
                              f"sensor_overrides (check the spelling)")
    rig.write_text(original + "seed: 3\n")
    with pytest.raises(ConfigError, match=rf"^{rig}: unknown key seed: .*; world.seed belongs in params.yaml$"):
        load_params(f)
    rig.write_text(original.split("sensor_overrides:")[0])
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value) == (f"{rig}: missing sensor_overrides: the file world.rig names must hold lidar, camera, "
                              f"ego_body, sensor_overrides (copy what is missing from the repository's "
                              f"configs/world_rig.yaml)")
    rig.write_text(original)
    assert load_params(f).world.lidar.max_range_m == 100.0


def test_a_bad_value_is_blamed_on_where_it_was_given(tmp_path):
    """In a setup file: the file and the key in it (and the params key); given over it in params.yaml or by --set:
    there."""
    f = _params_file(tmp_path)
    rig = _rig(tmp_path, "  max_range_m: 100.0\n", "  max_range_m: 500.0\n")
    with pytest.raises(ConfigError) as err:
        load_params(f)
    assert str(err.value) == (f"{rig}: lidar.max_range_m = 500.0 is invalid: Input should be less than or equal to "
                              f"300 (world.lidar.max_range_m)")
    assert load_params(f, ["world.lidar.max_range_m=90"]).world.lidar.max_range_m == 90.0
    with pytest.raises(ConfigError, match=r"^--set world.lidar.max_range_m=400: world.lidar.max_range_m = 400 is "
                                          r"invalid"):
        load_params(f, ["world.lidar.max_range_m=400"])
    inline = _params_file(tmp_path, "  rig: configs/world_rig.yaml", "  lidar:\n    max_range_m: 600.0\n"
                                                                     "  rig: configs/world_rig.yaml", name="in.yaml")
    with pytest.raises(ConfigError, match=rf"^{inline}: world.lidar.max_range_m = 600.0 is invalid"):
        load_params(inline)
    ref = _rig(tmp_path, "intensity_max: 255 ", "intensity_max: 100 ", name="reference.yaml")
    with pytest.raises(ConfigError, match=rf"^{ref}: intensity_max = 100 is invalid: .*\(reference.intensity_max\)"):
        load_params(f, ["world.lidar.max_range_m=90"])


def test_a_set_that_replaces_a_section_is_named_for_each_missing_setup_path(tmp_path):
    """Both setup paths are checked with the --set overrides in view: replacing the reference section drops its
    path, and the error names that --set, not the world's."""
    f = _params_file(tmp_path)
    with pytest.raises(ConfigError, match=r"^--set reference=\{seed: 1\}: reference.setup is missing"):
        load_params(f, ["world.seed=3", "reference={seed: 1}"])
