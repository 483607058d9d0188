"""The `particles` stage's pieces: reproducible field specs, region validation, sensor volumes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from weatheralign.config import PAPER_RAIN_FALL_M_S, params_from_dict
from weatheralign.medium.conditions import FieldSpec, field_seed, field_spec
from weatheralign.medium.distributions import SnowSizeDistribution, rain_field_fall_speed
from weatheralign.medium.field import ParticleField, Particles
from weatheralign.medium.validation import camera_air_volume, check_region, lidar_air_volume


@pytest.fixture
def cfg():
    return params_from_dict({}).particles


def test_field_spec_round_trip_rebuilds_the_same_field(cfg):
    spec = field_spec(cfg, "snow", "scene-0061", 1.7e9)
    again = FieldSpec.from_dict(spec.to_dict())
    assert again == spec
    a = spec.field().materialize([0, 0, 0], [4, 4, 4], 1.7e9 + 0.3)
    b = again.field().materialize([0, 0, 0], [4, 4, 4], 1.7e9 + 0.3)
    assert np.array_equal(a.ids, b.ids) and np.array_equal(a.positions, b.positions) and len(a) > 1000


def test_rain_falls_at_its_drop_size_speed_by_default_and_the_paper_preset_is_2_m_s(cfg):
    """Default (``terminal_velocity_m_s: null``): the median-volume drop's speed at the field's rate, also after the
    media stage replaces the rate; ``2.0``: the paper's fixed speed. LiDAR and cameras read the one field velocity."""
    assert cfg.rain.terminal_velocity_m_s is None
    spec = field_spec(cfg, "rain", "scene-0061", 0.0)
    assert spec.fall_speed_m_s == pytest.approx(rain_field_fall_speed(50.0)) == pytest.approx(6.613, abs=2e-3)
    np.testing.assert_allclose(spec.field().velocity_array, [0.0, 0.0, -rain_field_fall_speed(50.0)], rtol=1e-15)
    np.testing.assert_array_equal(spec.field(aligned=False).velocity_array, spec.field().velocity_array)
    assert FieldSpec.from_dict(spec.to_dict()) == spec
    tuned = dataclasses.replace(spec, rate_mm_h=5.0)  # what resolve_media does with a calibrated rate
    assert tuned.field().velocity_array[2] == pytest.approx(-4.799, abs=2e-3)
    paper = params_from_dict({"particles": {"rain": {"terminal_velocity_m_s": PAPER_RAIN_FALL_M_S}}}).particles
    assert field_spec(paper, "rain", "scene-0061", 0.0).field().velocity_array[2] == -2.0
    with pytest.raises(ValueError, match="terminal_velocity_m_s = None is invalid"):
        dataclasses.replace(field_spec(cfg, "snow", "s", 0.0), terminal_velocity_m_s=None).field()


def test_seeds_differ_per_scene_and_condition_and_unaligned_twin_is_independent(cfg):
    seeds = {field_seed(cfg.seed, c, s) for c in ("snow", "rain") for s in ("scene-0061", "scene-0103")}
    assert len(seeds) == 4 and field_seed(cfg.seed, "snow", "x") == field_seed(cfg.seed, "snow", "x")
    spec = field_spec(cfg, "rain", "scene-0061", 100.0)
    aligned = spec.field().materialize([0, 0, 0], [2, 2, 2], 100.0, min_diameter=1e-3)
    twin = spec.field(aligned=False).materialize([0, 0, 0], [2, 2, 2], 100.0, min_diameter=1e-3)
    assert spec.field(aligned=False).seed != spec.field().seed
    assert not np.isin(aligned.positions[:, 0], twin.positions[:, 0]).any()
    assert abs(len(aligned) - len(twin)) < 5 * np.sqrt(len(aligned))  # same statistics


