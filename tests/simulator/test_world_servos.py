"""Virtual servos as built: landing error within its bound, reproducible, reported by the
encoder; the true direction of the last move, kept through a reboot; the rig's
1-pulse position check still passes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.rig.config import default_rig_config, rig_config_from_dict
from gonio.rig.device import Rig
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.servo_model import VirtualServo
from gonio.simulator.virtual_bus import ServoBus

HOME = {1: 1536, 2: 2048, 3: 2048, 4: 0}


def _servo(**kw) -> VirtualServo:
    bus = ServoBus([VirtualServo(7, position=1000, **kw)], time_scale="virtual")
    s = bus.servos[7]
    s.write(64, bytes([1]))  # torque on
    return s


def _goto(s: VirtualServo, goal: int) -> int:
    s.write(116, int(goal).to_bytes(4, "little", signed=True))
    end = s.motion_end()
    if end is not None:
        s.clock = lambda: end + 1.0  # let the move finish
    return s.get("present_position")


@pytest.mark.parametrize("n", [1, 3])
def test_landing_error_never_exceeds_its_bound_and_is_used(n):
    s = _servo(landing_pulses=n, landing_seed=4)
    errors = []
    rng = np.random.default_rng(0)
    for goal in rng.integers(100, 4000, 200):
        errors.append(_goto(s, int(goal)) - int(goal))
    errors = np.array(errors)
    assert np.abs(errors).max() <= n
    assert set(errors.tolist()) == set(range(-n, n + 1))  # every value drawn, not a constant


def test_landing_is_reproducible_and_perfect_is_exact():
    goals = [1500, 200, 3000, 2999, 10]
    a = [_goto(s := _servo(landing_pulses=2, landing_seed=9), g) for g in goals]
    b = [_goto(t := _servo(landing_pulses=2, landing_seed=9), g) for g in goals]
    c = [_goto(u := _servo(landing_pulses=2, landing_seed=10), g) for g in goals]
    exact = [_goto(v := _servo(), g) for g in goals]
    assert a == b
    assert a != c
    assert exact == goals
    del s, t, u, v


def test_a_goal_within_the_band_does_not_move():
    s = _servo(landing_pulses=2, landing_seed=1)
    p = _goto(s, 1800)
    assert _goto(s, p + 1) == p  # inside the deadband: stays


def test_last_direction_is_the_motion_and_survives_reboot():
    s = _servo(last_direction=-1)
    assert s.last_direction == -1  # before any move: the world's initial side
    _goto(s, 1500)
    assert s.last_direction == 1
    _goto(s, 1200)
    assert s.last_direction == -1
    s.reboot()
    assert s.last_direction == -1
    assert s.true_state() == (1200, -1)


def _fast_config():
    d = default_rig_config().model_dump()
    for sv in d["servos"]:
        sv["velocity_deg_s"] = 0.0
        sv["acceleration_deg_s2"] = 0.0
    d["motion"]["poll_interval_s"] = 0.001
    return rig_config_from_dict(d)


def test_rig_moves_with_landing_error_pass_the_one_pulse_check():
    cfg = _fast_config()
    assert cfg.motion.position_tolerance_pulses == 1
    servos = [
        VirtualServo(i, position=p, landing_pulses=1, landing_seed=3) for i, p in HOME.items()
    ]
    bus = ServoBus(servos, time_scale="virtual")
    rng = np.random.default_rng(2)
    landed = []
    with Rig(cfg, transport=LoopbackTransport(bus)) as rig:
        for _ in range(15):
            target = {
                "light_azimuth": math.radians(rng.uniform(-80, -30)),
                "camera_azimuth": math.radians(rng.uniform(10, 60)),
                "stage_tilt": math.radians(rng.uniform(-30, 30)),
                "stage_spin": math.radians(rng.uniform(-90, 90)),
            }
            rig.move_joints(target)
            states = bus.servo_states()
            for s in cfg.servos:
                goal = round(s.pulses(target[s.joint]))
                landed.append(states[s.id][0] - goal)
    assert max(abs(e) for e in landed) <= 1
    assert any(e != 0 for e in landed)


def test_a_one_pulse_move_keeps_the_joint_on_its_side_of_the_backlash():
    """The controller counts a change within its 1-pulse tolerance as no move (the
    servo's deadband); a perfect servo (no landing band) moves that pulse but cannot
    carry the joint across a quarter-degree backlash, so its side stays."""
    s = _servo(last_direction=-1)
    assert _goto(s, 1001) == 1001 and s.last_direction == -1  # moved, side kept
    assert _goto(s, 1010) == 1010 and s.last_direction == 1  # a real move takes it up
    assert _goto(s, 1009) == 1009 and s.last_direction == 1
