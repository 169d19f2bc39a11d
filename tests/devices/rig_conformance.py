"""The :class:`gonio.devices.RigDevice` contract, as one test mixin for every rig backend.

A backend's test class (``tests/devices/test_rig_backends.py``) inherits
:class:`RigConformance` and provides two fixtures:

``servo_bus``
    The :class:`gonio.simulator.virtual_bus.ServoBus` behind the rig, its four servos at
    the preset's home pose (:data:`HOME_PULSES`): the tests read its encoders, silence a
    servo or inject a hardware error there, never through the rig.
``rig``
    A :class:`gonio.rig.device.Rig` of :func:`fast_rig_config`, opened on that bus.

Expectations come from outside the code under test: encoder counts of the virtual
servos turned into joint angles with the configuration's own formula, closed forms
(the home pose's pulses, joint angles from pulses), and the requested directions.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from gonio.devices import MoveResult, RigDevice, RigState
from gonio.errors import BusError, PoseRefused, RefusalReason, RigFault
from gonio.radiometry import spherical_to_direction
from gonio.rig.bus import BusTransport
from gonio.rig.config import JOINT_NAMES, RigConfig, default_rig_config, rig_config_from_dict

#: Present Position (pulses) of each servo of the default preset at its home pose:
#: light -45 deg -> 2048 - 512, camera and tilt 0 deg -> 2048 (zero at 180 deg), spin 0.
HOME_PULSES = {1: 1536, 2: 2048, 3: 2048, 4: 0}
#: One pulse of an XM430 (rad).
PULSE = 2 * math.pi / 4096
#: Ambient temperature of an idle virtual servo (degC).
AMBIENT_C = 30.0


def fast_rig_config() -> RigConfig:
    """The default preset with unlimited motion profiles and 1 ms polling."""
    d = default_rig_config().model_dump()
    for s in d["servos"]:
        s["velocity_deg_s"] = 0.0
        s["acceleration_deg_s2"] = 0.0
    d["motion"]["poll_interval_s"] = 0.001
    d["motion"]["move_timeout_s"] = 10.0
    return rig_config_from_dict(d)


def _angle(a, b) -> float:
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


class RigConformance:
    """Tests every rig backend must pass (fixtures ``rig`` and ``servo_bus``)."""

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def encoders(servo_bus) -> dict[int, int]:
        return {i: s.get("present_position") for i, s in servo_bus.servos.items()}

    @staticmethod
    def encoder_joints(rig, servo_bus) -> dict[str, float]:
        """Joint angles (rad) from the virtual servos' encoders, with the config's formula."""
        pulses = {i: s.get("present_position") for i, s in servo_bus.servos.items()}
        return {s.joint: s.joint_rad(pulses[s.id]) for s in rig.config.servos}

    @staticmethod
    def torque_enables_since(servo_bus, marks: dict[int, int]) -> list[tuple[int, int]]:
        return [
            (i, v) for i, s in servo_bus.servos.items() for _, v in s.torque_log[marks[i] :] if v
        ]

    # ------------------------------------------------------------------ interfaces
    def test_is_a_rig_device_on_a_bus_transport(self, rig):
        assert isinstance(rig, RigDevice)
        assert isinstance(rig.transport, BusTransport)

    # ------------------------------------------------------------------ read
    def test_read_reports_joints_temperatures_errors_in_si_units(self, rig, servo_bus):
        st = rig.read()
        assert isinstance(st, RigState)
        assert list(st.joints) == list(JOINT_NAMES)
        assert set(st.temperatures) == set(st.errors) == set(JOINT_NAMES)
        assert all(type(v) is float for v in st.joints.values())
        # closed form of the home pulses: (1536 - 2048) * 360 / 4096 = -45 deg, others 0
        assert st.joints["light_azimuth"] == pytest.approx(math.radians(-45.0), abs=1e-12)
        for j in ("camera_azimuth", "stage_tilt", "stage_spin"):
            assert st.joints[j] == pytest.approx(0.0, abs=1e-12)
        assert st.temperatures == {j: AMBIENT_C for j in JOINT_NAMES}
        assert st.errors == {j: 0 for j in JOINT_NAMES} and st.moving is False
        servo_bus.servos[2].inject_fault(0x04)  # overheating: reported, not raised
        assert rig.read().errors == dict.fromkeys(JOINT_NAMES, 0) | {"camera_azimuth": 0x04}

    # ------------------------------------------------------------------ move_to
    def test_move_to_reaches_the_requested_directions(self, rig, servo_bus):
        rng = np.random.default_rng(17)
        n = 0
        while n < 6:
            wi = spherical_to_direction(rng.uniform(0, 1.3), rng.uniform(-math.pi, math.pi))
            wo = spherical_to_direction(rng.uniform(0, 1.3), rng.uniform(-math.pi, math.pi))
            if _angle(wi, wo) < math.radians(20):
                continue  # would be refused for shadowing: tested below
            res = rig.move_to(wi, wo)
            assert isinstance(res, MoveResult)
            ai, ao = rig.kinematics.forward(self.encoder_joints(rig, servo_bus))
            # what the encoders show is what was asked, to the servos' resolution
            assert max(_angle(ai, wi), _angle(ao, wo)) < PULSE
            assert res.error_i == pytest.approx(_angle(ai, wi), abs=1e-12)
            assert res.error_o == pytest.approx(_angle(ao, wo), abs=1e-12)
            np.testing.assert_allclose(res.wi_achieved, ai, atol=1e-12)
            assert res.joints == pytest.approx(self.encoder_joints(rig, servo_bus), abs=1e-12)
            assert res.duration >= 0.0
            n += 1

    def test_move_to_with_the_home_joints_lands_on_the_home_pulses(self, rig, servo_bus):
        wi, wo = spherical_to_direction(0.6, 0.3), spherical_to_direction(0.5, 2.9)
        rig.move_to(wi, wo)
        assert self.encoders(servo_bus) != HOME_PULSES
        home = rig.config.home_rad
        hi, ho = rig.kinematics.forward(home)
        rig.move_to(hi, ho, joints=home)
        assert self.encoders(servo_bus) == HOME_PULSES

    def test_joints_hint_is_used_instead_of_solving_anew(self, rig, servo_bus):
        # The spin servo turns +-200 deg: spin 175 deg and -185 deg give the same
        # directions.  Solving picks the shorter move (175 deg); the hint says -185.
        q = {
            "light_azimuth": math.radians(-30),
            "camera_azimuth": math.radians(20),
            "stage_tilt": math.radians(10),
            "stage_spin": math.radians(175),
        }
        wi, wo = rig.kinematics.forward(q)
        hint = dict(q, stage_spin=math.radians(-185))
        rig.move_to(wi, wo, joints=hint)
        # spin servo: zero at 0 deg, 4096 pulses a turn: -185 deg -> -2104.9 pulses
        assert abs(self.encoders(servo_bus)[4] - (-185 * 4096 / 360)) < 1.0
        rig.move_to(*rig.kinematics.forward(rig.config.home_rad))
        rig.move_to(wi, wo)
        assert abs(self.encoders(servo_bus)[4] - 175 * 4096 / 360) < 1.0

    # ------------------------------------------------------------------ refusals
    @pytest.mark.parametrize(
        "case, reason",
        [
            ("parallel", RefusalReason.NO_SOLUTION),
            ("nan", RefusalReason.INVALID_DIRECTION),
            ("rim", RefusalReason.BEYOND_RIM),
            ("hint_limit", RefusalReason.JOINT_LIMIT),
            ("hint_shadow", RefusalReason.SHADOWING),
            ("hint_path", RefusalReason.PATH),
        ],
    )
    def test_refused_poses_raise_pose_refused_and_nothing_moves(self, rig, servo_bus, case, reason):
        home = rig.config.home_rad
        hints = {
            "hint_limit": dict(home, stage_spin=math.radians(210)),  # beyond +-200 deg
            "hint_shadow": dict(home, light_azimuth=math.radians(-3)),  # 3 deg from camera
            "hint_path": dict(home, light_azimuth=math.radians(45)),  # swings past camera
        }
        if case in hints:
            joints = hints[case]
            wi, wo = rig.kinematics.forward(joints)
        else:
            joints = None
            wi = {
                "parallel": spherical_to_direction(0.4, 1.0),
                "nan": np.array([np.nan, 0.0, 1.0]),
                "rim": spherical_to_direction(math.radians(88), 0.0),
            }[case]
            wo = spherical_to_direction(0.4, 1.0)
        before = self.encoders(servo_bus)
        goals = {i: s.get("goal_position") for i, s in servo_bus.servos.items()}
        marks = {i: len(s.torque_log) for i, s in servo_bus.servos.items()}
        with pytest.raises(PoseRefused) as info:
            rig.move_to(wi, wo, joints=joints)
        assert info.value.reason is reason
        assert self.encoders(servo_bus) == before
        assert {i: s.get("goal_position") for i, s in servo_bus.servos.items()} == goals
        assert self.torque_enables_since(servo_bus, marks) == []

    # ------------------------------------------------------------------ faults
    def test_silent_servo_raises_bus_error_not_pose_refused(self, rig, servo_bus):
        servo_bus.servos[2].silent = True
        try:
            with pytest.raises(BusError) as info:
                rig.read()
            assert info.value.servo == 2 and info.value.cause == "timeout"
            with pytest.raises(BusError) as info:
                rig.move_to(spherical_to_direction(0.3, 0.0), spherical_to_direction(0.5, 2.0))
            assert not isinstance(info.value, PoseRefused)
            assert info.value.servo == 2
        finally:
            servo_bus.servos[2].silent = False

    def test_hardware_error_raises_rig_fault_with_servo_and_bits_torque_off(self, rig, servo_bus):
        rig.move_to(spherical_to_direction(0.3, 0.0), spherical_to_direction(0.5, 2.0))
        assert servo_bus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
        servo_bus.servos[3].inject_fault(0x20)  # overload
        with pytest.raises(RigFault) as info:
            rig.move_to(spherical_to_direction(0.5, 1.0), spherical_to_direction(0.3, -2.0))
        assert (info.value.servo, info.value.error_bits) == (3, 0x20)
        assert "overload" in str(info.value)
        assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}

    def test_hardware_error_mid_move_stops_part_way(self, rig, servo_bus):
        rig.home()  # torque on: the next goal starts the move (not a zero-length hold)
        rig.servos["stage_spin"].write("profile_velocity", 2)  # slow: 2.75 deg/s
        servo_bus.servos[4].inject_fault(0x20, during_next_move=0.5)
        target = dict(rig.config.home_rad, stage_spin=math.radians(180))
        with pytest.raises(RigFault) as info:
            rig.move_to(*rig.kinematics.forward(target), joints=target)
        assert (info.value.servo, info.value.error_bits) == (4, 0x20)
        assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
        # tripped half way in servo time: 90 deg of 180 -> 1024 of 2048 pulses
        got = self.encoders(servo_bus)[4]
        assert abs(got - 1024) <= 2, got

    def test_torque_off_returns_the_ids_that_did_not_confirm(self, rig, servo_bus):
        rig.home()
        assert servo_bus.torque() == {1: 1, 2: 1, 3: 1, 4: 1}
        assert rig.torque_off() == []
        assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
        servo_bus.servos[3].silent = True
        try:
            assert rig.torque_off() == [3]
        finally:
            servo_bus.servos[3].silent = False

    def test_park_moves_home_and_cuts_torque(self, rig, servo_bus):
        rig.move_to(spherical_to_direction(0.3, 0.0), spherical_to_direction(0.5, 2.0))
        joints = rig.park()  # the preset parks at home
        assert self.encoders(servo_bus) == HOME_PULSES
        assert joints == pytest.approx(rig.config.home_rad, abs=1e-12)
        assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}

    def test_stop_ends_a_move_in_progress(self, rig, servo_bus):
        rig.servos["stage_spin"].write("profile_velocity", 1)  # 1.37 deg/s servo time
        target = dict(rig.config.home_rad, stage_spin=math.radians(190))
        goal = 190 * 4096 / 360
        outcome: list[BaseException | None] = []

        def move():
            try:
                rig.move_to(*rig.kinematics.forward(target), joints=target)
                outcome.append(None)
            except BaseException as exc:  # handed to the test thread
                outcome.append(exc)

        mover = threading.Thread(target=move)
        mover.start()
        under_way = threading.Event()
        for _ in range(5000):  # wait (with a deadline) until the spin servo is moving
            if servo_bus.servos[4].get("present_position") > 20 or outcome:
                under_way.set()
                break
            under_way.wait(0.001)
        rig.stop()
        mover.join(timeout=30)
        assert under_way.is_set() and not mover.is_alive()
        assert len(outcome) == 1 and isinstance(outcome[0], RigFault), outcome
        assert "stopped" in str(outcome[0])
        assert servo_bus.torque() == {1: 0, 2: 0, 3: 0, 4: 0}
        assert 20 < self.encoders(servo_bus)[4] < goal - 1
