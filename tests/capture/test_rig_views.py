"""Observations from a calibration session: board corners in the sample frame, mirror
spots, journal approach (missing in old journals) and per-pose problems."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gonio.capture.fiducials import BoardSpec
from gonio.capture.journal import sha256_bytes, xxh3_bytes
from gonio.capture.rig_views import calibration_observations
from gonio.errors import SessionError
from gonio.radiometry import spherical_to_direction
from gonio.radiometry.frames import look_at_rotation

DOC = {
    "sample": {"width": 0.05, "height": 0.05,
               "brdf": {"model": "lambert", "params": {"albedo": 0.5}}},
    "holder": {"width": 0.2, "height": 0.2},
    "lights": [{"type": "disk", "position": [0.0, 0.25, 0.433], "look_at": [0, 0, 0],
                "radius": 0.01, "radiance": [2e4] * 3}],
    "camera": {"resolution": [480, 360], "focal_length": 0.016, "fov_deg": 40.0,
               "position": [0.1, -0.2, 0.35]},
    "render": {"tolerance": 1e-3},
}  # fmt: skip
SPOT = (251.3, 160.7, 3.0)  # drawn spot: centre u, v (OpenCV px) and radius, px


def _pose(th, ph):
    C = 0.3 * spherical_to_direction(np.radians(th), np.radians(ph))
    R = look_at_rotation(C, np.zeros(3), up=np.array([0, 0, 1.0]))  # world-to-camera
    L = 0.5 * spherical_to_direction(np.radians(40), np.radians(ph + 180))
    return {"camera_position": C, "camera_rotation": R.T, "light_position": L,
            "light_normal": -L / 0.5}  # fmt: skip


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A calibration session written by hand: pose 0 (sample, approach recorded), pose 1
    (mirror: the board plus a drawn spot, no approach: an old journal), pose 2 (a view
    without the board) and a dark."""
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.scene import parse_scene
    from gonio.simulator.sensor import simulate_raw

    from .test_mirror_spot import disk_coverage

    scene = parse_scene(DOC)
    state = {}
    cam = SimulatedCamera(scene, pose_provider=lambda: state["p"])
    S = tmp_path_factory.mktemp("calib")
    (S / "raw").mkdir()
    recs = [{"type": "start", "resumed": False}]
    poses = [(_pose(30, 200), "sample"), (_pose(20, 100), "mirror"), (_pose(30, 200), "sample")]
    truth = []
    for p, (pose, kind) in enumerate(poses):
        state["p"] = pose
        radiance = cam.render().radiance.copy()
        if kind == "mirror":
            radiance += 40.0 * disk_coverage(radiance.shape[:2], *SPOT)[..., None]
        if p == 2:
            radiance[:] = 0.3  # a flat grey: no board
        truth.append(pose)
        joints = {"light_azimuth": 0.1 * p, "stage_tilt": -0.2, "stage_spin": 0.3}
        for f, t in enumerate((2e-5, 1e-4)):
            data = dng_bytes(simulate_raw(radiance, scene.camera, exposure_time=t, seed=10 * p + f))
            name = f"raw/p{p:04d}_f{f:02d}_{kind}.dng"
            (S / name).write_bytes(data)
            rec = {"type": "shot", "pose": p, "frame": f, "kind": kind, "file": name,
                   "bytes": len(data), "xxh3_128": xxh3_bytes(data), "sha256": sha256_bytes(data),
                   "joints": joints, "exposure_time": t, "iso": 100.0, "f_number": 8.0}  # fmt: skip
            if p == 0:
                rec["approach"] = {"light_azimuth": 1, "stage_tilt": -1, "stage_spin": 0}
            recs.append(rec)
    recs.append({"type": "shot", "pose": 3, "frame": 0, "kind": "dark", "file": "raw/x.dng"})
    (S / "journal.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    b = scene.holder.board
    board = BoardSpec(b.squares_x, b.squares_y, b.square_length, b.marker_length, b.dictionary)
    return S, board, scene.camera.intrinsics(), truth


def test_observations_of_a_calibration_session(session):
    S, board, K, truth = session
    boards, spots, problems = calibration_observations(S, board)
    assert [b.label for b in boards] == ["pose 0", "pose 1"]
    assert [s.label for s in spots] == ["pose 1"]
    assert [(p.label, p.what) for p in problems] == [("pose 2", "board")]
    assert "not visible" in problems[0].reason
    Kcv = K.copy()
    Kcv[:2, 2] -= 0.5  # the scene's pixel centres are at +0.5
    for obs, pose in zip(boards, truth, strict=False):
        # object points are in the SAMPLE frame: the true camera projects them onto the
        # detected corners
        R = np.asarray(pose["camera_rotation"]).T  # world-to-camera
        pc = (obs.object_points - pose["camera_position"]) @ R.T
        uv = pc[:, :2] / pc[:, 2:3] @ Kcv[:2, :2].T + Kcv[:2, 2]
        err = np.linalg.norm(uv - obs.image_points, axis=1)
        assert len(err) >= 20 and np.sqrt(np.mean(err**2)) < 0.3, err.max()
        assert np.allclose(obs.object_points[:, 2], 0.0)
    assert boards[0].approach == {"light_azimuth": 1, "stage_tilt": -1, "stage_spin": 0}
    assert boards[1].approach == {"light_azimuth": 0, "stage_tilt": 0, "stage_spin": 0}
    assert boards[1].joints["light_azimuth"] == pytest.approx(0.1)
    # the drawn spot (the scene's pixel grid: centre of pixel c at c + 0.5 there, at c in
    # OpenCV's; the disk was drawn on the array, so its OpenCV centre is SPOT itself)
    assert np.allclose(spots[0].image_point, SPOT[:2], atol=0.05), spots[0].image_point


def test_a_changed_frame_is_a_problem_not_an_error(session, tmp_path):
    import shutil

    S, board, _K, _t = session
    T = tmp_path / "copy"
    shutil.copytree(S, T)
    (T / "raw" / "p0000_f00_sample.dng").write_bytes(b"not a dng")
    (T / "raw" / "p0000_f01_sample.dng").unlink()
    boards, _spots, problems = calibration_observations(T, board)
    assert [b.label for b in boards] == ["pose 1"]
    frames = [p for p in problems if p.what == "frames"]
    assert len(frames) == 2 and all(p.label == "pose 0" for p in frames)


def test_not_a_session(tmp_path):
    with pytest.raises(SessionError, match="no journal.jsonl"):
        calibration_observations(tmp_path, BoardSpec())
