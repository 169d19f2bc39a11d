"""``gonio fit`` library options: bad values are usage errors, refused before any work."""

from __future__ import annotations

import pytest

from gonio.cli import run


@pytest.mark.parametrize("value", ["nan", "-1", "0", "inf"])
def test_a_connect_timeout_that_is_not_a_positive_time_is_a_usage_error(tmp_path, capsys, value):
    # NaN and negative timeouts reached dask's time parser: a KeyError or ValueError
    # traceback; inf would wait forever for a scheduler that is not there.
    lib = tmp_path / "LIB"
    code = run(
        "fit", str(tmp_path), "--out", str(lib), "--scheduler", "tcp://127.0.0.1:1",
        "--connect-timeout", value,
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--connect-timeout" in err and value in err and "positive finite" in err
    assert "Traceback" not in err
    assert not lib.exists()
