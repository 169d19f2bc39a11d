"""``reduction.toml`` and ``noise.json``: the pydantic models, their messages, the
example file, and the simulated session's document (exact floats)."""

from __future__ import annotations

import hashlib
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from gonio.app.sim_reduction import reduction_document, setup_from_scene
from gonio.capture.reduction_config import (
    load_reduction_config,
    resolve_setup,
    setup_from_config,
)
from gonio.errors import ConfigError, ReductionError, SessionError

EXAMPLE = Path(__file__).parents[2] / "examples" / "reduction.toml"

MINIMAL = """
[camera]
K = [[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]]
[noise]
gain = 0.4
read_noise = 1.2
[sample]
width = 0.05
height = 0.04
"""


def test_the_example_is_valid_and_says_what_it_means():
    cfg = load_reduction_config(EXAMPLE)
    setup = setup_from_config(cfg, EXAMPLE)
    # the numbers written in the example, read back by hand
    assert setup.K[0, 0] == 4470.2 and setup.K[1, 2] == 1999.5
    assert setup.dist.tolist() == [-0.082, 0.115, 0.0, 0.0, -0.031]
    assert setup.signature.cfa_pattern == "RGGB" and setup.signature.shape == (4000, 6000)
    assert (setup.noise.gain, setup.noise.read_noise, setup.noise.iso) == (0.42, 1.6, 100.0)
    assert setup.board.squares_x == 7 and setup.board.marker_length == 0.015
    assert setup.sample_size == (0.05, 0.05) and setup.light_radius == 0.01
    assert setup.reflectance.tolist() == [0.99] * 3
    assert setup.reflectance_std.tolist() == [0.005] * 3
    assert (setup.grid, setup.roi_fraction, setup.geometry) == (3, 0.6, "auto")
    assert (setup.max_board_obliquity_deg, setup.min_board_corners) == (60.0, 10)
    cal = setup.camera_calibration
    assert cal["rms_px"] == 0.18 and cal["dist_std"][4] == 0.0071
    assert cal["camera"] == {
        "backend": "gphoto2",
        "model": "Nikon D750",
        "serial": "3021458",
        "resolution": [6000, 4000],
    }
    # the digest the example states is that identity's (canonical JSON typed out here)
    ident = b'{"backend":"gphoto2","model":"Nikon D750","resolution":[6000,4000],'
    ident += b'"serial":"3021458"}'
    assert cal["digest"] == "sha256:" + hashlib.sha256(ident).hexdigest()
    # the commented `file =` form is shown
    text = EXAMPLE.read_text()
    assert '#   [camera]\n#   file = "camera.toml"\n' in text


def test_defaults_of_a_minimal_file(tmp_path):
    p = tmp_path / "reduction.toml"
    p.write_text(MINIMAL)
    setup = setup_from_config(load_reduction_config(p), p, reflectance=0.5)
    assert setup.signature is None and setup.dist is None and setup.light_radius is None
    assert setup.reflectance.tolist() == [0.5] * 3  # the plan's value when the file has none
    assert setup.noise.quantisation and setup.noise.iso == 100.0
    assert (setup.grid, setup.min_snr, setup.geometry_tolerance_deg) == (3, 5.0, 0.5)
    assert (setup.geometry, setup.max_board_obliquity_deg, setup.min_board_corners) == (
        "auto",
        60.0,
        10,
    )
    assert setup.gradient_chart == "auto"


