"""The fused numba kernels (``gonio.brdf.kernels``) against the numpy path they replace.

The numpy formulation of the microfacet lobes is the reference (it is the one validated
against Mitsuba 3 and against closed forms in the other ``tests/brdf`` modules); the
kernels must agree with it to 1e-14 relative on random and edge-case inputs, reproduce the
zero / NaN pattern exactly, and actually be the code that runs for large batches.  A
closed form (GGX and Beckmann at the normal: ``f = ks / (4 pi alpha^2)``) checks both
paths independently.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from gonio.brdf import get_model, kernels

RTOL = 1e-14

CONFIGS = [
    ("ggx", {}),
    ("ggx", {"fresnel": "schlick"}),
    ("ggx", {"fresnel": "conductor"}),
    ("ggx", {"fresnel": "dielectric"}),
    ("beckmann", {}),
    ("beckmann", {"fresnel": "conductor"}),
    ("beckmann", {"g1": "rational"}),
    ("beckmann", {"g1": "rational", "fresnel": "schlick"}),
    ("beckmann", {"g1": "rational", "fresnel": "dielectric"}),
]
IDS = [n + "".join(f"-{v}" for v in o.values()) for n, o in CONFIGS]

# Per-channel values inside the bounds (Au-like conductor, glass-like dielectric).
CHANNEL_VALUES = {
    "ks": [0.9, 0.5, 1.0],
    "alpha": [1e-4, 0.05, 0.7],
    "f0": [0.04, 0.5, 1.0],
    "eta": [1.2, 0.43, 2.5],
    "k": [0.0, 2.46, 8.0],
}


@pytest.fixture
def calls(monkeypatch):
    """Counts kernel invocations, to prove the fused path is the one under test."""
    counts = dict.fromkeys(
        ["ggx_hot", "ggx_hot_serial", "microfacet_eval", "microfacet_eval_serial"], 0
    )
    for name in counts:
        fn = getattr(kernels, name)

        def spy(*a, _fn=fn, _name=name):
            counts[_name] += 1
            return _fn(*a)

        monkeypatch.setattr(kernels, name, spy)
    return counts


def _numpy_path(monkeypatch, fn):
    with monkeypatch.context() as m:
        m.setenv("GONIO_NUMBA", "0")
        return fn()


def _hemisphere(rng: np.random.Generator, n: int, zmin: float = 0.0) -> np.ndarray:
    ct = rng.uniform(zmin, 1.0, n)
    ph = rng.uniform(0.0, 2 * math.pi, n)
    st = np.sqrt(1.0 - ct * ct)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)


def _edge_pairs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Random pairs interleaved with the stability cases of issue 2."""
    wi = _hemisphere(rng, n)
    wo = _hemisphere(rng, n)
    # Not exactly unit length, as after a float32 round trip (the numpy hot path and the
    # general path differ in the last bits for those: the kernels must mirror each).
    wi[: n // 8] = wi[: n // 8].astype(np.float32)
    k = np.arange(n)
    sel = k % 16
    wo[sel == 1] = wi[sel == 1]  # wi == wo
    wo[sel == 2] = wi[sel == 2] * [-1.0, -1.0, 1.0]  # wi == reflect(wo): h = normal
    wi[sel == 3] = [0.0, 0.0, 1.0]  # normal incidence
    wi[sel == 4] = [1.0, 0.0, 0.0]  # theta_i exactly 90 deg -> 0
    wo[sel == 5] = [0.0, -1.0, 0.0]  # theta_o exactly 90 deg -> 0
    wi[sel == 6] = [math.sin(math.radians(89.999)), 0.0, math.cos(math.radians(89.999))]
    wo[sel == 7] = [0.0, 1.0, 1e-300]  # grazing by a hair, still above the horizon
    wi[sel == 8, 2] *= -1.0  # below the horizon -> 0
    wo[sel == 9] = -wi[sel == 9]  # wi == -wo -> 0
    wi[sel == 10, 0] = np.nan  # NaN in -> NaN out
    wo[sel == 11, 2] = np.nan
    wi[sel == 12, 1] = np.nan  # ... but below the horizon wins
    wo[sel == 12, 2] = -0.5
    wo[sel == 13] = [0.0, 0.0, 1.0]
    wi[sel == 13] = [0.0, 0.0, 1.0]  # both at the normal
    return wi, wo


def _assert_same(fast: np.ndarray, ref: np.ndarray) -> None:
    assert fast.shape == ref.shape
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    np.testing.assert_array_equal(fast == 0.0, ref == 0.0)
    ok = np.isfinite(ref) & (ref != 0.0)
    assert np.all(np.isfinite(fast[ok]))
    # Relative to max(|ref|, smallest normal float): subnormal results (far-off-peak
    # Beckmann, ~1e-310) have fewer significant bits, so a last-bit difference in exp()
    # upstream is a 1e-14-scale relative one there; among normal values it is <= 2e-15.
    scale = np.maximum(np.abs(ref[ok]), np.finfo(np.float64).tiny)
    rel = np.abs(fast[ok] - ref[ok]) / scale
    assert rel.max(initial=0.0) <= RTOL, f"max rel diff {rel.max():.3g}"


@pytest.mark.parametrize(("name", "opts"), CONFIGS, ids=IDS)
@pytest.mark.parametrize("alpha", [1e-4, 0.2, 1.0])
def test_scalar_params_match_numpy(monkeypatch, calls, name, opts, alpha):
    m = get_model(name, **opts)
    rng = np.random.default_rng(7)
    wi, wo = _edge_pairs(rng, 6000)
    p = dict(m.defaults, alpha=alpha, ks=0.8)
    fast = m.eval(wi, wo, p)
    assert sum(calls.values()) == 1
    ref = _numpy_path(monkeypatch, lambda: m.eval(wi, wo, p))
    assert sum(calls.values()) == 1  # the reference did not use the kernels
    _assert_same(fast, ref)
    assert np.all(np.isnan(fast[10::16])) and np.all(np.isnan(fast[11::16]))
    for s in (4, 5, 8, 9, 12):
        assert np.all(fast[s::16] == 0.0)
    assert np.all(np.isfinite(fast[~np.isnan(wi).any(-1) & ~np.isnan(wo).any(-1)]))


@pytest.mark.parametrize(("name", "opts"), CONFIGS, ids=IDS)
def test_per_channel_params_match_numpy(monkeypatch, calls, name, opts):
    """The ``bind`` path: ``(N, 1, 3)`` directions against ``(3,)`` parameters."""
    m = get_model(name, **opts)
    rng = np.random.default_rng(11)
    wi, wo = _edge_pairs(rng, 4000)
    values = {k: CHANNEL_VALUES[k] for k in m.param_names}
    if opts.get("fresnel") == "dielectric":
        values["eta"] = [1.0, 1.5, 4.0]
    bound = m.bind(values)
    fast = bound.eval(wi, wo)
    assert calls["microfacet_eval_serial"] == 1
    ref = _numpy_path(monkeypatch, lambda: bound.eval(wi, wo))
    assert fast.shape == (4000, 3)
    _assert_same(fast, ref)


@pytest.mark.parametrize(
    ("name", "opts"), [CONFIGS[0], CONFIGS[2], CONFIGS[6]], ids=IDS[:1] + [IDS[2], IDS[6]]
)
def test_layouts_and_sums_match_numpy(monkeypatch, calls, name, opts):
    """Large batches (the model's chunked loop hands the lobe Fortran-ordered chunks),
    broadcast (stride-0) directions as the renderer passes them, and a sum of lobes."""
    rng = np.random.default_rng(3)
    wi, wo = _edge_pairs(rng, 40_000)
    m = get_model(name, **opts)
    cases = {
        "chunked": (m, wi, wo, {}),
        "broadcast": (
            m,
            wi[:5000, None, :].repeat(2, axis=1),
            np.broadcast_to(wo[:2][None, :, :], (5000, 2, 3)),
            {},
        ),
        "sum": (get_model(f"lambert+{name}", **opts), wi[:8000], wo[:8000], {"albedo": 0.3}),
    }
    for label, (model, a, b, p) in cases.items():
        before = sum(calls.values())
        fast = model.eval(a, b, p)
        assert sum(calls.values()) > before, label
        ref = _numpy_path(monkeypatch, lambda model=model, a=a, b=b, p=p: model.eval(a, b, p))
        _assert_same(fast, ref)


@pytest.mark.parametrize(
    ("name", "opts"), [CONFIGS[0], CONFIGS[2], CONFIGS[4]], ids=IDS[:1] + [IDS[2], IDS[4]]
)
def test_multithreaded_kernels_match_numpy(monkeypatch, calls, name, opts):
    """Batches of >= PARALLEL_PAIRS evaluations run on the multi-threaded kernels."""
    rng = np.random.default_rng(13)
    n = kernels.PARALLEL_PAIRS + 1000
    wi, wo = _edge_pairs(rng, n)
    m = get_model(name, **opts)
    # (N, 1, 3) directions are not chunked by the model, so the lobe sees the whole batch.
    fast = m.eval(wi[:, None, :], wo[:, None, :])
    ref = _numpy_path(monkeypatch, lambda: m.eval(wi[:, None, :], wo[:, None, :]))
    assert calls["ggx_hot"] + calls["microfacet_eval"] == 1
    assert fast.shape == (n, 1)
    _assert_same(fast, ref)
    bound = m.bind({"alpha": [0.01, 0.2, 0.6]})
    fast = bound.eval(wi[:30_000], wo[:30_000])
    assert calls["microfacet_eval"] == 1 + (name != "ggx" or bool(opts))
    _assert_same(fast, _numpy_path(monkeypatch, lambda: bound.eval(wi[:30_000], wo[:30_000])))


@pytest.mark.parametrize("name", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [1e-4, 0.01, 0.3, 1.0])
def test_closed_form_at_the_normal(monkeypatch, calls, name, alpha):
    """wi = wo = n: D = 1 / (pi alpha^2), G1 = 1, F = 1, so f = ks / (4 pi alpha^2)."""
    n = 5000
    z = np.tile([0.0, 0.0, 1.0], (n, 1))
    m = get_model(name)
    expected = 0.7 / (4.0 * math.pi * alpha * alpha)
    fast = m.eval(z, z, {"ks": 0.7, "alpha": alpha})
    assert sum(calls.values()) == 1
    ref = _numpy_path(monkeypatch, lambda: m.eval(z, z, {"ks": 0.7, "alpha": alpha}))
    np.testing.assert_allclose(fast, expected, rtol=1e-14, atol=0)
    np.testing.assert_allclose(ref, expected, rtol=1e-14, atol=0)


@pytest.mark.parametrize(("name", "opts"), CONFIGS, ids=IDS)
def test_reciprocity(calls, name, opts):
    rng = np.random.default_rng(5)
    wi, wo = _hemisphere(rng, 5000, 1e-3), _hemisphere(rng, 5000, 1e-3)
    m = get_model(name, **opts)
    a, b = m.eval(wi, wo), m.eval(wo, wi)
    assert sum(calls.values()) == 2
    # atol: far-off-peak Beckmann values are subnormal (~1e-317), where a last-bit
    # difference in the product order G1(wi) G1(wo) is a large relative one.
    np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-300)


