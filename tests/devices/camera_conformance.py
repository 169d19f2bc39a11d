"""One conformance test mixin for every camera backend (python-microscope style).

A backend's test class derives from :class:`CameraConformance` and provides
``make_camera()`` (an open camera) plus the class attributes below; the same tests then
run against the simulator's camera and against gphoto2 on libgphoto2's virtual camera.
What they pin is the contract of :class:`gonio.devices.Camera` that the session engine
relies on, not any backend's internals.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from gonio.capture.camera import RAW_SUFFIXES
from gonio.capture.raw import read_raw
from gonio.devices import Camera, CameraInfo, Light, Shot
from gonio.errors import CameraError


class CameraConformance:
    """Tests every camera backend must pass.

    Attributes
    ----------
    backend
        The name ``describe().backend`` must report.
    exposure_time, iso, f_number
        A request the backend supports (iso/f_number None: the camera's own).
    unsupported
        ``(exposure_time, iso, f_number)`` the backend cannot do, and ``unsupported_names``
        the setting the error message must name.
    """

    backend: str = ""
    #: whether the backend is also the rig's switchable light
    has_light: bool = False
    exposure_time: float = 0.01
    iso: float | None = None
    f_number: float | None = None
    unsupported: tuple[Any, Any, Any] = (0.01, None, None)
    unsupported_names: str = ""
    #: False only where a test double cannot name its file as RAW (the data still is)
    raw_suffix: bool = True

    def make_camera(self) -> Camera:  # pragma: no cover - provided by subclasses
        raise NotImplementedError

    @pytest.fixture
    def camera(self):
        cam = self.make_camera()
        try:
            yield cam
        finally:
            cam.close()

    def test_implements_the_camera_interface(self, camera):
        assert isinstance(camera, Camera)

    def test_describe_names_backend_and_model_in_json(self, camera):
        info = camera.describe()
        assert isinstance(info, CameraInfo)
        assert info.backend == self.backend
        assert isinstance(info.model, str) and info.model.strip()
        assert isinstance(info.settings, dict)
        # recorded in the manifest: must survive JSON
        doc = json.loads(json.dumps(info.to_json()))
        assert doc["backend"] == self.backend and doc["model"] == info.model

    def test_capture_returns_decodable_raw_with_the_exposure_used(self, camera):
        shot = camera.capture(self.exposure_time, self.iso, self.f_number)
        assert isinstance(shot, Shot)
        assert isinstance(shot.data, bytes) and len(shot.data) > 0
        assert shot.suffix == shot.suffix.lower() and shot.suffix.startswith(".")
        if self.raw_suffix:
            assert shot.suffix in RAW_SUFFIXES
        # the exposure actually used: finite, positive, within half a stop of the request
        assert math.isfinite(shot.exposure_time) and shot.exposure_time > 0
        assert abs(math.log2(shot.exposure_time / self.exposure_time)) <= 0.5
        for v in (shot.iso, shot.f_number):
            assert isinstance(v, float) and (math.isnan(v) or v > 0)
        frame = read_raw(shot.data, name="conformance shot")
        h, w = frame.shape
        assert h > 0 and w > 0
        json.dumps({k: v for k, v in shot.extra.items()})

    def test_closed_camera_raises_camera_error_and_close_is_idempotent(self, camera):
        camera.close()
        camera.close()
        with pytest.raises(CameraError):
            camera.capture(self.exposure_time, self.iso, self.f_number)

    def test_unsupported_setting_is_named(self, camera):
        with pytest.raises(CameraError, match=self.unsupported_names):
            camera.capture(*self.unsupported)

    def test_claims_exactly_the_abilities_it_has(self, camera):
        """The engine asks for abilities with isinstance: a backend must not claim a light
        it cannot switch (a real rig's light is separate hardware), nor hide one."""
        assert isinstance(camera, Light) is self.has_light
