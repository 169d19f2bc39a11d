"""The rig calibration's covariance record: written by ``calibrate_rig``, round trip
through the calibrated rig TOML, and bad tables refused naming the field."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from gonio.errors import ConfigError
from gonio.rig.calibration import CameraPrior, calibrate_rig, write_calibrated_rig
from gonio.rig.calibration_plan import rig_calibration_poses
from gonio.rig.calibration_record import ParameterCovariance
from gonio.rig.config import default_rig_config, load_rig_config


def _load_truth():
    path = Path(__file__).with_name("calibration_truth.py")
    spec = importlib.util.spec_from_file_location("gonio_tests_calibration_truth_cov", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ct = _load_truth()
NOMINAL = default_rig_config()


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    rng = np.random.default_rng(31)
    values = ct.draw_values(rng, NOMINAL)
    true_intr, K, dist, K_std, dist_std = ct.draw_camera(rng)
    boards, spots = ct.simulate(NOMINAL, values, rig_calibration_poses(NOMINAL), true_intr, rng)
    cal = calibrate_rig(NOMINAL, boards, spots, CameraPrior(K, dist, K_std, dist_std, rms_px=0.3))
    path = tmp_path_factory.mktemp("cov") / "rig_calibrated.toml"
    write_calibrated_rig(path, cal)
    return cal, path


def test_the_covariance_round_trips_through_the_rig_file(calibrated):
    cal, path = calibrated
    rec = load_rig_config(path).calibration.covariance
    assert rec is not None
    idx = [cal.names.index(n) for n in rec.names]
    # every fitted parameter with a finite std, in the fit's order, to the bit (the
    # record is the fit's matrix made exactly symmetric)
    assert len(rec.names) == int(np.isfinite(cal.std).sum())
    sub = cal.covariance[np.ix_(idx, idx)]
    np.testing.assert_array_equal(rec.array(), 0.5 * (sub + sub.T))
    # its diagonal is the record's standard deviations
    for n, v in zip(rec.names, np.sqrt(np.diag(rec.array())), strict=True):
        est = cal.record.parameters.get(n) or cal.record.intrinsics[n]
        assert v == pytest.approx(est.std, rel=1e-12)
    # off-diagonal terms carry information (the stage and arm terms are correlated)
    corr = rec.array() / np.outer(np.sqrt(np.diag(rec.array())), np.sqrt(np.diag(rec.array())))
    assert np.max(np.abs(corr - np.eye(len(rec.names)))) > 0.3


def _edited(path: Path, tmp_path: Path, edit) -> Path:
    import tomllib

    doc = tomllib.loads(path.read_text())
    edit(doc["calibration"]["covariance"])
    out = tmp_path / "edited.toml"
    out.write_text(tomli_w.dumps(doc))
    return out


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda c: c["names"].__setitem__(0, "warp_drive"), "warp_drive"),
        (lambda c: c["names"].__setitem__(1, c["names"][0]), "more than once"),
        (lambda c: c["matrix"].pop(), "expected"),
        (lambda c: c["matrix"][0].append(0.0), "expected"),
        (lambda c: c["matrix"][0].__setitem__(1, c["matrix"][0][1] + 1.0), "not symmetric"),
        (lambda c: c["matrix"][2].__setitem__(2, -1.0), "negative variance"),
        (lambda c: c.pop("matrix"), "matrix"),
    ],
)
def test_a_bad_covariance_table_is_refused_naming_the_field(calibrated, tmp_path, edit, match):
    _, path = calibrated
    bad = _edited(path, tmp_path, edit)
    with pytest.raises(ConfigError, match=match) as exc:
        load_rig_config(bad)
    assert "covariance" in str(exc.value)


def test_not_positive_semidefinite_is_refused():
    with pytest.raises(ValueError, match="positive semi-definite"):
        ParameterCovariance(
            names=["light_elevation", "camera_elevation"], matrix=[[1.0, 2.0], [2.0, 1.0]]
        )


def test_a_record_without_covariance_loads_as_before(calibrated, tmp_path):
    import tomllib

    _, path = calibrated
    doc = tomllib.loads(path.read_text())
    del doc["calibration"]["covariance"]
    out = tmp_path / "old.toml"
    out.write_text(tomli_w.dumps(doc))
    assert load_rig_config(out).calibration.covariance is None
