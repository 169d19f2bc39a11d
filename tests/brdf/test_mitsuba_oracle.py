"""The shared Mitsuba loader: variant selection, caching and the scalar fallback."""

from __future__ import annotations

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

oracle = pytest.importorskip("gonio.mitsuba_oracle")


def _mitsuba_or_skip(prefer):
    try:
        return oracle.load_mitsuba(prefer)
    except oracle.MitsubaUnavailableError as exc:
        pytest.skip(str(exc))


def test_scalar_variant_is_always_available():
    mi, variant = _mitsuba_or_skip("scalar")
    assert variant == "scalar_rgb" and mi.variant() == "scalar_rgb"
    assert issubclass(oracle.MitsubaUnavailableError, ImportError)


def test_llvm_variant_is_probed_and_usable_or_falls_back():
    mi, variant = _mitsuba_or_skip("llvm")
    assert variant in ("llvm_ad_rgb", "scalar_rgb")
    assert variant == ("llvm_ad_rgb" if oracle.llvm_usable() else "scalar_rgb")
    b = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": 0.2})
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(0.0, 0.6, 0.8)
    v = b.eval(mi.BSDFContext(), si, mi.Vector3f(0.0, -0.6, 0.8))
    # specular configuration, h = n: f cos = D G / (4 cos_i) = 1/(pi a^2) G / 3.2
    g1 = 2.0 / (1.0 + (1.0 + 0.04 * 0.75**2) ** 0.5)
    assert float(v[0][0] if variant.startswith("llvm") else v[0]) == pytest.approx(
        g1 * g1 / (3.141592653589793 * 0.04 * 3.2), rel=1e-5
    )
    # cached: the second call does not probe again and returns the same variant
    assert oracle.load_mitsuba("llvm")[1] == variant
    oracle.load_mitsuba("scalar")  # leave the process in the variant other tests expect


def test_bad_preference():
    with pytest.raises(ValueError, match="'llvm' or 'scalar'"):
        oracle.load_mitsuba("cuda")
