"""gonio's errors cross process boundaries as themselves (figure and dask workers)."""

from __future__ import annotations

import inspect
import pickle

import pytest

import gonio.errors as errors
from gonio.errors import (
    BusError,
    FileFormatError,
    GonioError,
    PoseRefused,
    RefusalReason,
    RigFault,
    UnknownNameError,
)

CASES = [
    FileFormatError("/data/a.h5", "no samples", field="brdf"),
    FileFormatError("b.bsdf", "truncated"),
    PoseRefused(RefusalReason.JOINT_LIMIT, "joint 3 would pass its limit"),
    BusError("servo 2 did not answer", servo=2, cause="timeout"),
    RigFault("overheated", servo=4, error_bits=0x04),
    UnknownNameError("unknown model 'x'"),
    errors.ConfigError("plan.toml: field 'x'"),
]


@pytest.mark.parametrize("err", CASES, ids=lambda e: type(e).__name__)
def test_round_trip_keeps_class_message_and_attributes(err):
    back = pickle.loads(pickle.dumps(err, protocol=pickle.HIGHEST_PROTOCOL))
    assert type(back) is type(err)
    assert str(back) == str(err) and back.args == err.args
    assert vars(back) == vars(err)


def test_every_error_class_pickles():
    """Each GonioError subclass of gonio.errors, built with its own signature."""
    made = {type(e) for e in CASES}
    for cls in vars(errors).values():
        if not (inspect.isclass(cls) and issubclass(cls, GonioError)) or cls in made:
            continue
        err = cls("a message")
        back = pickle.loads(pickle.dumps(err))
        assert type(back) is cls and str(back) == "a message"


def test_the_default_pickling_would_have_failed():
    """Why ``__reduce__`` exists: Exception's own rebuild calls cls(*args)."""
    err = FileFormatError("/data/a.h5", "no samples", field="brdf")
    with pytest.raises(TypeError):
        Exception.__reduce__(err)[0](*Exception.__reduce__(err)[1])
