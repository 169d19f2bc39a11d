"""The rig device: accuracy, faults, signals, bad input.

Most tests run the rig over the in-process loopback transport (the real packets, no pty,
no thread); the SDK-specific ones (signals in a child process, port and baud errors, a
thousand moves through a lossy pty) use the virtual bus on a pty.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest

from gonio.errors import BusError, ConfigError, PoseRefused, RefusalReason, RigError, RigFault
from gonio.radiometry import spherical_to_direction
from gonio.rig.config import default_rig_config, rig_config_from_dict
from gonio.rig.device import Rig
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.servo_model import VirtualServo
from gonio.simulator.virtual_bus import ServoBus, VirtualBus

RESOLUTION = math.radians(0.088)  # one pulse of an XM430


def random_pairs(rng, n):
    for _ in range(n):
        yield (
            spherical_to_direction(
                rng.uniform(0, math.radians(80)), rng.uniform(-math.pi, math.pi)
            ),
            spherical_to_direction(
                rng.uniform(0, math.radians(80)), rng.uniform(-math.pi, math.pi)
            ),
        )


def angle(a, b):
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


def test_moves_reach_requested_directions_within_servo_resolution(servo_bus, fast_config):
    vbus = servo_bus
    rng = np.random.default_rng(5)
    worst, n = 0.0, 0
    with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:
        for wi, wo in random_pairs(rng, 60):
            try:
                res = rig.move_to(wi, wo)
            except PoseRefused as exc:
                assert "apart" in str(exc)  # camera-shadow refusals only
                assert exc.reason is RefusalReason.SHADOWING
                continue
            # independent of the controller's own bookkeeping: the emulator's positions
            pulses = {i: vbus.servos[i].get("present_position") for i in (1, 2, 3, 4)}
            joints = {s.joint: s.joint_rad(pulses[s.id]) for s in fast_config.servos}
            ai, ao = rig.kinematics.forward(joints)
            worst = max(worst, angle(ai, wi), angle(ao, wo))
            assert res.error_i == pytest.approx(angle(ai, wi), abs=1e-12)
            n += 1
    assert n > 50
    assert worst < RESOLUTION
    assert all(v == 0 for v in vbus.torque().values())  # context exit cut torque


def test_moves_over_a_lossy_bus_are_retried_and_still_exact(fast_config, home_pulses):
    bus = ServoBus([1, 2, 3, 4], time_scale=200.0, fault_rate=0.05, seed=2)
    for i, p in home_pulses.items():
        bus.servos[i].set_position(p)
    rng = np.random.default_rng(3)
    done = 0
    with Rig(fast_config, transport=LoopbackTransport(bus, retries=6)) as rig:
        while done < 60:
            wi, wo = next(random_pairs(rng, 1))
            if rig.kinematics.check(wi, wo, rig.joints()) is not None:
                continue
            rig.move_to(wi, wo)
            # the encoders, not the rig's bookkeeping
            pulses = {i: s.get("present_position") for i, s in bus.servos.items()}
            ai, ao = rig.kinematics.forward(
                {s.joint: s.joint_rad(pulses[s.id]) for s in fast_config.servos}
            )
            assert max(angle(ai, wi), angle(ao, wo)) < RESOLUTION
            done += 1
        retries = rig.transport.counters["retries"]
    assert bus.stats.corrupted + bus.stats.dropped > 20 and retries > 20


@pytest.mark.slow
def test_thousand_moves_with_one_percent_bad_replies(
    gil_handover, make_config, home_pulses, caplog
):
    cfg = make_config(timeout_ms=15.0, retries=5)
    rng = np.random.default_rng(11)
    with VirtualBus([1, 2, 3, 4], time_scale=1000.0, fault_rate=0.01, seed=7) as bus:
        for i, p in home_pulses.items():
            bus.servos[i].set_position(p)
        caplog.set_level(logging.INFO, logger="gonio.rig.bus")
        done, worst = 0, 0.0
        with Rig(cfg, port=bus.port) as rig:
            while done < 1000:
                wi, wo = next(random_pairs(rng, 1))
                if rig.kinematics.check(wi, wo, rig.joints()) is not None:
                    continue
                res = rig.move_to(wi, wo)
                worst = max(worst, res.error_i, res.error_o)
                done += 1
        counters = dict(rig.transport.counters)  # after exit: the torque-off writes count too
        faults = bus.stats.corrupted + bus.stats.dropped
    retry_lines = [r for r in caplog.records if r.getMessage().startswith("retry ")]
    assert done == 1000 and worst < RESOLUTION
    assert faults > 50  # the faults really happened
    assert counters["retries"] == len(retry_lines) > 0  # every retry is in the log
    assert counters["retries"] >= faults * 0.5  # a fault costs at least one retry (or several)


def test_overload_mid_move_raises_fault_and_cuts_all_torque(servo_bus, fast_config):
    vbus = servo_bus
    d = fast_config.model_dump()
    d["servos"][2]["velocity_deg_s"] = 30.0  # tilt moves slowly enough to be caught
    cfg = rig_config_from_dict(d)
    with Rig(cfg, transport=LoopbackTransport(vbus)) as rig:
        rig.home()
        vbus.servos[3].inject_fault(0x20, during_next_move=0.5)
        target = dict(cfg.home_rad, stage_tilt=math.radians(40))
        with pytest.raises(RigFault) as info:
            rig.move_joints(target)
        msg = str(info.value)
        assert "servo 3" in msg and "stage_tilt" in msg and "0x20" in msg and "overload" in msg
        assert info.value.servo == 3 and info.value.error_bits == 0x20
        assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
        # stopped part way (not at the goal)
        tilt = vbus.servos[3].get("present_position")
        assert 2048 < tilt < 2048 + 455
        # torque cannot come back until REBOOT
        with pytest.raises(RigFault):
            rig.move_joints(cfg.home_rad)
        assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}


_MOVER = textwrap.dedent(
    """
    import math, sys
    from gonio.rig.config import default_rig_config, rig_config_from_dict
    from gonio.rig.device import Rig
    d = default_rig_config().model_dump()
    for s in d["servos"]:
        s["velocity_deg_s"] = 10.0
    cfg = rig_config_from_dict(d)
    with Rig(cfg, port=sys.argv[1]) as rig:
        target = dict(
            cfg.home_rad, light_azimuth=math.radians(-80), camera_azimuth=math.radians(70)
        )
        rig.move_joints(target)
    print("FINISHED")
    """
)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_move_leaves_torque_off(gil_handover, home_pulses, tmp_path, sig):
    script = tmp_path / "mover.py"
    script.write_text(_MOVER)
    with VirtualBus([1, 2, 3, 4], time_scale=1.0) as bus:
        for i, p in home_pulses.items():
            bus.servos[i].set_position(p)
        proc = subprocess.Popen(
            [sys.executable, str(script), bus.port],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            moving = threading.Event()
            for _ in range(3000):  # wait (with a deadline) until the move is under way
                if bus.servos[1].get("moving") and bus.servos[1].get("present_position") < 1516:
                    moving.set()
                    break
                if proc.poll() is not None:
                    break
                moving.wait(0.005)
            assert moving.is_set(), proc.communicate(timeout=5)
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert "FINISHED" not in out
        assert proc.returncode != 0
        assert "torque cut" in err or "cutting torque" in err or "KeyboardInterrupt" in err
        assert bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
        # it really stopped part way
        assert 1536 - 398 < bus.servos[1].get("present_position") < 1516


# ---------------------------------------------------------------------- bad input
def test_unknown_port(fast_config):
    with pytest.raises(RigError, match="/dev/does-not-exist"):
        Rig(fast_config, port="/dev/does-not-exist").open()


def test_wrong_baud_rate_before_anything_moves(vbus, fast_config):
    with pytest.raises(RigError, match="57600 baud"):
        Rig(fast_config, port=vbus.port, baud_rate=57600).open()
    assert all(not s.torque_log for s in vbus.servos.values())


def test_missing_servo_is_named(fast_config):
    bus = ServoBus([1, 2, 3])
    with pytest.raises(BusError, match=r"servo\(s\) 4 \(stage_spin\) did not answer") as info:
        Rig(fast_config, transport=LoopbackTransport(bus)).open()
    assert (info.value.servo, info.value.cause) == (4, "timeout")
    assert all(not s.torque_log for s in bus.servos.values())


def test_model_mismatch_is_named(fast_config):
    servos = [VirtualServo(1), VirtualServo(2, "XM430-W210"), VirtualServo(3), VirtualServo(4)]
    with pytest.raises(
        RigError, match=r"servo 2 \(camera_azimuth\) is XM430-W210 .*1030.*XM430-W350"
    ):
        Rig(fast_config, transport=LoopbackTransport(servos)).open()


def test_transport_and_port_are_exclusive(fast_config, loopback):
    with pytest.raises(RigError, match="either a transport or port"):
        Rig(fast_config, transport=loopback, port="/dev/ttyUSB0")


def test_duplicate_and_missing_ids_in_config():
    d = default_rig_config().model_dump()
    d["servos"][1]["id"] = 1
    with pytest.raises(ConfigError, match=r"duplicate servo ID\(s\) \[1\]"):
        rig_config_from_dict(d, "rig.toml")
    d = default_rig_config().model_dump()
    d["servos"] = d["servos"][:3]
    with pytest.raises(ConfigError, match="stage_spin"):
        rig_config_from_dict(d, "rig.toml")


def test_angles_outside_limits_refused_before_anything_moves(servo_bus, fast_config):
    vbus = servo_bus
    home = fast_config.home_rad
    with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:
        before = {i: s.get("goal_position") for i, s in vbus.servos.items()}
        with pytest.raises(PoseRefused, match=r"stage_tilt .*outside the limits") as info:
            rig.move_joints(dict(home, stage_tilt=math.radians(95)))
        assert info.value.reason is RefusalReason.JOINT_LIMIT
        with pytest.raises(PoseRefused, match="shadow") as info:
            rig.move_joints(dict(home, light_azimuth=math.radians(-3)))
        assert info.value.reason is RefusalReason.SHADOWING
        with pytest.raises(PoseRefused, match="refusing to move: the move would make") as info:
            rig.move_joints(dict(home, light_azimuth=math.radians(45)))  # passes the camera
        assert info.value.reason is RefusalReason.PATH
        with pytest.raises(PoseRefused, match="cannot reach") as info:
            rig.move_to(spherical_to_direction(0.3, 0.0), spherical_to_direction(0.3, 0.0))
        assert info.value.reason is RefusalReason.NO_SOLUTION
        assert {i: s.get("goal_position") for i, s in vbus.servos.items()} == before
        assert all(not any(v for _, v in s.torque_log) for s in vbus.servos.values())


def test_status_reports_si_units(servo_bus, fast_config):
    vbus = servo_bus
    vbus.servos[2].voltage_raw = 118
    with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:
        st = {s.dxl_id: s for s in rig.status().servos}
        assert st[2].voltage == pytest.approx(11.8)
        assert st[1].position == pytest.approx(math.radians(-45))
        assert st[3].temperature == pytest.approx(30.0)
        assert st[4].hardware_error == 0 and not st[4].torque


def test_torque_off_on_exception_inside_with_block(servo_bus, fast_config):
    vbus = servo_bus
    with pytest.raises(ZeroDivisionError):
        with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:
            rig.home()
            assert vbus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
            1 / 0  # noqa: B018
    assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}


def test_torque_off_on_exception_leaves_the_pty_in_place(vbus, fast_config):
    with pytest.raises(ZeroDivisionError):
        with Rig(fast_config, port=vbus.port):
            1 / 0  # noqa: B018
    assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
    assert os.path.exists(vbus.port)


def test_open_reboots_a_servo_left_in_fault_and_keeps_holding_ones(servo_bus, fast_config):
    vbus = servo_bus
    vbus.servos[2].inject_fault(0x04)  # overheating from an earlier session
    assert vbus.servos[2].get("hardware_error_status") == 0x04
    with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:
        assert vbus.servos[2].get("hardware_error_status") == 0
        rig.home()
        rig.hold_on_exit = True
    assert vbus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
    with Rig(fast_config, transport=LoopbackTransport(vbus)) as rig:  # does not drop the arms
        assert vbus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
        assert all(s.torque for s in rig.status().servos)
    assert vbus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}


def test_a_goal_rounded_past_a_limit_is_a_pulse_range_refusal(servo_bus, fast_config):
    # The spin limit, 200 deg, is 2275.56 pulses: a joint angle just inside it can round
    # up to 2276 (0.04 deg past the limit), and does when the directions asked for are
    # exactly those of 2276 pulses.
    lim = math.radians(200.0)
    with Rig(fast_config, transport=LoopbackTransport(servo_bus)) as rig:
        q = dict(fast_config.home_rad, stage_spin=lim - 1e-7)
        over = dict(q, stage_spin=rig.servos["stage_spin"].to_joint(2276))
        wi, wo = rig.kinematics.forward(over)  # exactly at the rounded-up pulse
        with pytest.raises(PoseRefused, match=r"stage_spin \(servo 4\): goal 2276 pulses") as e:
            rig.quantised_goals(wi, wo, q)
        assert e.value.reason is RefusalReason.PULSE_RANGE