def test_small_batches_stay_on_numpy(calls):
    m = get_model("ggx")
    rng = np.random.default_rng(1)
    m.eval(_hemisphere(rng, kernels.MIN_PAIRS - 1), _hemisphere(rng, kernels.MIN_PAIRS - 1))
    m.eval_with_grad(_hemisphere(rng, 10_000), _hemisphere(rng, 10_000))
    assert sum(calls.values()) == 0


def test_numba_is_loaded_only_by_a_large_batch():
    """Small evaluations (CLI plots) must not pay numba's import and load time."""
    code = (
        "import sys, numpy as np\n"
        "from gonio.brdf import get_model\n"
        "w = np.tile([0.0, 0.6, 0.8], (60_000, 1))\n"
        "m = get_model('ggx').bind({})\n"
        "a = m.eval(w, w)\n"  # 180 000 evaluations: loads the kernels
        "print('numba' in sys.modules)\n"
    )
    for n, loaded in (("20_000", "False"), ("60_000", "True")):
        out = subprocess.run(
            [sys.executable, "-c", code.replace("60_000", n)],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "GONIO_NUMBA": "1"},
        )
        assert out.stdout.split() == [loaded], (n, out.stdout, out.stderr)


def test_threshold_matches_the_hook():
    from gonio.brdf import microfacet

    assert microfacet._MIN_FUSED == kernels.MIN_PAIRS


