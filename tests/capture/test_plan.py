"""Plans: TOML validation (errors name the field), grids, symmetry reductions, exclusions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.capture.plan import expand_plan, load_plan, plan_from_dict
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
    from gonio.capture.session import build_schedule
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
