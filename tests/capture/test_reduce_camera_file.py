"""``[camera] file = "camera.toml"`` and ``--camera-calibration``: a camera calibration
read into the reduction setup, and refused when it was made with another camera."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from gonio.capture.reduction_config import (
    camera_identity,
    identity_digest,
    load_reduction_config,
    resolve_setup,
    setup_from_config,
)
from gonio.errors import ConfigError, ReductionError

REST = """
[noise]
gain = 0.4
read_noise = 1.2
[sample]
width = 0.05
height = 0.04
"""

SIM = {"backend": "simulated", "model": "gonio-sim", "serial": "SIM-0007", "resolution": [400, 300]}
# sha256 of the identity's canonical JSON, typed out here (sorted keys, no spaces)
SIM_JSON = '{"backend":"simulated","model":"gonio-sim","resolution":[400,300],"serial":"SIM-0007"}'
SIM_DIGEST = "sha256:" + hashlib.sha256(SIM_JSON.encode()).hexdigest()


def camera_toml(digest: str | None = SIM_DIGEST, serial: str = "SIM-0007") -> str:
    text = f"""
[camera]
K = [[812.5, 0.0, 201.25], [0.0, 811.0, 148.75], [0.0, 0.0, 1.0]]
dist = [-0.12, 0.05, 0.001, -0.0005, 0.0]
width = 400
height = 300
cfa_pattern = "rggb"

