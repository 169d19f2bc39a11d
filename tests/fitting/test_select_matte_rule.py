"""model='auto': the matte (gloss) rule never overrides a lobe a diffuse model cannot replace."""

import numpy as np

from gonio.brdf import get_model
from gonio.fitting import fit
from gonio.fitting.select import MAX_DIFFUSE_COST_RATIO, gloss_units


def test_strong_broad_lobe_is_kept_even_below_the_gloss_threshold(make_samples):
    # A broad, strong lobe: below 10 GU at 60 deg (so "matte" by the gloss rule alone),
    # yet no diffuse model comes near it (cost ratio far above MAX_DIFFUSE_COST_RATIO).
    truth = {"albedo": [0.5, 0.4, 0.3], "ks": [0.5] * 3, "alpha": [0.45] * 3}
    gloss = np.mean(gloss_units(get_model("lambert+ggx").bind(truth)))
    assert gloss < 10.0  # the case the rule used to get wrong
    s = make_samples("lambert+ggx", truth, n=400, seed=2, noise=1e-5)
    r = fit(s, model="auto")
    rows = {row["model"]: row for row in r.diagnostics["selection"]}
    assert rows["lambert"]["cost"] > MAX_DIFFUSE_COST_RATIO * rows["lambert+ggx"]["cost"]
    assert r.model in ("lambert+ggx", "lambert+beckmann"), r.diagnostics["selection_note"]


def test_faint_lobe_on_a_matte_sample_is_still_reported_diffuse(make_samples):
    # A faint broad sheen (wall-paint-like): the diffuse fit is nearly as good, gloss is low.
    truth = {"albedo": [0.6, 0.6, 0.6], "ks": [0.004] * 3, "alpha": [0.5] * 3}
    s = make_samples("lambert+ggx", truth, n=400, seed=3, noise=1e-4)
    r = fit(s, model="auto")
    assert r.model in ("lambert", "oren-nayar"), r.diagnostics["selection"]
