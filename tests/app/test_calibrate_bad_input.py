"""Bad input to the lab path's calibration steps, through the top-level CLI: exit code 1,
an ``error:`` line naming the thing, no traceback, and no output file changed.

Covered elsewhere (not repeated here): too few views and a board found in no image
(``tests/app/test_calibrate_camera_cli.py``), a camera calibration with another serial
(``tests/rig/test_calibrate_rig_cli.py``, ``tests/capture/test_reduce.py``).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from gonio.capture.camera_calibration import camera_digest, camera_identity
from gonio.capture.manifest import load_manifest
from gonio.cli import run
from gonio.rig.calibration_plan import rig_calibration_poses
from gonio.rig.config import default_rig_config, virtual_rig_document

TINY_PLAN = {
    "name": "tiny",
    "seed": 0,
    "settle_s": 0.0,
    "grid": {
        "kind": "spherical",
        "theta_i_deg": [30.0],
        "phi_i_deg": [0.0],
        "theta_o_deg": [30.0],
        "phi_o_deg": [180.0],
    },  # fmt: skip
    "bracket": {"policy": "adaptive", "exposure_time_s": 0.02, "max_frames": 2},
    "darks": {"count": 0},
    "reference": {
        "when": "start",
        "reflectance": 0.99,
        "poses": [{"theta_i_deg": 0, "theta_o_deg": 40, "phi_o_deg": 180}],
    },  # fmt: skip
    "simulation": {"width": 160, "height": 120},
}


def cli(capsys, *argv: str) -> tuple[int, str]:
    code = run(*argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, err


def digests(*paths: Path) -> dict[str, str | None]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None for p in paths
    }


def camera_file(path: Path, identity: dict) -> Path:
    """A camera calibration file of ``identity`` (gonio.capture.camera_calibration's
    schema), the K of a 640 x 480 camera."""
    w, h = identity["resolution"]
    cam = {
        "K": [[600.0, 0.0, w / 2 - 0.5], [0.0, 600.0, h / 2 - 0.5], [0.0, 0.0, 1.0]],
        "dist": [0.0] * 5,
        "width": w,
        "height": h,
        "calibration": {
            "created": "2026-12-01T00:00:00+00:00",
            "digest": camera_digest(identity),
            "camera": identity,
            "K_std": [0.5, 0.5, 0.5, 0.5],
            "dist_std": [1e-3] * 5,
            "rms_px": 0.2,
            "n_points": 1000,
            "views_used": ["v0"],
        },
    }
    path.write_text(tomli_w.dumps({"camera": cam}))
    return path


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    """A tiny simulated session at 160 x 120 with an earlier reduction's outputs."""
    d = tmp_path_factory.mktemp("tiny")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(tomli_w.dumps(TINY_PLAN))
    s = d / "S"
    cap = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    # an as-built world, so that the simulated camera has a serial like a real one
    sim = ["--camera", "simulated", "--world", "realistic", "--world-seed", "3"]
    assert run(*cap, *sim, "--out", str(s), "--quiet") == 0
    # stand-ins for an earlier reduction's outputs, which a refused one must leave alone
    (s / "samples.h5").write_bytes(b"an earlier reduction")
    (s / "reduction.json").write_text("{}")
    return d, s


def other_resolution_camera(tmp_path: Path, session: Path) -> tuple[Path, dict, dict]:
    ours = camera_identity(load_manifest(session)["camera"])
    assert ours is not None and list(ours["resolution"]) == [160, 120], ours
    other = {**ours, "resolution": [640, 480]}
    return camera_file(tmp_path / "camera.toml", other), ours, other


def test_reduce_refuses_a_camera_calibration_of_another_resolution(reduced, tmp_path, capsys):
    _, s = reduced
    cal, ours, other = other_resolution_camera(tmp_path, s)
    outputs = [s / "samples.h5", s / "reduction.json", s / "reduction.toml"]
    before = digests(*outputs)
    code, err = cli(capsys, "capture", "reduce", str(s), "--quiet", "--camera-calibration",
                    str(cal))  # fmt: skip
    assert code == 1, err
    assert err.startswith("error: ") and str(cal) in err, err
    assert camera_digest(other) in err and camera_digest(ours) in err, err
    assert digests(*outputs) == before