@pytest.mark.parametrize(
    "setting, plan, chart",
    [
        ("auto", {"reductions": {"isotropic": True}}, "isotropic"),
        ("auto", {"reductions": {"isotropic": False}}, "projected"),
        ("auto", {}, "projected"),
        ("auto", None, "projected"),
        ("projected", {"reductions": {"isotropic": True}}, "projected"),
        ("isotropic", {"reductions": {"isotropic": False}}, "isotropic"),
    ],
)
def test_the_budget_gradient_chart_follows_the_plans_isotropy_unless_set(
    tmp_path, setting, plan, chart
):
    """``[reduction] gradient_chart``: "auto" takes the plan's ``[reductions] isotropic``
    (a material declared isotropic); an explicit chart wins over the plan."""
    from gonio.capture.reduce import budget_gradient_chart

    p = tmp_path / "reduction.toml"
    p.write_text(MINIMAL + f'[reduction]\ngradient_chart = "{setting}"\n')
    setup = setup_from_config(load_reduction_config(p), p)
    assert setup.gradient_chart == setting
    manifest = {} if plan is None else {"plan": plan}
    assert budget_gradient_chart(setup.gradient_chart, manifest) == chart


@pytest.mark.parametrize(
    "change, field, what",
    [
        ("K = [[1, 0], [0, 1]]", "camera.K", ""),
        ("K = [[-800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]]", "camera.K", "> 0"),
        ("K = [[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 1, 1]]", "camera.K", "[0, 0, 1]"),
        ("K = [[800.0, 0, 319.5], [0, nan, 239.5], [0, 0, 1]]", "camera.K", "finite"),
        ("dist = [0.1, 0.2, 0.3]", "camera.dist", "4, 5, 8, 12 or 14"),
        ('cfa_pattern = "RGBW"', "camera.cfa_pattern", "RGGB"),
        ("width = 640", "camera", "both width and height"),
        ("gird = 6", "camera.gird", "Extra inputs are not permitted"),
    ],
)
def test_a_wrong_camera_field_is_named(tmp_path, change, field, what):
    p = tmp_path / "reduction.toml"
    text = MINIMAL.replace("[camera]\n", f"[camera]\n{change}\n")
    if change.startswith("K ="):
        text = text.replace("K = [[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]]\n", "", 1)
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_reduction_config(p)
    msg = str(exc.value)
    assert str(p) in msg and f"field '{field}" in msg and what in msg


@pytest.mark.parametrize(
    "section, field",
    [
        ("[noise]\ngain = -0.4\nread_noise = 1.2", "noise.gain"),
        ('[noise]\nfile = "n.json"\ngain = 0.4', "noise"),
        ("[noise]\niso = 200", "noise"),
        ("[reduction]\ngrid = 0", "reduction.grid"),
        ("[reduction]\ngrid = 6\nroi_fraction = 1.5", "reduction.roi_fraction"),
        ('[reduction]\ngeometry = "fiducials"', "reduction.geometry"),
        ('[reduction]\ngradient_chart = "polar"', "reduction.gradient_chart"),
        ("[reduction]\nmax_board_obliquity_deg = 95.0", "reduction.max_board_obliquity_deg"),
        ("[reduction]\nmin_board_corners = 3", "reduction.min_board_corners"),
        ("[reduction]\ngird = 6", "reduction.gird"),
        ("[board]\nsquares_x = 7\nmarker_length = 0.03", "board"),
        ('[board]\ndictionary = "DICT_9X9_1"', "board.dictionary"),
        # more markers than the dictionary: the reduction took minutes per frame over it
        ("[board]\nsquares_x = 100000", "board"),
        ("[board]\nsquares_x = 11\nsquares_y = 11", "board"),
        ("[light]\nradius = 0", "light.radius"),
        ("[reference]\nreflectance = 1.5", "reference.reflectance"),
    ],
)
def test_a_wrong_field_elsewhere_is_named(tmp_path, section, field):
    p = tmp_path / "reduction.toml"
    text = MINIMAL
    if section.startswith("[noise]"):
        text = text.replace("[noise]\ngain = 0.4\nread_noise = 1.2\n", "")
    p.write_text(text + section + "\n")
    with pytest.raises(ConfigError) as exc:
        load_reduction_config(p)
    assert str(p) in str(exc.value) and f"field '{field}'" in str(exc.value)


