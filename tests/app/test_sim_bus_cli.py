"""``gonio sim bus``: bad option values are usage errors, before any bus is served."""

from __future__ import annotations

import pytest

from gonio.cli import run


@pytest.mark.parametrize(
    ("option", "value"),
    [("--fault-rate", "nan"), ("--time-scale", "nan"), ("--time-scale", "inf")],
)
def test_non_finite_option_values_are_usage_errors_not_tracebacks(capsys, option, value):
    # click's FloatRange let NaN (and inf, without a maximum) through to the virtual bus,
    # whose ValueError came out as a traceback.
    code = run("sim", "bus", option, value)
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"'{option}'" in err and value in err and "finite" in err
    assert "Traceback" not in err