# --- RGL measured BRDFs -----------------------------------------------------------------


def _rgl_pairs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    wi, wo = _hemisphere(rng, n), _hemisphere(rng, n)
    k = n // 2  # half near the mirror direction, where glossy lobes are
    near = wi[:k] * [-1, -1, 1] + rng.normal(scale=0.08, size=(k, 3))
    near[:, 2] = np.abs(near[:, 2]) + 1e-3
    wo[:k] = near / np.linalg.norm(near, axis=1, keepdims=True)
    wi[k : k + 8] = [0.0, 0.0, 1.0]  # normal incidence
    wo[k + 8 : k + 16] = wi[k + 8 : k + 16] * [-1.0, -1.0, 1.0]  # exact mirror: m = n
    return wi, wo


def _anisotropic_file(rgl_file, tmp_path, reduction: int):
    from gonio.brdf.tensor_file import read_tensor_file, write_tensor_file

    # As in test_rgl_eval: phi_i slices scaled differently, so that phi_i interpolation
    # and the mirror reduction matter.
    lo, hi = {1: (-math.pi, math.pi), 2: (-math.pi, 0.0), 4: (-math.pi, -math.pi / 2)}[reduction]
    f = dict(read_tensor_file(rgl_file("vch_golden_yellow")))
    phis = np.linspace(lo, hi, 5).astype(np.float32)
    scale = (1 + 0.5 * np.cos(phis) + 0.2 * np.sin(phis)).astype(np.float32)
    f["phi_i"] = phis
    f["vndf"] = np.repeat(f["vndf"], 5, axis=0)
    f["luminance"] = np.repeat(f["luminance"], 5, axis=0)
    f["rgb"] = (np.repeat(f["rgb"], 5, axis=0) * scale[:, None, None, None, None]).astype(
        np.float32
    )
    path = tmp_path / f"aniso{reduction}.bsdf"
    write_tensor_file(path, f)
    return path


