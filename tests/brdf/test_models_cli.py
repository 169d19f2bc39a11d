"""Bad input and the ``gonio brdf list | plot | albedo`` commands, as a user runs them."""

from __future__ import annotations

import math

import matplotlib.image
import numpy as np
import pytest

from gonio.brdf import get_model, list_models
from gonio.cli import main
from gonio.errors import GonioError, ParameterError, UnknownNameError

KNOWN = ["beckmann", "blinn-phong", "ggx", "lambert", "oren-nayar", "phong", "ward", "ward-aniso"]


def run(capsys, *args):
    """Run the console entry point; return (exit code, stdout, stderr)."""
    with pytest.raises(SystemExit) as exc:
        main(list(args))
        raise SystemExit(0)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


# --- the library ------------------------------------------------------------------------


def test_list_models():
    assert list_models() == KNOWN


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(UnknownNameError) as exc:
        get_model("lambert+gxx")
    msg = str(exc.value)
    assert "'gxx'" in msg
    assert all(name in msg for name in KNOWN)


def test_unknown_option_and_option_value():
    with pytest.raises(ParameterError, match="takes no option 'fresnel'"):
        get_model("lambert", fresnel="schlick")
    with pytest.raises(UnknownNameError, match="choices: conductor, dielectric, none, schlick"):
        get_model("ggx", fresnel="metal")


@pytest.mark.parametrize(
    "name, params, pname, value, bounds",
    [
        ("ggx", {"alpha": 1.5}, "alpha", "1.5", "[0.0001, 1]"),
        ("ggx", {"alpha": 0.0}, "alpha", "0", "[0.0001, 1]"),
        ("lambert", {"albedo": -0.1}, "albedo", "-0.1", "[0, 1]"),
        ("oren-nayar", {"albedo": 0.99}, "albedo", "0.99", "[0, 0.98]"),
        ("phong", {"n": 2e6}, "n", "2e+06", "[0, 1e+06]"),
        ("lambert+ggx", {"albedo": [0.2, 0.5, 1.2]}, "albedo", "1.2", "[0, 1]"),
        ("ggx", {"alpha": float("nan")}, "alpha", "nan", "[0.0001, 1]"),
    ],
)
def test_out_of_bounds_names_parameter_value_and_bounds(name, params, pname, value, bounds):
    m = get_model(name)
    with pytest.raises(ParameterError) as exc:
        m.eval(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), params)
    msg = str(exc.value)
    assert f"'{pname}'" in msg and f"= {value} " in msg and bounds in msg
    with pytest.raises(ParameterError):
        m.bind(params)
    with pytest.raises(ParameterError):
        m.albedo(0.0, params)


def test_unknown_parameter_lists_the_model_parameters():
    with pytest.raises(ParameterError, match="no parameter 'roughness'.*ks, alpha"):
        get_model("ggx").eval(np.array([0, 0, 1.0]), np.array([0, 0, 1.0]), {"roughness": 0.1})


def test_bad_direction_shape():
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        get_model("ggx").eval(np.zeros(2), np.zeros(3), {})


# --- the command line -------------------------------------------------------------------


def test_cli_list(capsys):
    code, out, _ = run(capsys, "brdf", "list")
    assert code == 0
    for name in KNOWN:
        assert name in out
    assert "alpha" in out and "[0.0001, 1]" in out


def test_cli_unknown_model_exits_nonzero_with_known_names(capsys, tmp_path):
    code, _, err = run(capsys, "brdf", "albedo", "gxx")
    assert code == 1
    assert "unknown BRDF model 'gxx'" in err and "ggx" in err
    code, _, err = run(capsys, "brdf", "plot", "gxx", "--out", str(tmp_path / "a.png"))
    assert code == 1 and "lambert" in err
    assert not (tmp_path / "a.png").exists()


def test_cli_out_of_bounds_exits_nonzero_with_message(capsys, tmp_path):
    code, _, err = run(capsys, "brdf", "albedo", "ggx", "--param", "alpha=2")
    assert code == 1
    assert "error: parameter 'alpha' of model 'ggx' = 2 is outside its bounds [0.0001, 1]" in err
    out = tmp_path / "keep.png"
    out.write_bytes(b"precious")
    code, _, err = run(capsys, "brdf", "plot", "ggx", "-p", "alpha=2", "--out", str(out))
    assert code == 1 and "'alpha'" in err
    assert out.read_bytes() == b"precious"  # nothing overwritten on bad input


@pytest.mark.parametrize("bad", ["alpha", "alpha=x", "alpha=0.1,0.2"])
def test_cli_malformed_param_is_a_usage_error(capsys, bad):
    code, _, err = run(capsys, "brdf", "albedo", "ggx", "--param", bad)
    assert code == 2 and "--param" in err


