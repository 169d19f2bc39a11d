"""Fit figures: the slice curves are the model along the plane of incidence and pass through
noise-free in-plane samples; the z map is zero for a perfect fit; odd inputs do not crash."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples
from gonio.fitting.plots import (
    plot_residual_map,
    plot_slices,
    scaled_residuals,
    slices_figure,
)
from gonio.fitting.result import FitResult

GGX = {"albedo": [0.4, 0.3, 0.2], "ks": [0.6, 0.5, 0.4], "alpha": [0.25, 0.25, 0.25]}
THETA_I = (0.0, 20.0, 50.0)
SIGNED_O = np.arange(-80.0, 81.0, 7.5)  # deg, + on the mirror side


def _result(model: str, params: dict, n: int, used: np.ndarray | None = None) -> FitResult:
    """A FitResult at given parameters, as a perfect fit would return it (no optimiser)."""
    p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
    C = len(next(iter(p.values())))
    channels = ("R", "G", "B") if C == 3 else ("Y",)
    return FitResult(
        model=model,
        model_options={},
        channels=channels,
        params=p,
        std={k: np.zeros(C) for k in p},
        covariance=np.zeros((0, 0)),
        param_labels=(),
        shape_params=(),
        linear_params=(),
        loss="weighted_l2",
        robust=None,
        cost=0.0,
        residuals=np.zeros((n, C)),
        used=np.ones(n, dtype=bool) if used is None else used,
        n_samples=n,
        n_params=0,
        nfev=0,
        njev=0,
        algorithm=[],
        status=1,
        message="constructed",
        success=True,
    )


def _in_plane_samples(model: str, params: dict, phi_i_deg: float = 35.0):
    """Samples exactly in the plane of incidence at THETA_I x SIGNED_O, the plane rotated
    to azimuth ``phi_i_deg`` (so the plot must use relative azimuths), plus out-of-plane
    samples (relative azimuth 90 deg) and one flagged in-plane outlier."""
    m = get_model(model)
    p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
    phi = np.radians(phi_i_deg)
    wi, wo, signed = [], [], []
    for ti in np.radians(THETA_I):
        for s in np.radians(SIGNED_O):
            wi.append([np.sin(ti) * np.cos(phi), np.sin(ti) * np.sin(phi), np.cos(ti)])
            # The mirror side is the azimuth opposite the light: phi + pi for s > 0.
            wo.append([-np.sin(s) * np.cos(phi), -np.sin(s) * np.sin(phi), np.cos(s)])
            signed.append(np.degrees(s))
    n_in = len(wi)
    # (At normal incidence every azimuth is in the plane of incidence: none there.)
    for ti in np.radians(THETA_I[1:]):
        for to in np.radians([20.0, 40.0, 60.0]):
            wi.append([np.sin(ti) * np.cos(phi), np.sin(ti) * np.sin(phi), np.cos(ti)])
            a = phi + np.pi / 2
            wo.append([np.sin(to) * np.cos(a), np.sin(to) * np.sin(a), np.cos(to)])
    wi, wo = np.array(wi), np.array(wo)
    f = m.eval(wi[:, None, :], wo[:, None, :], p)
    y = f.copy()
    flags = np.zeros(len(wi), dtype=np.uint32)
    y[3] *= 50.0  # a flagged outlier that must not be drawn
    flags[3] = 1
    sigma = 0.01 * f
    sigma[5] = np.nan  # unknown sigma: drawn without an error bar
    s = BRDFSamples(wi=wi, wo=wo, brdf=y, brdf_std=sigma, flags=flags, channels=None)
    return s, f, np.array(signed), n_in


def _lines(fig, prefix: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """gid -> concatenated (x, y) over the panels, in panel order (list per panel)."""
    out: dict[str, list] = {}
    for ax in fig.axes:
        for ln in ax.lines:
            gid = ln.get_gid()
            if gid and gid.startswith(prefix):
                out.setdefault(gid, []).append(
                    (np.asarray(ln.get_xdata()), np.asarray(ln.get_ydata()))
                )
    return out


def test_fitted_curve_passes_through_noise_free_in_plane_points() -> None:
    s, f, signed, n_in = _in_plane_samples("lambert+ggx", GGX)
    r = _result("lambert+ggx", GGX, len(s))
    fig = slices_figure(r, s)
    curves = _lines(fig, "fit:")
    points = _lines(fig, "measured:")
    assert set(curves) == {"fit:R", "fit:G", "fit:B"}
    assert len(curves["fit:R"]) == len(THETA_I)  # one panel per discrete theta_i
    n_per = len(SIGNED_O)
    for c, name in enumerate("RGB"):
        for b in range(len(THETA_I)):
            xc, yc = curves[f"fit:{name}"][b]
            assert np.all(np.diff(xc) > 0) and xc.size > 200  # a smooth curve, not a zig-zag
            xp, yp = points[f"measured:{name}"][b]
            rows = np.arange(b * n_per, (b + 1) * n_per)
            rows = rows[rows != 3]  # the flagged outlier is not drawn
            # Only the in-plane, unflagged samples are drawn, at their signed theta_o.
            np.testing.assert_allclose(np.sort(xp), np.sort(signed[rows]), atol=1e-9)
            # The curve, interpolated at each sample's angle, is the sample's noise-free
            # value (computed above from the model at the sample's own directions).
            at = np.exp(np.interp(signed[rows], xc, np.log(yc)))
            np.testing.assert_allclose(at, f[rows, c], rtol=2e-4)
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_log_panels_label_their_decades_in_plain_text() -> None:
    # no mathtext (its parser cost a tenth of a second per process): "10⁻²" as characters
    sharp = {"albedo": [0.02] * 3, "ks": [0.8] * 3, "alpha": [0.05] * 3}  # spans decades
    s, _, _, _ = _in_plane_samples("lambert+ggx", sharp)
    fig = slices_figure(_result("lambert+ggx", sharp, len(s)), s)
    log_axes = [ax for ax in fig.axes if ax.get_yscale() == "log"]
    assert log_axes
    fmt = log_axes[0].yaxis.get_major_formatter()
    labels = [fmt(v, k) for k, v in enumerate((1e-3, 1e-2, 0.1, 1.0, 10.0, 100.0))]
    assert labels == ["10⁻³", "10⁻²", "10⁻¹", "10⁰", "10¹", "10²"]


def test_wrong_parameters_give_a_curve_off_the_points() -> None:
    # The check above can fail: a curve of other parameters misses the points.
    s, f, signed, _ = _in_plane_samples("lambert+ggx", GGX)
    wrong = dict(GGX, alpha=[0.3, 0.3, 0.3])
    fig = slices_figure(_result("lambert+ggx", wrong, len(s)), s)
    xc, yc = _lines(fig, "fit:")["fit:R"][1]
    rows = np.arange(len(SIGNED_O), 2 * len(SIGNED_O))
    at = np.interp(signed[rows], xc, yc)
    assert np.max(np.abs(at / f[rows, 0] - 1)) > 0.05
    import matplotlib.pyplot as plt

    plt.close(fig)


def test_z_map_is_zero_for_a_perfect_fit_and_exact_for_an_offset() -> None:
    s, f, _, _ = _in_plane_samples("lambert+ggx", GGX)
    r = _result("lambert+ggx", GGX, len(s))
    z, label, lim = scaled_residuals(r, s)
    keep = s.flags == 0
    assert z.shape == (keep.sum(), 3) and lim == 5.0 and "sigma" in label
    sig = s.brdf_std[keep]
    known = np.isfinite(sig)
    np.testing.assert_allclose(z[known], 0.0, atol=1e-9)
    assert np.all(np.isnan(z[~known]))
    # measured = 1.1 x model with sigma = 1 % of the model: z = 0.1 / 0.01 = 10 exactly
    s2 = BRDFSamples(wi=s.wi, wo=s.wo, brdf=1.1 * f, brdf_std=0.01 * f, flags=s.flags)
    z2, _, _ = scaled_residuals(r, s2)
    np.testing.assert_allclose(z2, 10.0, rtol=1e-9)
    # Without any sigma: log2(measured / fitted) = log2(2) = 1
    s3 = BRDFSamples(wi=s.wi, wo=s.wo, brdf=2.0 * f, flags=s.flags)
    lr, label3, lim3 = scaled_residuals(r, s3)
    assert "log2" in label3 and lim3 == 2.0
    np.testing.assert_allclose(lr, 1.0, rtol=1e-12)


@pytest.mark.parametrize("channels", [3, 1])
def test_files_written_for_rgb_and_one_channel(tmp_path, channels: int) -> None:
    if channels == 3:
        s, _, _, _ = _in_plane_samples("lambert+ggx", GGX)
        r = _result("lambert+ggx", GGX, len(s))
    else:
        params = {"albedo": [0.5]}
        s0, _, _, _ = _in_plane_samples("lambert", {"albedo": [0.5, 0.5, 0.5]})
        s = BRDFSamples(wi=s0.wi, wo=s0.wo, brdf=s0.brdf[:, :1], flags=s0.flags, channels=("Y",))
        r = _result("lambert", params, len(s))
    a = plot_slices(r, s, tmp_path / "slices.png")
    b = plot_residual_map(r, s, tmp_path / "residuals.png")
    for p in (a, b):
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


def test_few_flagged_and_unused_samples_do_not_crash(tmp_path) -> None:
    s, _, _, _ = _in_plane_samples("lambert+ggx", GGX)
    # Two usable samples, the rest unused by the fit; then none at all.
    used = np.zeros(len(s), dtype=bool)
    used[[0, len(s) - 1]] = True
    for mask in (used, np.zeros(len(s), dtype=bool)):
        r = _result("lambert+ggx", GGX, len(s), used=mask)
        assert plot_slices(r, s, tmp_path / "s.png").stat().st_size > 5_000
        assert plot_residual_map(r, s, tmp_path / "r.png").stat().st_size > 5_000
