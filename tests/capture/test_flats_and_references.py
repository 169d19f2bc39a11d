"""Plans with flat fields, darks for them and repeated reference groups (issue 16): the
tables' validation, the schedule's order, the engine's steps on fake devices, the rig
time in every shot record, and the refusals before anything moves."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.capture.engine import Engine, SessionDevices
from gonio.capture.plan import estimate_plan, plan_digest, plan_from_dict
from gonio.capture.schedule import build_schedule, with_reference_groups
from gonio.capture.session_plan import PlanState, session_plan
from gonio.capture.sessions import check_calibration_devices
from gonio.devices import MoveResult, RigState, Shot
from gonio.errors import CameraError, ConfigError, SessionError

GRID = {"theta_i_deg": [0, 20, 40], "theta_o_deg": [30, 50], "phi_o_deg": [180]}
REF = [
    {"theta_i_deg": 0, "theta_o_deg": 30},
    {"theta_i_deg": 30, "theta_o_deg": 30, "phi_o_deg": 180},
]


def _doc(**tables):
    return {
        "grid": dict(GRID),
        "bracket": {"policy": "fixed", "exposures_s": [0.002, 0.008]},
        **tables,
    }


@pytest.mark.parametrize(
    ("tables", "field"),
    [
        ({"flats": {"count": -1}}, "flats.count"),
        ({"flats": {"count": 101}}, "flats.count"),
        ({"flats": {"count": 2, "exposure_s": 0}}, "flats.exposure_s"),
        ({"flats": {"count": 2, "iso": -100}}, "flats.iso"),
        ({"flats": {"count": 2, "when": "middle"}}, "flats.when"),
        ({"flats": {"cout": 2}}, "flats.cout"),
        ({"reference": {"poses": REF, "every_poses": -1}}, "reference.every_poses"),
        ({"reference": {"poses": REF, "every_poses": "often"}}, "reference.every_poses"),
    ],
)
def test_bad_flats_and_reference_tables_name_the_field(tables, field):
    with pytest.raises(ConfigError) as info:
        plan_from_dict(_doc(**tables), "plan.toml")
    msg = str(info.value)
    assert "plan.toml" in msg and f"field '{field}" in msg


def test_default_tables_keep_the_plan_digest():
    """A plan without flats or repeated references dumps (and digests) as before the
    tables existed: sessions from before resume unchanged."""
    plain = plan_from_dict(_doc(reference={"poses": REF}))
    dumped = plain.model_dump()
    assert "flats" not in dumped and "every_poses" not in dumped["reference"]
    spelled = plan_from_dict(_doc(reference={"poses": REF, "every_poses": 0}, flats={"count": 0}))
    assert plan_digest(spelled) == plan_digest(plain)
    used = plan_from_dict(_doc(reference={"poses": REF, "every_poses": 2}, flats={"count": 3}))
    assert plan_digest(used) != plan_digest(plain)
    assert used.model_dump()["flats"]["count"] == 3


@pytest.mark.parametrize(
    ("n", "every", "when", "expected"),
    [
        (5, 0, "start", "RRsssss"),
        (5, 0, "end", "sssssRR"),
        (5, 2, "start", "RRssRRssRRs"),
        (4, 2, "start", "RRssRRssRR"),
        (5, 2, "end", "ssRRssRRsRR"),
        (4, 2, "end", "ssRRssRR"),
        (3, 5, "end", "sssRR"),
    ],
)
def test_reference_group_repeats_after_every_n_samples(n, every, when, expected):
    plan = plan_from_dict(_doc(reference={"poses": REF, "every_poses": every, "when": when}))
    got = "".join(with_reference_groups(["s"] * n, ["R", "R"], plan))
    assert got == expected
    # the estimator counts the same groups
    assert plan.reference_repeats(n) == expected.count("R") // 2


def test_schedule_places_flats_darks_and_reference_groups():
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics

    kin = Kinematics(default_rig_config())
    plan = plan_from_dict(
        _doc(
            reference={"poses": REF, "every_poses": 2},
            flats={"count": 2, "when": "start"},
            darks={"count": 1, "when": "end"},
        )
    )
    sched = build_schedule(plan, kin, kin.config.park_rad)
    kinds = "".join(
        {"sample": "s", "reference": "R", "flat": "F", "dark": "D"}[s["kind"]] for s in sched.steps
    )
    n = kinds.count("s")
    assert n == 6
    assert kinds == "F" + "RR" + "ssRR" * 3 + "D"
    est = estimate_plan(plan)
    # 6 samples + 4 groups of 2 references, 2 frames each; 2 flats; darks at 2 + 1 times
    assert est.n_poses == 6 + 8
    assert est.n_frames == 14 * 2 + 2 + 1 * 3


# --------------------------------------------------------------------------------------
# The steps on fake devices


class Rig:
    def read(self):
        return RigState(joints={"a": 1.0})

    def move_to(self, wi, wo, *, joints=None):
        z = np.asarray(wi, float)
        return MoveResult(z, np.asarray(wo, float), z, np.asarray(wo, float), {}, 0, 0, 1.0)

    def stop(self):
        pass

    def park(self):
        return {}

    def torque_off(self):
        return []


class Clock:
    """Rig time: one second more at each read."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        self.t += 1.0
        return self.t


class Camera:
    def __init__(self, clock, events):
        self.clock, self.events = clock, events

    def describe(self):
        raise NotImplementedError

    def capture(self, exposure_time, iso, f_number):
        self.events.append(("shot", exposure_time, iso, self.clock.t))
        return Shot(f"{len(self.events)}".encode(), ".dng", exposure_time, float(iso or "nan"), 8)

    def close(self):
        pass


