"""Shared helpers of the fitting tests: directions and synthetic samples from models."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples


def random_directions(rng: np.random.Generator, n: int, max_theta_deg: float = 85.0) -> np.ndarray:
    """Directions uniform in solid angle over the cap theta <= max_theta_deg."""
    cmin = np.cos(np.radians(max_theta_deg))
    z = cmin + (1.0 - cmin) * rng.random(n)
    phi = 2 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1)


def specular_pairs(
    rng: np.random.Generator, n: int, spread: float = 0.3
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs near the mirror configuration (half vector near the normal), so narrow lobes
    are sampled."""
    wi = random_directions(rng, n, 75.0)
    h = np.column_stack([spread * rng.standard_normal((n, 2)), np.ones(n)])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    wo = 2 * np.sum(wi * h, axis=1, keepdims=True) * h - wi
    bad = wo[:, 2] <= 0.02
    wo[bad] = random_directions(rng, int(bad.sum()), 80.0)
    return wi, wo


def model_samples(
    name: str,
    params: dict,
    n: int = 300,
    seed: int = 0,
    noise: float = 0.0,
    read: float = 0.0,
    options: dict | None = None,
) -> BRDFSamples:
    """Samples of model ``name`` at ``params`` (per-channel arrays); half random pairs, half
    near-mirror.  ``noise``: photon-noise factor (var = noise * f), ``read``: read-noise sigma;
    ``brdf_std`` is the true sigma."""
    rng = np.random.default_rng(seed)
    m = get_model(name, **(options or {}))
    wi1 = random_directions(rng, n - n // 2)
    wo1 = random_directions(rng, n - n // 2)
    wi2, wo2 = specular_pairs(rng, n // 2)
    wi = np.vstack([wi1, wi2])
    wo = np.vstack([wo1, wo2])
    p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
    f = m.eval(wi[:, None, :], wo[:, None, :], p)
    f = np.broadcast_to(f, (n, 3)).copy()
    if noise or read:
        sig = np.sqrt(noise * f + read**2)
        y = f + sig * rng.standard_normal(f.shape)
        return BRDFSamples(wi=wi, wo=wo, brdf=y, brdf_std=sig)
    return BRDFSamples(wi=wi, wo=wo, brdf=f)


@pytest.fixture
def make_samples():
    return model_samples
