"""``gonio calibrate rig``: digests checked, parameters printed, the calibrated rig
written (and never overwritten), through the top-level CLI's error handling.

The session's observations come from the test's own simulated as-built rig (monkeypatched
in place of ``gonio.capture.rig_views.calibration_observations``, which reads frames);
the camera calibration file follows ``gonio.capture.camera_calibration``'s schema.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import click
import numpy as np
import pytest
import tomli_w

pytest.importorskip("gonio.capture.rig_views", reason="B's observation reader (issue 15)")
camcal = pytest.importorskip("gonio.capture.camera_calibration")

from gonio.cli import run  # noqa: E402
from gonio.rig.calibration import PARAMETER_NAMES, parameters_of  # noqa: E402
from gonio.rig.calibration_plan import rig_calibration_poses  # noqa: E402
from gonio.rig.config import default_rig_config, load_rig_config  # noqa: E402


def _load_truth():
    path = Path(__file__).with_name("calibration_truth.py")
    spec = importlib.util.spec_from_file_location("gonio_tests_calibration_truth", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ct = _load_truth()
NOMINAL = default_rig_config()
IDENTITY = {"backend": "simulated", "model": "gonio-sim", "serial": "A1", "resolution": [640, 480]}


@pytest.fixture
def session(tmp_path, monkeypatch):
    import gonio.app.calibrate_cli as calibrate_cli
    import gonio.capture.manifest as manifest
    import gonio.capture.rig_views as rig_views

    rng = np.random.default_rng(4)
    values = ct.draw_values(rng, NOMINAL)
    true_intr, K, dist, K_std, dist_std = ct.draw_camera(rng)
    boards, spots = ct.simulate(NOMINAL, values, rig_calibration_poses(NOMINAL), true_intr, rng)
    s = tmp_path / "S"
    s.mkdir()
    doc = {
        "rig": json.loads(NOMINAL.model_dump_json(exclude_none=True)),
        "camera": {"backend": "simulated", "model": "gonio-sim", "settings": {"serial": "A1"}},
        "simulation": {"width": 640, "height": 480},
    }
    monkeypatch.setattr(manifest, "load_manifest", lambda d: doc)
    monkeypatch.setattr(rig_views, "calibration_observations", lambda d, b: (boards, spots, []))
    monkeypatch.setattr(calibrate_cli, "_board_from", lambda p, d: (None, "the test's board"))

    def camera_file(path: Path, identity: dict) -> Path:
        cam = {
            "K": K.tolist(),
            "dist": [float(x) for x in dist],
            "width": 640,
            "height": 480,
            "calibration": {
                "created": "2026-12-01T00:00:00+00:00",
                "digest": camcal.camera_digest(identity),
                "camera": identity,
                "K_std": [float(x) for x in K_std],
                "dist_std": [float(x) for x in dist_std],
                "rms_px": 0.2,
                "n_points": 1000,
                "views_used": ["v0"],
            },
        }
        path.write_text(tomli_w.dumps({"camera": cam}))
        return path

    rig = tmp_path / "rig.toml"
    rig.write_text(tomli_w.dumps(json.loads(NOMINAL.model_dump_json(exclude_none=True))))
    return s, rig, camera_file, values


def test_calibrate_rig_writes_the_calibrated_rig(session, tmp_path, capsys):
    s, rig, camera_file, truth = session
    cam = camera_file(tmp_path / "camera.toml", IDENTITY)
    out = tmp_path / "rig_calibrated.toml"
    argv = ["calibrate", "rig", str(s), "--rig", str(rig), "--camera-calibration", str(cam)]
    code = _run_rig([*argv, "--out", str(out), "--plot", str(tmp_path / "res.png")])
    assert code == 0, capsys.readouterr()
    text = capsys.readouterr().out
    assert "stage_tilt.backlash" in text and "not observable" in text
    loaded = load_rig_config(out)
    got = parameters_of(loaded, NOMINAL)
    for n in PARAMETER_NAMES:
        std = loaded.calibration.parameters[n].std
        assert abs(got[n] - truth[n]) < 5 * std or n.endswith("backlash"), n
    assert (tmp_path / "res.png").stat().st_size > 0
    before = out.read_bytes()
    assert _run_rig([*argv, "--out", str(out)]) == 1
    assert "exists" in capsys.readouterr().err
    assert out.read_bytes() == before


def test_a_calibration_of_another_camera_is_refused(session, tmp_path, capsys):
    s, rig, camera_file, _ = session
    other = {**IDENTITY, "serial": "B2"}
    cam = camera_file(tmp_path / "camera.toml", other)
    out = tmp_path / "rig_calibrated.toml"
    code = _run_rig(
        ["calibrate", "rig", str(s), "--rig", str(rig), "--camera-calibration", str(cam)]
        + ["--out", str(out)]
    )
    assert code == 1
    err = capsys.readouterr().err
    assert camcal.camera_digest(other) in err
    assert camcal.camera_digest(IDENTITY) in err
    assert not out.exists()


def _run_rig(argv: list[str]) -> int:
    """``gonio ARGV`` with the ``calibrate rig`` command registered as the integrator will
    (``gonio.app.calibrate_cli.calibrate.add_command``)."""
    from gonio.app.calibrate_cli import calibrate
    from gonio.app.calibrate_rig_cli import plan_cmd, rig_cmd

    for cmd in (rig_cmd, plan_cmd):
        if cmd.name not in calibrate.commands:
            calibrate.add_command(cmd)
    import gonio.cli as cli

    if "calibrate" not in cli._SUBCOMMANDS:
        cli.cli.add_command(calibrate)
    assert isinstance(calibrate, click.Group)
    return run(*argv)