def test_params_drive_the_spec(cfg):
    changed = params_from_dict({"particles": {"snow": {"rate_mm_h": 4.0, "wind_m_s": [3.0, 0.0]}}}).particles
    spec = field_spec(changed, "snow", "s", 0.0)
    assert spec.rate_mm_h == 4.0 and spec.field().velocity == (3.0, 0.0, -1.5)
    light = field_spec(cfg, "snow", "s", 0.0).field()
    # heavier snow: more extinction, larger flakes (in Hahner's model also fewer of them)
    assert spec.field().extinction() > light.extinction()
    assert spec.field().spectrum.moment(1) > light.spectrum.moment(1)


class _Mislabelled:
    """A field that claims ``claimed``'s statistics (density, size spectrum, expected counts) but materialises the
    particles of ``source``, every diameter scaled by ``diameter_scale``: a wrong field `check_region` must catch."""

    def __init__(self, claimed: ParticleField, source: ParticleField, diameter_scale: float = 1.0) -> None:
        self.claimed, self.source, self.diameter_scale = claimed, source, diameter_scale

    @property
    def spectrum(self):
        return self.claimed.spectrum

    def number_density(self, min_diameter: float = 0.0) -> float:
        return self.claimed.number_density(min_diameter)

    def expected_count(self, bounds_min, bounds_max, min_diameter: float = 0.0) -> float:
        return self.claimed.expected_count(bounds_min, bounds_max, min_diameter)

    def materialize(self, bounds_min, bounds_max, t, **kwargs) -> Particles:
        p = self.source.materialize(bounds_min, bounds_max, t, **kwargs)
        return dataclasses.replace(p, diameters=p.diameters * self.diameter_scale)


@pytest.mark.parametrize("wrong, count_ok, sizes_ok", [
    (None, True, True),  # the field itself
    ("snowfall 8 mm/h", False, False),  # another rate: density and spectrum both wrong
    ("diameters x 1.03", True, False),  # right count, sizes 3 % too large
])
def test_region_check_accepts_the_field_and_rejects_a_wrong_distribution(cfg, wrong, count_ok, sizes_ok):
    field = field_spec(cfg, "snow", "scene-0061", 0.0).field()
    if wrong is None:
        region = field
    elif wrong.startswith("snowfall"):
        heavy = dataclasses.replace(field, distribution=SnowSizeDistribution(8.0, field.distribution.terminal_velocity))
        assert heavy.spectrum.lam != field.spectrum.lam
        region = _Mislabelled(field, heavy)
    else:
        region = _Mislabelled(field, field, diameter_scale=1.03)
    check = check_region(region, np.array([500.0, 500.0, 5.0]), 0.0, 200_000)
    assert check.realised > 20_000 and check.expected == pytest.approx(field.expected_count(
        check.centre - check.side / 2, check.centre + check.side / 2))
    assert (abs(check.z_score) < 4) == count_ok, check.z_score
    assert (check.chi2_pvalue > 1e-3) == sizes_ok, check.chi2_pvalue
    if not sizes_ok:
        assert check.chi2_pvalue < 1e-6


def test_sensor_volumes_match_closed_forms():
    e0, e1, R = -30.0, 10.0, 50.0
    free = lidar_air_volume(R, 1000.0, 1e6, (e0, e1), samples=800)  # far above ground, no layer top
    exact = 2 * np.pi / 3 * R**3 * (np.sin(np.radians(e1)) - np.sin(np.radians(e0)))
    assert free == pytest.approx(exact, rel=5e-3)
    assert lidar_air_volume(R, 1.84, 30.0, (e0, e1)) < 0.5 * exact  # the ground cuts most of the downward band
    K = np.array([[800.0, 0, 400], [0, 800.0, 225], [0, 0, 1]])
    frustum = camera_air_volume(K, 800, 450, 1000.0, 40.0, 1e6)
    assert frustum == pytest.approx((800 / 800) * (450 / 800) * 40.0**3 / 3, rel=1e-2)
