"""Adaptive acquisition against the regular grid, on real simulated sessions (issue 17).

Each material is measured once by a real simulated session (composition root's device
opener, virtual time, ``perfect`` world, 160 x 120 frames) on a regular grid (theta_i,
theta_o every 20 deg to 80, phi_o every 90 deg: 30 poses).  Its coarser regular grids are subsets
of it; the adaptive loop of ``benchmarks/adaptive.py`` (seed design, fit every
candidate, :func:`gonio.fitting.design.score_candidates`, :func:`choose_batch`,
:func:`stopping`) picks its poses from the same measured pool.  The error is the one of
the benchmark: the median relative difference of the chosen model from the truth over
:func:`gonio.fitting.design.hemisphere_directions`.

"Never worse at equal time": at every grid's session time (the scheduler's travel +
exposures + downloads), the adaptive run's fit at that time is no worse than the grid's
beyond twice the grid fit's median predicted relative sigma of f from the samples' noise
(the statistical resolution of the error figure: two fits whose errors differ by less
are the same fit within their noise; the analytic materials sit at that floor).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from gonio.fitting import design

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
THETA = (0.0, 20.0, 40.0, 60.0, 80.0)
PHI = (0.0, 90.0, 180.0)
GRIDS = ((40, 90), (20, 90))
#: the ``gonio fit --model auto`` candidates (the benchmark adds a Fresnel lobe)
CANDIDATES = ("lambert", "oren-nayar", "lambert+ggx", "lambert+beckmann")


def _load(name: str):
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(name, mod)
    spec.loader.exec_module(mod)
    return sys.modules[name]


@pytest.fixture(scope="module")
def bench():
    return _load("adaptive")


@pytest.fixture(scope="module")
def pools(tmp_path_factory, bench):
    """Material name -> (material, measured pool), one real session each, made on first
    use."""
    S = bench.sessions
    # GONIO_ADAPTIVE_TEST_ROOT keeps the sessions between runs (for working on the design)
    keep = os.environ.get("GONIO_ADAPTIVE_TEST_ROOT")
    root = Path(keep) if keep else tmp_path_factory.mktemp("adaptive")
    made: dict = {}

    def get(name: str):
        if name not in made:
            m = next(x for x in S.materials() if x.name == name)
            if m.file is not None and not m.file.is_file():
                pytest.skip(f"RGL file {m.file} not found")
            made[name] = (m, S.load_pool(S.dense_session(root, m, theta=THETA, phi=PHI)))
        return made[name]

    return get


def _grid_fit(bench, pool, truth, th, ph):
    pos = bench.sessions.grid_positions(pool, th, ph)
    ev = bench.evaluate(pool, pos, truth, CANDIDATES)
    best = ev["fits"][int(np.argmax(ev["weights"]))]
    # the noise-only predicted relative sigma of f over the hemisphere: the resolution of
    # the error figure (the reported covariance also holds the shared calibration scale
    # and the rig's stated geometry, which the perfect world does not have)
    wi, wo = truth.wi[:512], truth.wo[:512]
    f, v = design.predictive(best, wi, wo, design.noise_covariance(best, ev["samples"]))
    sigma = float(np.median(np.max(np.sqrt(v) / np.abs(f), axis=1)))
    return {"poses": len(pos), "time_s": bench.sessions.session_time_s(pool, [pos]),
            "error": ev["error"], "sigma": sigma, "model": ev["model"]}  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        "lambert+ggx(alpha=0.3)",
        # no candidate follows paper_white (chi^2/dof ~ 500): grids and adaptive run are
        # fitted by the aligned fit (gonio.fitting.model_error.fit_aligned: relative
        # residuals, Cauchy, coverage weights); 2026-12-02: adaptive 0.0261 against the
        # 30-pose grid's 0.0275 (with the discrepancy in the sigmas before; with the
        # noise weights alone the adaptive run ended at 0.556 against 0.533)
        "rgl:paper_white",
    ],
)
def test_adaptive_never_ends_worse_than_the_grid_of_the_same_time(bench, pools, name):
    m, pool = pools(name)
    truth = bench.Truth(m, n=2048)
    grids = [_grid_fit(bench, pool, truth, th, ph) for th, ph in GRIDS]
    assert grids[-1]["poses"] == len(pool.pose_ids)  # the finest grid is the whole session
    rounds = bench.adaptive_run(pool, truth, seed_poses=9, batch=4, candidates=CANDIDATES,
                                max_poses=len(pool.pose_ids) - 2)  # fmt: skip
    for r in rounds:
        print(f"  adaptive {r['poses']} poses {r['time_s']:.0f} s {r['model']} {r['error']:.4g}")
    seen = 0
    for g in grids:
        e = bench.error_at(rounds, g["time_s"])
        print(f"{name}: grid {g['poses']} poses {g['time_s']:.0f} s {g['model']} error "
              f"{g['error']:.4g} (sigma {g['sigma']:.3g}); adaptive at that time {e}")  # fmt: skip
        if e is None:  # the seed design alone takes longer than this grid
            continue
        seen += 1
        assert e <= g["error"] + 2.0 * g["sigma"], (name, g["poses"], e, g["error"])
    assert seen >= 1


@pytest.mark.slow
def test_stopping_rule_honoured_and_sigma_consistent_with_the_truth(bench, pools):
    """Asked for 1 % relative sigma on alpha, each run stops at the first round whose
    reported sigma reaches it, and the fitted alpha is within its sigma of the truth.

    Three runs on disjoint thirds of the measured poses (independent frames and noise;
    alpha is a shape parameter, untouched by the shared reference scale).  The check is
    sum z^2 <= 16.27 (chi^2 with 3 degrees of freedom at p = 0.001) and |z| < 3.29 each;
    its power against a reported sigma k times too small: P(chi^2_3 > 16.27 / k^2) =
    0.25 at k = 2, 0.61 at k = 3, 0.89 at k = 5.  A target below the floor the
    systematic terms leave (0.1 %) is never reported as reached.
    """
    m, pool = pools("lambert+ggx(alpha=0.3)")
    truth = bench.Truth(m, n=512)
    alpha = m.params["alpha"][0]
    thirds = [np.arange(k, len(pool.pose_ids), 3) for k in range(3)]
    z = []
    for part in thirds:
        sub = _subpool(bench, pool, part)
        rounds = bench.adaptive_run(sub, truth, seed_poses=6, batch=2, max_poses=10,
                                    candidates=CANDIDATES,
                                    target_rel_sigma={"alpha": 0.01},
                                    stop_on_target=True)  # fmt: skip
        rel = [r["stop"]["rel_sigma"].get("alpha") for r in rounds]
        reached = [x is not None and x <= 0.01 for x in rel]
        assert reached[-1], rel
        assert not any(reached[:-1]), rel  # stopped at the first round that reached it
        last = rounds[-1]
        a, s = last["params"]["alpha"][0], last["std"]["alpha"][0]
        assert s / a == pytest.approx(rel[-1])
        z.append((a - alpha) / s)
    print("alpha z over three disjoint runs:", np.round(z, 3))
    assert np.all(np.abs(z) < 3.29) and float(np.sum(np.square(z))) <= 16.27, z
    # a target below what the reported covariance can reach is not reached: the run goes
    # on to its pose budget and says why
    rounds = bench.adaptive_run(_subpool(bench, pool, thirds[0]), truth, seed_poses=6, batch=2,
                                max_poses=8, target_rel_sigma={"alpha": 1e-5},
                                candidates=CANDIDATES,
                                stop_on_target=True)  # fmt: skip
    assert rounds[-1]["poses"] == 8
    assert "alpha rel sigma" in rounds[-1]["stop"]["reason"]
    assert rounds[-1]["stop"]["reason"].startswith("not reached")


def _subpool(bench, pool, positions):
    """The pool restricted to ``positions`` (its samples too)."""
    import dataclasses

    positions = np.asarray(positions, dtype=int)
    keep = np.isin(pool.samples.pose, pool.pose_ids[positions])
    return dataclasses.replace(
        pool,
        samples=bench.sessions._take(pool.samples, keep),
        pose_ids=pool.pose_ids[positions],
        wi=pool.wi[positions],
        wo=pool.wo[positions],
        joints=[pool.joints[k] for k in positions],
        exposure_s=pool.exposure_s[positions],
        frames=pool.frames[positions],
    )