def _one_theta_file(rgl_file, tmp_path):
    from gonio.brdf.tensor_file import read_tensor_file, write_tensor_file

    # a single tabulated incident elevation: the kernel pads its slices to two
    f = dict(read_tensor_file(rgl_file("paper_white")))
    f["theta_i"] = f["theta_i"][3:4].copy()
    for name in ("vndf", "luminance", "rgb"):
        f[name] = np.ascontiguousarray(f[name][:, 3:4])
    path = tmp_path / "one_theta.bsdf"
    write_tensor_file(path, f)
    return path


def _sigma_rows_file(rgl_file, tmp_path):
    from gonio.brdf.tensor_file import read_tensor_file, write_tensor_file

    # a projected area that varies with phi_i: the isotropic path with both azimuths
    f = dict(read_tensor_file(rgl_file("paper_white")))
    f["sigma"] = (f["sigma"] * np.array([[1.0], [1.25]])).astype(np.float32)
    path = tmp_path / "sigma_rows.bsdf"
    write_tensor_file(path, f)
    return path


@pytest.fixture
def rgl_calls(monkeypatch):
    counts = {"n": 0}
    fn = kernels.rgl_eval

    def spy(*a):
        counts["n"] += 1
        return fn(*a)

    monkeypatch.setattr(kernels, "rgl_eval", spy)
    return counts


