"""``gonio capture reduce``'s options: refused before any work, naming the option."""

from __future__ import annotations

import pytest

from gonio.cli import run


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("--tolerance-deg", "nan"),
        ("--tolerance-deg", "inf"),
        ("--roi-fraction", "nan"),
        ("--max-region-spread-deg", "nan"),
    ],
)
def test_non_finite_option_values_are_refused_naming_the_option(tmp_path, capsys, option, value):
    # click's FloatRange let NaN (and inf without a maximum) through: the reduction ran
    # with a NaN tolerance and exited 0, or (--roi-fraction nan) failed later with an
    # unrelated "no reference-target frames".
    code = run("capture", "reduce", str(tmp_path), option, value, "--quiet")
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"'{option}'" in err and value in err and "finite" in err
    assert "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # nothing written
