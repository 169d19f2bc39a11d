"""Bad input found by the audit of 2026-12-07, through the top-level CLI: a clear error
naming the option or file, a non-zero exit, nothing already on disk replaced.

Covered beside their subsystems: the reduction's outputs (tests/capture/test_reduce.py),
the serial port's lock (tests/rig/test_transport_lock.py)."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.cli import run
from gonio.dataset import BRDFSamples, save_samples


@pytest.fixture
def samples_file(tmp_path):
    rng = np.random.default_rng(0)
    t, p = rng.uniform(0, 1.2, (2, 200)), rng.uniform(0, 6.28, (2, 200))

    def d(k):
        return np.stack([np.sin(t[k]) * np.cos(p[k]), np.sin(t[k]) * np.sin(p[k]), np.cos(t[k])], 1)

    path = tmp_path / "ok.h5"
    brdf = np.full((200, 3), 0.16)
    save_samples(path, BRDFSamples(wi=d(0), wo=d(1), brdf=brdf, brdf_std=np.full((200, 3), 0.01)))
    return path


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["-m", "lambert+ggx[fresnel=schlick]", "--option", "fresnel=dielectric"], "give it once"),
        (["-m", "lambert+ggx[fresnel=schlick,fresnel=none]"], "given twice"),
        (["-m", "lambert", "--candidates", "lambert,ggx"], "--candidates chooses"),
        (["--candidates", ""], "at least one model"),
        (["-m", "lambert", "--f-scale", "2"], "give --robust too"),
        (["-m", "lambert", "--robust", "huber", "--f-scale", "1e308"], "at most 1e+06"),
    ],
)
def test_fit_options_that_contradict_or_do_nothing_are_refused(
    samples_file, tmp_path, capsys, args, words
):
    code = run("fit", str(samples_file), *args, "--no-plots", "--out", str(tmp_path / "f"))
    assert code in (1, 2)
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err
    assert not (tmp_path / "f").exists()


def test_fit_out_is_not_the_current_folder(samples_file, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    for out in (".", str(tmp_path)):
        assert run("fit", str(samples_file), "-m", "lambert", "--no-plots", "--out", out) == 1
        assert "the current folder" in capsys.readouterr().err
    assert run("fit", str(samples_file), "-m", "lambert", "--no-plots", "--out", "sub") == 0
    assert (tmp_path / "sub" / "fit.json").is_file() and (tmp_path / "ok.h5").is_file()


def test_a_library_does_not_replace_files_no_library_fit_wrote(samples_file, tmp_path, capsys):
    lib = tmp_path / "lib" / "m"
    lib.mkdir(parents=True)
    (lib / "samples.h5").write_bytes(samples_file.read_bytes())
    out = tmp_path / "out"
    (out / "m").mkdir(parents=True)
    (out / "summary.csv").write_text("precious")
    (out / "m" / "fit.json").write_text("precious")
    args = ["fit", str(tmp_path / "lib"), "-m", "lambert", "--no-plots", "--workers", "0"]
    assert run(*args, "--out", str(out)) == 1
    err = capsys.readouterr().err
    assert "no library fit wrote them" in err and "summary.csv" in err
    assert (out / "summary.csv").read_text() == "precious"
    assert (out / "m" / "fit.json").read_text() == "precious"
    # a library's own earlier outputs are its to update
    assert run(*args, "--out", str(tmp_path / "new")) == 0
    assert run(*args, "--out", str(tmp_path / "new")) == 0
    assert run(*args, "--out", str(out), "--force") == 0
    assert (out / "summary.csv").read_text() != "precious"


@pytest.mark.parametrize(
    "argv",
    [
        ["sim", "bus", "--seed", "-1"],
        ["sim", "bus", "--time-scale", "1e308"],
        ["calibrate", "plan", "--kind", "rig", "--out", "{tmp}/p.toml", "--seed", "-5"],
        ["demo", "--seed", "-1", "--out", "{tmp}/d"],
        ["demo", "--sim-speed", "1e308", "--out", "{tmp}/d"],
    ],
)
def test_out_of_range_seeds_and_speeds_are_usage_errors(tmp_path, capsys, argv):
    code = run(*[a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert code == 2
    err = capsys.readouterr().err
    assert "--seed" in err or "--time-scale" in err or "--sim-speed" in err
    assert "Traceback" not in err and not (tmp_path / "d").exists()


def test_two_outputs_naming_one_file_are_refused(tmp_path, capsys):
    from gonio.cli import distinct_outputs

    with pytest.raises(Exception, match="--truth and --preview name the same file"):
        distinct_outputs(("--out", tmp_path / "r.dng"), ("--truth", tmp_path / "t.png"),
                         ("--preview", tmp_path / "./t.png"))  # fmt: skip
    distinct_outputs(("--out", tmp_path / "a"), ("--plot", None), ("--truth", tmp_path / "b"))


def test_a_fit_error_names_the_input_file(tmp_path, capsys):
    """Nothing to fit (every BRDF value 0): the error names the file given, not only
    the dataset (a MERL file of zeros said "samples.brdf: all ... zero")."""
    rng = np.random.default_rng(1)
    w = rng.normal(size=(50, 3)) + [0, 0, 3]
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    path = tmp_path / "zeros.h5"
    save_samples(path, BRDFSamples(wi=w, wo=w[::-1], brdf=np.zeros((50, 3)),
                                   brdf_std=np.full((50, 3), 0.01)))  # fmt: skip
    assert run("fit", str(path), "-m", "lambert", "--no-plots", "--out", str(tmp_path / "f")) == 1
    err = capsys.readouterr().err
    assert str(path) in err and "zero" in err and "Traceback" not in err
