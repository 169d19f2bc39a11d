"""Does the reported uncertainty hold against the world? (issue 16's accuracy harness)

The lab path on a ``realistic`` as-built world: camera and rig calibration once, then one
measurement session per material (``lambert+ggx``, ``lambert+ggx[fresnel=schlick]``, the
measured RGL paper white) on the calibrated rig, reduced with the calibrated camera and
fitted (:mod:`gonio.app.budget_harness`).  The truth is the material's own BRDF at the
reported directions (the closed-form model, the RGL file), never the code under test.

Targets (issue 16): sample z-scores with an RMS in [0.8, 1.25] per channel and per theta
band (>= ``MIN_BAND_SAMPLES`` = 100 samples) with the full budget, after whitening by the
covariance the budget states (the raw RMS is printed too); the fitted BRDF within 1 %
(median relative error); every fitted parameter within 3 reported sigma.  The harness
states the room's diffuse-light bound (stray + ambient, 7e-4) as ``[light]
stray_fraction``; a truth multi-valued at normal incidence (the RGL file) is not judged
on the poses around the pole (printed apart).  A budget of noise alone must be
caught: that is what shows the harness can fail.

World seed: 1601 (issue 16's seeds, 1601..1609, are named by no other test: the fixed
world seeds of the other tests are below 40 and the random ones are drawn from
[0, 2^31), where hitting 1601 is a one-in-10^9 chance).  ``benchmarks/budget.py`` runs
the same harness over several seeds.

Bands are judged where the window is a real test (>= ``MIN_BAND_SAMPLES`` samples, up to
80 deg: ``gonio.app.budget_harness.judge``); every band is printed.
"""

from __future__ import annotations

import json

import pytest

from gonio.app.budget_harness import (
    MIN_BAND_SAMPLES,
    Z_RANGE,
    capabilities,
    default_materials,
    judge,
    noise_only_outside,
    run_world,
)

SEED = 1601
MATERIALS = ("lambert+ggx", "lambert+ggx[fresnel=schlick]", "rgl:paper_white")


#: issue 16's last misses on this world (the 70-80 deg band's G at z RMS 1.27, ks of
#: lambert+ggx at -3.8 sigma) were the regions' aperture bias at grazing near-specular
#: poses, now corrected by the reduction (gonio.capture.aperture; DEVELOPING.md).  With
#: it and the hot pixels found against their neighbourhood (2026-12-02): 70-80 deg G raw
#: z RMS 1.11, whitened 1.02; ks z -1.7/-2.6/-2.1 (schlick f0 -2.4, alpha 2.1)
SAMPLE_Z_CASES = MATERIALS
FIT_CASES = MATERIALS


@pytest.fixture(scope="module")
def world(tmp_path_factory, rgl_file):
    try:
        rgl = rgl_file("paper_white")
    except pytest.skip.Exception:
        rgl = None
    run = run_world(tmp_path_factory.mktemp("budget"), SEED, default_materials(rgl))
    print(f"\nbudget harness: world seed {SEED}, capabilities {capabilities()}")
    print(f"seconds {json.dumps({k: round(v, 1) for k, v in run.seconds.items()})}")
    return run


def _report(world, name: str) -> dict:
    if name not in world.materials:
        pytest.skip(f"{name}: material not measured (RGL file not found)")
    return world.materials[name]


def _print_bands(name: str, rep: dict) -> None:
    for which in ("whitened", "full", "noise_only"):
        rows = rep["samples"][which]["bands"]
        txt = ", ".join(
            f"{b}: " + "/".join(f"{v:.2f}" for c, v in r.items() if c != "n") + f" (n {r['n']})"
            for b, r in rows.items()
        )
        print(f"{name} z RMS R/G/B {which}: {txt}")
    pole = rep.get("pole") or {}
    if pole.get("n_set_apart"):
        rows = pole["samples"]["whitened"]["bands"]
        txt = ", ".join(
            f"{b}: " + "/".join(f"{v:.2f}" for c, v in r.items() if c != "n") + f" (n {r['n']})"
            for b, r in rows.items()
        )
        print(
            f"{name}: poses {pole['poses']} around the pole set apart (truth asymmetry "
            f"{pole['truth_asymmetry']:.3f}), whitened z RMS R/G/B: {txt}"
        )


@pytest.mark.slow
def test_a_noise_only_budget_is_caught(world):
    """The harness can fail: with the noise term alone, the z-scores of the glossy
    material are outside the range somewhere (geometry and radiometry are missing)."""
    rep = _report(world, "lambert+ggx")
    _print_bands("lambert+ggx", rep)
    bad = noise_only_outside(rep)
    assert bad, f"world seed {SEED}: noise-only z RMS within {Z_RANGE} everywhere: {rep}"


@pytest.mark.slow
@pytest.mark.parametrize("name", SAMPLE_Z_CASES)
def test_sample_z_scores_with_the_full_budget(world, name):
    rep = _report(world, name)
    _print_bands(name, rep)
    bands = rep["samples"]["full"]["bands"]
    judged = [b for b, r in bands.items() if r["n"] >= MIN_BAND_SAMPLES]
    assert "70-80" in judged, f"world seed {SEED}, {name}: no 70-80 deg band: {bands}"
    failures = judge(rep).get("z_full")
    assert not failures, f"world seed {SEED}, {name}: z RMS outside {Z_RANGE}: {failures}"


@pytest.mark.slow
@pytest.mark.parametrize("name", FIT_CASES)
def test_fit_within_a_percent_and_its_parameters_within_3_sigma(world, name):
    rep = _report(world, name)
    f = rep["fit"]
    print(
        f"{name}: model {f['model']}, median rel. BRDF error {f['median_rel_brdf_error']:.3%} "
        f"(against {f['reference']}), z {json.dumps(f['z'])}"
    )
    assert f["success"], f"world seed {SEED}, {name}: fit failed"
    assert f["median_rel_brdf_error"] <= 0.01, f"world seed {SEED}, {name}: {f}"
    far = judge(rep).get("params")
    assert not far, f"world seed {SEED}, {name}: parameters >= 3 sigma off: {far}"
