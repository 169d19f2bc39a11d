"""A simulated session through the radiometric calibration (issue 16): repeated reference
groups with their rig times, the warnings of a session without flats or without darks
(in the result, reduction.json and the CLI's output), and flat frames (written here as
DNGs of a uniform panel through the reduction's cos^4 vignetting, with dead pixels)
masking the dead pixels and changing the samples by no more than the flat term they
state.

One capture (about 8 s) serves every test; the sessions without darks and with flats are
copies of it whose journals were edited (the reduction reads only what the journal
lists)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from gonio.capture.journal import read_journal, sha256_bytes, xxh3_bytes
from gonio.capture.reduce import reduce_session
from gonio.cli import run

pytestmark = pytest.mark.slow

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "e2e"))
from test_virtual_time import PLAN, SCENE  # noqa: E402

PLAN_H2 = PLAN.replace("[darks]\ncount = 1", "[darks]\ncount = 2").replace(
    "[reference]", "[reference]\nevery_poses = 2"
)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from gonio.rig.config import virtual_rig_document

    d = tmp_path_factory.mktemp("radiometry")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN_H2)
    (d / "scene.toml").write_text(SCENE)
    out = d / "S"
    args = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    assert run(*args, "--camera", "simulated", "--out", str(out), "--quiet") == 0
    return out


def _copy(session: Path, name: str, edit) -> Path:
    dst = session.parent / name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(session, dst, ignore=shutil.ignore_patterns("samples.*", "reduction.json"))
    recs = edit(read_journal(dst / "journal.jsonl"), dst)
    (dst / "journal.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    return dst


def test_reference_groups_carry_rig_times_and_the_warnings_name_what_is_missing(session):
    res = reduce_session(session, out=session / "a.h5", plot=False)
    doc = json.loads((session / "reduction.json").read_text())
    groups = doc["radiometric"]["reference_groups"]
    assert len(groups) == 3  # at the start and after every 2 of the 4 sample poses
    times = [g["time"] for g in groups]
    assert times == sorted(times) and times[0] < times[-1]
    shots = [r for r in read_journal(session / "journal.jsonl") if r["type"] == "shot"]
    assert all(isinstance(r["rig_time"], float) for r in shots)
    # darks were shot: only the flats are missing
    assert doc["warnings"] == res.warnings
    assert len(res.warnings) == 1
    w = res.warnings[0]
    assert "no flat fields" in w and "[flats] count = 0" in w and "'flat' term" in w
    assert "prnu = 0.01" in w and "median" in w and "%" in w


def test_samples_say_how_strongly_the_rooms_light_enters_each_one(session):
    """``stray_gain = G0 / G``: the light's direct irradiance at normal incidence over the
    sample's.  At the rig's fixed light radius G goes as cos(theta_i) (the distance and
    the light's profile differ by percents over the sample), so gain cos(theta_i) ~ 1;
    the attributes carry the stated bound and the reference regions' mean gain, which
    the stray term of the budget uses (s / sqrt(3) gain f)."""
    from gonio.dataset import load_samples

    reduce_session(session, out=session / "g.h5", plot=False)
    s = load_samples(session / "g.h5")
    ok = np.asarray(s.valid)
    assert s.stray_gain is not None and s.stray_gain.shape == s.brdf.shape
    g = s.stray_gain[ok]
    np.testing.assert_allclose(g * s.wi[ok, 2:3], 1.0, atol=0.05)
    assert s.attrs["stray_fraction"] == pytest.approx(5e-4)
    g_ref = np.asarray(s.attrs["stray_reference_gain"])
    assert g_ref.shape == (3,) and np.all((g_ref >= 0.95) & (g_ref < 1.0 / np.cos(np.radians(80))))
    np.testing.assert_allclose(
        s.budget["stray"][ok], 5e-4 / np.sqrt(3) * g * np.abs(s.brdf[ok]), rtol=1e-12
    )


def test_a_session_without_darks_warns_and_states_the_dark_term(session, capsys):
    no_darks = _copy(
        session, "no_darks", lambda recs, d: [r for r in recs if r.get("kind") != "dark"]
    )
    assert run("capture", "reduce", str(no_darks), "--quiet", "--no-plot") == 0
    err = capsys.readouterr().err
    doc = json.loads((no_darks / "reduction.json").read_text())
    dark = [w for w in doc["warnings"] if "no dark frames" in w]
    assert len(dark) == 1
    assert "'dark' term" in dark[0] and "dsnu_e = 5 e-" in dark[0] and "median" in dark[0]
    assert any("no flat fields" in w for w in doc["warnings"])
    for w in doc["warnings"]:  # printed by the CLI, even with --quiet
        assert f"warning: {w}" in err


def test_paths_and_warnings_are_printed_as_written_not_as_markup(session, capsys, monkeypatch):
    """rich reads ``[word]`` as markup and drops it: a session folder named with brackets
    and the warnings' plan tables (``[flats]``) must reach the terminal as they are."""
    monkeypatch.setenv("COLUMNS", "400")  # no wrapping inside a long path
    odd = _copy(session, "S[red] [flats]", lambda recs, d: recs)
    assert run("capture", "reduce", str(odd), "--no-plot") == 0
    err = capsys.readouterr().err  # the reduction's tables and lines go to stderr
    assert f"wrote {odd / 'samples.h5'}" in err, err
    # (plain text already; kept so that a move to rich's markup would show here)
    assert "warning: no flat fields in this session ([flats] count = 0)" in err, err
    assert run("capture", "inspect", str(odd)) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{odd}  plan "), out


def _flat_dng(template, level: float, dead: list[tuple[int, int]], seed: int, K) -> bytes:
    """A uniform panel over the lens: ``level`` DN through the reduction's cos^4, photon
    noise of the simulated sensor's gain, dead pixels at 2 % response."""
    from gonio.capture.pixel_calibration import cos4_inverse
    from gonio.simulator.dng import dng_bytes

    rng = np.random.default_rng(seed)
    shape = template.mosaic.shape
    mean = level / cos4_inverse(shape, K)
    for p in dead:
        mean[p] *= 0.02
    electrons = rng.poisson(mean / 0.5) * 0.5  # 0.5 DN per electron
    mosaic = np.clip(np.round(template.black_level + electrons), 0, template.white_level)
    from dataclasses import replace

    return dng_bytes(replace(template, mosaic=mosaic.astype(np.uint16)))


def test_flats_mask_dead_pixels_and_change_samples_within_the_flat_term(session):
    from gonio.capture.manifest import load_manifest
    from gonio.capture.raw import read_raw
    from gonio.capture.reduction_config import resolve_setup
    from gonio.simulator.sensor import RawFrame as SimFrame

    setup = resolve_setup(session, load_manifest(session), None)
    recs = read_journal(session / "journal.jsonl")
    dark_t = sorted({r["exposure_time_requested"] for r in recs if r.get("kind") == "dark"})
    t = dark_t[len(dark_t) // 2]  # darks exist at this exposure
    first = next(r for r in recs if r.get("type") == "shot")
    fr = read_raw((session / first["file"]).read_bytes())
    dead = [(101, 150), (150, 201), (140, 180)]
    template = SimFrame(
        mosaic=np.zeros(fr.shape, np.uint16),
        cfa_pattern=fr.signature.cfa_pattern,
        black_level=int(np.round(np.min(fr.black_level))),
        white_level=int(fr.white_level),
        colour_matrix=np.eye(3),
        as_shot_neutral=np.ones(3),
        exposure_time=t,
        f_number=8.0,
        iso=float(first["iso"] or 100.0),
        focal_length=0.016,
        model=str(fr.extra.get("model", "gonio simulated camera")),
    )

    def add_flats(recs, d):
        out = list(recs)
        stop = out.pop()  # the stop record stays last
        for k in range(4):
            data = _flat_dng(template, 6000.0, dead, k, setup.K)
            name = f"raw/p9999_f{k:02d}_flat.dng"
            (d / name).write_bytes(data)
            rec = {"type": "shot", "pose": 9999, "frame": k, "kind": "flat"}
            rec |= {"exposure_time": t, "exposure_time_requested": t, "iso": template.iso}
            rec |= {"f_number": 8.0, "file": name, "bytes": len(data)}
            rec |= {"sha256": sha256_bytes(data), "xxh3_128": xxh3_bytes(data)}
            out.append(rec)
        out.append({"type": "pose_done", "pose": 9999})
        return [*out, stop]

    flats = _copy(session, "flats", add_flats)
    plain = reduce_session(session, out=session / "plain.h5", plot=False)
    with_flats = reduce_session(flats, out=flats / "f.h5", plot=False)
    doc = with_flats.summary
    assert doc["radiometric"]["flat_frames"] == 4
    assert doc["radiometric"]["masked_pixels"] == len(dead)
    assert not any("no flat fields" in w for w in with_flats.warnings)
    from gonio.dataset import load_samples

    a, b = load_samples(plain.path), load_samples(with_flats.path)
    ok = (a.flags == 0) & (b.flags == 0)
    assert ok.sum() >= 8
    # the terms the reduction stated for the flat-fielded session
    from gonio.capture import reduce as R
    from gonio.capture.manifest import load_manifest as lm

    run_ = R._PoseRun(flats, setup, R._kinematics(lm(flats)), read_journal(flats / "journal.jsonl"))
    run_.measure_all(1, None)
    run_.samples(lm(flats))
    u_flat = np.concatenate(
        [m.radiometric_rel_std["flat"] for m in run_.measurements if m.kind == "sample"]
    )
    rel = np.abs(b.brdf[ok] / a.brdf[ok] - 1)
    assert rel.max() > 0  # the flat changed the samples
    # the gain map's noise, divided out of samples and references alike, moves each
    # sample by no more than its flat term (and the references' share of it)
    assert np.all(rel <= 5 * np.sqrt(u_flat[ok] ** 2 + np.median(u_flat[ok]) ** 2))
    assert np.median(u_flat[ok]) < 0.2 * 0.01  # far below the PRNU statement it replaces


def _simulator_has_flats() -> bool:
    from gonio.simulator.rig_camera import TARGETS

    return "flat" in TARGETS


@pytest.mark.skipif(
    not _simulator_has_flats(),
    reason="the simulated camera's flat-field panel (set_target('flat')) is not in this "
    "simulator yet; the flat step is tested on fake devices in test_flats_and_references",
)
def test_a_simulated_session_with_flats_reduces_with_its_flat_field(tmp_path):
    from gonio.rig.config import virtual_rig_document

    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    plan = PLAN_H2.replace("[reference]", "[flats]\ncount = 3\nexposure_s = 0.01\n[reference]")
    (tmp_path / "plan.toml").write_text(plan)
    (tmp_path / "scene.toml").write_text(SCENE)
    out = tmp_path / "S"
    args = ["capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml")]
    assert run(*args, "--camera", "simulated", "--out", str(out), "--quiet") == 0
    recs = read_journal(out / "journal.jsonl")
    flats = [r for r in recs if r.get("type") == "shot" and r["kind"] == "flat"]
    assert len(flats) == 3 and all("rig_time" in r for r in flats)
    darks = {r["exposure_time_requested"] for r in recs if r.get("kind") == "dark"}
    assert 0.01 in darks  # the flats are dark-subtracted
    res = reduce_session(out, plot=False)
    assert res.summary["radiometric"]["flat_frames"] == 3
    assert not any("no flat fields" in w for w in res.warnings)


def test_a_black_region_of_an_undarked_pose_states_its_dark_term_in_absolute_units(session):
    """Relative to a radiance of exactly 0 the dark offset is infinite, and times a BRDF
    of 0 it was NaN (with a RuntimeWarning): in 1/sr it is the offset over the region's
    irradiance, at L = 0 ``d sum(w_k / e_k) / sum(w_k) / sqrt(N_c) / E`` with
    ``w_k = e_k^2 / var_k(0)`` and ``d = dsnu_e g``."""
    import warnings

    from gonio.capture import reduce as R
    from gonio.capture.manifest import load_manifest

    no_darks = _copy(
        session, "no_darks_black", lambda recs, d: [r for r in recs if r.get("kind") != "dark"]
    )
    manifest = load_manifest(no_darks)
    setup = R.resolve_setup(no_darks, manifest, None)
    run_ = R._PoseRun(
        no_darks, setup, R._kinematics(manifest), read_journal(no_darks / "journal.jsonl")
    )
    run_.measure_all(1, None)
    sample = [m for m in run_.measurements if m.kind == "sample"]
    m = next(m for m in sample if np.any(m.flags == 0))
    assert m.pose in run_.cal.undarked
    j = int(np.flatnonzero(m.flags == 0)[0])
    m.radiance[j] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        s = run_.samples(manifest)
    row = sum(len(x.flags) for x in sample[: sample.index(m)]) + j
    assert np.all(s.brdf[row] == 0)
    dark = s.budget["dark"][row]
    assert np.all(np.isfinite(dark)) and np.all(dark > 0)
    assert np.all(np.isfinite(s.brdf_std[row]))
    w = np.array(
        [e * e / setup.noise.variance(0.0, iso=iso) for e, iso, _ in run_.cal.exposures[m.pose]]
    )
    e = np.array([e for e, _, _ in run_.cal.exposures[m.pose]])
    g = np.array([setup.noise.at_iso(iso).gain for _, iso, _ in run_.cal.exposures[m.pose]])
    offset = setup.dsnu_e * np.sum(w * g / e) / np.sum(w)
    np.testing.assert_allclose(dark, offset / np.sqrt(m.n_sites[j]) / s.irradiance[row], rtol=1e-9)
    # a region beside it keeps the relative term times its BRDF
    k = int(np.flatnonzero(m.flags == 0)[1])
    np.testing.assert_allclose(
        s.budget["dark"][row - j + k],
        m.radiometric_rel_std["dark"][k] * np.abs(s.brdf[row - j + k]),
        rtol=1e-12,
    )
