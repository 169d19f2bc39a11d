"""SVBRDF accuracy on a simulated sample with known maps, and the dask engines on it.

A simulated session (virtual bus, rendered DNGs, 320 x 240) of the inline 4 x 4
lambert+ggx maps of ``examples/svbrdf_scene.toml`` on the demo's simulated camera
(:func:`gonio.app.demo.scene_document`: 2 mm disk light, 3 x 3 anti-aliasing), through
``gonio capture run``, ``gonio capture reduce --texels 4`` and ``gonio fit texels.h5
--svbrdf``.  The plan: the fewest poses found to determine lambert+ggx in every texel
(two leave it underdetermined; 3 -- theta_i 30, theta_o 0/30/60 -- left one texel of 16
with an infinite sigma): theta_i 20 and 45 deg x theta_o 0, 45 and 60 deg opposite, i.e.
the mirror configuration 45/45 through every texel's specular lobe (across the sample the
half vector moves by a few degrees, so each texel sees its lobe at another offset), and
five poses on its flanks at half-vector offsets 7.5-22.5 deg (45/60, 20/0, 20/45, 20/60,
45/0), diffuse-dominated for the glossy texels: they fix the albedo and, with the mirror
pose, the lobe's width.
``benchmarks/svbrdf_accuracy.py`` uses 8 poses.
The world is the perfect one: the simulated rig and camera are what the reduction is
told, so for geometry this is a self-consistency check of the per-texel chain; the
accuracy on an as-built world (with gonio's own calibrations) is the benchmark's
``--world realistic`` run (worlds 11 and 12: 100 % of texels within 3 sigma).

Independent reference: the simulator's ``SESSION/truth/svbrdf.h5`` (the reduction and the
fit never read it).  Checked: every texel with all its parameters within 3 reported sigma
of the truth (issue 18: >= 95 % of texels), the maps' median relative errors, the default
output folder (beside texels.h5) with its Mitsuba 3 and MaterialX exports, and a real
``dask scheduler`` + two ``dask worker`` processes and a LocalCluster giving the same
bytes (every dataset of svbrdf.h5, every map PNG) as ``--workers 0``.
``benchmarks/svbrdf_accuracy.py`` runs such sessions (and realistic worlds).
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
import tomli_w

from gonio.cli import run
from gonio.rig.config import virtual_rig_document
from gonio.simulator.svbrdf import read_truth

REPO = Path(__file__).resolve().parents[2]
N = 4

PLAN = {
    "name": "svbrdf accuracy",
    "seed": 5,
    "settle_s": 0.0,
    "grid": {
        "kind": "spherical",
        "theta_i_deg": [20, 45],
        "phi_i_deg": [0],
        "theta_o_deg": [0, 45, 60],
        "phi_o_deg": [180],
    },
    "bracket": {"policy": "adaptive", "exposure_time_s": 0.002, "roi": [0.42, 0.42, 0.58, 0.58]},
    "darks": {"count": 1},
    "reference": {"poses": [{"theta_i_deg": 0, "theta_o_deg": 30}]},
    "simulation": {"scene": "scene.toml", "width": 320, "height": 240},
}

# --no-energy: the example's bright blue texels (albedo 0.65 + ks 0.45) reflect more than
# they receive at some angles, which the energy bound would not let the fit reach.
FIT = ("-m", "lambert+ggx", "--no-energy", "--no-plots")


def _scene() -> dict:
    from gonio.app.demo import Material, scene_document

    example = tomllib.loads((REPO / "examples" / "svbrdf_scene.toml").read_text())
    scene = scene_document(Material("svbrdf", model="lambert"), 320, 240)
    for key in ("width", "height", "brdf", "maps"):
        scene["sample"][key] = example["sample"][key]
    return scene


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    d = tmp_path_factory.mktemp("svbrdf_accuracy")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "scene.toml").write_text(tomli_w.dumps(_scene()))
    (d / "plan.toml").write_text(tomli_w.dumps(PLAN))
    s = d / "S"
    args = ("--rig", str(d / "rig.toml"), "--camera", "simulated", "--out", str(s), "--quiet")
    assert run("capture", "run", str(d / "plan.toml"), *args) == 0
    assert run("capture", "reduce", str(s), "--texels", str(N), "--quiet", "--no-plot") == 0
    fit = ("fit", str(s / "texels.h5"), "--svbrdf", *FIT, "--workers", "0")
    assert run(*fit) == 0
    return s, s / "svbrdf"  # the default folder: beside texels.h5


def _datasets(f: h5py.File) -> list[str]:
    names: list[str] = []
    f.visititems(lambda n, obj: names.append(n) if isinstance(obj, h5py.Dataset) else None)
    return names


def _outputs(out: Path) -> dict[str, bytes]:
    """Every dataset of svbrdf.h5 and every map PNG, as bytes."""
    got: dict[str, bytes] = {}
    with h5py.File(out / "svbrdf.h5", "r") as f:
        for name in _datasets(f):
            got[name] = f[name][()].tobytes()
    for p in sorted(out.glob("*.png")):
        got[p.name] = p.read_bytes()
    got["maps.json"] = (out / "maps.json").read_bytes()
    return got


@pytest.mark.slow
def test_fitted_maps_within_three_sigma_of_the_truth(session, capsys):
    s, out = session
    truth = read_truth(s / "truth" / "svbrdf.h5").params_at(N, N)
    with h5py.File(out / "svbrdf.h5", "r") as f:
        assert f["success"][()].all()
        fitted = {k: (f[f"params/{k}"][()], f[f"std/{k}"][()]) for k in truth}
    ok, rel = [], {}
    for k, t in truth.items():
        v, sd = fitted[k]
        # an infinite sigma (undetermined) would put any error "within 3 sigma"
        assert np.all(np.isfinite(sd) & (sd > 0)), (k, sd)
        z = np.abs(v - t) / sd
        ok.append(np.all((z[..., :1] if k == "alpha" else z) < 3, axis=-1))  # alpha: one
        rel[k] = float(np.median(np.abs(v / t - 1)))
    frac = float(np.mean(np.all(ok, axis=0)))
    with capsys.disabled():
        print(f"\ntexels with every parameter within 3 sigma: {frac:.3f}; median rel. error {rel}")
    assert frac >= 0.95
    # measured 0.6 % (albedo), 0.6 % (alpha), 1.4 % (ks); a pooled fit's (one material
    # for the whole sample) are 21-69 %
    assert all(r < 0.025 for r in rel.values()), rel


@pytest.mark.slow
def test_default_folder_holds_the_renderer_exports(session):
    """Without ``--out`` the maps go beside texels.h5, with both renderer exports: the
    Mitsuba 3 scene and the MaterialX document, each with its textures, and the MaterialX
    mapping's error stated in maps.json (finite, for every texel)."""
    s, out = session
    assert out == s / "svbrdf" and (out / "svbrdf.h5").is_file()
    for doc, prefix in (("material.xml", "mitsuba_"), ("material.mtlx", "mtlx_")):
        assert (out / doc).is_file(), doc
        textures = {p.name for p in out.glob(f"{prefix}*.png")}
        assert textures, prefix
        # every texture the document names is in the folder
        named = set(re.findall(rf"{prefix}\w+\.png", (out / doc).read_text()))
        assert named and named <= textures, (doc, named - textures)
    err = json.loads((out / "maps.json").read_text())["exports"]["materialx"]["relative_rmse"]
    assert err["texels"] == N * N
    assert 0 < err["median"] <= err["max"] < np.inf, err


@pytest.mark.slow
def test_real_cluster_and_local_cluster_give_the_same_bytes(session, dask_cluster):
    s, out = session
    address, _ = dask_cluster
    ref = _outputs(out)
    assert {"params/albedo", "std/alpha", "cost", "albedo.png"} <= set(ref)
    for name, engine in (("scheduler", ("--scheduler", address)), ("local", ("--workers", "2"))):
        o = out.with_name(name)
        # two texels a task: several tasks on each worker
        cmd = ("fit", str(s / "texels.h5"), "--svbrdf", *FIT, "--block-texels", "2")
        assert run(*cmd, *engine, "--out", str(o)) == 0, name
        got = _outputs(o)
        assert got.keys() == ref.keys(), name
        assert [k for k in ref if got[k] != ref[k]] == [], name