@pytest.mark.parametrize(
    "material",
    ["paper_white", "vch_golden_yellow", "aniso1", "aniso2", "aniso4", "one_theta", "sigma_rows"],
)
def test_rgl_kernel_matches_numpy(monkeypatch, rgl_calls, rgl_file, tmp_path, material):
    from gonio.brdf import rgl

    if material.startswith("aniso"):
        b = rgl.read_rgl(_anisotropic_file(rgl_file, tmp_path, int(material[-1])))
        assert not b.isotropic
    elif material == "sigma_rows":
        b = rgl.read_rgl(_sigma_rows_file(rgl_file, tmp_path))
        assert b.isotropic and not b._relative_only
    elif material == "one_theta":
        b = rgl.read_rgl(_one_theta_file(rgl_file, tmp_path))
        assert b.theta_i.size == 1
    else:
        b = rgl.read_rgl(rgl_file(material))
        assert b._relative_only  # every shared file: one arctangent for the azimuths
    wi, wo = _rgl_pairs(np.random.default_rng(17), 6000)
    wi[5000] = [0.6, 0.0, -0.8]  # below the horizon: 0
    wo[5001] = [np.nan, 0.0, 0.5]  # NaN in: NaN out
    wi[5002] = [np.inf, 0.0, 0.5]  # infinite in: NaN out
    wo[5003] = [0.0, 0.6, -0.8]  # wo below the horizon: 0
    wi[5004], wo[5004] = [0.0, 0.6, -0.8], [0.3, np.nan, 0.5]  # NaN wins over the horizon
    wi[5005] = [1.0, 0.0, 0.0]  # on the horizon: 0
    # normal incidence with signed zeros: phi_i = atan2(+-0, +-0) is +-0 or +-pi
    wi[5006], wi[5007], wi[5008] = [-0.0, 0.0, 1.0], [-0.0, -0.0, 1.0], [0.0, -0.0, 1.0]
    fast = b.eval(wi, wo)
    assert rgl_calls["n"] == 1
    ref = _numpy_path(monkeypatch, lambda: b.eval(wi, wo))
    assert rgl_calls["n"] == 1
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    assert np.all(fast[[5000, 5003, 5005]] == 0.0)
    assert np.all(np.isnan(fast[[5001, 5002, 5004]]))
    assert np.isfinite(np.delete(fast, [5001, 5002, 5004], axis=0)).all()
    assert np.count_nonzero(np.isfinite(ref) & (ref != 0)) > 5000 * b._n_ch  # not trivial
    # the same IEEE operations in the same order (the angles included: both paths take
    # them from gonio.brdf.rgl's arctangent), so the two agree bit for bit
    np.testing.assert_array_equal(fast, ref)


def test_rgl_values_come_in_one_layout_whichever_path_made_them(monkeypatch, rgl_calls, rgl_file):
    """C order from the kernel, the numpy path with every pair above the horizon (whose
    transposed table read gave F order before) and the masked numpy path: a caller's
    sum over the values (an einsum, directional_albedo) rounds by their layout, so equal
    values in two layouts summed to different bits."""
    from gonio.brdf import rgl

    b = rgl.read_rgl(rgl_file("paper_white"))
    wi, wo = _rgl_pairs(np.random.default_rng(4), 6000)
    fast = b.eval(wi, wo)
    assert rgl_calls["n"] == 1
    ref = _numpy_path(monkeypatch, lambda: b.eval(wi, wo))
    wi_m = wi.copy()
    wi_m[0, 2] = -0.5  # one pair below the horizon: the masked numpy path
    masked = _numpy_path(monkeypatch, lambda: b.eval(wi_m, wo))
    assert rgl_calls["n"] == 1
    for f in (fast, ref, masked):
        assert f.flags.c_contiguous
    np.testing.assert_array_equal(fast, ref)
    g = np.random.default_rng(5).uniform(size=(2000, 3))
    sums = [np.einsum("mkc,mk->mc", f.reshape(2000, 3, -1), g) for f in (fast, ref)]
    assert sums[0].tobytes() == sums[1].tobytes()


def test_read_only_inputs_share_one_compilation():
    """Writeable and read-only inputs (a frozen caller's directions, broadcast per-channel
    parameters) reach the kernels as one argument type: the writeable flag is part of
    numba's type, and each mix was a compilation of its own (~30 s for ``rgl_eval``)."""
    m = get_model("ggx", fresnel="schlick")
    rng = np.random.default_rng(5)
    wi, wo = _hemisphere(rng, 6000)[:, None, :], _hemisphere(rng, 6000)[:, None, :]
    frozen_wi, frozen_wo = wi.copy(), wo.copy()
    frozen_wi.flags.writeable = frozen_wo.flags.writeable = False
    channels = {"ks": [0.9, 0.5, 1.0], "alpha": [0.2, 0.3, 0.4], "f0": [0.04, 0.5, 0.9]}
    runs = [
        (wi, wo, m.bind(channels)),
        (frozen_wi, frozen_wo, m.bind(channels)),
        (wi, frozen_wo, m.bind({"ks": 0.9, "alpha": 0.2, "f0": 0.04})),
    ]
    counts = []
    for a, b, bound in runs:
        bound.eval(a, b)
        counts.append(len(kernels.microfacet_eval_serial.signatures))
    assert counts[1:] == counts[:1] * 2
