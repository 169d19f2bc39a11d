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


# --- issue 14.7 / 14.1: outputs replaced as a set, one writer per output folder --------


def _samples_file(tmp_path, make_samples):
    s = make_samples("lambert", {"albedo": [0.2, 0.4, 0.6]}, n=120, seed=2, noise=1e-3)
    return save_samples(tmp_path / "samples.h5", s)


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_force_replaces_the_outputs_as_a_set(tmp_path, make_samples):
    from gonio.atomic import stale_temporaries

    src = _samples_file(tmp_path, make_samples)
    out = tmp_path / "fit"
    run = CliRunner().invoke
    assert run(cli, ["fit", str(src), "-m", "lambert", "--out", str(out)]).exit_code == 0
    (out / "notes.txt").write_text("the user's own file")
    old = _snapshot(out)
    assert {"fit.json", "material.xml", "slices.png", "residuals.png"} <= set(old)
    res = run(cli, ["fit", str(src), "-m", "oren-nayar", "--out", str(out), "--force",
                    "--no-plots"])  # fmt: skip
    assert res.exit_code == 0, res.output
    new = _snapshot(out)
    # The new set: its fit.json alone (oren-nayar has no Mitsuba equivalent, --no-plots),
    # no material.xml or plot of the previous fit beside it; non-output files stay.
    assert json.loads(new["fit.json"])["model"] == "oren-nayar"
    assert "no Mitsuba export" in res.output
    assert set(new) == {"fit.json", "notes.txt", ".gonio.lock"}
    assert new["notes.txt"] == old["notes.txt"]
    assert stale_temporaries(tmp_path) == [] and stale_temporaries(out) == []


def test_a_failed_output_phase_leaves_the_old_set(tmp_path, make_samples, monkeypatch):
    import gonio.fitting.plots as plots

    src = _samples_file(tmp_path, make_samples)
    out = tmp_path / "fit"
    assert (
        CliRunner().invoke(cli, ["fit", str(src), "-m", "lambert", "--out", str(out)]).exit_code
        == 0
    )
    old = _snapshot(out)

    def broken(*a, **k):
        raise RuntimeError("disk full while plotting")

    monkeypatch.setattr(plots, "plot_residual_map", broken)
    monkeypatch.setenv("GONIO_PLOT_WORKER", "0")  # the in-process path draws both figures
    res = CliRunner().invoke(cli, ["fit", str(src), "-m", "oren-nayar", "--out", str(out),
                                   "--force"])  # fmt: skip
    assert res.exit_code != 0
    assert _snapshot(out) == old  # fit.json and slices.png of the new fit were staged only
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit", "samples.h5"]


_HOLDER = """
import sys
from gonio.locks import hold_lock
with hold_lock(sys.argv[1], "test"):
    print("held", flush=True)
    sys.stdin.readline()
"""


def test_a_second_fit_into_a_held_output_is_refused_naming_the_pid(tmp_path, make_samples):
    import subprocess
    import sys

    from gonio.cli import main

    src = _samples_file(tmp_path, make_samples)
    out = tmp_path / "fit"
    assert (
        CliRunner().invoke(cli, ["fit", str(src), "-m", "lambert", "--out", str(out)]).exit_code
        == 0
    )
    old = _snapshot(out)
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out / ".gonio.lock")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        with pytest.raises(SystemExit) as e:
            main(["fit", str(src), "-m", "oren-nayar", "--out", str(out), "--force"])
        assert e.value.code == 1
    finally:
        holder.communicate("done\n")
    assert _snapshot(out) == old
    # and once the holder is gone the lock is free again
    res = CliRunner().invoke(cli, ["fit", str(src), "-m", "oren-nayar", "--out", str(out),
                                   "--force"])  # fmt: skip
    assert res.exit_code == 0, res.output


