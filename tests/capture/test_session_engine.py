"""The engine alone, on fake devices: replies go back into the plan, device exceptions
are thrown into it, documents reach the subscribers in order, faults are journaled from
the exception's fields, and the finalizer always runs."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import xxhash

from gonio.capture.engine import Engine, SessionDevices, run_plan
from gonio.capture.messages import Checkpoint, Emit, Move, Read, SetLight, Settle, Shoot
from gonio.devices import MoveResult, RigState, Shot
from gonio.errors import BusError, PoseRefused, RefusalReason, RigFault


class FakeRig:
    def __init__(self, fail=None, unconfirmed=()):
        self.calls, self.fail, self.unconfirmed = [], fail, list(unconfirmed)

    def read(self):
        self.calls.append("read")
        return RigState(joints={"a": 1.0}, temperatures={"a": 30.0})

    def move_to(self, wi, wo, *, joints=None):
        self.calls.append(("move", tuple(wi), joints))
        if self.fail is not None:
            raise self.fail
        z = np.zeros(3)
        return MoveResult(np.asarray(wi), np.asarray(wo), z, z, dict(joints or {}), 0, 0, 0)

    def stop(self):
        pass

    def park(self):
        self.calls.append("park")
        return {}

    def torque_off(self):
        self.calls.append("torque_off")
        return self.unconfirmed


class FakeCamera:
    def __init__(self):
        self.named, self.light = [], True

    def describe(self):
        raise NotImplementedError

    def next_shot(self, step, frame):
        self.named.append((step, frame))

    def capture(self, exposure_time, iso, f_number):
        data = f"frame {self.named[-1]} at {exposure_time}".encode()
        return Shot(data, ".dng", exposure_time, float(iso or "nan"), 8.0)

    def close(self):
        pass

    def set_light(self, on):
        self.light = on

    def set_target(self, kind):
        pass


def test_replies_and_exceptions_go_back_into_the_plan(tmp_path):
    (tmp_path / "raw").mkdir()
    rig, cam = FakeRig(), FakeCamera()
    slept, docs, seen = [], [], []
    dev = SessionDevices(rig, cam, cam, cam, sleep=slept.append)
    engine = Engine(dev, tmp_path, [docs.append])

    def plan():
        state = yield Read()
        seen.append(state.joints)
        moved = yield Move(0, (0.0, 0.0, 1.0), (0.5, 0.0, 0.8), {"a": 2.0})
        seen.append(moved.joints)
        yield Settle(0.25)
        cap = yield Shoot(0, 1, 0.01, 100.0, None, "raw/p0000_f01_sample")
        seen.append(cap)
        rig.fail = PoseRefused(RefusalReason.SHADOWING, "the camera would shadow the light")
        try:
            yield Move(1, (0.0, 0.0, 1.0), (0.0, 0.0, 1.0))
        except PoseRefused as exc:
            seen.append(exc.reason)
        doc = yield Checkpoint({"type": "pose_done", "pose": 0})
        seen.append(doc)

    engine.execute(plan())
    assert seen[0] == {"a": 1.0} and seen[1] == {"a": 2.0}
    assert rig.calls[1] == ("move", (0.0, 0.0, 1.0), {"a": 2.0})
    assert slept == [0.25]
    cap = seen[2]
    data = (tmp_path / "raw" / "p0000_f01_sample.dng").read_bytes()
    assert cap.file == "raw/p0000_f01_sample.dng" and data == cap.shot.data
    assert cap.sha256 == hashlib.sha256(data).hexdigest()
    assert cap.xxh3_128 == xxhash.xxh3_128_hexdigest(data) and cap.bytes == len(data)
    assert cam.named == [(0, 1)]  # the shot was named before it was taken
    assert seen[3] is RefusalReason.SHADOWING
    assert docs == [seen[4]] and docs[0]["type"] == "pose_done" and "time" in docs[0]


@pytest.mark.parametrize(
    ("exc", "fields"),
    [
        (RigFault("servo 3 overheated", servo=3, error_bits=0x04), {"servo": 3, "error_bits": 4}),
        (RigFault("move timed out"), {"error_bits": 0}),
        (BusError("servo 1 did not answer", servo=1, cause="timeout"),
         {"servo": 1, "cause": "timeout"}),
    ],
)  # fmt: skip
def test_faults_are_journaled_from_the_exception_fields(tmp_path, exc, fields):
    rig, cam = FakeRig(fail=exc, unconfirmed=[2]), FakeCamera()
    docs = []
    engine = Engine(SessionDevices(rig, cam, cam, cam), tmp_path, [docs.append])

    def plan():
        yield SetLight(False)
        yield Move(0, (0.0, 0.0, 1.0), (0.5, 0.0, 0.8))
        yield Emit({"type": "never"})

    out = run_plan(engine, plan(), {"type": "start"})
    assert out.status == "fault" and out.error is exc
    types = [d["type"] for d in docs]
    assert types == ["start", "fault", "stop"]
    fault = {k: v for k, v in docs[1].items() if k not in ("type", "time")}
    assert fault == {"source": "rig", "error": str(exc), **fields}
    stop = docs[2]
    # the finalizer parked, cut torque and says which servo did not confirm it
    assert rig.calls[-2:] == ["park", "torque_off"] and cam.light is True
    assert stop["parked"] is True and stop["torque_off"] is False
    assert stop["torque_unconfirmed"] == [2]
