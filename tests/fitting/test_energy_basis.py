"""The energy check's albedo basis, one quadrature per lobe, against the model's albedo."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.fitting.fit import ENERGY_THETA, _albedo_basis, _lobe_parameters
from gonio.fitting.losses import get_loss
from gonio.fitting.objective import prepare_problem


@pytest.mark.parametrize(
    "name,options",
    [
        ("lambert", {}),
        ("oren-nayar", {}),
        ("lambert+ggx", {}),
        ("lambert+beckmann", {"g1": "rational"}),
        ("lambert+ggx+ggx", {}),  # repeated names: ks_2, alpha_2, ks_3, alpha_3
        ("lambert+ggx", {"fresnel": "schlick"}),
    ],
)
def test_basis_columns_are_the_models_albedo_of_each_linear_parameter(name, options, make_samples):
    m = get_model(name, **options)
    assert _lobe_parameters(m) is not None
    s = make_samples("lambert", {"albedo": [0.3, 0.3, 0.3]}, n=200, seed=1)
    prob = prepare_problem(m, s, get_loss("cosine_l2"))
    rng = np.random.default_rng(0)
    lo, hi = prob.lb_shape, prob.ub_shape
    thetas = lo + (hi - lo) * rng.uniform(0.05, 0.6, (3, prob.n_shape))
    B = _albedo_basis(prob, thetas)  # (M, T, K)
    assert B.shape == (3, ENERGY_THETA.size, prob.n_linear)
    for i, th in enumerate(thetas):
        for j, lin in enumerate(prob.linear_names):
            p = {n: float(t) for n, t in zip(prob.shape_names, th, strict=True)}
            unit = min(1.0, prob.ub_lin[j])  # (Oren-Nayar's albedo <= 0.98)
            p.update({n: (unit if n == lin else 0.0) for n in prob.linear_names})
            ref = m.albedo(ENERGY_THETA, p) / unit  # the model's own sum over its lobes
            # Lambert's column is exactly 1; the quadrature reaches it to ~1e-11
            np.testing.assert_allclose(B[i, :, j], ref, rtol=1e-10, atol=0)
