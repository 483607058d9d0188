from pathlib import Path

import pytest

from weatheralign.config import ConfigError, apply_override, load_params, params_from_dict

from .conftest import REPO


def test_repository_params_load_with_defaults():
    p = load_params(REPO / "params.yaml")
    assert p.world.num_train_scenes == 8 and p.world.num_val_scenes == 2
    assert p.world.lidar.firings_per_ring == 1085
    assert p.paths.data == Path("data")


def test_out_of_range_value_names_key_and_range(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("world:\n  ego_speed_max: 30\n")
    with pytest.raises(ConfigError) as err:
        load_params(f)
    msg = str(err.value)
    assert "world.ego_speed_max" in msg and "30" in msg and "less than or equal to 12" in msg


def test_unknown_key_is_refused():
    with pytest.raises(ConfigError, match=r"world.num_scenes .*unknown key"):
        params_from_dict({"world": {"num_scenes": 3}})


def test_cross_field_check():
    with pytest.raises(ConfigError, match="ego_speed_min"):
        params_from_dict({"world": {"ego_speed_min": 11, "ego_speed_max": 6}})


def test_set_overrides_parse_yaml_values(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("world:\n  seed: 1\n")
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

    import yaml

    repo = Path(__file__).resolve().parents[1]
    dynamic = {"reference.split_files.clear", "reference.split_files.light", "reference.split_files.dense"}
    # ^ read per level by weatheralign.reference.layout.split_files_of (getattr over LEVELS)

    def leaves(d: dict, prefix: tuple = ()):
        for k, v in d.items():
            yield from (leaves(v, prefix + (k,)) if isinstance(v, dict) else [prefix + (k,)])

    code = "\n".join(p.read_text() for d in ("src", "flows", "tasks") for p in (repo / d).rglob("*.py")
                     if p.name != "config.py")
    tree = yaml.safe_load((repo / "params.yaml").read_text())
    unread = [".".join(k) for k in leaves(tree)
              if ".".join(k) not in dynamic and not re.search(r"\." + re.escape(k[-1]) + r"\b", code)]
    assert not unread, f"params keys no code reads: {unread}"
