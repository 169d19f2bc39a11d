"""The operator as the real rig's target changer (the calibration mirror put in by hand)."""

from __future__ import annotations

import pytest

from gonio.app.operator import OperatorTargetChanger
from gonio.capture.engine import SessionDevices, finalize
from gonio.errors import SessionError


def test_asks_once_per_change_and_waits_for_the_answer():
    prompts = []
    ch = OperatorTargetChanger(lambda p: prompts.append(p) or "", interactive=True)
    ch.set_target("sample")  # already there: nobody is asked
    ch.set_target("mirror")
    ch.set_target("mirror")
    ch.set_target("sample")
    assert ch.asked == ["mirror", "sample"]
    assert len(prompts) == 2 and "MIRROR" in prompts[0] and "SAMPLE" in prompts[1]


def test_refuses_without_a_terminal_and_stops_on_end_of_input():
    with pytest.raises(SessionError, match="not a terminal"):
        OperatorTargetChanger(interactive=False)

    def eof(_prompt):
        raise EOFError

    ch = OperatorTargetChanger(eof, interactive=True)
    with pytest.raises(SessionError, match="waiting for the operator"):
        ch.set_target("mirror")
    assert ch.current == "sample"
    with pytest.raises(SessionError, match="target must be one of"):
        ch.set_target("lens cap")


class _Rig:
    def __init__(self, log):
        self.log = log

    def park(self):
        self.log.append("park")

    def torque_off(self):
        self.log.append("torque_off")
        return []


def test_the_finalizer_makes_the_rig_safe_before_asking_the_operator():
    log: list[str] = []
    ch = OperatorTargetChanger(lambda p: log.append("asked") or "", interactive=True)
    ch.current = "mirror"
    out = finalize(SessionDevices(_Rig(log), camera=None, target=ch))
    assert log == ["park", "torque_off", "asked"]
    assert out["parked"] and out["torque_off"] and ch.current == "sample"