class Switches:
    """A light switch and a target changer that record what they are told."""

    def __init__(self, events):
        self.events = events

    def set_light(self, on):
        self.events.append(("light", on))

    def set_target(self, kind):
        self.events.append(("target", kind))


def _run(tmp_path, plan, steps, *, target=True, light=True):
    (tmp_path / "raw").mkdir(exist_ok=True)
    events, docs, clock = [], [], Clock()
    sw = Switches(events)
    dev = SessionDevices(
        Rig(),
        Camera(clock, events),
        light=sw if light else None,
        target=sw if target else None,
        clock=clock,
    )
    engine = Engine(dev, tmp_path, [docs.append])
    engine.execute(session_plan(steps, plan, PlanState(), lambda j: ((0, 0, 1), (0, 0, 1)), 2.0))
    return events, [d for d in docs if d["type"] == "shot"]


SAMPLE = {"kind": "sample", "wi": [0.0, 0.0, 1.0], "wo": [0.5, 0.0, 0.866], "joints": None}


def test_flat_step_swaps_the_panel_in_shoots_and_puts_the_sample_back(tmp_path):
    plan = plan_from_dict(
        _doc(flats={"count": 3, "exposure_s": 0.02, "iso": 200}, darks={"count": 2})
    )
    steps = [{"kind": "flat", "wi": None, "wo": None}, dict(SAMPLE), {"kind": "dark"}]
    events, shots = _run(tmp_path, plan, steps)
    targets = [e for e in events if e[0] == "target"]
    assert targets == [("target", "flat"), ("target", "sample")]
    flat_i = events.index(("target", "flat"))
    back_i = events.index(("target", "sample"))
    flats = [e for e in events[flat_i:back_i] if e[0] == "shot"]
    assert [(e[1], e[2]) for e in flats] == [(0.02, 200)] * 3
    recs = [r for r in shots if r["kind"] == "flat"]
    assert len(recs) == 3 and {r["file"].split("_")[-1] for r in recs} == {"flat.dng"}
    assert all(r["exposure_time_requested"] == 0.02 for r in recs)
    # darks at every bracket exposure (ISO of the bracket) and at the flats' (their ISO)
    darks = [(r["exposure_time_requested"], r["iso"]) for r in shots if r["kind"] == "dark"]
    assert sorted(darks) == sorted(
        [(0.002, 100.0)] * 2 + [(0.008, 100.0)] * 2 + [(0.02, 200.0)] * 2,
    )


def test_every_shot_record_carries_the_rig_time_read_before_it(tmp_path):
    plan = plan_from_dict(_doc(darks={"count": 1}))
    events, shots = _run(tmp_path, plan, [dict(SAMPLE), {"kind": "dark"}])
    stamps = [e[3] for e in events if e[0] == "shot"]
    assert [r["rig_time"] for r in shots] == stamps  # the clock's value when it was shot
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)


def test_no_clock_no_rig_time(tmp_path):
    (tmp_path / "raw").mkdir()
    docs = []
    events: list = []
    dev = SessionDevices(Rig(), Camera(Clock(), events))
    plan = plan_from_dict(_doc())
    Engine(dev, tmp_path, [docs.append]).execute(
        session_plan([dict(SAMPLE)], plan, PlanState(), lambda j: ((0, 0, 1), (0, 0, 1)), 2.0)
    )
    shots = [d for d in docs if d["type"] == "shot"]
    assert shots and all("rig_time" not in r for r in shots)


def test_flats_without_a_target_changer_are_a_camera_error_not_a_silent_sample(tmp_path):
    plan = plan_from_dict(_doc(flats={"count": 1}))
    with pytest.raises(CameraError, match=r"\[flats\] count"):
        _run(tmp_path, plan, [{"kind": "flat", "wi": None, "wo": None}], target=False)


@pytest.mark.parametrize(
    ("tables", "light", "target", "words"),
    [
        (
            {"darks": {"count": 2}},
            False,
            True,
            ["[darks] count = 2", "--light relay:PORT", "--light operator"],
        ),
        ({"flats": {"count": 4}}, True, False, ["[flats] count = 4", "target changer"]),
    ],
)
def test_calibration_frames_without_their_device_are_refused(tables, light, target, words):
    plan = plan_from_dict(_doc(**tables))
    with pytest.raises(SessionError) as info:
        check_calibration_devices(plan, light, target)
    for w in words:
        assert w in str(info.value)
    check_calibration_devices(plan, True, True)  # with both: nothing to refuse


def test_a_flat_step_cut_short_continues_on_resume(tmp_path):
    (tmp_path / "raw").mkdir()
    plan = plan_from_dict(_doc(flats={"count": 3}))
    steps = [{"kind": "flat", "wi": None, "wo": None}, dict(SAMPLE)]
    events, docs, clock = [], [], Clock()
    sw = Switches(events)
    dev = SessionDevices(Rig(), Camera(clock, events), light=sw, target=sw, clock=clock)
    first = {"type": "shot", "pose": 0, "frame": 0, "kind": "flat", "exposure_time_requested": 0.01}
    state = PlanState(done={1}, shots={0: [first]})
    Engine(dev, tmp_path, [docs.append]).execute(
        session_plan(steps, plan, state, lambda j: ((0, 0, 1), (0, 0, 1)), 2.0)
    )
    shots = [d for d in docs if d["type"] == "shot"]
    assert [(r["pose"], r["frame"], r["kind"]) for r in shots] == [(0, 1, "flat"), (0, 2, "flat")]
    assert [e for e in events if e[0] == "target"] == [("target", "flat"), ("target", "sample")]
    assert [d["pose"] for d in docs if d["type"] == "pose_done"] == [0]
