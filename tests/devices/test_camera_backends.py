"""The camera conformance tests against every backend: the simulator's rig camera, and
gphoto2 on libgphoto2's virtual camera (``VCAMERADIR``, serving a DNG file)."""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))  # --import-mode=importlib: find the mixin

from camera_conformance import CameraConformance  # noqa: E402

# must be set before python-gphoto2 is first imported in this process
os.environ.setdefault("VCAMERADIR", tempfile.mkdtemp(prefix="gonio-vcam-"))


def _rig_poses():
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics

    cfg = default_rig_config()
    kin = Kinematics(cfg)
    wi = np.array([np.sin(np.radians(20)), 0.0, np.cos(np.radians(20))])
    wo = np.array([-np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    q = kin.inverse(wi, wo)
    return lambda: kin.poses(q)


class TestSimulatedRigCamera(CameraConformance):
    backend = "simulated"
    has_light = True
    exposure_time = 0.01
    iso = 100.0
    f_number = 8.0
    unsupported = (-1.0, None, None)
    unsupported_names = "exposure_time"

    def make_camera(self):
        from gonio.simulator.rig_camera import SimulatedRigCamera

        return SimulatedRigCamera(None, _rig_poses(), seed=7, width=32, height=24)

    def test_a_frame_with_the_light_off_is_dark(self, camera):
        """Dark frames: with the light off the frame is the sensor's black level and
        noise only, far below the same exposure with the light on."""
        from gonio.capture.raw import read_raw

        camera.next_shot(1, 0)
        lit = read_raw(camera.capture(0.05, 100, 8).data)
        camera.set_light(False)
        camera.next_shot(1, 1)
        dark = read_raw(camera.capture(0.05, 100, 8).data)
        camera.set_light(True)
        # ``linear`` is DN above the black level: zero-mean noise when dark
        assert lit.linear.mean() > 50 * max(abs(dark.linear.mean()), dark.linear.std() / 10)

    def test_seeded_shots_are_reproducible_per_step_and_frame(self, camera):
        """The same (seed, step, frame) renders the same bytes; another frame, other
        noise (the session seed comes at construction, never through capture)."""
        from gonio.devices import SeededShots

        assert isinstance(camera, SeededShots)
        shots = []
        for step, frame in ((3, 1), (3, 1), (3, 2)):
            camera.next_shot(step, frame)
            shots.append(camera.capture(0.01, 100, 8).data)
        assert shots[0] == shots[1] and shots[0] != shots[2]
        other = self.make_camera().__class__(None, _rig_poses(), seed=8, width=32, height=24)
        other.next_shot(3, 1)
        assert other.capture(0.01, 100, 8).data != shots[0]


@pytest.fixture
def vcam_dng(tmp_path, monkeypatch):
    pytest.importorskip("gphoto2")
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.rig_camera import minimal_scene
    from gonio.simulator.scene import parse_scene
    from gonio.simulator.sensor import simulate_raw

    scene = parse_scene(minimal_scene(32, 24))
    frame = simulate_raw(
        np.full((24, 32, 3), 0.01),
        scene.camera,
        exposure_time=0.01,
        iso=100,
        f_number=8,
        seed=np.random.default_rng(0),
    )
    d = tmp_path / "vcam"
    d.mkdir()
    # libgphoto2's virtual camera (an emulated D750) captures only files named *.jpg: the
    # bytes are a DNG all the same, which the backend must deliver unchanged
    (d / "frame.jpg").write_bytes(dng_bytes(frame))
    monkeypatch.setenv("VCAMERADIR", str(d))
    return d


class TestGPhoto2VirtualCamera(CameraConformance):
    backend = "gphoto2"
    exposure_time = 0.01
    iso = None  # the virtual camera has no ISO widget
    f_number = 8.0
    unsupported = (0.01, 100.0, None)
    unsupported_names = "no iso setting"
    raw_suffix = False  # see vcam_dng: the virtual camera names every capture .jpg

    @pytest.fixture(autouse=True)
    def _vcam(self, vcam_dng):
        self.dir = vcam_dng

    def make_camera(self):
        from gonio.capture.camera import open_camera

        return open_camera("gphoto2", require_raw=False)

    def test_delivers_the_file_byte_for_byte(self, camera):
        shot = camera.capture(self.exposure_time, self.iso, self.f_number)
        assert shot.data == (self.dir / "frame.jpg").read_bytes()