def test_not_toml_and_missing_sections(tmp_path):
    p = tmp_path / "reduction.toml"
    p.write_text("[camera\nK = 1")
    with pytest.raises(ConfigError, match="not a valid TOML file"):
        load_reduction_config(p)
    p.write_text(MINIMAL.replace("[sample]\nwidth = 0.05\nheight = 0.04\n", ""))
    with pytest.raises(ConfigError, match="field 'sample': Field required"):
        load_reduction_config(p)
    # no [noise] is allowed when a noise.json stands in; without one it is an error
    p.write_text(MINIMAL.replace("[noise]\ngain = 0.4\nread_noise = 1.2\n", ""))
    with pytest.raises(ReductionError, match="field 'noise': missing"):
        setup_from_config(load_reduction_config(p), p)
    (tmp_path / "noise.json").write_text('{"gain": 0.3, "read_noise": 2.0}')
    setup = resolve_setup(tmp_path, {})
    assert (setup.noise.gain, setup.noise.read_noise) == (0.3, 2.0)


def test_noise_file_and_noise_json_precedence(tmp_path):
    p = tmp_path / "reduction.toml"
    p.write_text(MINIMAL.replace("gain = 0.4\nread_noise = 1.2", 'file = "cal/n.json"'))
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "n.json").write_text('{"gain": 0.7, "read_noise": 3.0, "iso": 200}')
    assert resolve_setup(tmp_path, {}).noise.gain == 0.7  # relative to the toml
    (tmp_path / "noise.json").write_text('{"gain": 0.3, "read_noise": 2.0}')
    assert resolve_setup(tmp_path, {}).noise.gain == 0.3  # the session's noise.json wins
    (tmp_path / "noise.json").write_text('{"gain": 0.3}')
    with pytest.raises(ConfigError, match=r"noise\.json.*field 'read_noise'"):
        resolve_setup(tmp_path, {})


def test_no_reduction_toml_says_how_to_get_one(tmp_path):
    with pytest.raises(SessionError) as exc:
        resolve_setup(tmp_path, {"simulation": {"scene": {}}})
    assert "no reduction.toml" in str(exc.value)
    assert "python -m gonio.app.sim_reduction" in str(exc.value)
    # an explicit --config is read instead
    (tmp_path / "lab.toml").write_text(MINIMAL)
    assert resolve_setup(tmp_path, {}, config=tmp_path / "lab.toml").sample_size == (0.05, 0.04)


def awkward_scene():
    """A scene whose camera matrix has no short decimal form."""
    from gonio.simulator.scene import parse_scene

    return parse_scene(
        {
            "sample": {"width": 0.0517, "height": 0.0493, "brdf": {"model": "lambert"}},
            "holder": {"width": 0.16, "height": 0.16, "board": {"square_length": 0.0213}},
            "lights": [
                {
                    "type": "disk",
                    "position": [0.0, 0.25, 0.433],
                    "look_at": [0, 0, 0],
                    "radius": 0.0117,
                    "radiance": [1.0, 1.0, 1.0],
                }
            ],
            "camera": {
                "resolution": [333, 251],
                "focal_length": 0.0161,
                "fov_deg": 29.7,
                "position": [0.1, -0.2, 0.35],
                "sensor": {"read_noise": 2.9, "gain_at_base_iso": 0.37, "cfa_pattern": "GRBG"},
            },
        }
    )


def test_the_scene_document_round_trips_to_the_bit_through_toml(tmp_path):
    scene = awkward_scene()
    doc = reduction_document(scene, 0.97)
    p = tmp_path / "reduction.toml"
    p.write_text(tomli_w.dumps(doc))
    assert tomllib.loads(p.read_text()) == doc  # every float back to the same bits
    from_file = setup_from_config(load_reduction_config(p), p)
    direct = setup_from_scene(scene, 0.97)
    assert from_file.K.tobytes() == direct.K.tobytes()
    assert from_file.noise == direct.noise and from_file.board == direct.board
    assert from_file.sample_size == direct.sample_size == (0.0517, 0.0493)
    assert from_file.signature == direct.signature
    # what the document says, against the scene's own numbers: OpenCV's pixel centres
    # are the simulator's minus half a pixel; the noise model in DN is electrons x gain
    K_sim = scene.camera.intrinsics()
    assert from_file.K[0, 2] == K_sim[0, 2] - 0.5 and from_file.K[1, 2] == K_sim[1, 2] - 0.5
    assert from_file.K[0, 0] == K_sim[0, 0] and from_file.K[1, 1] == K_sim[1, 1]
    assert from_file.noise.read_noise == 2.9 * 0.37 and from_file.noise.gain == 0.37
    assert from_file.signature.cfa_pattern == "GRBG" and from_file.signature.shape == (251, 333)
    assert from_file.light_radius == 0.0117 and from_file.board.square_length == 0.0213


