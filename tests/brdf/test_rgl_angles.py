"""The RGL evaluator's own arctangent (gonio.brdf.rgl._atan2 & co.) against libm.

Both evaluation paths (numpy and the numba kernel) take their angles from a table-plus-
series arctangent instead of libm's, for speed; these tests hold it to libm's ``atan2``
and ``asin`` (the independent reference), including the signs of zero and the axes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.brdf import rgl


def _ulps(mine: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.abs(mine - ref) / np.spacing(np.maximum(np.abs(ref), 1e-300))


def test_atan2_within_two_ulp_of_libm():
    rng = np.random.default_rng(190)
    n = 200_000
    # magnitudes over 26 decades, all four quadrants
    y = rng.normal(size=n) * np.exp(rng.uniform(-30, 30, n))
    x = rng.normal(size=n) * np.exp(rng.uniform(-30, 30, n))
    ref = np.array([math.atan2(a, b) for a, b in zip(y, x, strict=True)])
    assert _ulps(rgl._atan2(y, x), ref).max() <= 2.0


def test_atan01_on_the_table_nodes_and_between():
    t = np.concatenate([np.linspace(0.0, 1.0, 100_001), np.arange(257) / 256.0])
    ref = np.array([math.atan(v) for v in t])
    assert _ulps(rgl._atan01(t), ref).max() <= 1.0


@pytest.mark.parametrize(
    "y,x",
    [
        (0.0, 0.0),
        (-0.0, 0.0),
        (0.0, -0.0),
        (-0.0, -0.0),
        (1.0, 0.0),
        (-1.0, 0.0),
        (0.0, 1.0),
        (0.0, -1.0),
        (-0.0, -1.0),
        (1.0, 1.0),
        (-1.0, -1.0),
        (1.0, -1.0),
        (1e-300, 1.0),
        (1.0, -1e-300),
        (np.inf, 1.0),
    ],
)
def test_atan2_special_values_as_libm(y, x):
    got = float(rgl._atan2(np.array(y), np.array(x)))
    ref = math.atan2(y, x)
    assert got == ref and math.copysign(1.0, got) == math.copysign(1.0, ref)


def test_elevation_within_three_ulp_of_libm_asin():
    rng = np.random.default_rng(191)
    v = rng.normal(size=(200_000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[:, 2] = np.abs(v[:, 2])
    v[:8] = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.6, 0.0, 0.8]] * 2
    ref = np.array(
        [2.0 * math.asin(min(1.0, 0.5 * math.sqrt(a * a + b * b + (c - 1) ** 2))) for a, b, c in v]
    )
    assert _ulps(rgl._elevation(v), ref).max() <= 3.0