[camera.calibration]
K_std = [[0.4, 0.0, 0.3], [0.0, 0.4, 0.25], [0.0, 0.0, 0.0]]
dist_std = [0.002, 0.004, 0.0001, 0.0001, 0.0]
rms_px = 0.21
created = "2026-12-01T20:00:00Z"
views_used = ["view 0", "view 1", "view 2"]
views_rejected = [{{view = "view 3", reason = "board not found"}}]
camera = {{backend = "simulated", model = "gonio-sim", serial = "{serial}", \
resolution = [400, 300]}}
"""
    if digest is not None:
        text += f'digest = "{digest}"\n'
    return text


def manifest(**changes):
    cam = {
        "backend": "simulated",
        "model": "gonio-sim",
        "serial": "SIM-0007",
        "sensor_size_mm": [6.0, 4.5],
        "settings": {"resolution": [400, 300], "focal_length_m": 0.016},
    }
    cam.update(changes)
    return {"camera": cam, "reference": {"reflectance": 0.99}}


def session(tmp_path, camera_text: str | None = None, reduction_camera: str | None = None):
    """A session directory with a reduction.toml whose [camera] is ``file = "camera.toml"``
    (or ``reduction_camera``), and the camera file."""
    s = tmp_path / "S"
    s.mkdir(parents=True)
    if camera_text is not None:
        (s / "camera.toml").write_text(camera_text)
    cam = reduction_camera or '[camera]\nfile = "camera.toml"\n'
    (s / "reduction.toml").write_text(cam + REST)
    return s


def test_identity_digest_is_sha256_of_the_canonical_json():
    assert identity_digest(SIM) == SIM_DIGEST
    # the manifest records serial and resolution where the camera put them
    assert camera_identity(manifest()["camera"]) == SIM
    rec = {"backend": "gphoto2", "model": "Nikon D750", "settings": {"serial": "3021"}}
    assert camera_identity(rec) == {
        "backend": "gphoto2",
        "model": "Nikon D750",
        "serial": "3021",
        "resolution": None,
    }
    assert camera_identity({}) is None


def test_camera_file_relative_to_the_reduction_toml_is_read_with_its_calibration(tmp_path):
    s = session(tmp_path, camera_toml())
    setup = resolve_setup(s, manifest())
    np.testing.assert_array_equal(
        setup.K, [[812.5, 0.0, 201.25], [0.0, 811.0, 148.75], [0.0, 0.0, 1.0]]
    )
    assert setup.dist.tolist() == [-0.12, 0.05, 0.001, -0.0005, 0.0]
    assert setup.signature.cfa_pattern == "RGGB" and setup.signature.shape == (300, 400)
    cal = setup.camera_calibration
    assert cal["rms_px"] == 0.21 and cal["digest"] == SIM_DIGEST
    assert cal["K_std"][0] == [0.4, 0.0, 0.3] and cal["dist_std"][1] == 0.004
    assert cal["camera"]["serial"] == "SIM-0007"
    assert cal["views_rejected"] == [{"view": "view 3", "reason": "board not found"}]
    assert setup.camera_file == str(s / "camera.toml")
    # the rest of the document is read as before
    assert setup.sample_size == (0.05, 0.04) and setup.noise.gain == 0.4


def test_camera_calibration_option_replaces_the_documents_camera(tmp_path):
    inline = "[camera]\nK = [[700.0, 0, 199.5], [0, 700.0, 149.5], [0, 0, 1]]\n"
    s = session(tmp_path, reduction_camera=inline)
    assert resolve_setup(s, manifest()).K[0, 0] == 700.0
    cal = tmp_path / "elsewhere" / "camera.toml"
    cal.parent.mkdir()
    cal.write_text(camera_toml())
    setup = resolve_setup(s, manifest(), camera_calibration=cal)
    assert setup.K[0, 0] == 812.5 and setup.dist[0] == -0.12
    assert setup.camera_calibration["digest"] == SIM_DIGEST


def test_a_calibration_of_another_camera_is_refused_naming_both_digests(tmp_path):
    other = identity_digest({**SIM, "serial": "SIM-0008"})
    s = session(tmp_path, camera_toml(digest=other, serial="SIM-0008"))
    with pytest.raises(ReductionError) as exc:
        resolve_setup(s, manifest())
    msg = str(exc.value)
    assert str(s / "camera.toml") in msg
    assert other in msg and SIM_DIGEST in msg
    assert "serial" in msg and "SIM-0008" in msg and "SIM-0007" in msg
    # the same through --camera-calibration, against a session of another resolution
    s2 = session(
        tmp_path / "b", reduction_camera="[camera]\nK = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n"
    )
    cal = tmp_path / "camera.toml"
    cal.write_text(camera_toml())
    m = manifest(settings={"resolution": [800, 600]})
    with pytest.raises(ReductionError, match="made with another camera") as exc:
        resolve_setup(s2, m, camera_calibration=cal)
    assert str(cal) in str(exc.value) and SIM_DIGEST in str(exc.value)
    assert identity_digest({**SIM, "resolution": [800, 600]}) in str(exc.value)


def test_identity_is_checked_only_when_both_sides_record_it(tmp_path):
    s = session(tmp_path, camera_toml(digest=None, serial="SIM-0008"))
    assert resolve_setup(s, manifest()).camera_calibration.get("digest") is None
    s2 = session(tmp_path / "b", camera_toml(digest=identity_digest({**SIM, "serial": "X"})))
    assert resolve_setup(s2, {}).K[0, 0] == 812.5  # the manifest records no camera


def test_same_identity_under_another_digest_spelling_is_accepted(tmp_path):
    """A digest written with other JSON separators: the identity table decides."""
    compact = hashlib.sha256(SIM_JSON.replace(",", ", ").replace(":", ": ").encode())
    s = session(tmp_path, camera_toml(digest="sha256:" + compact.hexdigest()))
    assert resolve_setup(s, manifest()).K[0, 0] == 812.5


@pytest.mark.parametrize(
    "camera_table, field",
    [
        ('[camera]\nfile = "camera.toml"\nK = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n', "camera"),
        ("[camera]\ncfa_pattern = 'RGGB'\n", "camera"),
        ('[camera]\nfile = "camera.toml"\n[camera.calibration]\nrms_px = 0.2\n', "camera"),
    ],
)
def test_file_and_numbers_together_or_neither_are_refused(tmp_path, camera_table, field):
    p = tmp_path / "reduction.toml"
    p.write_text(camera_table + REST)
    with pytest.raises(ConfigError) as exc:
        load_reduction_config(p)
    assert str(p) in str(exc.value) and f"field '{field}'" in str(exc.value)


@pytest.mark.parametrize(
    "text, named",
    [
        (None, "file not found"),
        ("[camera\n", "not a valid TOML"),
        ("[lens]\nK = 1\n", "field 'camera': missing"),
        (camera_toml().replace("rms_px = 0.21", "rms_px = -1"), "calibration.rms_px"),
        (camera_toml().replace('digest = "sha256:', 'digest = "md5:'), "calibration.digest"),
        (camera_toml().replace("dist = [", "dist = [0.0, "), "dist"),
        ('[camera]\nfile = "other.toml"\n', "camera.file"),
    ],
)
def test_a_bad_camera_file_is_named(tmp_path, text, named):
    s = session(tmp_path, text)
    config = load_reduction_config(s / "reduction.toml")
    with pytest.raises(ConfigError) as exc:
        setup_from_config(config, s / "reduction.toml")
    msg = str(exc.value)
    assert str(s / "camera.toml") in msg and named in msg


def test_a_camera_that_reports_no_size_matches_its_calibration(tmp_path):
    """gphoto2 reports neither serial nor resolution: `gonio calibrate camera` records the
    frames' size in the identity, and the reduction checks against that size."""
    from gonio.capture.camera_calibration import camera_digest, camera_identity

    record = {"backend": "simulated", "model": "gonio-sim", "serial": "SIM-0007"}
    digest = camera_digest(camera_identity(record, (400, 300)))  # the calibration's side
    s = session(tmp_path, camera_toml(digest=digest))
    assert resolve_setup(s, {"camera": record, "reference": {"reflectance": 0.99}}).K[0, 0] == 812.5
    other = camera_digest(camera_identity(record, (640, 480)))  # made at another size
    s2 = session(
        tmp_path / "b",
        camera_toml(digest=other).replace("resolution = [400, 300]", "resolution = [640, 480]"),
    )
    with pytest.raises(ReductionError, match="another camera"):
        resolve_setup(s2, {"camera": record, "reference": {"reflectance": 0.99}})
