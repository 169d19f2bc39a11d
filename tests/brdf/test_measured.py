"""``gonio.brdf.load`` (format by content), the albedo quadrature, and the CLI commands."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from gonio.brdf import load
from gonio.brdf.measured import directional_albedo, sniff_format
from gonio.brdf.merl import MERLBRDF
from gonio.cli import main, run


def test_format_is_recognised_by_content_not_name(rgl_file, tmp_path):
    disguised = tmp_path / "looks_like_merl.binary"
    shutil.copy(rgl_file("paper_white"), disguised)
    b = load(disguised)
    assert b.format == "rgl" and b.description == "White A4 paper (160 gsm)"

    m = MERLBRDF(np.random.default_rng(0).random((3, 90, 90, 180)))
    p = tmp_path / "table.bsdf"  # a MERL table with an RGL extension
    m.write(p)
    assert sniff_format(p) == "merl"
    back = load(p)
    assert back.format == "merl"
    np.testing.assert_array_equal(back.raw, m.raw)


# ------------------------------------------------------------------ albedo quadrature
def test_albedo_of_lambertian():
    def lam(wi, wo):
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return np.where(up, 0.8 / np.pi, 0.0)[..., None] * [1.0, 0.5, 0.25]

    # exact up to the quadrature error from the kink where the horizon cuts the grid
    # (documented accuracy ~1e-4; measured 6e-5)
    a = directional_albedo(lam, np.radians([0.0, 30.0, 60.0, 85.0]))
    np.testing.assert_allclose(a, np.array([[0.8, 0.4, 0.2]] * 4), rtol=1e-4)


def test_albedo_of_narrow_lobe_closed_form():
    # f = D(h) cos(theta_h) / (4 (wi.h) cos(theta_o)) with a GGX D (alpha = 0.05): its
    # albedo at normal incidence is the NDF mass of the half vectors with wo above the
    # horizon, theta_h < 45 deg: tan^2 / (alpha^2 + tan^2) = 1 / (1 + alpha^2).
    alpha = 0.05

    def lobe(wi, wo):
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        c = h[..., 2]
        d = alpha**2 / (np.pi * (c * c * (alpha**2 - 1) + 1) ** 2)
        f = d * c / (4 * np.einsum("...i,...i", wi, h) * wo[..., 2])
        return f[..., None] * np.ones(3)

    a = directional_albedo(lobe, np.array([0.0]))
    np.testing.assert_allclose(a, 1 / (1 + alpha**2), rtol=1e-4)


def test_albedo_nan_theta():
    a = directional_albedo(lambda wi, wo: np.ones(wo.shape[:-1] + (3,)), np.array([np.nan, 0.2]))
    assert np.all(np.isnan(a[0])) and np.all(np.isfinite(a[1]))


# ------------------------------------------------------------------ CLI
def _run(argv, capsys):
    with pytest.raises(SystemExit) as ei:
        main(argv)
    out = capsys.readouterr()
    return ei.value.code, out.out, out.err


def test_info_prints_format_description_dimensions_albedo(rgl_file, capsys):
    code = run("brdf", "info", str(rgl_file("paper_white")), "--theta-i-deg", "0,45")
    out = capsys.readouterr().out
    assert code in (0, None)
    for words in ("RGL-EPFL tensor_file v1.0", "White A4 paper", "32 x 32", "directional albedo"):
        assert words in out
    a = load(rgl_file("paper_white")).albedo(np.radians([45.0]))[0]
    assert f"{a[0]:.4f}" in out


def test_info_bad_file_exits_nonzero_with_message(tmp_path, capsys):
    p = tmp_path / "junk.bsdf"
    p.write_bytes(b"tensor_file\x00\x01\x00" + b"\xff" * 10)
    code, _, err = _run(["brdf", "info", str(p)], capsys)
    assert code == 1
    assert "error:" in err and str(p) in err and "Traceback" not in err


@pytest.mark.parametrize("angles", ["nan", "0,nan", "inf", "-inf", "95", ""])
def test_info_refuses_angles_outside_0_90_naming_the_option(tmp_path, capsys, angles):
    # NaN passed the range check (every comparison with it is false): info printed a row
    # of NaN albedos and exited 0.  The angles are checked before the file is read.
    p = tmp_path / "any.bsdf"
    p.write_bytes(b"never read")
    code, out, err = _run(["brdf", "info", str(p), "--theta-i-deg", angles], capsys)
    assert code == 2, (out, err)
    assert "--theta-i-deg" in err and f"got {angles!r}" in err and "[0, 90)" in err
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def converted(refdata, tmp_path_factory):
    """Run ``gonio brdf convert`` once: refused onto an existing file, then with --force."""
    src = refdata / "rgl" / "paper_white_rgb.bsdf"
    if not src.is_file():
        pytest.skip(f"{src} not found")
    out = tmp_path_factory.mktemp("convert") / "paper.binary"
    out.write_bytes(b"precious")
    runs = {}
    for key, extra in (("plain", []), ("force", ["--force"])):
        runs[key] = (run("brdf", "convert", *extra, str(src), str(out)), out.read_bytes()[:16])
    return src, out, runs


def test_convert_refuses_to_overwrite_without_force(converted):
    _, _, runs = converted
    code, head = runs["plain"]
    assert code == 1
    assert head == b"precious"  # nothing overwritten


def test_convert_with_force_writes_a_merl_table(converted):
    src, out, runs = converted
    assert runs["force"][0] in (0, None)
    assert out.stat().st_size == 34_992_012
    merl = load(out)
    assert merl.format == "merl"
    rgl = load(src)
    # same interface; the white paper is nearly Lambertian and nearly reciprocal, so the
    # symmetrised table stays within a few % of the source away from grazing angles
    wi = np.array([[0.3, 0.1, 0.948683], [0.0, 0.6, 0.8]])
    wo = np.array([[-0.5, 0.2, 0.842615], [0.1, -0.5, 0.860233]])
    for b in (rgl, merl):
        assert b.eval(wi, wo).shape == (2, 3)
        assert isinstance(b.metadata, dict) and isinstance(b.description, str)
    rel = np.abs(merl.eval(wi, wo) / rgl.eval(wi, wo) - 1)
    assert np.all(rel < 0.05), rel
    a_rgl, a_merl = rgl.albedo(np.radians([30.0])), merl.albedo(np.radians([30.0]))
    np.testing.assert_allclose(a_merl, a_rgl, rtol=0.03)


def test_convert_rejects_other_output_formats(rgl_file, tmp_path, capsys):
    code, _, err = _run(
        ["brdf", "convert", str(rgl_file("paper_white")), str(tmp_path / "x.bsdf")], capsys
    )
    assert code == 2 and ".binary" in err


def test_info_on_a_merl_table(converted, capsys):
    _, out, _ = converted
    assert run("brdf", "info", str(out), "--theta-i-deg", "20") in (0, None)
    text = capsys.readouterr().out
    assert "MERL binary" in text and "theta_h 90 x theta_d 90 x phi_d 180" in text
    assert "missing entries" in text and "directional albedo" in text


# ITU-R BT.709-6 item 3.2 luminance weights (also sRGB's): the reference for the Y column.
BT709 = np.array([0.2126, 0.7152, 0.0722])


def test_info_prints_the_luminance_weighted_albedo(tmp_path, capsys):
    # a constant, coloured MERL table: Y must be the BT.709 weighting of the RGB albedo
    from gonio.brdf.merl import DIMS, SCALES

    rho = np.array([0.2, 0.5, 0.8])
    raw = np.broadcast_to((rho / np.pi / SCALES)[:, None, None, None], (3, *DIMS)).copy()
    path = tmp_path / "coloured.binary"
    MERLBRDF(raw).write(path)
    assert run("brdf", "info", str(path), "--theta-i-deg", "0,40") in (0, None)
    out = capsys.readouterr().out
    assert "Y (sRGB)" in out
    rows = [line.split("│")[1:-1] for line in out.splitlines() if line.count("│") == 6]
    values = np.array([[float(c) for c in r] for r in rows])
    assert values.shape == (2, 5) and list(values[:, 0]) == [0.0, 40.0]
    rgb, y = values[:, 1:4], values[:, 4]
    np.testing.assert_allclose(rgb, np.broadcast_to(rho, (2, 3)), atol=2e-3)
    # both columns are printed to 4 decimals: rounding alone moves them by 1e-4
    np.testing.assert_allclose(y, rgb @ BT709, atol=1e-4)
