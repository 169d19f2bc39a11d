"""``gonio capture reduce`` on a whole simulated session, and what bad input does to it."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tomllib

import numpy as np
import pytest
import rawpy
import tomli_w
import xxhash
from sim_sessions import (
    REFERENCE_NORMAL,
    REFERENCE_OBLIQUE,
    capture,
    grid_plan,
    scene_toml,
    write_inputs,
)

from gonio.app.sim_reduction import write_reduction_toml
from gonio.capture.journal import read_journal
from gonio.cli import run
from gonio.dataset import Flag, load_samples

pytestmark = pytest.mark.slow  # captures a simulated session (virtual bus, renders)

ALBEDO = np.array([0.6, 0.5, 0.4])

PLAN_ARGS = dict(
    seed=5,
    theta_i_deg=[20, 40],
    theta_o_deg=[30, 50],
    references=[REFERENCE_NORMAL, REFERENCE_OBLIQUE],
)
PLAN = grid_plan("reduce-test", darks=2, **PLAN_ARGS)
SCENE = scene_toml(resolution=(400, 300))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A simulated session: real dynamixel-sdk on the virtual bus, rendered DNGs."""
    d = tmp_path_factory.mktemp("reduce")
    write_inputs(d, PLAN, SCENE)
    capture(d)
    # written at capture time from the camera; the manifest's scene must give the same
    # setup (write_reduction_toml refuses a different file)
    write_reduction_toml(d / "S")
    return d / "S"


def copy_session(src, dst):
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("samples.*", "reduction.json"))
    return dst


def raw_hashes(s):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in (s / "raw").iterdir()}


