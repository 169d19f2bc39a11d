"""Fixtures for the rig tests: virtual servos in-process (loopback) or behind a pty served
by a thread (for the dynamixel-sdk), and a fast rig configuration."""

from __future__ import annotations

import math
import sys

import pytest

from gonio.rig.config import default_rig_config, rig_config_from_dict
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.virtual_bus import ServoBus, VirtualBus

#: Present Position (pulses) of each servo of the default preset at its home pose.
HOME_PULSES = {1: 1536, 2: 2048, 3: 2048, 4: 0}
SERVO_RESOLUTION = math.radians(0.088)


@pytest.fixture
def gil_handover():
    """The emulator thread and the SDK's busy-polling client share the GIL: hand it over
    every 0.2 ms instead of 5 ms so replies are not delayed by the interpreter."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(2e-4)
    yield
    sys.setswitchinterval(old)


def _make_config(**bus_overrides):
    """The default preset with unlimited profiles (fast moves) and quick polling."""
    d = default_rig_config().model_dump()
    for s in d["servos"]:
        s["velocity_deg_s"] = 0.0
        s["acceleration_deg_s2"] = 0.0
    d["motion"]["poll_interval_s"] = 0.001
    d["motion"]["move_timeout_s"] = 10.0
    d["bus"].update(bus_overrides)
    return rig_config_from_dict(d)


@pytest.fixture
def make_config():
    """Factory: the fast preset with ``bus`` fields overridden."""
    return _make_config


@pytest.fixture
def fast_config():
    return _make_config()


@pytest.fixture
def home_pulses():
    return dict(HOME_PULSES)


@pytest.fixture
def vbus(gil_handover):
    """Four XM430-W350 at the preset's home pose, servo time 200x faster than real."""
    with VirtualBus([1, 2, 3, 4], time_scale=200.0, seed=0) as bus:
        for i, p in HOME_PULSES.items():
            bus.servos[i].set_position(p)
        yield bus


@pytest.fixture
def servo_bus():
    """Four XM430-W350 at the preset's home pose, in-process, servo time 200x real."""
    bus = ServoBus([1, 2, 3, 4], time_scale=200.0, seed=0)
    for i, p in HOME_PULSES.items():
        bus.servos[i].set_position(p)
    return bus


@pytest.fixture
def loopback(servo_bus):
    """A transport straight into ``servo_bus`` (no pty, no thread)."""
    return LoopbackTransport(servo_bus)
