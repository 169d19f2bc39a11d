"""The rig device contract (tests/devices/rig_conformance.py) on every rig backend.

* :class:`TestRigOverSdkOnPty`: the real :class:`~gonio.rig.device.Rig` with its default
  transport (dynamixel-sdk and pyserial) on the virtual bus's pseudo-terminal;
* :class:`TestRigOverLoopback`: the same ``Rig`` given the in-process
  :class:`~gonio.simulator.loopback.LoopbackTransport` (no pty, no thread).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from gonio.rig.device import Rig
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.virtual_bus import ServoBus, VirtualBus


def _load_mixin():
    # the tests are not a package (pytest's importlib mode): load the mixin by path
    path = Path(__file__).with_name("rig_conformance.py")
    spec = importlib.util.spec_from_file_location("gonio_tests_rig_conformance", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_mixin = _load_mixin()
RigConformance = _mixin.RigConformance
HOME_PULSES = _mixin.HOME_PULSES
fast_rig_config = _mixin.fast_rig_config

#: Servo time runs this many times faster than the wall clock.
TIME_SCALE = 200.0


class TestRigOverSdkOnPty(RigConformance):
    @pytest.fixture
    def servo_bus(self):
        # the emulator thread shares the GIL with the SDK's busy-polling client: hand it
        # over every 0.2 ms instead of 5 ms so replies are not held up by the interpreter
        old = sys.getswitchinterval()
        sys.setswitchinterval(2e-4)
        try:
            with VirtualBus([1, 2, 3, 4], time_scale=TIME_SCALE, seed=0) as bus:
                for i, p in HOME_PULSES.items():
                    bus.servos[i].set_position(p)
                yield bus
        finally:
            sys.setswitchinterval(old)

    @pytest.fixture
    def rig(self, servo_bus):
        with Rig(fast_rig_config(), port=servo_bus.port) as rig:
            yield rig


class TestRigOverLoopback(RigConformance):
    @pytest.fixture
    def servo_bus(self):
        bus = ServoBus([1, 2, 3, 4], time_scale=TIME_SCALE, seed=0)
        for i, p in HOME_PULSES.items():
            bus.servos[i].set_position(p)
        return bus

    @pytest.fixture
    def rig(self, servo_bus):
        with Rig(fast_rig_config(), transport=LoopbackTransport(servo_bus)) as rig:
            yield rig