def test_calibrate_rig_refuses_a_camera_calibration_of_another_resolution(
    reduced, tmp_path, capsys
):
    d, s = reduced
    cal, ours, other = other_resolution_camera(tmp_path, s)
    out = tmp_path / "rig_calibrated.toml"
    out.write_text("# an earlier calibration, kept\n")
    plot = tmp_path / "res.png"
    before = digests(out, plot)
    code, err = cli(capsys, "calibrate", "rig", str(s), "--rig", str(d / "rig.toml"),
                    "--camera-calibration", str(cal), "--out", str(out), "--plot", str(plot),
                    "--force")  # fmt: skip
    assert code == 1, err
    assert err.startswith("error: ") and camera_digest(other) in err, err
    assert camera_digest(ours) in err, err
    assert digests(out, plot) == before


def _calibration_truth():
    path = Path(__file__).parents[1] / "rig" / "calibration_truth.py"
    spec = importlib.util.spec_from_file_location("gonio_tests_calibration_truth_e2", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_calibrate_rig_refuses_observations_approaching_a_joint_from_one_side(
    tmp_path, monkeypatch, capsys
):
    """A rig plan edited so that every pose approaches the tilt from the same side: its
    backlash is undetermined, and the calibration says so before writing anything.  The
    observations come from tests/rig/calibration_truth.py's independent simulation
    (the frames' detection is tested elsewhere)."""
    import gonio.app.calibrate_cli as calibrate_cli
    import gonio.capture.manifest as manifest
    import gonio.capture.rig_views as rig_views

    ct = _calibration_truth()
    nominal = default_rig_config()
    rng = np.random.default_rng(11)
    values = ct.draw_values(rng, nominal)
    intr, K, dist, K_std, dist_std = ct.draw_camera(rng)
    poses = rig_calibration_poses(nominal)
    boards, spots = ct.simulate(nominal, values, poses, intr, rng,
                                force_side={"stage_tilt": 1})  # fmt: skip
    assert {b.approach["stage_tilt"] for b in boards} == {1}
    identity = {"backend": "simulated", "model": "gonio-sim", "serial": "A1",
                "resolution": [640, 480]}  # fmt: skip
    doc = {
        "rig": json.loads(nominal.model_dump_json(exclude_none=True)),
        "camera": {"backend": "simulated", "model": "gonio-sim", "settings": {"serial": "A1"}},
        "simulation": {"width": 640, "height": 480},
    }
    s = tmp_path / "S"
    s.mkdir()
    monkeypatch.setattr(manifest, "load_manifest", lambda d: doc)
    monkeypatch.setattr(rig_views, "calibration_observations", lambda d, b: (boards, spots, []))
    monkeypatch.setattr(calibrate_cli, "_board_from", lambda p, d: (None, "the test's board"))
    cam = camera_file(tmp_path / "camera.toml", identity)
    cam_doc = tomllib.loads(cam.read_text())
    cam_doc["camera"]["K"] = K.tolist()
    cam_doc["camera"]["dist"] = [float(x) for x in dist]
    cam_doc["camera"]["calibration"]["K_std"] = [float(x) for x in K_std]
    cam_doc["camera"]["calibration"]["dist_std"] = [float(x) for x in dist_std]
    cam.write_text(tomli_w.dumps(cam_doc))
    rig = tmp_path / "rig.toml"
    rig.write_text(tomli_w.dumps(doc["rig"]))
    out = tmp_path / "rig_calibrated.toml"
    code, err = cli(capsys, "calibrate", "rig", str(s), "--rig", str(rig),
                    "--camera-calibration", str(cam), "--out", str(out))  # fmt: skip
    assert code == 1, err
    assert err.startswith("error: "), err
    assert "stage_tilt.backlash" in err and "same side" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "table, named",
    [
        ("squares_x = 7.5", "squares_x"),
        ('squares_y = "7"', "squares_y"),
        ("marker_length = 0.03", "marker_length must be smaller"),
        ("dictionary = 5", "dictionary"),
        # more markers than DICT_4X4_50 holds: it stalled for minutes per image
        ("squares_x = 100000\nmarker_length = 0.015", "350000 markers, more than the 50"),
    ],
)
def test_a_bad_board_table_is_named_not_a_traceback(tmp_path, capsys, table, named):
    board = tmp_path / "board.toml"
    board.write_text(f"[board]\nsquare_length = 0.02\n{table}\n")
    (tmp_path / "imgs").mkdir()
    out = tmp_path / "camera.toml"
    code, err = cli(
        capsys, "calibrate", "camera", str(tmp_path / "imgs"), "--board", str(board),
        "--calibration", str(out),
    )  # fmt: skip
    assert code == 1 and "error:" in err and named in err, err
    assert not out.exists()


