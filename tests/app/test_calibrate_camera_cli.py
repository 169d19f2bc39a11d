"""``gonio calibrate camera``: solve from an image folder and from a shot session, the
table and file it writes, and its refusals (exit code 1, nothing overwritten)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.capture.camera_calibration import load_camera_calibration
from gonio.cli import run
from gonio.radiometry.frames import look_at_rotation

SQUARES, SQUARE, MARKER, PX = (8, 6), 0.025, 0.018, 80  # board; PX px per square in the print
K_TRUE = np.array([[800.0, 0, 322.0], [0, 800.0, 236.0], [0, 0, 1]])
W, H = 640, 480
BOARD_TOML = (
    "[board]\nsquares_x = 8\nsquares_y = 6\nsquare_length = 0.025\nmarker_length = 0.018\n"
    'dictionary = "DICT_4X4_50"\n'
)


def board_print():
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    b = cv2.aruco.CharucoBoard(SQUARES, SQUARE, MARKER, d)
    m = PX  # a white margin of one square
    img = b.generateImage((SQUARES[0] * PX + 2 * m, SQUARES[1] * PX + 2 * m), marginSize=m)
    return img, m


def pinhole_view(img, m, R, t, ss=4):
    """The printed board seen by a pinhole camera (K_TRUE, pose R, t in the board frame),
    as an exact homography, supersampled ss x ss per pixel (area average)."""
    # print pixel (x, y), centres at integers -> board metres
    s, o = SQUARE / PX, (0.5 - m) * SQUARE / PX
    P = np.array([[s, 0, o], [0, s, o], [0, 0, 1]])
    Hb = K_TRUE @ np.column_stack([R[:, 0], R[:, 1], t]) @ P
    # supersampled image: u_ss = ss u + (ss - 1) / 2 (centres at integers both ways)
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1]])
    big = cv2.warpPerspective(img, S @ Hb, (W * ss, H * ss), flags=cv2.INTER_LINEAR,
                              borderValue=90)  # fmt: skip
    return cv2.resize(big, (W, H), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("views")
    img, m = board_print()
    rng = np.random.default_rng(5)
    centre = np.array([SQUARES[0] * SQUARE / 2, SQUARES[1] * SQUARE / 2, 0.0])
    for k in range(9):
        th, ph = np.radians(rng.uniform(15, 45)), rng.uniform(0, 2 * np.pi)
        pos = centre + rng.uniform(0.3, 0.38) * np.array(
            [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)]
        )
        aim = centre + np.r_[rng.normal(0, 0.02, 2), 0]
        R = look_at_rotation(pos, aim, up=np.array([rng.normal(), -1.0, 0]))
        cv2.imwrite(str(d / f"view{k:02d}.png"), pinhole_view(img, m, R, -R @ pos))
    (d.parent / "board.toml").write_text(BOARD_TOML)
    return d


def test_calibrate_an_image_folder(folder, tmp_path, capsys):
    out = tmp_path / "camera.toml"
    board = folder.parent / "board.toml"
    args = ["calibrate", "camera", str(folder), "--board", str(board), "--calibration", str(out)]
    assert run(*args, "--plot", "--camera-model", "test cam") == 0
    printed = capsys.readouterr().out
    assert "reprojection RMS" in printed and "fx" in printed and "k3" in printed
    cam = load_camera_calibration(out)
    est = np.array(cam.K)
    std = np.array(cam.calibration.K_std)
    truth = np.r_[K_TRUE[0, 0], K_TRUE[1, 1], K_TRUE[0, 2], K_TRUE[1, 2]]
    got = np.r_[est[0, 0], est[1, 1], est[0, 2], est[1, 2]]
    assert np.all(np.abs(got - truth) < np.maximum(5 * std, 0.5)), (got - truth, std)
    assert abs(got[0] / truth[0] - 1) < 3e-3
    assert len(cam.calibration.views_used) == 9 and cam.calibration.camera.model == "test cam"
    assert (tmp_path / "camera_views.png").stat().st_size > 1000
    # a second run refuses to overwrite, and leaves the file as it was
    before = out.read_bytes()
    assert run(*args) == 2  # a usage error (click), before any work
    assert "exists" in capsys.readouterr().err and out.read_bytes() == before
    assert run(*args, "--force") == 0


def test_too_few_views_is_an_error(folder, tmp_path, capsys):
    few = tmp_path / "few"
    few.mkdir()
    for p in sorted(folder.glob("*.png"))[:4]:
        (few / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "camera.toml"
    code = run("calibrate", "camera", str(few), "--board", str(folder.parent / "board.toml"),
               "--calibration", str(out))  # fmt: skip
    assert code == 1
    assert f"error: {few}: 4 views with a board, need at least 6" in capsys.readouterr().err
    assert not out.exists()


def test_no_board_anywhere_is_an_error(tmp_path, capsys):
    d = tmp_path / "blank"
    d.mkdir()
    for k in range(3):
        cv2.imwrite(str(d / f"b{k}.png"), np.full((120, 160), 100, np.uint8))
    assert run("calibrate", "camera", str(d), "--calibration", str(tmp_path / "c.toml")) == 1
    err = capsys.readouterr().err
    assert "error:" in err and "not found in any of the 3 images" in err and str(d) in err
    assert "Traceback" not in err


def test_source_or_plan(tmp_path, capsys):
    assert run("calibrate", "camera", "--calibration", str(tmp_path / "c.toml")) == 2
    assert "either SOURCE" in capsys.readouterr().err


def test_help_teaches():
    from click.testing import CliRunner

    from gonio.cli import cli

    res = CliRunner().invoke(cli, ["calibrate", "camera", "--help"])
    assert res.exit_code == 0
    assert "calibrateCameraExtended" in res.output and "--plan" in res.output


PLAN = """
name = "camera views"
seed = 3
[grid]
theta_i_deg = [30]
phi_i_deg = [0]
theta_o_deg = [10, 30, 45, 60]
phi_o_deg = [120, 180, 240]
[reductions]
isotropic = false
reciprocity = false
[darks]
count = 0
[bracket]
policy = "fixed"
exposures_s = [0.004]
"""

SCENE = """
[sample]
width = 0.05
height = 0.05
brdf = { model = "lambert", params = { albedo = 0.5 } }
[holder]
width = 0.22
height = 0.22
[holder.board]
squares_x = 9
squares_y = 9
square_length = 0.02
marker_length = 0.015
[[lights]]
type = "disk"
position = [0.0, 0.25, 0.433]
look_at = [0.0, 0.0, 0.0]
radius = 0.01
radiance = [400.0, 400.0, 400.0]
[camera]
resolution = [480, 360]
focal_length = 0.016
fov_deg = 40.0
position = [0.1, -0.2, 0.35]
[render]
tolerance = 1e-3
"""


@pytest.mark.slow
def test_shoot_then_calibrate_on_the_simulated_rig(tmp_path, capsys):
    """--plan --rig --camera simulated --out: the views are shot as 'gonio capture run'
    shoots them (journal, manifest), then solved; the simulated camera's K is found."""
    from gonio.capture.manifest import read_manifest
    from gonio.rig.config import virtual_rig_document
    from gonio.simulator.scene import load_scene

    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    (tmp_path / "scene.toml").write_text(SCENE)
    out, session = tmp_path / "camera.toml", tmp_path / "S"
    code = run("calibrate", "camera", "--plan", str(tmp_path / "plan.toml"),
               "--rig", str(tmp_path / "rig.toml"), "--camera", "simulated",
               "--scene", str(tmp_path / "scene.toml"), "--out", str(session),
               "--calibration", str(out), "--quiet")  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert (session / "journal.jsonl").is_file()
    assert read_manifest(session).camera.backend == "simulated"
    cam = load_camera_calibration(out)
    K = load_scene(tmp_path / "scene.toml").camera.intrinsics()
    truth = np.r_[K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5]
    est = np.array(cam.K)
    got = np.r_[est[0, 0], est[1, 1], est[0, 2], est[1, 2]]
    std = np.array(cam.calibration.K_std)
    assert np.all(np.abs(got - truth) < np.maximum(5 * std, 1.0)), (got - truth, std)
    assert cam.calibration.camera.backend == "simulated" and cam.cfa_pattern