def test_the_refusal_message_names_the_holder(tmp_path, make_samples, capsys):
    import subprocess
    import sys

    from gonio.cli import main

    src = _samples_file(tmp_path, make_samples)
    out = tmp_path / "fit"
    out.mkdir()
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(out / ".gonio.lock")],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        capsys.readouterr()
        with pytest.raises(SystemExit):
            main(["fit", str(src), "-m", "lambert", "--out", str(out)])
        err = " ".join(capsys.readouterr().err.split())
    finally:
        holder.communicate("done\n")
    assert f"error: output {out}/ is in use by process {holder.pid}" in err
    assert sorted(p.name for p in out.iterdir()) == [".gonio.lock"]


def test_fit_prints_the_variance_split_of_samples_with_geometric_modes(
    tmp_path, make_samples, monkeypatch
):
    """Samples with geometric modes (as a reduction with the full budget writes them):
    the summary shows each parameter's share of noise, geometry and calibration, which
    add up to its whole variance; samples without modes print no such table."""
    import dataclasses

    import gonio.fitting.cli as fit_cli

    s = make_samples("lambert+ggx", {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3],
                     "alpha": 0.2}, n=200, seed=1, noise=1e-4, read=1e-3)  # fmt: skip
    s.attrs["calibration_rel_std"] = [0.01, 0.01, 0.01]
    n = len(s)
    modes = np.zeros((n, 1, 6))
    modes[:, 0, 3] = 0.005 * s.wo[:, 2]  # the camera arm tilted (x), 1 sigma
    modes[:, 0, 5] = -0.005 * s.wo[:, 0]
    src = save_samples(tmp_path / "samples.h5", s)
    for with_modes in (True, False):
        m = dataclasses.replace(
            s, geometry_modes=modes, geometry_mode_scope=np.array(["session"]),
            geometry_mode_names=np.array(["arm tilt"]), pose=np.zeros(n, np.int32),
        ) if with_modes else s  # fmt: skip
        monkeypatch.setattr(fit_cli, "_load_input", lambda path, m=m: (m, "samples"))
        out = tmp_path / f"fit{with_modes}"
        res = CliRunner().invoke(
            cli, ["fit", str(src), "-m", "lambert+ggx", "--out", str(out), "--no-plots"]
        )
        assert res.exit_code == 0, res.output
        d = json.loads((out / "fit.json").read_text())
        if not with_modes:
            assert "variance_split" not in d["diagnostics"]
            assert "share of each parameter" not in res.output
            continue
        split = d["diagnostics"]["variance_split"]
        i = split["labels"].index("albedo[G]")
        parts = [split[k][i] for k in ("noise", "geometry", "calibration")]
        assert all(p > 0 for p in parts)
        np.testing.assert_allclose(sum(parts), d["std"]["albedo"][1] ** 2, rtol=1e-9)
        assert "share of each parameter" in res.output
        line = next(x for x in res.output.splitlines() if "albedo[G]" in x)
        shares = [f"{p / sum(parts):.0%}" for p in parts]
        assert all(sh in line for sh in shares), (line, shares)


@pytest.mark.slow
def test_auto_on_an_rgl_file_gives_the_scipy_optimum(tmp_path, rgl_file):
    # Independent reference: the same cosine-L2 objective minimised by scipy's trf from the
    # best point of a fine ln(alpha) grid (variable projection by lsq_linear per point).
    from scipy.optimize import least_squares, lsq_linear

    from gonio.brdf import get_model, load
    from gonio.fitting.losses import get_loss
    from gonio.fitting.objective import prepare_problem
    from gonio.fitting.sampling import sample_brdf

    src = rgl_file("vch_golden_yellow")
    out = tmp_path / "fit"
    res = CliRunner().invoke(cli, ["fit", str(src), "--model", "auto", "--out", str(out)])
    assert res.exit_code == 0, res.output
    d = json.loads((out / "fit.json").read_text())
    assert d["model"] == "lambert+ggx"
    for name in ("slices.png", "residuals.png"):  # slices.png from the plot worker
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    s = sample_brdf(load(src))
    prob = prepare_problem(get_model("lambert+ggx"), s, get_loss("cosine_l2"))
    w = prob.weights

    def grid_cost(alpha):
        f = get_model("lambert+ggx").eval_with_grad(prob.wi, prob.wo, {"alpha": alpha})[1]
        G = np.stack([f["albedo"], f["ks"]], axis=-1)
        return sum(
            lsq_linear(G * w[:, c, None], w[:, c] * prob.y[:, c], bounds=(0, 1)).cost
            for c in range(prob.n_channels)
        )

    alphas = np.exp(np.linspace(np.log(1e-3), 0.0, 120))
    a_best = alphas[int(np.argmin([grid_cost(a) for a in alphas]))]
    x0 = prob.pack(np.array([a_best]), np.full((2, prob.n_channels), 0.3))
    ref = least_squares(
        lambda x: prob.residuals(x).ravel(),
        x0,
        jac=lambda x: prob.dense_jacobian(x)[1],
        bounds=prob.x_bounds(),
        method="trf",
        ftol=1e-14,
        xtol=1e-14,
        gtol=1e-14,
    )
    theta, a = prob.unpack(ref.x)
    np.testing.assert_allclose(d["params"]["alpha"], theta[0], rtol=1e-6)
    for j, name in enumerate(("albedo", "ks")):
        np.testing.assert_allclose(d["params"][name], a[j], rtol=1e-5, atol=1e-8)


