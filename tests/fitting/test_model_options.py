"""Model options in fits: ``"name[key=value]"`` specs, Fresnel candidates for ``auto``, and
``gonio fit --option``.

References: the generating parameters of synthetic data (a closed form), and the shared RGL
measurements of a glossy vinyl film, whose specular peak is Fresnel-like (it rises towards
grazing incidence and turns white there).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from gonio.brdf import load
from gonio.cli import cli
from gonio.errors import FitError, UnknownNameError
from gonio.fitting import fit
from gonio.fitting.export import mitsuba_dict
from gonio.fitting.sampling import sample_brdf
from gonio.fitting.select import (
    DEFAULT_CANDIDATES,
    FRESNEL_CANDIDATES,
    format_model_spec,
    parse_model_spec,
)

GLOSSY_SCHLICK = {"albedo": [0.3, 0.2, 0.1], "ks": [0.8, 0.7, 0.6], "alpha": 0.15, "f0": 0.08}


@pytest.mark.parametrize(
    ("spec", "name", "opts"),
    [
        ("lambert+ggx", "lambert+ggx", {}),
        (" lambert+ggx[fresnel=schlick] ", "lambert+ggx", {"fresnel": "schlick"}),
        (
            "beckmann[fresnel = dielectric, g1=rational]",
            "beckmann",
            {"fresnel": "dielectric", "g1": "rational"},
        ),
        ("ggx[]", "ggx", {}),
    ],
)
def test_parse_model_spec(spec, name, opts):
    assert parse_model_spec(spec) == (name, opts)
    assert parse_model_spec(format_model_spec(name, opts)) == (name, opts)


@pytest.mark.parametrize("spec", ["ggx[fresnel]", "ggx[fresnel=schlick", "[fresnel=x]", "ggx]x["])
def test_bad_model_spec_is_a_clear_error(spec):
    with pytest.raises(UnknownNameError, match="model spec"):
        parse_model_spec(spec)


def test_spec_name_recovers_fresnel_parameters(make_samples):
    # noise-free data from the Fresnel-weighted model: the spec fits it exactly
    s = make_samples("lambert+ggx", GLOSSY_SCHLICK, n=400, seed=3, options={"fresnel": "schlick"})
    r = fit(s, "lambert+ggx[fresnel=schlick]", loss="l2")
    assert r.model == "lambert+ggx" and r.model_options == {"fresnel": "schlick"}
    for k, v in GLOSSY_SCHLICK.items():
        np.testing.assert_allclose(r.params[k], np.broadcast_to(v, (3,)), rtol=1e-6)
    # the same fit through model_options; explicit options win over the spec's
    r2 = fit(s, "lambert+ggx[fresnel=none]", loss="l2", model_options={"fresnel": "schlick"})
    np.testing.assert_allclose(r2.params["f0"], 0.08, rtol=1e-6)
    # Mitsuba 3 has no Schlick-weighted rough conductor: the export refuses, clearly
    with pytest.raises(FitError, match="fresnel='schlick'.*no exact Mitsuba 3 counterpart"):
        mitsuba_dict(r)


def test_auto_with_fresnel_candidates(make_samples):
    cands = DEFAULT_CANDIDATES + FRESNEL_CANDIDATES
    noise = {"noise": 1e-4, "read": 1e-3}
    s = make_samples(
        "lambert+ggx", GLOSSY_SCHLICK, n=600, seed=4, options={"fresnel": "schlick"}, **noise
    )
    r = fit(s, "auto", candidates=cands)
    assert (r.model, r.model_options) == ("lambert+ggx", {"fresnel": "schlick"})
    assert r.params["f0"][0] == pytest.approx(0.08, rel=0.05)
    names = [row["model"] for row in r.diagnostics["selection"]]
    assert names == list(cands)
    # data without Fresnel (F = 1): BIC does not pay for the extra f0
    plain = {"albedo": [0.3, 0.2, 0.1], "ks": [0.2, 0.15, 0.1], "alpha": 0.15}  # albedo < 1
    s1 = make_samples("lambert+ggx", plain, n=600, seed=5, **noise)
    r1 = fit(s1, "auto", candidates=cands)
    assert (r1.model, r1.model_options) == ("lambert+ggx", {})
    with pytest.raises(FitError, match="candidate specs"):
        fit(s1, "auto", model_options={"fresnel": "schlick"})


@pytest.mark.slow
def test_fresnel_lobe_fits_the_ibiza_vinyl_much_better(rgl_file):
    # measured: the specular peak of this film rises and whitens towards grazing; a
    # Fresnel-free lobe cannot follow it (fitted cosine-L2 costs 838 vs 112 on the CLI grid)
    s = sample_brdf(load(rgl_file("cc_ibiza_sunset")))
    plain = fit(s, "lambert+ggx", loss="cosine_l2")
    schlick = fit(s, "lambert+ggx[fresnel=schlick]", loss="cosine_l2")
    assert schlick.success and plain.success
    assert schlick.cost < 0.2 * plain.cost
    assert 0.02 < schlick.params["f0"][0] < 0.5  # a dielectric coating, not F = 1
    log_plain = fit(s, "lambert+ggx", loss="log")
    log_schlick = fit(s, "lambert+ggx[fresnel=schlick]", loss="log")
    assert log_schlick.cost < 0.95 * log_plain.cost


def _cli(*args):
    return CliRunner().invoke(cli, ["fit", *map(str, args)])


def test_cli_option_passes_model_options(tmp_path, make_samples):
    from gonio.dataset import save_samples

    s = make_samples(
        "lambert+ggx", GLOSSY_SCHLICK, n=300, seed=6, options={"fresnel": "schlick"}, noise=1e-5
    )
    src = save_samples(tmp_path / "samples.h5", s)
    out = tmp_path / "fit"
    out.mkdir()
    (out / "material.xml").write_text("<bsdf>an earlier fit</bsdf>")
    res = _cli(src, "-m", "lambert+ggx", "--option", "fresnel=schlick", "--out", out, "--force")
    assert res.exit_code == 0, res.output
    d = json.loads((out / "fit.json").read_text())
    assert d["model"] == "lambert+ggx" and d["model_options"] == {"fresnel": "schlick"}
    np.testing.assert_allclose(d["params"]["f0"], 0.08, rtol=0.05)
    # no Mitsuba material, said so, and the stale one of the earlier fit is gone
    assert "no Mitsuba export" in res.output
    assert not (out / "material.xml").exists()
    # the bracket spec in --model and in --candidates
    res2 = _cli(src, "-m", "lambert+ggx[fresnel=schlick]", "--out", tmp_path / "b", "--no-plots")
    assert res2.exit_code == 0, res2.output
    d2 = json.loads((tmp_path / "b" / "fit.json").read_text())
    assert d2["model_options"] == {"fresnel": "schlick"}
    # the table's title names the model as asked (rich read the brackets as markup)
    title = " ".join(res2.output.split())  # however rich wraps the title
    assert "lambert+ggx[fresnel=schlick] fitted to samples.h5" in title, res2.output
    res3 = _cli(
        src,
        "--candidates",
        "lambert,lambert+ggx,lambert+ggx[fresnel=schlick]",
        "--out",
        tmp_path / "c",
        "--no-plots",
    )
    assert res3.exit_code == 0, res3.output
    d3 = json.loads((tmp_path / "c" / "fit.json").read_text())
    assert d3["model_options"] == {"fresnel": "schlick"}
    sel = [row["model"] for row in d3["diagnostics"]["selection"]]
    assert sel == ["lambert", "lambert+ggx", "lambert+ggx[fresnel=schlick]"]
    table = res3.output.split("model selection")[1]  # the selection table's rows
    assert "lambert+ggx[fresnel=schlick]" in table, res3.output


@pytest.mark.parametrize(
    ("args", "code", "text"),
    [
        (["--option", "fresnel"], 2, "KEY=VALUE"),
        (["-m", "auto", "--option", "fresnel=schlick"], 2, "--candidates"),
        (["-m", "lambert+ggx", "--option", "fresnel=nope"], 1, "'nope'"),
        (["-m", "lambert", "--option", "fresnel=schlick"], 1, "'fresnel'"),
    ],
)
def test_cli_bad_option(tmp_path, make_samples, args, code, text):
    from gonio.dataset import save_samples

    src = save_samples(tmp_path / "s.h5", make_samples("lambert", {"albedo": 0.5}, n=50))
    res = _cli(src, *args, "--out", tmp_path / "o")
    assert res.exit_code == code, res.output
    assert text in res.output + str(res.exception)
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("material", "kind"),
    [
        ("paper_white", "diffuse"),
        ("colodur_napoli_4f", "diffuse"),
        ("vch_golden_yellow", "specular"),
        ("cc_ibiza_sunset", "specular"),
    ],
)
def test_auto_with_fresnel_candidates_on_rgl_materials(material, kind, rgl_file):
    # The Fresnel candidates fit the matte materials' grazing sheen better (wall paint:
    # 7x lower cost than Lambert) but must not turn them glossy: the gloss rule decides
    # while the diffuse cost is within MAX_DIFFUSE_COST_RATIO (10) of the best.  On the
    # CLI's grid (the user's path) the wall paint's ratio is 7.1; on a coarser grid
    # (5 x 12 x 24) it exceeds 10 and the 1-GU sheen is kept, which is one reason these
    # candidates are opt-in (see gonio.fitting.select).
    s = sample_brdf(load(rgl_file(material)))
    r = fit(s, "auto", candidates=DEFAULT_CANDIDATES + FRESNEL_CANDIDATES)
    assert (r.model in ("lambert", "oren-nayar")) == (kind == "diffuse"), (
        r.model,
        r.diagnostics["selection_note"],
    )
    costs = {row["model"]: row["cost"] for row in r.diagnostics["selection"]}
    # a Fresnel lobe never fits worse than the same lobe with F = 1 (f0 = 1 is nested)
    for name in ("lambert+ggx", "lambert+beckmann"):
        assert costs[f"{name}[fresnel=schlick]"] <= costs[name] * (1 + 1e-6), costs
