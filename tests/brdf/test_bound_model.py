"""``Model.bind`` / ``BoundModel`` for any channel count, and ``FitResult.bind`` using it.

The reference is the unbound model evaluated one channel at a time with scalar parameters.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.brdf.base import BoundModel
from gonio.errors import ParameterError
from gonio.fitting.result import FitResult


def _directions(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    v[0, 0, 2] = -0.2  # one light below the horizon: exactly 0 in every channel
    return v[0], v[1]


def _per_channel(model, params: dict, c: int) -> dict:
    return {k: (np.asarray(v)[c] if np.ndim(v) else v) for k, v in params.items()}


@pytest.mark.parametrize("C", [1, 3, 5])
def test_eval_and_albedo_equal_the_model_channel_by_channel(C):
    model = get_model("lambert+ggx", fresnel="schlick")
    params = {
        "albedo": np.linspace(0.1, 0.6, C),
        "ks": np.linspace(0.3, 0.05, C),
        "alpha": 0.25,  # shared: broadcast to every channel
        "f0": np.full(C, 0.04) if C > 1 else [0.04],
    }
    wi, wo = _directions(64, seed=C)
    bound = model.bind(params, channels=C)
    assert isinstance(bound, BoundModel) and bound.channels == C
    if C > 1:  # inferred from the arrays' last axis (a lone (1,) stays grey RGB: below)
        assert model.bind(params).channels == C
    f = bound.eval(wi, wo)
    assert f.shape == (64, C)
    ref = np.stack([model.eval(wi, wo, _per_channel(model, params, c)) for c in range(C)], -1)
    np.testing.assert_allclose(f, ref, rtol=1e-14, atol=0)
    assert np.all(f[0] == 0.0)
    theta = np.radians([0.0, 35.0, 70.0])
    a = bound.albedo(theta)
    assert a.shape == (3, C)
    ref_a = np.stack([model.albedo(theta, _per_channel(model, params, c)) for c in range(C)], -1)
    np.testing.assert_allclose(a, ref_a, rtol=1e-14, atol=0)


def test_scalars_broadcast_to_three_channels_or_to_the_count_given():
    model = get_model("lambert")
    assert model.bind({"albedo": 0.4}).eval([0, 0, 1.0], [0, 0.6, 0.8]).shape == (3,)
    five = model.bind({"albedo": 0.4}, channels=5)
    np.testing.assert_allclose(five.eval([0, 0, 1.0], [0, 0.6, 0.8]), np.full(5, 0.4 / np.pi))
    # a last axis of 1 broadcasts too
    one = model.bind({"albedo": [0.4]}, channels=5)
    np.testing.assert_allclose(one.albedo(0.3), np.full(5, 0.4), rtol=1e-3)
    assert model.bind({"albedo": [0.4]}).channels == 3  # as before: (1,) is grey RGB


def test_bad_channel_counts_are_refused_by_name():
    model = get_model("lambert+ggx")
    with pytest.raises(ParameterError, match="'albedo' .*\\(3,\\).*'ks' .*\\(5,\\)"):
        model.bind({"albedo": [0.1, 0.2, 0.3], "ks": np.full(5, 0.1)})
    with pytest.raises(ParameterError, match="'albedo' must .* 4 colour channels"):
        model.bind({"albedo": [0.1, 0.2, 0.3]}, channels=4)
    with pytest.raises(ParameterError, match="positive integer"):
        model.bind({}, channels=0)
    with pytest.raises(ParameterError, match="outside its bounds"):
        model.bind({"albedo": [0.1, 1.5]})


def _fit_result(model: str, params: dict[str, np.ndarray], channels: tuple[str, ...]):
    nan = np.full(len(channels), np.nan)
    return FitResult(
        model=model,
        model_options={},
        channels=channels,
        params=params,
        std={k: nan for k in params},
        covariance=np.zeros((0, 0)),
        param_labels=(),
        shape_params=("alpha",),
        linear_params=("albedo", "ks"),
        loss="l2",
        robust=None,
        cost=0.0,
        residuals=np.zeros((0, len(channels))),
        used=np.zeros(0, bool),
        n_samples=0,
        n_params=0,
        nfev=0,
        njev=0,
        algorithm=[],
        status=0,
        message="",
        success=True,
    )


@pytest.mark.parametrize("channels", [("Y",), ("R", "G", "B"), tuple("abcde")])
def test_fit_result_binds_to_its_own_channel_count(channels):
    C = len(channels)
    params = {
        "albedo": np.linspace(0.2, 0.7, C),
        "ks": np.linspace(0.1, 0.3, C),
        "alpha": np.full(C, 0.3),  # shape parameters are repeated per channel
    }
    bound = _fit_result("lambert+ggx", params, channels).bind()
    assert isinstance(bound, BoundModel) and bound.channels == C
    wi, wo = _directions(16, seed=7)
    model = get_model("lambert+ggx")
    ref = np.stack([model.eval(wi, wo, _per_channel(model, params, c)) for c in range(C)], -1)
    np.testing.assert_allclose(bound.eval(wi, wo), ref, rtol=1e-14, atol=0)
