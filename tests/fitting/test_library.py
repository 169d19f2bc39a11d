"""Material libraries (``gonio fit DIR_OR_GLOB --out LIB/``) on dask.distributed.

The reference is the public fitting API called here, in the test process, on the same
coarse grid of directions: ``gonio.fitting.fit(sample_brdf(load(file), grid), "auto")``.
Every engine (this process, a real ``dask scheduler`` with two ``dask worker`` processes,
a ``LocalCluster``) must give exactly that result, written once per material.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

import gonio.atomic
from gonio.brdf import load
from gonio.cli import run
from gonio.dataset import save_samples
from gonio.fitting import fit
from gonio.fitting.export import result_to_dict
from gonio.fitting.library import FitOptions, find_materials, fit_library
from gonio.fitting.library_summary import read_summary_rows
from gonio.fitting.sampling import sample_brdf
from gonio.locks import LOCK_NAME, LockedError, hold_lock

MATERIALS = ("cc_ibiza_sunset", "colodur_napoli_4f", "paper_white", "vch_golden_yellow")
# The coarse grid spelled out (not taken from the module under test): 5 x 9 x 18 pairs.
COARSE = {"theta_i_deg": (0.0, 20.0, 40.0, 60.0, 80.0), "n_theta_o": 9, "n_phi_o": 18}
OPTIONS = FitOptions(plots=False, sampling="coarse")
CLI_OPTS = ("--model", "auto", "--sampling", "coarse", "--no-plots")
REPO = Path(__file__).resolve().parents[2]


def _json(obj):
    return json.loads(json.dumps(obj))


def _fit_doc(folder: Path) -> dict:
    return json.loads((folder / "fit.json").read_text())


@pytest.fixture(scope="module")
def rgl_folder(tmp_path_factory, rgl_file) -> Path:
    """The 4 shared RGL files, copied (tests change their copies)."""
    d = tmp_path_factory.mktemp("rgl")
    for m in MATERIALS:
        shutil.copy(rgl_file(m), d / f"{m}_rgb.bsdf")
    return d


@pytest.fixture(scope="module")
def reference(rgl_file) -> dict[str, dict]:
    """material -> fit.json content of the fit made directly with the public API, with
    BLAS on one thread as in the workers (``threads_per_worker=1``): a BLAS pool of
    another size sums in another order, and the optimiser's evaluation counts can
    differ by one from roundoff."""
    from threadpoolctl import threadpool_limits

    out = {}
    with threadpool_limits(limits=1):
        for m in MATERIALS:
            s = sample_brdf(load(rgl_file(m)), **COARSE)
            assert len(s.wi) == 810
            out[f"{m}_rgb"] = _json(result_to_dict(fit(s, "auto")))
    return out


@pytest.fixture(scope="module")
def single_process_lib(rgl_folder, tmp_path_factory) -> Path:
    """The library made in this process (``workers=0``: no dask)."""
    lib = tmp_path_factory.mktemp("single") / "LIB"
    report = fit_library(rgl_folder, lib, OPTIONS, workers=0)
    assert sorted(report.fitted) == sorted(f"{m}_rgb" for m in MATERIALS)
    return lib


@pytest.fixture
def count_writes(monkeypatch):
    """Every folder written through gonio.atomic.atomic_directory, in order."""
    written: list[Path] = []
    real = gonio.atomic.atomic_directory

    @contextlib.contextmanager
    def counting(path, **kw):
        with real(path, **kw) as stage:
            yield stage
        written.append(Path(path))

    monkeypatch.setattr(gonio.atomic, "atomic_directory", counting)
    return written


def _assert_matches_reference(lib: Path, reference: dict) -> None:
    for name, ref in reference.items():
        assert _fit_doc(lib / name) == ref, name


# ------------------------------------------------------------------ results identical


def test_single_process_matches_direct_fits(single_process_lib, reference, rgl_folder):
    _assert_matches_reference(single_process_lib, reference)
    rows = {r["material"]: r for r in read_summary_rows(single_process_lib / "summary.parquet")}
    assert sorted(rows) == sorted(reference)
    for name, ref in reference.items():
        row = rows[name]
        assert row["status"] == "fitted" and row["error"] is None
        assert row["source"] == str((rgl_folder / f"{name}.bsdf").resolve())
        assert row["cost"] == ref["cost"] and row["bic"] == ref["diagnostics"]["bic"]
        assert row["n_samples"] == 810
        for p, values in ref["params"].items():
            for c, v, s in zip(ref["channels"], values, ref["std"][p], strict=True):
                assert row[f"param.{p}.{c}"] == v and row[f"sigma.{p}.{c}"] == s
        sel = json.loads(row["selection"])
        assert [s["model"] for s in sel] == [s["model"] for s in ref["diagnostics"]["selection"]]
    # the CSV holds the same table (floats written to round-trip)
    import csv

    with open(single_process_lib / "summary.csv", newline="") as fh:
        csv_rows = {r["material"]: r for r in csv.DictReader(fh)}
    for name, row in rows.items():
        assert float(csv_rows[name]["cost"]) == row["cost"]
        assert csv_rows[name]["model"] == row["model"]


@pytest.mark.slow
def test_real_cluster_matches_single_process(
    dask_cluster, rgl_folder, single_process_lib, reference, tmp_path, count_writes
):
    address, _ = dask_cluster
    lib = tmp_path / "LIB"
    report = fit_library(rgl_folder, lib, OPTIONS, scheduler=address)
    assert sorted(report.fitted) == sorted(reference) and not report.failed
    for name in reference:
        for f in ("fit.json", "material.xml"):
            assert (lib / name / f).read_bytes() == (single_process_lib / name / f).read_bytes()
    _assert_matches_reference(lib, reference)
    assert sorted(count_writes) == sorted(lib / n for n in reference)


@pytest.mark.slow
def test_local_cluster_cli_unreadable_file(rgl_folder, reference, tmp_path, capsys):
    """The default engine (a LocalCluster) through the CLI; a corrupt file in the folder
    is named, the others are fitted (as the direct fits), the exit code is 1 and the
    summary lists the failure."""
    src = tmp_path / "src"
    shutil.copytree(rgl_folder, src)
    bad = src / "broken" / "scratched_rgb.bsdf"
    bad.parent.mkdir()
    bad.write_bytes(b"tensor_file? no: a few bytes of something else\n")
    lib = tmp_path / "LIB"
    assert run("fit", str(src), "--out", str(lib), "--workers", "2", *CLI_OPTS) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "error:" in err and "Traceback" not in err
    _assert_matches_reference(lib, reference)
    rows = {r["material"]: r for r in read_summary_rows(lib / "summary.parquet")}
    assert rows["broken__scratched_rgb"]["status"] == "failed"
    assert str(bad) in rows["broken__scratched_rgb"]["error"]
    assert not (lib / "broken__scratched_rgb").exists()
    assert {rows[n]["status"] for n in reference} == {"fitted"}


# ------------------------------------------------------------------ faults


@pytest.mark.slow
def test_worker_killed_mid_run(dask_cluster, rgl_folder, reference, tmp_path, count_writes):
    """SIGKILL of a worker process while it fits: the run finishes, its task is redone
    (the scheduler's story shows it processing twice), each material written once."""
    address, watcher = dask_cluster
    killed: dict[str, object] = {}

    def kill_a_busy_worker(client):
        pids = client.run(os.getpid)
        deadline = time.monotonic() + 120
        # wait (on the scheduler's state) for a worker to hold a task, then kill it
        while time.monotonic() < deadline:
            busy = {w: keys for w, keys in watcher.processing().items() if keys}
            if busy:
                worker, keys = sorted(busy.items())[0]
                os.kill(pids[worker], signal.SIGKILL)
                killed.update(worker=worker, keys=list(keys))
                return
            time.sleep(0.02)

    import threading

    def on_client(client):
        threading.Thread(target=kill_a_busy_worker, args=(client,), daemon=True).start()

    lib = tmp_path / "LIB"
    report = fit_library(rgl_folder, lib, OPTIONS, scheduler=address, on_client=on_client)
    assert killed, "no worker was seen busy"
    assert not report.failed and sorted(report.fitted) == sorted(reference)
    _assert_matches_reference(lib, reference)
    assert sorted(count_writes) == sorted(lib / n for n in reference)  # once each
    assert sorted(report.written) == sorted(set(report.written))
    story = watcher.story(*killed["keys"])
    for key in killed["keys"]:
        # entries (source, key, start, finish, ...): the task went to processing again
        starts = [t for t in story if t[0] == "scheduler" and t[1] == key and t[3] == "processing"]
        assert len(starts) >= 2, (key, story)
    watcher.wait_for_workers(2, timeout=120)  # the nanny restarts the killed worker


def test_unreachable_scheduler_cli(rgl_folder, tmp_path, capsys):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"  # nothing listens there
    lib = tmp_path / "LIB"
    code = run(
        "fit", str(rgl_folder), "--out", str(lib), "--scheduler", address,
        "--connect-timeout", "1", *CLI_OPTS,
    )  # fmt: skip
    assert code == 1
    err = capsys.readouterr().err
    assert address in err and "error:" in err and "Traceback" not in err
    assert not lib.exists()  # before any work: nothing created


@pytest.mark.slow
def test_ctrl_c_leaves_no_worker(rgl_folder, tmp_path):
    """SIGINT to the CLI process while its local cluster fits: exit 130, and none of its
    worker processes is left.  Six copies of each file (24 materials, standard grid), so
    the run is still fitting when the signal arrives (4 fits can be over by then)."""
    lib = tmp_path / "LIB"
    many = tmp_path / "many"
    many.mkdir()
    for f in sorted(rgl_folder.glob("*.bsdf")):
        for k in range(6):
            shutil.copy(f, many / f"{f.stem}_{k}.bsdf")
    rgl_folder = many
    proc = subprocess.Popen(
        [sys.executable, "-m", "gonio", "fit", str(rgl_folder), "--out", str(lib),
         "--workers", "2", "--no-plots"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200"},
        # SIGINT at its default, as in a terminal: a test runner's worker may have it
        # ignored, and an ignored SIGINT is inherited (Python then installs no
        # KeyboardInterrupt handler: in the suite the run went on to exit 0)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    try:
        for line in proc.stdout:  # wait for the tasks to be submitted
            if line.startswith("fitting 24 material(s)"):
                break
        else:
            pytest.fail(f"no start line; stderr: {proc.stderr.read()}")
        children = psutil.Process(proc.pid).children(recursive=True)
        workers = [p for p in children if "spawn_main" in " ".join(p.cmdline())]
        assert len(workers) >= 2, [p.cmdline() for p in children]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    # 130 from gonio's handler; on a loaded machine the interpreter was seen (1 run in
    # 5) to end by the signal itself after "aborted", i.e. after the cleanup ran: the
    # shell reports 130 for both
    assert proc.returncode in (130, -signal.SIGINT), err
    assert ("aborted" in err or "interrupted" in err) and "Traceback" not in err, err
    # the workers are gone when the CLI has exited ...
    left = []
    for p in workers:
        with contextlib.suppress(psutil.NoSuchProcess):
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                left.append((p.pid, p.status()))
    assert left == [], err
    # ... and multiprocessing's resource tracker ends by itself once its parent has gone
    _, alive = psutil.wait_procs(children, timeout=30)
    assert [p.pid for p in alive if p.status() != psutil.STATUS_ZOMBIE] == []
    # whatever was written is a whole material; no half-written folder or temporary
    if lib.exists():
        assert gonio.atomic.stale_temporaries(lib) == []
        for d in lib.iterdir():
            if d.is_dir():
                assert (d / "fit.json").is_file() and (d / "input.json").is_file()


# ------------------------------------------------------------------ reruns, locks


def test_rerun_skips_unchanged_refits_changed(
    single_process_lib, rgl_folder, reference, tmp_path, count_writes
):
    src = tmp_path / "src"
    shutil.copytree(rgl_folder, src)
    lib = tmp_path / "LIB"
    shutil.copytree(single_process_lib, lib)
    inodes = {n: (lib / n / "fit.json").stat().st_ino for n in reference}
    r1 = fit_library(src, lib, OPTIONS, workers=0)
    assert sorted(r1.skipped) == sorted(reference) and r1.fitted == [] and count_writes == []
    assert {n: (lib / n / "fit.json").stat().st_ino for n in reference} == inodes
    assert {r["status"] for r in read_summary_rows(lib / "summary.parquet")} == {"unchanged"}
    # one input changes: colodur's file now holds paper white's bytes
    shutil.copy(src / "paper_white_rgb.bsdf", src / "colodur_napoli_4f_rgb.bsdf")
    r2 = fit_library(src, lib, OPTIONS, workers=0)
    assert r2.fitted == ["colodur_napoli_4f_rgb"] and len(r2.skipped) == 3
    assert count_writes == [lib / "colodur_napoli_4f_rgb"]
    assert _fit_doc(lib / "colodur_napoli_4f_rgb") == reference["paper_white_rgb"]
    rows = {r["material"]: r["status"] for r in read_summary_rows(lib / "summary.parquet")}
    assert rows["colodur_napoli_4f_rgb"] == "fitted" and rows["paper_white_rgb"] == "unchanged"
    # other fit options: every material is refitted
    r3 = fit_library(src, lib, FitOptions(model="lambert", plots=False, sampling="coarse"),
                     workers=0)  # fmt: skip
    assert sorted(r3.fitted) == sorted(reference)
    assert {_fit_doc(lib / n)["model"] for n in reference} == {"lambert"}


def test_second_writer_refused(single_process_lib, rgl_folder, tmp_path):
    lib = tmp_path / "LIB"
    shutil.copytree(single_process_lib, lib)
    before = {p: p.read_bytes() for p in lib.rglob("*") if p.is_file() and p.name != LOCK_NAME}
    with hold_lock(lib / LOCK_NAME, "the other writer"):
        with pytest.raises(LockedError, match=str(os.getpid())):
            fit_library(rgl_folder, lib, OPTIONS, workers=0, force=True)
    after = {p: p.read_bytes() for p in lib.rglob("*") if p.is_file() and p.name != LOCK_NAME}
    assert after == before


@pytest.mark.slow
def test_samples_files_same_as_single_fit(tmp_path, make_samples, capsys):
    """A session's samples.h5 in a library gets the files a single `gonio fit` writes,
    with the same fit (the library with plots, the single fit without: plots are slow)."""
    s = make_samples(
        "lambert+ggx", {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.2},
        n=200, seed=1, noise=1e-4, read=1e-3,
    )  # fmt: skip
    sessions = tmp_path / "sessions"
    save_samples(sessions / "S1" / "samples.h5", s)
    single = tmp_path / "single"
    assert run("fit", str(sessions / "S1" / "samples.h5"), "-m", "lambert+ggx",
               "--out", str(single), "--no-plots") == 0  # fmt: skip
    lib = tmp_path / "LIB"
    assert run("fit", str(sessions / "*" / "samples.h5"), "-m", "lambert+ggx",
               "--out", str(lib), "--workers", "0") == 0  # fmt: skip
    fitted = {p.name for p in (lib / "S1").iterdir()}
    plots = {"slices.png", "residuals.png"}
    assert fitted == {p.name for p in single.iterdir() if p.name != LOCK_NAME} | plots | {
        "input.json"
    }
    for name in plots:
        assert (lib / "S1" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert _fit_doc(lib / "S1") == _fit_doc(single)
    assert (lib / "S1" / "material.xml").read_bytes() == (single / "material.xml").read_bytes()
    record = json.loads((lib / "S1" / "input.json").read_text())
    assert record["kind"] == "samples" and record["options"]["plots"] is True
    # the grid of measured files does not concern a session: still up to date
    capsys.readouterr()
    assert run("fit", str(sessions), "-m", "lambert+ggx", "--out", str(lib), "--workers", "0",
               "--sampling", "coarse") == 0  # fmt: skip
    assert "1 material(s) unchanged" in capsys.readouterr().out


def test_a_merl_file_is_fitted_to_its_closed_form(tmp_path):
    """A MERL ``.binary`` in the library's folder is found and fitted like the RGL files:
    a table written with ``write_merl`` whose every bin holds a lambertian rho / pi (the
    closed form, stored as value / channel scale) gives lambert with albedo rho, and its
    input record names the file."""
    from gonio.brdf.merl import DIMS, MERLBRDF, SCALES, write_merl

    rho = np.array([0.7, 0.5, 0.3])
    src = tmp_path / "src"
    src.mkdir()
    raw = np.broadcast_to((rho / np.pi / SCALES)[:, None, None, None], (3, *DIMS))
    write_merl(src / "matte.binary", MERLBRDF(raw))
    lib = tmp_path / "LIB"
    options = FitOptions(model="lambert", plots=False, sampling="coarse")
    report = fit_library(src, lib, options, workers=0)
    assert report.fitted == ["matte"] and not report.failed
    doc = _fit_doc(lib / "matte")
    assert doc["model"] == "lambert"
    np.testing.assert_allclose(doc["params"]["albedo"], rho, rtol=1e-6)
    record = json.loads((lib / "matte" / "input.json").read_text())
    assert record["kind"] == "measured" and record["source"] == str(src / "matte.binary")


def test_unknown_model_refused_before_work(rgl_folder, tmp_path, capsys):
    lib = tmp_path / "LIB"
    assert run("fit", str(rgl_folder), "-m", "lambert+ggz", "--out", str(lib)) == 1
    assert "'ggz'" in capsys.readouterr().err
    assert not lib.exists()


# ------------------------------------------------------------------ inputs


def test_find_materials_names_and_rejects(tmp_path):
    (tmp_path / "a" / "S1").mkdir(parents=True)
    (tmp_path / "a" / "S1" / "samples.h5").write_bytes(b"x")
    (tmp_path / "a" / "x.bsdf").write_bytes(b"x")
    (tmp_path / "a" / "x.binary").write_bytes(b"x")  # the same name as x.bsdf
    (tmp_path / "a" / ".hidden.bsdf").write_bytes(b"x")
    (tmp_path / "a" / "notes.txt").write_text("x")
    (tmp_path / "samples.h5").write_bytes(b"x")
    found, rejected = find_materials(tmp_path / "a")
    names = [m.name for m in found]
    assert names[0] == "S1" and len(names) == 3
    assert all(n.startswith("x-") for n in names[1:]) and names[1] != names[2]
    assert rejected == []
    found, rejected = find_materials(str(tmp_path / "a" / "*"))
    assert [p.name for p, _ in rejected] == ["notes.txt"]
    assert {m.kind for m in found} == {"samples", "measured"}
    found, _ = find_materials(tmp_path, exclude=(tmp_path / "a").resolve())
    assert [m.name for m in found] == [tmp_path.name]  # samples.h5 at the root
    with pytest.raises(Exception, match="no samples.h5"):
        find_materials(tmp_path / "a" / "S1" / "*.bsdf")


def test_library_options_refused_for_one_file(rgl_file, tmp_path):
    code = run("fit", str(rgl_file("paper_white")), "--out", str(tmp_path / "o"),
               "--workers", "2")  # fmt: skip
    assert code == 2 and not (tmp_path / "o").exists()
