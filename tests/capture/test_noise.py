"""Photon-transfer noise model: estimation from synthetic flat and dark frame pairs."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.capture.noise import NoiseModel, estimate_noise
from gonio.capture.raw import RawFrame
from gonio.errors import ConfigError, FileFormatError, ReductionError

GAIN = 0.4  # DN per electron
READ_E = 3.0  # electrons
BLACK = 512
WHITE = 16383
CH = np.tile(np.array([[0, 1], [1, 2]], np.int8), (100, 100))  # RGGB, 200 x 200


def shoot(rng, electrons_mean, name, iso=100.0, exposure_time=0.01, f_number=8.0):
    """A sensor written independently of the code under test: Poisson + Gauss + ADC."""
    e = rng.poisson(np.broadcast_to(electrons_mean, CH.shape)).astype(float)
    dn = np.round(BLACK + GAIN * (e + rng.normal(0, READ_E, CH.shape)))
    dn = np.clip(dn, 0, WHITE)
    return RawFrame(
        name,
        dn - BLACK,
        CH,
        dn >= WHITE,
        np.full(CH.shape, float(BLACK)),
        float(WHITE),
        "RGGB",
        exposure_time,
        iso,
        f_number,
    )


def test_photon_transfer_recovers_gain_and_read_noise():
    rng = np.random.default_rng(1)
    qe = np.array([0.8, 1.0, 0.6])[CH]
    flats = [
        (shoot(rng, lv * qe, f"f{lv}a"), shoot(rng, lv * qe, f"f{lv}b"))
        for lv in (500, 2000, 5000, 10000, 20000, 30000)
    ]
    darks = [(shoot(rng, 0.0, "d1"), shoot(rng, 0.0, "d2"))]
    pt = estimate_noise(flats, darks)
    # statistical precision: ~20000 pixels per point, 18 points -> slope to ~0.5 %
    assert pt.model.gain == pytest.approx(GAIN, rel=0.02)
    assert pt.model.read_noise == pytest.approx(GAIN * READ_E, rel=0.03)
    assert np.allclose(pt.gain_per_channel, GAIN, rtol=0.03)
    assert pt.model.iso == 100.0


def test_fixed_pattern_noise_cancels_in_pairs():
    rng = np.random.default_rng(2)
    prnu = 1 + 0.02 * rng.standard_normal(CH.shape)  # 2 % pixel response non-uniformity
    flats = [(shoot(rng, lv * prnu, "a"), shoot(rng, lv * prnu, "b")) for lv in (2000, 20000)]
    pt = estimate_noise(flats, [(shoot(rng, 0.0, "d1"), shoot(rng, 0.0, "d2"))])
    # PRNU alone would add (0.02 * 0.4 * 20000)^2 = 25600 DN^2 at the top level
    assert pt.model.gain == pytest.approx(GAIN, rel=0.03)


def test_model_variance_and_iso_scaling(tmp_path):
    m = NoiseModel(gain=0.4, read_noise=1.2, iso=100)
    assert m.variance(1000.0) == pytest.approx(0.4 * 1000 + 1.44 + 1 / 12)
    assert m.variance(-5.0) == pytest.approx(1.44 + 1 / 12)
    m4 = m.at_iso(400)
    assert (m4.gain, m4.read_noise) == pytest.approx((1.6, 4.8))
    assert m.variance(1000.0, iso=400) == pytest.approx(1.6 * 1000 + 4.8**2 + 1 / 12)
    m.save(tmp_path / "n.json")
    assert NoiseModel.load(tmp_path / "n.json") == m
    (tmp_path / "bad.json").write_text('{"gain": 0.4}')
    with pytest.raises(ConfigError, match=r"bad\.json.*field 'read_noise': Field required"):
        NoiseModel.load(tmp_path / "bad.json")
    (tmp_path / "bad.json").write_text('{"gain": -0.4, "read_noise": 1.2}')
    with pytest.raises(ConfigError, match=r"bad\.json.*field 'gain'.*greater than 0"):
        NoiseModel.load(tmp_path / "bad.json")
    (tmp_path / "bad.json").write_text('{"gain": 0.4, "read_noise": 1.2, "iso": "high"}')
    with pytest.raises(ConfigError, match=r"bad\.json.*field 'iso'"):
        NoiseModel.load(tmp_path / "bad.json")
    (tmp_path / "bad.json").write_text("[1, 2")
    with pytest.raises(FileFormatError, match=r"bad\.json.*not a readable JSON noise model"):
        NoiseModel.load(tmp_path / "bad.json")
    with pytest.raises(ReductionError, match="gain"):
        NoiseModel(gain=0.0, read_noise=1.0)


def test_one_level_is_not_enough():
    rng = np.random.default_rng(3)
    with pytest.raises(ReductionError, match="two or more"):
        estimate_noise([(shoot(rng, 1000.0, "a"), shoot(rng, 1000.0, "b"))])
    with pytest.raises(ReductionError, match="ISO"):
        estimate_noise([(shoot(rng, 1000.0, "a"), shoot(rng, 1000.0, "b", iso=200))])


@pytest.mark.parametrize(
    ("b_settings", "named"),
    [({"exposure_time": 0.04}, "exposure time (0.01 and 0.04)"), ({"f_number": 5.6}, "f-number")],
)
def test_a_pair_of_two_settings_is_refused_naming_both_frames(b_settings, named):
    # A pair shot at two exposures gave a "gain" thousands of times too large (the level
    # step, not the noise, in the difference), written as the noise model with exit 0.
    rng = np.random.default_rng(4)
    flats = [
        (shoot(rng, 1000.0, "lo_a.dng"), shoot(rng, 4000.0, "lo_b.dng", **b_settings)),
        (shoot(rng, 8000.0, "hi_a.dng"), shoot(rng, 8000.0, "hi_b.dng")),
    ]
    with pytest.raises(ReductionError) as info:
        estimate_noise(flats)
    msg = str(info.value)
    assert "lo_a.dng" in msg and "lo_b.dng" in msg and named in msg and "identical" in msg


def test_exif_rounding_of_one_setting_is_still_a_pair():
    rng = np.random.default_rng(5)
    flats = [
        (shoot(rng, lv, "a", exposure_time=1 / 50), shoot(rng, lv, "b", exposure_time=0.02))
        for lv in (2000.0, 20000.0)
    ]
    assert estimate_noise(flats).model.gain == pytest.approx(GAIN, rel=0.05)
