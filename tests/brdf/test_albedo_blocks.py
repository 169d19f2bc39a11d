"""The albedo quadrature gives the same bits whatever the block of cases it evaluates at
once (gonio.brdf.albedo evaluates the integrand in cache-sized blocks of a chunk)."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import albedo
from gonio.brdf.lobes import OrenNayarLobe, WardLobe
from gonio.brdf.microfacet import BeckmannLobe, GGXLobe

N = 30  # more than one chunk (albedo._CHUNK = 24), blocks of unequal size


def _cases(lobe, rng) -> dict[str, np.ndarray]:
    if isinstance(lobe, OrenNayarLobe):
        return {"albedo": np.ones(N), "sigma": rng.uniform(0.0, 1.0, N)}
    if getattr(lobe, "anisotropic", False):
        ax, ay = rng.uniform(0.01, 0.5, (2, N))
        return {"ks": np.ones(N), "alpha_x": ax, "alpha_y": ay}
    p = {"ks": np.ones(N), "alpha": 10.0 ** rng.uniform(-3.0, 0.0, N)}
    if "f0" in {s.name for s in lobe.specs}:
        p["f0"] = np.full(N, 0.04)
    return p


@pytest.mark.parametrize(
    "lobe",
    [
        GGXLobe(),
        GGXLobe(fresnel="schlick"),
        BeckmannLobe(),
        OrenNayarLobe(),
        WardLobe(anisotropic=True),
    ],
    ids=["ggx", "ggx-schlick", "beckmann", "oren-nayar", "ward-aniso"],
)
def test_albedo_is_the_same_in_any_block_size(lobe, monkeypatch):
    rng = np.random.default_rng(7)
    p = _cases(lobe, rng)
    theta = rng.uniform(0.0, 1.55, N)
    phi = rng.uniform(-3.0, 3.0, N)  # phi != 0: every component of dot(h, wi) counts
    monkeypatch.setattr(albedo, "_BLOCK_NODES", 1)  # one case per block
    single = albedo.lobe_albedo(lobe, theta, p, phi)
    monkeypatch.setattr(albedo, "_BLOCK_NODES", 10**9)  # the whole chunk at once
    whole = albedo.lobe_albedo(lobe, theta, p, phi)
    monkeypatch.undo()
    default = albedo.lobe_albedo(lobe, theta, p, phi)
    assert np.all(np.isfinite(default)) and np.all((default > 0) & (default <= 1 + 1e-9))
    np.testing.assert_array_equal(single, whole)
    np.testing.assert_array_equal(default, whole)
