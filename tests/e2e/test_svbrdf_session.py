"""A simulated capture session of the spatially varying example scene, reduced.

``examples/svbrdf_scene.toml`` (inline 4 x 4 maps of albedo, ks and alpha) is captured
through ``gonio capture run`` (virtual bus, rendered DNGs) at 320 x 240 on two poses and
reduced by ``gonio capture reduce --texels 4``.  Independent reference: the
reduced BRDF of each region against the analytic model evaluated with the parameters of
the texel the region covers (read from the session's ``truth/svbrdf.h5``).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.cli import run
from gonio.rig.config import virtual_rig_document
from gonio.simulator.svbrdf import read_truth

REPO = Path(__file__).resolve().parents[2]

PLAN = """
name = "svbrdf-small"
seed = 3
settle_s = 0.2
[grid]
theta_i_deg = [20, 45]
phi_i_deg = [0]
theta_o_deg = [30]
phi_o_deg = [180]
[bracket]
policy = "adaptive"
roi = [0.42, 0.42, 0.58, 0.58]
exposure_time_s = 0.002
[darks]
count = 1
[reference]
poses = [{theta_i_deg = 0, theta_o_deg = 30}]
[simulation]
scene = "svbrdf_scene.toml"
width = 320
height = 240
"""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("svbrdf")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN)
    shutil.copy(REPO / "examples" / "svbrdf_scene.toml", d / "svbrdf_scene.toml")
    s = d / "S"
    args = ("capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml"))
    assert run(*args, "--camera", "simulated", "--out", str(s), "--quiet") == 0
    # a texel reduction: the 4 x 4 region grid covers the 4 x 4 texels (roi 1.0), with
    # the texel margins and no aperture correction (its neighbours are other materials)
    reduce = ("capture", "reduce", str(s), "--texels", "4")
    assert run(*reduce, "--quiet", "--no-plot") == 0
    return s


@pytest.mark.slow
def test_the_session_holds_the_truth_and_a_relocatable_scene(session):
    truth = read_truth(session / "truth" / "svbrdf.h5")
    assert truth.model == "lambert+ggx" and truth.texels == (4, 4)
    # the scene's inline numbers, row 0 at +y, column 0 at -x
    assert truth.params["ks"][0, :, 0].tolist() == [0.05, 0.15, 0.30, 0.45]
    assert truth.params["alpha"][:, 0, 0].tolist() == [0.10, 0.18, 0.28, 0.40]
    manifest = json.loads((session / "manifest.json").read_text())
    sample = manifest["simulation"]["scene"]["sample"]
    assert sample["maps"]["ks"][0] == [0.05, 0.15, 0.30, 0.45]
    assert str(session.parent) not in json.dumps(manifest["simulation"])


@pytest.mark.slow
def test_each_reduced_region_is_the_brdf_of_its_texel(session):
    truth = read_truth(session / "truth" / "svbrdf.h5")
    with h5py.File(session / "samples.h5") as f:
        wi, wo, brdf = f["wi"][:], f["wo"][:], f["brdf"][:]
    assert len(brdf) == 2 * 16 and np.all(np.isfinite(brdf))
    model = get_model(truth.model)
    P = {k: v.reshape(16, 3) for k, v in truth.params.items()}
    # every sample against every texel's BRDF at the sample's directions
    F = model.eval(wi[:, None, None, :], wo[:, None, None, :], {k: v[None] for k, v in P.items()})
    err = np.max(np.abs(F / brdf[:, None, :] - 1), axis=-1)
    best = np.argmin(err, axis=1)
    # The reduction's region k of a 4 x 4 grid (today's samples.h5 order) covers texel
    # (3 - k // 4, k % 4): its region rows start at -y, the texel rows at +y.
    k = np.arange(len(brdf)) % 16
    np.testing.assert_array_equal(best, (3 - k // 4) * 4 + k % 4)
    # the region's centre direction stands for the whole texel: a few % (highlights)
    assert np.median(err.min(axis=1)) < 0.01 and np.max(err.min(axis=1)) < 0.03