def test_a_world_table_that_is_not_a_table_is_named(tmp_path):
    from gonio.errors import ConfigError
    from gonio.simulator.world import load_world

    with pytest.raises(ConfigError, match="tables"):
        load_world({"preset": "realistic", "rig": "x"})


@pytest.mark.parametrize(
    ("option", "value", "expect"),
    [
        ("--spot-exposure", "nan", "finite"),
        ("--board-exposure", "nan", "finite"),
        ("--board-exposure", "inf", "finite"),
        ("--board-exposure", "1e9", "at most 3600 s"),
    ],
)
def test_calibrate_plan_refuses_an_exposure_its_plan_could_not_hold(
    tmp_path, capsys, option, value, expect
):
    # It wrote the plan and said so (exit 0); `gonio capture run` then refused the plan's
    # bracket.exposures_s.  A plan that exists already is left as it was.
    out = tmp_path / "camera_plan.toml"
    out.write_bytes(b"precious")
    code, err = cli(
        capsys, "calibrate", "plan", "--kind", "camera", "--out", str(out), "--force",
        option, value,
    )  # fmt: skip
    assert code == 2, err
    assert option in err and value in err.replace("1e+09", "1e9") and expect in err, err
    assert out.read_bytes() == b"precious"


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        (["--seed", "3"], "--seed applies to --kind rig"),
        (["--camera-calibration", "CAM"], "--camera-calibration applies to --kind rig"),
        (["--seed", "3", "--camera-calibration", "CAM"], "--camera-calibration and --seed apply"),
    ],
)
def test_calibrate_plan_says_a_camera_plan_ignores_rig_options(tmp_path, capsys, extra, named):
    # --kind camera dropped --camera-calibration and --seed without a word
    cam = tmp_path / "camera.toml"
    cam.write_text("")
    out = tmp_path / "camera_plan.toml"
    args = [str(cam) if a == "CAM" else a for a in extra]
    code, err = cli(capsys, "calibrate", "plan", "--kind", "camera", "--out", str(out), *args)
    assert code == 2 and named in err, err
    assert not out.exists()
    code, err = cli(capsys, "calibrate", "plan", "--kind", "camera", "--out", str(out))
    assert code == 0 and out.exists(), err


def test_calibrate_rig_refuses_another_rig_and_outputs_that_collide(reduced, tmp_path, capsys):
    """A --rig of another geometry than the session's nominal rig (the servos' digest
    alone let it through: the calibration recorded the wrong rig as its nominal), --out
    and --plot naming one file, and an output among the session's own files."""
    d, s = reduced
    rig = (d / "rig.toml").read_text()
    assert "camera_radius_m = " in rig
    other = tmp_path / "other_rig.toml"
    other.write_text(_with_camera_radius(rig, 0.46))
    out = tmp_path / "rig_calibrated.toml"
    base = ["calibrate", "rig", str(s), "--camera-calibration", str(d / "rig.toml")]
    code, err = cli(capsys, *base, "--rig", str(other), "--out", str(out))
    assert code == 1 and "differs from the rig session" in err, err
    assert "geometry.camera_radius_m" in err and not out.exists()
    code, err = cli(capsys, *base, "--rig", str(d / "rig.toml"), "--out", str(out),
                    "--plot", str(out))  # fmt: skip
    assert code == 2 and "--out and --plot name the same file" in err, err
    manifest = (s / "manifest.json").read_bytes()
    code, err = cli(capsys, *base, "--rig", str(d / "rig.toml"), "--out",
                    str(s / "manifest.json"), "--force")  # fmt: skip
    assert code == 2 and "one of the session's own files" in err, err
    assert (s / "manifest.json").read_bytes() == manifest


def _with_camera_radius(doc: str, value: float) -> str:
    lines = doc.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("camera_radius_m"))
    lines[k] = f"camera_radius_m = {value}"
    return "\n".join(lines) + "\n"