def test_a_failing_plot_worker_fails_the_fit_and_keeps_the_old_set(tmp_path, make_samples,
                                                                    monkeypatch):  # fmt: skip
    import gonio.fitting.plots as plots

    src = _samples_file(tmp_path, make_samples)
    out = tmp_path / "fit"
    assert (
        CliRunner().invoke(cli, ["fit", str(src), "-m", "lambert", "--out", str(out)]).exit_code
        == 0
    )
    old = _snapshot(out)

    def broken(*a, **k):
        raise RuntimeError("no fonts")

    monkeypatch.setattr(plots, "slices_png", broken)  # the worker is forked with it
    res = CliRunner().invoke(cli, ["fit", str(src), "-m", "oren-nayar", "--out", str(out),
                                   "--force"])  # fmt: skip
    assert res.exit_code != 0
    assert "drawing slices.png failed: RuntimeError: no fonts" in str(res.exception)
    assert _snapshot(out) == old


def test_the_plot_workers_draw_the_same_pngs_as_this_process(make_samples):
    from gonio.fitting import cli as fit_cli
    from gonio.fitting import fit, plots

    s = make_samples("lambert+ggx", {"albedo": [0.2] * 3, "ks": [0.3] * 3, "alpha": 0.2},
                     n=300, seed=2, noise=1e-4, read=1e-3)  # fmt: skip
    r = fit(s, "lambert+ggx")
    with fit_cli._start_plot_worker() as worker:
        assert worker.active  # Linux
        jobs = [worker.submit(plots.slices_png, r, s), worker.submit(plots.residuals_png, r, s)]
        pngs = [j.result() for j in jobs]
    assert pngs == [plots.slices_png(r, s), plots.residuals_png(r, s)]


def test_a_failing_residual_drawer_is_named(tmp_path, make_samples, monkeypatch):
    import gonio.fitting.plots as plots

    src = _samples_file(tmp_path, make_samples)

    def broken(*a, **k):
        raise ValueError("bad colours")

    monkeypatch.setattr(plots, "residuals_png", broken)  # inherited by the fork
    res = CliRunner().invoke(cli, ["fit", str(src), "-m", "lambert", "--out",
                                   str(tmp_path / "fit")])  # fmt: skip
    assert res.exit_code != 0
    assert "drawing residuals.png failed: ValueError: bad colours" in str(res.exception)
    assert not (tmp_path / "fit" / "fit.json").exists()


def test_fitting_a_measured_file_imports_neither_h5py_nor_numba():
    # start-up is most of `gonio fit FILE.bsdf` (issue 19): what its path imports, in a
    # fresh interpreter (h5py ~0.15 s, numba ~0.5 s of CPU; neither is needed for it)
    import subprocess
    import sys

    code = (
        "import sys, gonio.cli, gonio.fitting.cli, gonio.fitting.sampling, gonio.brdf, "
        "gonio.fitting.fit, gonio.fitting.select, gonio.fitting.export; "
        "print(sorted(m for m in ('h5py', 'numba', 'matplotlib') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
