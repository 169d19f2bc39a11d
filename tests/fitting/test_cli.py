"""``gonio fit`` as a user runs it: samples.h5 and a measured .bsdf file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from gonio.cli import cli
from gonio.dataset import save_samples


def test_fit_samples_file(tmp_path, make_samples):
    s = make_samples(
        "lambert+ggx",
        {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.2},
        n=200,
        seed=1,
        noise=1e-4,
        read=1e-3,
    )
    src = save_samples(tmp_path / "samples.h5", s)
    out = tmp_path / "fit"
    res = CliRunner().invoke(cli, ["fit", str(src), "--model", "lambert+ggx", "--out", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads((out / "fit.json").read_text())
    np.testing.assert_allclose(d["params"]["alpha"], 0.2, rtol=0.05)
    for name in ("material.xml", "slices.png", "residuals.png"):
        assert (out / name).stat().st_size > 0
    assert "alpha" in res.output and "±" in res.output
    # a second run refuses to overwrite, and leaves the first result untouched
    before = (out / "fit.json").read_bytes()
    res2 = CliRunner().invoke(cli, ["fit", str(src), "--model", "lambert", "--out", str(out)])
    assert res2.exit_code != 0 and "--force" in str(res2.exception)
    assert (out / "fit.json").read_bytes() == before


@pytest.mark.slow
def test_fit_rgl_file_auto(tmp_path, rgl_file):
    out = tmp_path / "paper"
    res = CliRunner().invoke(
        cli, ["fit", str(rgl_file("paper_white")), "--out", str(out), "--no-plots"]
    )
    assert res.exit_code == 0, res.output
    d = json.loads((out / "fit.json").read_text())
    assert d["model"] in ("lambert", "oren-nayar")
    assert "model selection" in res.output


def test_bad_input_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "broken.h5"
    bad.write_bytes(b"not hdf5")
    from gonio.cli import main

    with pytest.raises(SystemExit) as e:
        main(["fit", str(bad), "--out", str(tmp_path / "o")])
    assert e.value.code == 1
    assert not (tmp_path / "o").exists()
