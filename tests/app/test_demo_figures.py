"""The demo's figure worker draws the files the main process would draw.

The reference is the plotting functions called in this process (``figure_worker(enabled=
False)`` and the plain functions): the spawned worker must write the same bytes, report
its errors in the main process, and leave no process behind.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from gonio.app.demo_figures import figure_worker, residual_map, result_path
from gonio.brdf import get_model
from gonio.dataset import BRDFSamples, save_samples
from gonio.errors import GonioError
from gonio.fitting import fit
from gonio.radiometry.frames import spherical_to_direction


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("figs")
    rng = np.random.default_rng(4)
    n = 400
    wi = spherical_to_direction(rng.uniform(0, 1.3, n), np.zeros(n))
    wo = spherical_to_direction(rng.uniform(0, 1.3, n), rng.uniform(0, 2 * np.pi, n))
    f = get_model("lambert").bind({"albedo": np.array([0.5, 0.4, 0.3])}).eval(wi, wo)
    f = f * (1 + 0.01 * rng.standard_normal(f.shape))
    path = save_samples(d / "samples.h5", BRDFSamples(wi=wi, wo=wo, brdf=f, brdf_std=0.01 * f))
    from gonio.dataset import load_samples

    return d, path, fit(load_samples(path), model="lambert")


def test_worker_draws_the_same_files_as_this_process(fitted):
    d, path, result = fitted
    (d / "here").mkdir()
    (d / "there").mkdir()
    ref_res = residual_map(result, str(path), str(d / "here" / "residuals.png"))
    with figure_worker() as worker:
        assert worker.active
        pid = worker.pid
        job = worker.submit(residual_map, result, str(path), str(d / "there" / "residuals.png"))
        res = result_path(job)
    assert res.read_bytes() == (d / "here" / "residuals.png").read_bytes()
    assert ref_res.endswith("residuals.png")
    # shut down and reaped on exit: no worker process left
    assert not worker.active
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)


def test_a_figure_error_is_raised_in_the_main_process(fitted, tmp_path):
    _, path, result = fitted
    missing = tmp_path / "nope" / "samples.h5"
    seen = {}
    for enabled in (True, False):
        with figure_worker(enabled=enabled) as worker:
            job = worker.submit(residual_map, result, str(missing), str(tmp_path / "s.png"))
            with pytest.raises(GonioError, match="nope") as info:
                result_path(job)
            seen[enabled] = (type(info.value), str(info.value))
    # the worker's error arrives as the class and message the function raised here
    assert seen[True] == seen[False]
    assert not (tmp_path / "s.png").exists()
