"""SVBRDF end to end: capture a simulated session of a spatially varying sample, reduce it
per texel, fit every texel, compare the maps with the simulator's truth.

``examples/svbrdf_scene.toml`` (inline 4 x 4 lambert+ggx maps) through ``gonio capture
run`` (virtual bus, rendered DNGs, 320 x 240, 8 poses with two mirror configurations),
``gonio capture reduce --texels 4`` and ``gonio fit S/texels.h5 --svbrdf``.  Independent
reference: ``SESSION/truth/svbrdf.h5`` (the scene's maps, written by the simulator; the
reduction and the fit never read it).  ``--no-energy``: some of the example's texels
(albedo 0.65 + ks 0.45 in blue) have a directional albedo above 1, which the default
energy constraint would not let the fit reach.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from gonio.cli import run
from gonio.rig.config import virtual_rig_document
from gonio.simulator.svbrdf import read_truth

REPO = Path(__file__).resolve().parents[2]

PLAN = """
name = "svbrdf-fit"
seed = 3
settle_s = 0.2
[grid]
theta_i_deg = [20, 45]
phi_i_deg = [0]
theta_o_deg = [0, 20, 45, 60]
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


@pytest.mark.slow
def test_fitted_maps_hold_the_truth(tmp_path, capsys):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    shutil.copy(REPO / "examples" / "svbrdf_scene.toml", tmp_path / "svbrdf_scene.toml")
    s = tmp_path / "S"
    args = ("capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml"))
    assert run(*args, "--camera", "simulated", "--out", str(s), "--quiet") == 0
    assert run("capture", "reduce", str(s), "--texels", "4", "--quiet", "--no-plot") == 0
    fit = ("fit", str(s / "texels.h5"), "--svbrdf", "-m", "lambert+ggx", "--no-energy")
    assert run(*fit, "--workers", "0", "--no-plots") == 0
    out = s / "svbrdf"  # the default: beside texels.h5
    assert (out / "material.xml").is_file() and (out / "material.mtlx").is_file()
    truth = read_truth(s / "truth" / "svbrdf.h5").params_at(4, 4)
    with h5py.File(out / "svbrdf.h5", "r") as f:
        assert f["success"][()].all()
        fitted = {k: (f[f"params/{k}"][()], f[f"std/{k}"][()]) for k in truth}
    z, rel = [], {}
    for k, t in truth.items():
        v, sd = fitted[k]
        zk = np.abs(v - t) / sd
        z.append((zk[..., :1] if k == "alpha" else zk).ravel())  # alpha: once per texel
        rel[k] = float(np.median(np.abs(v / t - 1)))
    frac = float(np.mean(np.concatenate(z) < 3))
    print(f"within 3 sigma: {frac:.3f}; median relative error {rel}")
    assert frac >= 0.95
    assert all(r < 0.02 for r in rel.values()), rel
