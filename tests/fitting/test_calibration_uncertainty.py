"""A calibration scale shared by all samples adds p * rel_std to the linear parameters."""

import numpy as np

from gonio.dataset import load_samples, save_samples
from gonio.fitting import fit


def test_common_scale_uncertainty_reaches_linear_params_only(make_samples, tmp_path):
    truth = {"albedo": [0.5, 0.4, 0.3], "ks": [0.2] * 3, "alpha": [0.2] * 3}
    s = make_samples("lambert+ggx", truth, n=600, seed=4, noise=1e-7)
    base = fit(s, model="lambert+ggx")
    rel = np.array([0.01, 0.02, 0.005])
    s.attrs["calibration_rel_std"] = rel.tolist()
    # through the file, as the reduction hands it over
    s2 = load_samples(save_samples(tmp_path / "s.h5", s))
    r = fit(s2, model="lambert+ggx")
    for name in ("albedo", "ks"):
        p = r.params[name]
        expected = np.sqrt(base.std[name] ** 2 + (p * rel) ** 2)
        np.testing.assert_allclose(r.std[name], expected, rtol=1e-6)
        assert np.all(r.std[name] > 0.9 * p * rel)  # dominated by the calibration
    np.testing.assert_allclose(r.std["alpha"], base.std["alpha"], rtol=1e-9)
    # albedo and ks of one channel move together under a common scale: correlation > 0
    labels = list(r.param_labels)
    i, j = labels.index("albedo[R]"), labels.index("ks[R]")
    c = r.covariance
    assert c[i, j] / np.sqrt(c[i, i] * c[j, j]) > 0.9