def test_cli_albedo_table_and_energy_warning(capsys):
    code, out, err = run(
        capsys, "brdf", "albedo", "lambert", "-p", "albedo=0.6", "--theta-i", "0,45"
    )
    assert code == 0 and "0.600000" in out and "warning" not in err
    assert "Y (sRGB)" not in out  # a grey albedo is its own luminance-weighted value
    # 0.9 diffuse + 0.9 specular reflect more than they receive
    args = ["brdf", "albedo", "lambert+ggx", "-p", "albedo=0.9", "-p", "ks=0.9", "--theta-i", "30"]
    code, out, err = run(capsys, *args)
    assert code == 0 and "warning: the directional albedo exceeds 1" in err
    code, _, err = run(capsys, *args, "--strict")
    assert code == 1 and "exceeds 1" in err


def test_cli_albedo_per_channel(capsys):
    code, out, _ = run(
        capsys, "brdf", "albedo", "lambert", "-p", "albedo=0.1,0.2,0.3", "--theta-i", "10"
    )
    assert code == 0
    assert "0.100000" in out and "0.200000" in out and "0.300000" in out
    # the luminance-weighted albedo beside them: a Lambertian's albedo is its parameter,
    # weighted by ITU-R BT.709-6's 0.2126 R + 0.7152 G + 0.0722 B
    assert "Y (sRGB)" in out
    assert f"{0.2126 * 0.1 + 0.7152 * 0.2 + 0.0722 * 0.3:.6f}" in out  # 0.186420


def test_cli_plot_model_writes_png(capsys, tmp_path):
    out = tmp_path / "figs" / "ggx.png"
    code, stdout, _ = run(
        capsys, "brdf", "plot", "lambert+ggx", "--fresnel", "schlick", "-p", "albedo=0.5,0.3,0.2",
        "-p", "alpha=0.05", "--theta-i", "30", "--theta-i", "60", "--out", str(out),
    )  # fmt: skip
    assert code == 0 and str(out) in stdout
    img = matplotlib.image.imread(out)
    assert img.ndim == 3 and img.shape[1] > img.shape[0] > 200
    assert img[..., :3].std() > 0.05  # not a blank canvas
    assert list(out.parent.iterdir()) == [out]  # no temporary file left behind


def test_cli_plot_rejects_unknown_image_type(capsys, tmp_path):
    code, _, err = run(capsys, "brdf", "plot", "ggx", "--out", str(tmp_path / "x.txt"))
    assert code == 2 and ".png" in err


def test_cli_plot_measured_file(capsys, tmp_path, rgl_file):
    path = rgl_file("paper_white")
    out = tmp_path / "paper.png"
    code, _, err = run(capsys, "brdf", "plot", str(path), "--theta-i", "45", "--out", str(out))
    assert code == 0, err
    assert matplotlib.image.imread(out).shape[0] > 200
    code, _, err = run(capsys, "brdf", "plot", str(path), "-p", "alpha=0.1", "--out", str(out))
    assert code == 2 and "analytic models only" in err


def test_cli_missing_file_is_reported(capsys, tmp_path):
    code, _, err = run(
        capsys, "brdf", "plot", str(tmp_path / "nope.bsdf"), "--out", str(tmp_path / "a.png")
    )
    assert code == 2 and "no such file" in err


def test_cli_bad_theta(capsys):
    code, _, err = run(capsys, "brdf", "albedo", "ggx", "--theta-i", "95")
    assert code == 2 and "[0, 90]" in err


def test_errors_are_gonio_errors():
    assert issubclass(ParameterError, GonioError) and issubclass(UnknownNameError, GonioError)
    assert math.isfinite(get_model("ggx").albedo(0.0, {}))


def test_cli_takes_model_options_written_as_fit_writes_them(capsys):
    """``lambert+ggx[fresnel=schlick]`` (how ``gonio fit --candidates`` and fit.json name
    a model) is the model ``--fresnel schlick`` makes; the two disagreeing is an error,
    and a broken spec is named."""
    base = ["--theta-i", "0,70", "-p", "f0=0.2"]
    code, bracket, _ = run(capsys, "brdf", "albedo", "lambert+ggx[fresnel=schlick]", *base)
    assert code == 0
    code, option, _ = run(capsys, "brdf", "albedo", "lambert+ggx", "--fresnel", "schlick", *base)
    assert code == 0 and bracket == option
    code, plain, _ = run(capsys, "brdf", "albedo", "lambert+ggx", "--theta-i", "0,70")
    assert code == 0 and plain != bracket
    code, _, err = run(
        capsys, "brdf", "albedo", "lambert+ggx[fresnel=schlick]", "--fresnel", "conductor"
    )
    assert code == 2 and "fresnel=schlick" in err and "--fresnel conductor" in err
    code, _, err = run(capsys, "brdf", "albedo", "lambert+ggx[fresnel=schlick")
    assert code != 0 and "model spec" in err and "Traceback" not in err