def replace_frame(s, rel, data):
    """Put other bytes in a frame *and* its journal record, as if the camera sent them."""
    (s / rel).write_bytes(data)
    lines = []
    for line in (s / "journal.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r.get("file") == rel:
            r["sha256"] = hashlib.sha256(data).hexdigest()
            r["xxh3_128"] = xxhash.xxh3_128_hexdigest(data)
            r["bytes"] = len(data)
        lines.append(json.dumps(r))
    (s / "journal.jsonl").write_text("\n".join(lines) + "\n")


def dng_like(path, *, pattern=None, value=None):
    """A DNG with another frame's mosaic (or a constant), written by the simulator."""
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.sensor import RawFrame as SimFrame

    with rawpy.imread(str(path)) as r:
        mosaic = r.raw_image_visible.copy()
    if value is not None:
        mosaic[:] = value
    return dng_bytes(
        SimFrame(
            mosaic, pattern or "RGGB", 512, 16383, np.eye(3), np.ones(3), 0.001, 8.0, 100.0, 0.016
        )
    )


def sample_files(s, pose=None):
    recs = [
        r
        for r in read_journal(s / "journal.jsonl")
        if r.get("type") == "shot" and r["kind"] == "sample"
    ]
    poses = sorted({r["pose"] for r in recs})
    p = poses[0] if pose is None else pose
    return [r["file"] for r in recs if r["pose"] == p], p


def test_reduce_cli_gives_calibrated_lambertian_samples(session, tmp_path):
    s = copy_session(session, tmp_path / "S")
    before = raw_hashes(s)
    assert run("capture", "reduce", str(s), "--quiet") == 0
    assert raw_hashes(s) == before  # RAW files untouched
    samples = load_samples(s / "samples.h5")
    assert len(samples) == 4 * 9 and samples.valid.all()
    truth = ALBEDO / np.pi  # a Lambertian BRDF, closed form
    rel = np.abs(samples.brdf / truth - 1)
    # the noise term against the closed form; the whole budget holds the type-B terms of
    # what this session did not shoot (no flats: the stated 1 % PRNU per pixel), so it
    # may only be wider than the error, never narrower
    z = (samples.brdf - truth) / samples.budget["noise"]
    z_all = (samples.brdf - truth) / samples.brdf_std
    print(f"median rel err {np.median(rel):.2e}, z mean {z.mean():+.2f} std {z.std():.2f}")
    assert np.median(rel) <= 0.01
    assert 0.8 <= z.std() <= 1.25
    assert z_all.std() <= 1.25
    # the directions reported are those of the regions, close to the rig's
    recs = [r for r in read_journal(s / "journal.jsonl") if r.get("kind") == "sample"]
    wo_rig = np.array([r["wo_achieved"] for r in recs])
    ang = np.degrees(np.arccos(np.clip(samples.wo @ wo_rig.T, -1, 1))).min(axis=1)
    assert ang.max() < 3.0  # regions sit within ~1.5 cm of the centre at 0.4 m
    assert samples.frames[0].startswith("raw/") and samples.frames[0].endswith(".dng")
    summary = json.loads((s / "reduction.json").read_text())
    assert summary["kept"] == 36 and summary["reference_poses"] == 2
    assert (s / "samples.png").stat().st_size > 1000
    assert (s / "samples.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # radiance and irradiance are camera units, and say so; their ratio is the BRDF
    import h5py

    from gonio.capture.reduce import IRRADIANCE_UNITS, RADIANCE_UNITS

    with h5py.File(s / "samples.h5") as f:
        assert f["radiance"].attrs["units"] == RADIANCE_UNITS
        assert f["irradiance"].attrs["units"] == IRRADIANCE_UNITS
        assert "W/" not in RADIANCE_UNITS + IRRADIANCE_UNITS
        assert f["brdf"].attrs["units"] == "1/sr"
    np.testing.assert_allclose(samples.radiance / samples.irradiance, samples.brdf, rtol=1e-12)


def test_reduce_twice_gives_the_same_file(session, tmp_path):
    s = copy_session(session, tmp_path / "S")
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    first = (s / "samples.h5").read_bytes()
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    assert (s / "samples.h5").read_bytes() == first


def test_direct_dng_reading_gives_libraws_samples(session, tmp_path, monkeypatch):
    """The simulator's DNGs are read without LibRaw's unpack (gonio.capture.plain_dng):
    the samples must be those of LibRaw's decoding (GONIO_DIRECT_DNG=0), byte for byte."""
    from gonio.capture.plain_dng import read_plain_dng
    from gonio.capture.reduce import reduce_session

    s = copy_session(session, tmp_path / "S")
    files, _ = sample_files(s)
    assert read_plain_dng((s / files[0]).read_bytes()) is not None  # the direct path ran
    monkeypatch.delenv("GONIO_DIRECT_DNG", raising=False)
    reduce_session(s, out=tmp_path / "direct.h5", plot=False, threads=1)
    monkeypatch.setenv("GONIO_DIRECT_DNG", "0")
    reduce_session(s, out=tmp_path / "libraw.h5", plot=False, threads=1)
    assert (tmp_path / "direct.h5").read_bytes() == (tmp_path / "libraw.h5").read_bytes()


def test_board_detection_ahead_in_the_worker(session, tmp_path, monkeypatch):
    """With two threads the next poses' boards are found in the loader's worker, with
    their decoding (pose_measure.detect_board); the samples are those of one thread,
    and a pose queued that way hands back what its job computed."""
    import threading

    import gonio.capture.pose_measure as pm
    import gonio.capture.reduce as red
    from gonio.capture.frame_loader import FrameLoader

    s = copy_session(session, tmp_path / "S")
    where = []
    detect = red.detect_board

    def recorded(*a, **kw):
        where.append(threading.current_thread().name)
        return detect(*a, **kw)

    monkeypatch.setattr(red, "detect_board", recorded)  # ahead, in the loader's worker
    monkeypatch.setattr(pm, "detect_board", recorded)  # in measure_pose
    red.reduce_session(s, out=tmp_path / "one.h5", plot=False, threads=1)
    assert where and not any(w.startswith("gonio-reduce") for w in where)
    where.clear()
    red.reduce_session(s, out=tmp_path / "two.h5", plot=False, threads=2)
    assert any(w.startswith("gonio-reduce") for w in where)  # some ran ahead
    assert (tmp_path / "one.h5").read_bytes() == (tmp_path / "two.h5").read_bytes()
    recs = [r for r in read_journal(s / "journal.jsonl") if r.get("type") == "shot"][:2]
    started = threading.Event()

    def then(results):
        started.set()
        return [fr is not None for fr, _ in results]

    with FrameLoader(s, None, 2) as loader:
        loader.prefetch_pose(recs, then)
        assert started.wait(60)
        results, value = loader.pose_results(recs)
        assert value == [True, True] and all(fr is not None for fr, _ in results)
        assert loader.pose_results(recs)[1] is None  # not queued (any more): done here
    with FrameLoader(s, None, 1) as loader:  # one thread: nothing runs ahead
        loader.prefetch_pose(recs, then)
        assert loader.pose_results(recs)[1] is None


@pytest.mark.parametrize("threads", [1, 2])
def test_threads_give_the_same_file_and_a_changed_byte_is_caught(session, tmp_path, threads):
    """Frames are decoded in worker threads while poses are measured: the output must not
    depend on it, and the journal's digest check must still see one flipped pixel byte
    (XXH3-128; sha256 for a journal written before XXH3 was recorded)."""
    from gonio.capture.reduce import reduce_session

    s = copy_session(session, tmp_path / "S")
    reduce_session(s, out=tmp_path / "one.h5", plot=False, threads=1)
    reduce_session(s, out=tmp_path / "two.h5", plot=False, threads=2)
    assert (tmp_path / "one.h5").read_bytes() == (tmp_path / "two.h5").read_bytes()
    files, _ = sample_files(s)
    data = bytearray((s / files[0]).read_bytes())
    data[-1000] ^= 0x01  # a pixel's lowest bit: the decode alone cannot tell
    (s / files[0]).write_bytes(bytes(data))
    res = reduce_session(s, plot=False, threads=threads)
    assert "XXH3-128 digest differs from the journal" in res.summary["frame_problems"][files[0]]
    # an older journal has only the sha256: that is checked instead
    journal = s / "journal.jsonl"
    old = [json.loads(ln) for ln in journal.read_text().splitlines()]
    assert any("xxh3_128" in r for r in old)
    journal.write_text("".join(json.dumps(r | {"xxh3_128": None}) + "\n" for r in old))
    res = reduce_session(s, plot=False, threads=threads)
    assert "sha256 differs from the journal" in res.summary["frame_problems"][files[0]]
    samples = load_samples(res.path)
    rows = [k for k, fr in enumerate(samples.frames) if files[0] in fr.split(";")]
    if len(files) == 1:  # the pose has no other frame: its samples are invalid
        assert rows and (samples.flags[rows] & Flag.INVALID).all()
    else:  # measured without the changed frame
        assert not rows


def test_bad_frames_are_reported_and_their_samples_flagged(session, tmp_path, capsys):
    s = copy_session(session, tmp_path / "S")
    files_a, pose_a = sample_files(s)
    poses = sorted(
        {r["pose"] for r in read_journal(s / "journal.jsonl") if r.get("kind") == "sample"}
    )
    files_b, pose_b = sample_files(s, poses[1])
    files_c, pose_c = sample_files(s, poses[2])
    files_d, pose_d = sample_files(s, poses[3])
    # a: truncated after capture (the journal's byte count no longer matches)
    for f in files_a:
        data = (s / f).read_bytes()
        (s / f).write_bytes(data[: len(data) // 2])
    # b: the camera delivered a GRBG frame in an RGGB session
    for f in files_b:
        replace_frame(s, f, dng_like(s / f, pattern="GRBG"))
    # c: an all-saturated bracket
    for f in files_c:
        replace_frame(s, f, dng_like(s / f, value=16383))
    # d: frames in which the board cannot be seen (the light was off: dark frames)
    dark = next(r["file"] for r in read_journal(s / "journal.jsonl") if r.get("kind") == "dark")
    for f in files_d:
        replace_frame(s, f, (s / dark).read_bytes())
    assert run("capture", "reduce", str(s)) == 0
    out = capsys.readouterr().err
    samples = load_samples(s / "samples.h5")
    summary = json.loads((s / "reduction.json").read_text())
    problems = summary["frame_problems"]
    assert all("bytes, the journal recorded" in problems[f] for f in files_a)
    assert all("CFA pattern is GRBG" in problems[f] and "RGGB" in problems[f] for f in files_b)
    failed = {fp["pose"]: fp["reason"] for fp in summary["failed_poses"]}
    assert pose_a in failed and pose_b in failed and "no decodable frame" in failed[pose_b]
    by_pose = {}
    for k, fr in enumerate(samples.frames):
        pose = int(fr.split("/p")[1][:4])
        by_pose.setdefault(pose, []).append(k)
    for p in (pose_a, pose_b):
        assert (samples.flags[by_pose[p]] & Flag.INVALID).all()
    assert (samples.flags[by_pose[pose_c]] & Flag.SATURATED).all()
    assert np.isnan(samples.brdf[by_pose[pose_c]]).all()
    # no board: with geometry "auto" (the default) the rig's pose stands in, not flagged
    # for it (these dark frames are underexposed anyway) ...
    assert not (samples.flags[by_pose[pose_d]] & Flag.GEOMETRY_MISMATCH).any()
    assert (samples.flags[by_pose[pose_d]] & Flag.UNDEREXPOSED).all()
    assert samples.valid.sum() == 0
    assert "rejected: saturated" in out and f"wrote {s / 'samples.h5'}" in out
    # ... with "board" it stands in too, and the samples say the board was lost
    board = tmp_path / "board.h5"
    assert run("capture", "reduce", str(s), "--geometry", "board", "--out", str(board)) == 0
    flags = load_samples(board).flags
    assert (flags[by_pose[pose_d]] & Flag.GEOMETRY_MISMATCH).all()


def test_no_reference_and_not_a_session_are_clear_errors(session, tmp_path, capsys):
    s = copy_session(session, tmp_path / "S")
    lines = [
        ln
        for ln in (s / "journal.jsonl").read_text().splitlines()
        if json.loads(ln).get("kind") != "reference"
    ]
    (s / "journal.jsonl").write_text("\n".join(lines) + "\n")
    (s / "samples.h5").write_bytes(b"keep me")
    # a file at the default output that no reduction wrote is refused up front
    assert run("capture", "reduce", str(s), "--quiet") == 1
    assert "samples.h5 exists and is not a gonio samples file" in capsys.readouterr().err
    # allowed to replace it, the reduction fails before writing anything
    assert run("capture", "reduce", str(s), "--quiet", "--force") == 1
    assert "no reference-target frames" in capsys.readouterr().err
    assert (s / "samples.h5").read_bytes() == b"keep me"  # nothing overwritten
    (tmp_path / "empty").mkdir()
    assert run("capture", "reduce", str(tmp_path / "empty")) == 1
    assert "not a session directory" in capsys.readouterr().err


def test_lab_session_with_reduction_toml_and_noise_json(session, tmp_path):
    """A real camera's session has no simulated scene: the camera matrix, board, sample
    size and light come from SESSION/reduction.toml, the noise model from noise.json."""
    s = copy_session(session, tmp_path / "S")
    manifest = json.loads((s / "manifest.json").read_text())
    manifest["simulation"] = None
    (s / "manifest.json").write_text(json.dumps(manifest))
    f = 0.5 * 400 / np.tan(np.radians(15.0))  # fov 30 deg over 400 pixels
    (s / "reduction.toml").write_text(f"""
[camera]
K = [[{f}, 0, 199.5], [0, {f}, 149.5], [0, 0, 1]]
cfa_pattern = "RGGB"
width = 400
height = 300
[noise]
file = "noise.json"
[board]
squares_x = 7
squares_y = 7
square_length = 0.02
marker_length = 0.015
dictionary = "DICT_4X4_50"
[sample]
width = 0.05
height = 0.05
[light]
radius = 0.01
[reduction]
grid = 2
""")
    (s / "noise.json").write_text('{"gain": 0.4, "read_noise": 1.2, "iso": 100}')
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    samples = load_samples(s / "samples.h5")
    assert len(samples) == 4 * 4 and samples.valid.all()
    assert np.median(np.abs(samples.brdf / (ALBEDO / np.pi) - 1)) <= 0.01
    (s / "reduction.toml").write_text("[camera]\nK = [[1, 0], [0, 1]]\n")
    assert run("capture", "reduce", str(s), "--quiet") == 1


def test_reference_reflectance_of_the_plan_is_what_the_simulated_camera_renders(tmp_path):
    """A plan whose reference target has reflectance 0.5: the simulated camera must render
    the target at 0.5 (not its 0.99 default), else the reduction, which calibrates with
    the manifest's 0.5, reports the sample's BRDF about half the truth.  The session is
    captured the way ``gonio capture run`` does it (the session API with the composition
    root's device opener), which hands the plan's reflectance to the camera."""
    import tomllib

    from gonio.app.devices import device_opener
    from gonio.capture.plan import load_plan
    from gonio.capture.reduce import reduce_session
    from gonio.capture.sessions import run_session
    from gonio.rig.config import load_rig_config

    plan_text = grid_plan("reduce-test", darks=0, reflectance=0.5, **PLAN_ARGS)
    write_inputs(tmp_path, plan_text)
    plan = load_plan(tmp_path / "plan.toml")
    assert plan.reference.reflectance == 0.5
    cfg = load_rig_config(tmp_path / "rig.toml")
    simulation = {"scene": tomllib.loads(SCENE), "width": None, "height": None, "time_scale": 100}
    out = tmp_path / "S"
    run_session(out, plan, cfg, device_opener(), camera_backend="simulated", simulation=simulation)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["reference"]["reflectance"] == 0.5
    write_reduction_toml(out)
    res = reduce_session(out, plot=False)
    samples = load_samples(res.path)
    assert samples.attrs["reference_reflectance"] == pytest.approx([0.5, 0.5, 0.5])
    ok = samples.valid
    assert ok.sum() >= 0.5 * len(ok)
    # closed form of the Lambertian sample; with the default 0.99 target the ratio is 0.505
    rel = np.abs(samples.brdf[ok] / (ALBEDO / np.pi) - 1)
    assert np.median(rel) <= 0.01


def test_reduce_refuses_to_overwrite_a_file_that_is_not_samples(session, tmp_path):
    s = copy_session(session, tmp_path / "S")
    precious = tmp_path / "precious.h5"
    precious.write_bytes(b"someone's thesis data")
    assert run("capture", "reduce", str(s), "--out", str(precious), "--quiet") == 1
    assert precious.read_bytes() == b"someone's thesis data"
    # an earlier samples file is replaced (re-running a reduction is safe), and --force
    # replaces anything
    out = tmp_path / "samples.h5"
    assert run("capture", "reduce", str(s), "--out", str(out), "--quiet", "--no-plot") == 0
    assert run("capture", "reduce", str(s), "--out", str(out), "--quiet", "--no-plot") == 0
    assert (
        run("capture", "reduce", str(s), "--out", str(precious), "--quiet", "--no-plot", "--force")
        == 0
    )
    assert load_samples(precious).n_channels == 3


def test_a_session_without_reduction_toml_is_a_clear_error(session, tmp_path, capsys):
    s = copy_session(session, tmp_path / "S")
    setup = (s / "reduction.toml").read_bytes()
    (s / "reduction.toml").unlink()
    assert run("capture", "reduce", str(s), "--quiet") == 1
    err = capsys.readouterr().err
    assert "no reduction.toml" in err and "python -m gonio.app.sim_reduction" in err
    assert not (s / "samples.h5").exists()
    # --config reads a setup kept elsewhere, with the same result as the session's own
    (tmp_path / "lab.toml").write_bytes(setup)
    out = tmp_path / "with_config.h5"
    cmd = ("capture", "reduce", str(s), "--quiet", "--no-plot")
    assert run(*cmd, "--config", str(tmp_path / "lab.toml"), "--out", str(out)) == 0
    (s / "reduction.toml").write_bytes(setup)
    assert run(*cmd, "--out", str(tmp_path / "own.h5")) == 0
    a, b = load_samples(out), load_samples(tmp_path / "own.h5")
    assert np.array_equal(a.brdf, b.brdf, equal_nan=True) and np.array_equal(a.wo, b.wo)


def test_write_reduction_toml_is_idempotent_and_keeps_a_lab_file(session, tmp_path):
    from gonio.errors import SessionError

    s = copy_session(session, tmp_path / "S")
    before = (s / "reduction.toml").read_bytes()
    stat = (s / "reduction.toml").stat()
    assert write_reduction_toml(s) == s / "reduction.toml"
    assert (s / "reduction.toml").read_bytes() == before
    assert (s / "reduction.toml").stat().st_ino == stat.st_ino  # not even rewritten
    # a lab's own calibration: another light radius
    assert "radius = 0.01\n" in before.decode()
    (s / "reduction.toml").write_text(before.decode().replace("radius = 0.01\n", "radius = 0.02\n"))
    lab = (s / "reduction.toml").read_bytes()
    with pytest.raises(SessionError, match="exists with another setup"):
        write_reduction_toml(s)
    assert (s / "reduction.toml").read_bytes() == lab
    write_reduction_toml(s, overwrite=True)
    assert (s / "reduction.toml").read_bytes() == before


HOLD_REDUCTION = """
import sys
from gonio.capture.reduce import reduce_session

def progress(done, total):
    if done == 1:  # the output's lock is held and nothing is written yet: wait here
        print("measuring", flush=True)
        sys.stdin.readline()

res = reduce_session(sys.argv[1], progress=progress, plot=False)
print("wrote", res.path, flush=True)
"""


def test_a_second_reduction_into_the_same_output_refuses(session, tmp_path):
    """Two processes: the first reduction is held mid-way (its progress callback waits on
    stdin); the second, into the same samples.h5, must refuse at once naming the first's
    PID, exit 1 with no traceback, and write nothing."""
    s = copy_session(session, tmp_path / "S")
    env = dict(os.environ, GONIO_NUMBA=os.environ.get("GONIO_NUMBA", "1"))
    first = subprocess.Popen(
        [sys.executable, "-c", HOLD_REDUCTION, str(s)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert first.stdout.readline().strip() == "measuring"
        second = subprocess.run(
            [sys.executable, "-m", "gonio", "capture", "reduce", str(s), "--quiet"],
            capture_output=True,
            text=True,
            env=env,
        )
        assert second.returncode == 1, second.stderr
        assert f"in use by process {first.pid}" in second.stderr
        assert second.stderr.startswith("error: ") and "Traceback" not in second.stderr
        assert not any(s.glob("samples.*")) and not (s / "reduction.json").exists()
        first.stdin.write("go\n")
        first.stdin.flush()
        out, err = first.communicate(timeout=600)
        assert first.returncode == 0, err
        assert f"wrote {s / 'samples.h5'}" in out
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    # the lock died with its holder: the next reduction runs
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    assert load_samples(s / "samples.h5").valid.all()


def test_a_broken_config_file_is_refused_naming_it_and_keeps_the_samples(session, tmp_path, capsys):
    """``--config`` with a file that is not TOML, or a field out of its model: exit 1
    naming the file (and field), and the previous samples.h5 is left as it was."""
    s = copy_session(session, tmp_path / "S")
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    before = (s / "samples.h5").read_bytes()
    broken = tmp_path / "broken.toml"
    broken.write_text("[camera\n")
    good = tomllib.loads((s / "reduction.toml").read_text())
    good["camera"]["K"] = [[1.0, 0.0], [0.0, 1.0]]
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(tomli_w.dumps(good))
    for path, named in ((broken, "not a valid TOML"), (wrong, "camera.K")):
        capsys.readouterr()
        assert run("capture", "reduce", str(s), "--quiet", "--config", str(path)) == 1
        err = capsys.readouterr().err
        assert str(path) in err and named in err and "Traceback" not in err
        assert (s / "samples.h5").read_bytes() == before


def test_a_camera_calibration_of_another_camera_is_refused_and_nothing_written(
    session, tmp_path, capsys
):
    """``--camera-calibration`` made with another camera (its digest is not the manifest
    camera's): exit 1 naming the file and both digests; no samples.h5 is written."""
    from gonio.capture.manifest import load_manifest
    from gonio.capture.reduction_config import camera_identity, identity_digest

    s = copy_session(session, tmp_path / "S")
    ours = camera_identity(load_manifest(s)["camera"])
    assert ours is not None
    other = identity_digest({**ours, "serial": "another-camera"})
    cam = tomllib.loads((s / "reduction.toml").read_text())["camera"]
    cam["calibration"] = {"rms_px": 0.2, "digest": other}
    cal = tmp_path / "camera.toml"
    cal.write_text(tomli_w.dumps({"camera": cam}))
    assert run("capture", "reduce", str(s), "--quiet", "--camera-calibration", str(cal)) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "Traceback" not in err
    assert str(cal) in err and other in err and identity_digest(ours) in err
    assert not (s / "samples.h5").exists() and not (s / "reduction.json").exists()
    # the session's own camera digest is accepted, and reduces as the inline [camera]
    cam["calibration"]["digest"] = identity_digest(ours)
    cal.write_text(tomli_w.dumps({"camera": cam}))
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    plain = load_samples(s / "samples.h5")
    out = tmp_path / "with_file.h5"
    args = ("capture", "reduce", str(s), "--quiet", "--no-plot", "--out", str(out))
    assert run(*args, "--camera-calibration", str(cal)) == 0
    np.testing.assert_array_equal(load_samples(out).brdf, plain.brdf)


def test_the_budget_is_stored_summed_and_printed(session, tmp_path, capsys):
    """samples.h5 holds the budget (issue 16): brdf_std is the root sum of squares of the
    per-sample terms, the modes have their scopes and the samples their poses; reduce
    and inspect print the largest terms."""
    from gonio.dataset import BUDGET_TERMS

    s = copy_session(session, tmp_path / "S")
    capsys.readouterr()
    assert run("capture", "reduce", str(s)) == 0
    err = capsys.readouterr().err
    assert "Uncertainty budget" in err and "noise" in err
    samples = load_samples(s / "samples.h5")
    n = len(samples)
    assert set(samples.budget) == set(BUDGET_TERMS)
    rss = np.sqrt(sum(v**2 for v in samples.budget.values()))
    np.testing.assert_allclose(samples.brdf_std, rss, rtol=1e-12)
    # a Lambertian sample has no gradient: the geometry term is far below the noise, and
    # the noise term alone is still honest against the closed form
    assert np.all(samples.budget["geometry"] < 0.3 * samples.budget["noise"])
    z = (samples.brdf - ALBEDO / np.pi) / samples.budget["noise"]
    assert 0.8 <= z.std() <= 1.25
    m = samples.geometry_modes.shape[1]
    assert samples.geometry_modes.shape == (n, m, 6)
    assert list(samples.geometry_mode_scope).count("pose") == 6
    # no calibration record: the nominal joint tolerance, one mode per joint offset
    assert list(samples.geometry_mode_scope).count("session") == 4
    assert all(x.startswith("nominal ") for x in samples.geometry_mode_names[:4])
    assert set(samples.geometry_source) == {"board"}
    assert len(set(samples.pose)) == 4 and np.all(np.bincount(samples.pose)[samples.pose] == 9)
    # a 0.1 deg joint offset moves the light by about that much: the modes' size
    lam = np.degrees(np.linalg.norm(samples.geometry_modes[:, :4, :3], axis=2))
    assert 0.02 < np.max(lam) < 0.2
    np.testing.assert_array_equal(samples.shared_budget["reference"], 0.0)
    summary = json.loads((s / "reduction.json").read_text())
    terms = {r["term"]: r for r in summary["budget"]["terms"]}
    # no flats and one reference group: the stated PRNU and drift (type B) are the
    # largest terms, as the warnings say
    assert max(terms, key=lambda t: terms[t]["share"]) in ("flat", "drift")
    assert any("no flat fields" in w for w in summary["warnings"])
    assert any("one group" in w for w in summary["warnings"])
    assert summary["budget"]["session_mode_source"] == "nominal"
    assert run("capture", "inspect", str(s), "--no-verify") == 0
    out = capsys.readouterr().out
    assert "Uncertainty budget" in out and "noise" in out


def test_outputs_that_are_not_a_reductions_are_never_replaced(session, tmp_path, capsys):
    """Files no reduction wrote keep their content: the user's own file at the default
    SESSION/samples.h5, a reduction.json beside --out, an --out named like the files
    written beside it, the session's own journal (even with --force), a folder at the
    output; a malformed shot record is named, not a traceback."""
    s = copy_session(session, tmp_path / "S")
    (s / "samples.h5").write_text("my notes")
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 1
    assert "samples.h5 exists and is not a gonio samples file" in capsys.readouterr().err
    assert (s / "samples.h5").read_text() == "my notes"
    out = tmp_path / "out"
    out.mkdir()
    (out / "reduction.json").write_text("notes")
    assert run("capture", "reduce", str(s), "--out", str(out / "a.h5"), "--quiet") == 1
    assert "reduction.json exists and no reduction of a.h5 wrote it" in capsys.readouterr().err
    assert (out / "reduction.json").read_text() == "notes"
    assert run("capture", "reduce", str(s), "--out", str(out / "samples.png"), "--quiet") == 1
    assert "written beside the samples file" in capsys.readouterr().err
    journal = (s / "journal.jsonl").read_bytes()
    args = ["--out", str(s / "journal.jsonl"), "--force", "--quiet"]
    assert run("capture", "reduce", str(s), *args) == 2  # a usage error
    assert "one of the session's own files" in capsys.readouterr().err
    assert (s / "journal.jsonl").read_bytes() == journal
    (s / "samples.h5").unlink()
    (s / "samples.h5").mkdir()
    assert run("capture", "reduce", str(s), "--quiet", "--force") == 1
    assert "exists and is not a regular file" in capsys.readouterr().err
    (s / "samples.h5").rmdir()
    lines = (s / "journal.jsonl").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if json.loads(ln)["type"] == "shot")
    rec = json.loads(lines[k])
    rec["rig_time"] = "x"
    lines[k] = json.dumps(rec)
    (s / "journal.jsonl").write_text("\n".join(lines) + "\n")
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 1
    err = capsys.readouterr().err
    assert f"record {k + 1} (shot): field 'rig_time'" in err and "Traceback" not in err
    assert not (s / "samples.h5").exists()


def test_unusable_reference_frames_are_named(session, tmp_path, capsys):
    """Every reference frame truncated: the error names the files and what is wrong with
    them, not only that no reference frame is left."""
    s = copy_session(session, tmp_path / "S")
    refs = sorted((s / "raw").glob("*_reference.dng"))
    assert refs
    for p in refs:
        with open(p, "r+b") as fh:
            fh.truncate(1000)
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 1
    err = capsys.readouterr().err
    assert "no reference-target frame could be used" in err
    assert refs[0].name in err and "truncated" in err


def test_shots_of_poses_beyond_the_schedule_are_said_not_dropped_in_silence(
    session, tmp_path, capsys
):
    s = copy_session(session, tmp_path / "S")
    lines = (s / "journal.jsonl").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if json.loads(ln).get("kind") == "sample")
    rec = json.loads(lines[k])
    rec["pose"] = 999
    lines[k] = json.dumps(rec)
    (s / "journal.jsonl").write_text("\n".join(lines) + "\n")
    assert run("capture", "reduce", str(s), "--quiet", "--no-plot") == 0
    err = capsys.readouterr().err
    assert "pose(s) 999, beyond the schedule's" in err and "not reduced" in err
    doc = json.loads((s / "reduction.json").read_text())
    assert any("pose(s) 999" in w for w in doc["warnings"])
