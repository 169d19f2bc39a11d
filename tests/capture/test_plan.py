"""Plans: TOML validation (errors name the field), grids, symmetry reductions, exclusions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.capture.plan import expand_plan, load_plan, plan_digest, plan_from_dict
from gonio.errors import ConfigError, SessionError
from gonio.radiometry import half_diff_from_directions

REPO_EXAMPLE = __import__("pathlib").Path(__file__).resolve().parents[2] / "examples" / "plan.toml"


def _plan(**grid):
    return {"grid": grid}


def test_example_plan_loads():
    plan = load_plan(REPO_EXAMPLE)
    assert plan.bracket.policy in ("adaptive", "fixed")
    assert expand_plan(plan).poses


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        ({"grid": {"theta_i_deg": [0], "theta_o_deg": [0]}, "bracket": {"iso": -1}}, "bracket.iso"),
        ({"grid": {"theta_i_deg": [0], "theta_o_deg": [95]}}, "grid"),
        ({"grid": {"theta_i_deg": [0]}}, "grid"),
        (
            {"grid": {"theta_i_deg": [0], "theta_o_deg": [0]}, "bracket": {"policy": "fixed"}},
            "bracket",
        ),
        (
            {"grid": {"theta_i_deg": [0], "theta_o_deg": [0]}, "darks": {"count": "two"}},
            "darks.count",
        ),
        ({"grid": {"theta_i_deg": [0], "theta_o_deg": [0]}, "exposure": 1}, "exposure"),
        ({}, "grid"),
    ],
)
def test_invalid_plan_names_the_field(doc, field):
    with pytest.raises(ConfigError) as info:
        plan_from_dict(doc, "plan.toml")
    msg = str(info.value)
    assert "plan.toml" in msg and f"field '{field}" in msg


def test_bad_toml_and_missing_file(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text("[grid\n")
    with pytest.raises(ConfigError, match="not a valid TOML"):
        load_plan(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_plan(tmp_path / "missing.toml")


def test_spherical_grid_is_the_cartesian_product():
    theta_o = {"start": 0, "stop": 40, "step": 20}
    plan = plan_from_dict(
        _plan(theta_i_deg=[10, 20], phi_i_deg=[0], theta_o_deg=theta_o, phi_o_deg=[0, 90])
    )
    ex = expand_plan(plan)
    assert ex.n_grid == 2 * 1 * 3 * 2
    # theta_o = 0 with phi_o 0 and 90 is the same pose (the azimuth of the normal is
    # meaningless): measured once, even without symmetry reductions
    assert len(ex.poses) == 10 and ex.n_reduced == 2
    wi = np.array([p.wi for p in ex.poses])
    assert np.allclose(np.degrees(np.arccos(wi[:, 2]))[:5], 10)
    assert np.allclose(np.linalg.norm(wi, axis=1), 1)


def test_isotropic_and_reciprocity_reductions_counts():
    # theta in {30, 60}, relative azimuths {0, 90, 180} after folding: 2 * 2 * 3 = 12
    # isotropic poses; reciprocity keeps unordered theta pairs {30,30},{30,60},{60,60}: 9.
    g = {"theta_i_deg": [30, 60], "phi_i_deg": [0, 90], "theta_o_deg": [30, 60],
         "phi_o_deg": [0, 90, 180, 270]}  # fmt: skip
    full = expand_plan(plan_from_dict({"grid": g}))
    iso = expand_plan(plan_from_dict({"grid": g, "reductions": {"isotropic": True}}))
    both = expand_plan(
        plan_from_dict({"grid": g, "reductions": {"isotropic": True, "reciprocity": True}})
    )
    assert len(full.poses) == 32
    assert len(iso.poses) == 12 and iso.n_reduced == 20
    assert len(both.poses) == 9 and both.n_reduced == 23
    # isotropic poses are canonical: phi_i = 0, phi_o in [0, 180]
    for p in iso.poses:
        a = p.angles_deg()
        assert abs(a["phi_i_deg"]) < 1e-6 and -1e-6 <= a["phi_o_deg"] <= 180 + 1e-6


def test_reciprocity_alone_keeps_one_of_each_swapped_pair():
    g = {"theta_i_deg": [20, 40], "phi_i_deg": [0], "theta_o_deg": [20, 40], "phi_o_deg": [0]}
    ex = expand_plan(plan_from_dict({"grid": g, "reductions": {"reciprocity": True}}))
    # (20,20), (20,40), (40,20)==(20,40) swapped, (40,40)
    assert len(ex.poses) == 3 and ex.n_reduced == 1


def test_exclusions_have_reasons():
    g = {"theta_i_deg": [0, 45, 88], "phi_i_deg": [0], "theta_o_deg": [45, 50], "phi_o_deg": [0]}
    plan = plan_from_dict(
        {"grid": g, "exclusions": {"grazing_limit_deg": 80, "min_separation_deg": 10}}
    )
    ex = expand_plan(plan)
    reasons = [e.reason for e in ex.excluded]
    # theta_i = 88 twice (grazing); wi = wo at (45, 45) and 5 deg apart at (45, 50)
    assert sum("grazing" in r for r in reasons) == 2
    assert sum("shadows the light" in r for r in reasons) == 2
    assert len(ex.poses) == 6 - 4
    assert all("exclusions." in r for r in reasons)  # the reason names the plan field


def test_rig_check_excludes_with_the_rig_reason():
    g = {"theta_i_deg": [30], "phi_i_deg": [0], "theta_o_deg": [10, 30, 50], "phi_o_deg": [180]}

    def check(wi, wo):
        return "stage_tilt beyond its limit" if wo[2] > 0.95 else None

    ex = expand_plan(plan_from_dict({"grid": g}), rig_check=check)
    assert [e.reason for e in ex.excluded] == ["stage_tilt beyond its limit"]
    assert len(ex.poses) == 2


def test_half_difference_grid_round_trips():
    g = {
        "kind": "half_difference",
        "theta_h_deg": [0, 20],
        "phi_h_deg": [0],
        "theta_d_deg": [10, 30, 80],
        "phi_d_deg": [0],
    }
    ex = expand_plan(plan_from_dict({"grid": g, "exclusions": {"grazing_limit_deg": 90}}))
    assert ex.n_grid == 6
    # theta_h = 20, theta_d = 80 puts a direction below the horizon: excluded
    assert any("horizon" in e.reason or "grazing" in e.reason for e in ex.excluded)
    for p in ex.poses:
        th, _, td, _ = half_diff_from_directions(np.array(p.wi), np.array(p.wo))
        assert min(abs(math.degrees(th) - v) for v in (0, 20)) < 1e-6
        assert min(abs(math.degrees(td) - v) for v in (10, 30, 80)) < 1e-6


def test_no_reachable_pose_is_a_session_error():
    from gonio.capture.schedule import build_schedule
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics

    cfg = default_rig_config()
    # wi == wo everywhere: the camera would sit on the light
    plan = plan_from_dict(
        {"grid": {"theta_i_deg": [30, 40], "theta_o_deg": [30, 40]}, "reductions": {}}
    )
    g = {"theta_i_deg": [30], "phi_i_deg": [0], "theta_o_deg": [30], "phi_o_deg": [0]}
    plan = plan_from_dict({"grid": g})
    with pytest.raises(SessionError, match="no reachable pose"):
        build_schedule(plan, Kinematics(cfg), cfg.park_rad)


# --- issue 14.2 (validation half): settle_s is bounded ------------------------------

_G1 = {"theta_i_deg": [0], "theta_o_deg": [30]}


@pytest.mark.parametrize("value", [-0.1, 60.5, 1e308, float("inf"), float("nan")])
def test_settle_s_outside_zero_to_sixty_seconds_is_refused(value):
    with pytest.raises(ConfigError, match=r"plan.toml.*field 'settle_s'"):
        plan_from_dict({"grid": _G1, "settle_s": value}, "plan.toml")


def test_settle_s_within_bounds_is_kept():
    assert plan_from_dict({"grid": _G1, "settle_s": 60}).settle_s == 60.0
    assert plan_from_dict({"grid": _G1, "settle_s": 0}).settle_s == 0.0


# --- issue 14.6: every time in a plan is finite and at most an hour --------------------


@pytest.mark.parametrize(
    ("section", "values", "field"),
    [
        ("bracket", {"exposure_time_s": float("inf")}, "bracket.exposure_time_s"),
        (
            "bracket",
            {"exposure_time_s": 1e308, "max_exposure_s": 1e308},
            "bracket.exposure_time_s",
        ),
        ("bracket", {"max_exposure_s": 3601}, "bracket.max_exposure_s"),
        ("bracket", {"min_exposure_s": float("inf")}, "bracket.min_exposure_s"),
        ("bracket", {"policy": "fixed", "exposures_s": [0.01, 1e308]}, "bracket.exposures_s.1"),
        ("bracket", {"policy": "fixed", "exposures_s": [float("inf")]}, "bracket.exposures_s.0"),
        ("bracket", {"shot_overhead_s": float("inf")}, "bracket.shot_overhead_s"),
        ("darks", {"count": 1, "exposure_times_s": [1e308]}, "darks.exposure_times_s.0"),
        ("darks", {"count": 1, "exposure_times_s": [float("inf")]}, "darks.exposure_times_s.0"),
    ],
)
def test_times_must_be_finite_and_physical(section, values, field):
    with pytest.raises(ConfigError) as info:
        plan_from_dict({"grid": _G1, section: values}, "plan.toml")
    assert f"field '{field}'" in str(info.value)


def test_an_hour_is_the_longest_exposure_accepted():
    p = plan_from_dict({"grid": _G1, "bracket": {"exposure_time_s": 3600, "max_exposure_s": 3600}})
    assert p.bracket.exposure_time_s == 3600.0


# --- issue 14.3: resource limits, checked before the grid is expanded ------------------


def _deg_range(n, step):
    return {"start": 0, "stop": (n - 1) * step, "step": step}


def _no_expansion(monkeypatch):
    import gonio.capture.plan as plan_mod

    def boom(grid):
        raise AssertionError("the grid was expanded")

    monkeypatch.setattr(plan_mod, "_grid_directions", boom)


def test_a_972000_pose_plan_is_refused_before_expanding_with_the_figures(monkeypatch):
    # The dry run: 90 x 90 x 120 without symmetry reductions.
    g = {
        "theta_i_deg": _deg_range(90, 1),
        "theta_o_deg": _deg_range(90, 1),
        "phi_o_deg": _deg_range(120, 3),
    }
    plan = plan_from_dict({"grid": g, "bracket": {"max_frames": 4}}, "big.toml")
    _no_expansion(monkeypatch)
    with pytest.raises(ConfigError) as info:
        expand_plan(plan, source="big.toml")
    msg = str(info.value)
    n = 90 * 90 * 120
    assert n == 972_000
    assert msg.startswith("big.toml: plan 'plan' is too large")
    assert f"{n:,} poses > limits.max_poses = 50,000" in msg
    # 4 frames a pose, 30 MB each (no simulation resolution given)
    assert f"up to {n:,} poses and {4 * n:,} frames" in msg
    assert f"{4 * n * 30e6 / 1e12:.3g} TB of RAW files" in msg
    assert "[limits]" in msg


def test_a_45_9_million_pose_plan_is_refused_before_allocating(monkeypatch):
    import tracemalloc

    g = {
        "theta_i_deg": _deg_range(90, 1),
        "phi_i_deg": _deg_range(50, 7.2),
        "theta_o_deg": _deg_range(85, 1),
        "phi_o_deg": _deg_range(120, 3),
    }
    plan = plan_from_dict({"grid": g, "limits": {"max_poses": 10**9, "max_frames": 10**10,
                                                  "max_bytes": 1e18}})  # fmt: skip
    n = 90 * 50 * 85 * 120
    assert n == 45_900_000
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError) as info:
            expand_plan(plan)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10e6  # the expansion would need ~47 GB; nothing of it was allocated
    msg = str(info.value)
    assert f"{n:,} grid poses" in msg and "of memory > limits.max_memory_bytes" in msg
    # memory: 1 kB per grid pose + 40 B per pair of poses to order
    assert f"{(n * 1024 + 40 * (n + 1) ** 2) / 1e15:.3g} PB of memory" in msg


def test_isotropy_is_counted_on_the_axes_so_a_big_reduced_grid_passes(monkeypatch):
    from gonio.capture.plan import estimate_plan

    # 36 x 36 azimuths, but only 19 relative azimuths in [0, 180] survive isotropy.
    g = {
        "theta_i_deg": _deg_range(9, 10),
        "phi_i_deg": _deg_range(36, 10),
        "theta_o_deg": _deg_range(9, 10),
        "phi_o_deg": _deg_range(36, 10),
    }
    est = estimate_plan(plan_from_dict({"grid": g, "reductions": {"isotropic": True}}))
    assert est.n_grid == 9 * 36 * 9 * 36
    assert est.n_poses == 9 * 9 * 19
    plan = plan_from_dict({"grid": g, "reductions": {"isotropic": True},
                           "limits": {"max_poses": 9 * 9 * 19}})  # fmt: skip
    ex = expand_plan(plan)
    assert len(ex.poses) <= est.n_poses


def test_frame_bytes_come_from_the_simulation_resolution():
    from gonio.capture.plan import estimate_plan

    plan = plan_from_dict(
        {
            "grid": {"theta_i_deg": [0, 30], "theta_o_deg": [10, 20, 30]},
            "bracket": {"policy": "fixed", "exposures_s": [0.01, 0.1]},
            "darks": {"count": 3},
            "simulation": {"width": 64, "height": 48},
        }
    )
    est = estimate_plan(plan)
    assert est.n_poses == 6 and est.n_frames == 6 * 2 + 3 * 2
    assert est.frame_bytes == 64 * 48 * 2 + 65536
    with pytest.raises(ConfigError, match=r"18 frames > limits.max_frames = 17"):
        expand_plan(plan.model_copy(update={"limits": plan.limits.model_copy(
            update={"max_frames": 17})}))  # fmt: skip


def test_a_large_allowed_expansion_reports_progress():
    g = {"theta_i_deg": _deg_range(10, 5), "theta_o_deg": _deg_range(10, 5),
         "phi_o_deg": _deg_range(30, 12)}  # fmt: skip
    calls = []
    ex = expand_plan(plan_from_dict({"grid": g}), progress=lambda d, t: calls.append((d, t)))
    n = 10 * 10 * 30
    assert ex.n_grid == n
    assert calls[0] == (0, n) and calls[-1] == (n, n)
    done = [d for d, _ in calls]
    assert done == sorted(done) and 90 <= len(calls) <= 102


def test_default_limits_leave_digests_and_manifests_unchanged():
    # A plan without [limits] dumps as before the table existed (sessions resume).
    p = plan_from_dict({"grid": _G1})
    assert "limits" not in p.model_dump(mode="json")
    # the digest the code before [limits] gave this plan
    assert plan_digest(p) == "1fb1cdf5815bc3dd382480b905e0f8ce8063d235acd0b8c0edc49e70aab267a0"
    q = plan_from_dict({"grid": _G1, "limits": {"max_poses": 7}})
    assert q.model_dump(mode="json")["limits"]["max_poses"] == 7
    assert plan_from_dict(q.model_dump(mode="json")).limits.max_poses == 7


def test_excluded_poses_carry_a_code_the_rig_chose():
    """Exclusions are grouped and journaled by code, not by parsing their sentences."""
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics

    kin = Kinematics(default_rig_config())
    g = {"theta_i_deg": [30, 89], "phi_i_deg": [0], "theta_o_deg": [30], "phi_o_deg": [180, 0]}
    plan = plan_from_dict({"grid": g, "exclusions": {"grazing_limit_deg": 85}})
    ex = expand_plan(plan, rig_check=kin.refusal)
    codes = {(round(e.pose.angles_deg()["theta_i_deg"]), e.code) for e in ex.excluded}
    assert (89, "plan") in codes  # the plan's own grazing limit
    rig = [e for e in ex.excluded if e.code != "plan"]
    assert rig, ex.excluded
    for e in rig:  # the rig's code is the one its own check gives for that pose
        assert e.code == kin.refusal(np.array(e.pose.wi), np.array(e.pose.wo)).reason.value


# --- the reference target's reflectance: refused in the plan, not after the session ----


@pytest.mark.parametrize("value", [0.0, -0.5, 1.5, [0.9, 0.0, 0.9], [0.9, 2.0, 0.9]])
def test_a_reference_reflectance_outside_0_1_is_refused_naming_the_field(value):
    # It was accepted, copied into the session's reduction.toml and refused only by the
    # reduction, after the whole session had been shot.
    doc = {"grid": _G1, "reference": {"reflectance": value}}
    with pytest.raises(ConfigError) as info:
        plan_from_dict(doc, "plan.toml")
    assert "plan.toml" in str(info.value)
    assert "field 'reference.reflectance" in str(info.value)


@pytest.mark.parametrize("value", [1.0, 0.02, [0.5, 0.6, 0.99]])
def test_a_reference_reflectance_in_0_1_is_kept(value):
    plan = plan_from_dict({"grid": _G1, "reference": {"reflectance": value}})
    assert plan.reference.reflectance == (tuple(value) if isinstance(value, list) else value)