def test_a_scene_without_a_board_cannot_be_reduced():
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(
        {
            "sample": {"width": 0.05, "height": 0.05, "brdf": {"model": "lambert"}},
            "holder": {"width": 0.16, "height": 0.16, "board": None},
            "lights": [{"type": "point", "position": [0, 0.2, 0.4], "intensity": 1.0}],
            "camera": {"resolution": [64, 48], "fov_deg": 30.0, "position": [0.1, -0.2, 0.35]},
        }
    )
    with pytest.raises(ReductionError, match="no ChArUco board"):
        reduction_document(scene)


def test_a_point_light_has_no_radius():
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(
        {
            "sample": {"width": 0.05, "height": 0.05, "brdf": {"model": "lambert"}},
            "holder": {"width": 0.16, "height": 0.16},
            "lights": [{"type": "point", "position": [0, 0.2, 0.4], "intensity": 1.0}],
            "camera": {"resolution": [64, 48], "fov_deg": 30.0, "position": [0.1, -0.2, 0.35]},
        }
    )
    doc = reduction_document(scene)
    assert "light" not in doc and "reference" not in doc
    assert np.isfinite(setup_from_scene(scene).K).all()


def test_a_simulated_sessions_camera_is_the_nominal_one():
    """Only what a lab knows before calibrating: f = focal length / pitch, the principal
    point at the image centre (OpenCV: (W - 1) / 2), no distortion, even when the scene's
    camera has its principal point elsewhere; the text tells the lab to use camera.toml."""
    from gonio.app.sim_reduction import reduction_toml_text
    from gonio.simulator.scene import parse_scene

    scene = parse_scene(
        {
            "sample": {"width": 0.05, "height": 0.05, "brdf": {"model": "lambert"}},
            "holder": {"width": 0.16, "height": 0.16, "board": {}},
            "lights": [{"type": "point", "position": [0, 0.2, 0.4], "intensity": 1.0}],
            "camera": {
                "resolution": [640, 480],
                "focal_length": 0.016,
                "pixel_pitch": 4e-6,
                "principal_point": [331.0, 229.0],
                "position": [0.1, -0.2, 0.35],
            },
        }
    )
    doc = reduction_document(scene)
    f = 0.016 / 4e-6  # 4000 px, to the rounding of the division
    assert doc["camera"]["K"] == [[f, 0.0, 319.5], [0.0, f, 239.5], [0.0, 0.0, 1.0]]
    assert abs(f - 4000.0) < 1e-9
    assert "dist" not in doc["camera"]
    text = reduction_toml_text(doc)
    assert 'file = "camera.toml"' in text and "gonio calibrate camera" in text
    assert tomllib.loads(text) == doc


def test_a_board_of_more_markers_than_its_dictionary_says_how_many(tmp_path):
    p = tmp_path / "reduction.toml"
    p.write_text(MINIMAL + "[board]\nsquares_x = 11\nsquares_y = 11\n")
    with pytest.raises(
        ConfigError, match=r"11 x 11 ChArUco board has 60 markers.*50 of DICT_4X4_50"
    ):
        load_reduction_config(p)
    # 10 x 10 needs exactly the 50 the dictionary holds
    p.write_text(MINIMAL + "[board]\nsquares_x = 10\nsquares_y = 10\n")
    assert load_reduction_config(p).board.squares_x == 10
