"""Reduction time per RAW frame against bare rawpy decoding of the same frames, at equal threads.

Usage::

    python benchmarks/reduce.py [--size 1600x1200 --size 320x240] [--session DIR] [--repeats 5]

For every ``--size`` (default 1600x1200, a lab camera's order of size, and 320x240, the
demo's frames, where the fixed costs of a pose dominate) a simulated session is captured
first (virtual servo bus, rendered DNGs: 8 sample poses, 2 reference poses, 3-frame
brackets: 30 frames) in a temporary directory; ``--session DIR`` reduces an existing
session instead (one case).  Ten poses, not a handful: a session's first frames are
decoded before anything can overlap them and its last pose is measured with nothing left
to decode; a lab session has hundreds of frames, where the per-frame figure is the
steady state's.

The two sides, timed with :mod:`equal_threads` (wall clock, >= 5 interleaved repetitions
after a warm-up, median / min / max, figures per frame):

- **gonio**: ``reduce_session`` -- everything ``gonio capture reduce`` does (journal digest
  check, decoding, darks, board detection, HDR merge, calibration, budget, writing
  samples.h5) except the plot -- with ``threads=1``, and with all cores;
- **baseline**: ``rawpy.imread(path)`` + unpack (``raw_image_visible``) of every frame: on
  one thread, and in a ``concurrent.futures`` thread pool of all cores (LibRaw releases
  the GIL while it opens and unpacks).

Besides numba and BLAS (``equal_threads.threads``), OpenCV's own thread pool (board
detection) is pinned to the same count (a local helper: ``equal_threads`` does not know
OpenCV).  ``ratio`` is gonio's time over rawpy's at one thread each (lower is better:
``<= target`` passes); ``ratio_worst`` pairs gonio's slowest run with rawpy's fastest.

gonio reads the simulator's DNGs without LibRaw's unpack (:mod:`gonio.capture.plain_dng`:
the strip is the mosaic), which is what ``ratio`` measures.  A lab camera's RAW files
(compressed, other makers) still go through LibRaw, so each case also times a third side
interleaved with the other two, **gonio_libraw**: the same reduction with
``GONIO_DIRECT_DNG=0`` (every frame unpacked by LibRaw, as a camera's would be);
``ratio_libraw_decode`` is its time over rawpy's, the cost of everything the reduction
does beyond LibRaw's decoding.  Prints one JSON object; its top level is the first
size's case.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from equal_threads import all_cores, compare, machine, speedup, threads  # noqa: E402

TARGET = 1.5

PLAN = """
name = "bench-reduce"
seed = 11
[grid]
theta_i_deg = [15, 30, 45, 60]
phi_i_deg = [0]
theta_o_deg = [30, 50]
phi_o_deg = [180]
[bracket]
policy = "fixed"
exposures_s = [{t1}, {t2}, {t3}]
[reference]
poses = [
  {{theta_i_deg = 0, theta_o_deg = 30}},
  {{theta_i_deg = 30, theta_o_deg = 30, phi_o_deg = 180}},
]
[simulation]
scene = "scene.toml"
"""

SCENE = """
[sample]
width = 0.05
height = 0.05
[sample.brdf]
model = "ggx"
params = {{ alpha = 0.2, ks = 0.8 }}
[holder]
width = 0.16
height = 0.16
[holder.board]
[[lights]]
type = "disk"
position = [0.0, 0.25, 0.433]
look_at = [0.0, 0.0, 0.0]
radius = 0.01
radiance = [2.0e4, 2.0e4, 2.0e4]
[camera]
resolution = [{w}, {h}]
focal_length = 0.016
fov_deg = 30.0
position = [0.1, -0.2, 0.35]
look_at = [0.0, 0.0, 0.0]
[render]
tolerance = 1e-3
antialias = 2
"""


def make_session(root: Path, width: int, height: int) -> Path:
    """A simulated session (its reduction.toml written at capture), through the library:
    stdout carries only the benchmark's JSON."""
    from gonio.app.simulation import simulated_run
    from gonio.capture.plan import load_plan
    from gonio.capture.sessions import run_session
    from gonio.rig.config import load_rig_config, virtual_rig_document

    (root / "rig.toml").write_text(virtual_rig_document())
    # keeps the diffuse reference near half scale; the simulated sensor's signal per
    # pixel does not depend on the frame size (this was 0.0005 (480/1600)^2 4 for every
    # size, so the 1600x1200 session is the one measured before)
    t = 1.8e-4
    (root / "plan.toml").write_text(PLAN.format(t1=t / 4, t2=t, t3=4 * t))
    (root / "scene.toml").write_text(SCENE.format(w=width, h=height))
    plan = load_plan(root / "plan.toml")
    sim = simulated_run(plan, root / "plan.toml", None, "virtual")
    run_session(
        root / "S",
        plan,
        load_rig_config(root / "rig.toml"),
        sim.opener,
        camera_backend="simulated",
        simulation=sim.simulation,
        attachments=sim.attachments,
    )
    return root / "S"


@contextlib.contextmanager
def pinned(n: int) -> Iterator[int]:
    """``equal_threads.threads(n)`` plus OpenCV's pool (board detection)."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(n)
    try:
        with threads(n):
            yield n
    finally:
        cv2.setNumThreads(before)


@contextlib.contextmanager
def libraw_decode(on: bool) -> Iterator[None]:
    """``GONIO_DIRECT_DNG=0`` while ``on``: every frame goes through LibRaw's unpack."""
    before = os.environ.get("GONIO_DIRECT_DNG")
    if on:
        os.environ["GONIO_DIRECT_DNG"] = "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("GONIO_DIRECT_DNG", None)
        else:
            os.environ["GONIO_DIRECT_DNG"] = before


def per_frame(st: dict[str, Any], n: int) -> dict[str, Any]:
    out = {k: st[k] / n for k in ("median", "min", "max")}
    return {**out, "runs": [round(r / n, 6) for r in st["runs"]], "threads": st["threads"]}


def stage_profile(session: Path, out: Path, n_frames: int) -> dict[str, float]:
    """Where one single-thread reduction's wall time goes, ms per frame (one run,
    instrumented; the stages are nested: detection and the pose kernel are parts of
    measure_pose, and budget of samples)."""
    import gonio.capture.frame_loader as fl
    import gonio.capture.pose_measure as pm
    import gonio.capture.reduce as red

    acc: dict[str, float] = defaultdict(float)
    saved = []

    def wrap(obj: Any, name: str, key: str) -> None:
        f = getattr(obj, name)
        saved.append((obj, name, f))

        def timed(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                acc[key] += time.perf_counter() - t0

        setattr(obj, name, timed)

    wrap(fl, "read_file", "read file")
    wrap(fl, "frame_problem", "journal digest (XXH3)")
    wrap(fl, "read_raw", "decode (read_raw)")
    wrap(red, "measure_pose", "measure_pose")
    wrap(pm, "detect_pose_in_frame", "  board detection")
    wrap(pm, "_pose_sums_fused", "  pose kernel (fused merge + region sums)")
    wrap(red._PoseRun, "samples", "samples (calibration, budget)")
    wrap(red._PoseRun, "_budget", "  budget")
    wrap(red, "save_samples", "write samples.h5")
    try:
        t0 = time.perf_counter()
        red.reduce_session(session, out=out, plot=False, threads=1)
        total = time.perf_counter() - t0
    finally:
        for obj, name, f in reversed(saved):
            setattr(obj, name, f)
    top = [k for k in acc if not k.startswith(" ")]
    prof = {k: round(1e3 * v / n_frames, 3) for k, v in acc.items()}
    prof["rest"] = round(1e3 * (total - sum(acc[k] for k in top)) / n_frames, 3)
    prof["total"] = round(1e3 * total / n_frames, 3)
    return prof


def run_case(session: Path, tmp: Path, repeats: int) -> dict[str, Any]:
    import rawpy

    from gonio.capture.journal import read_journal
    from gonio.capture.raw import read_raw
    from gonio.capture.reduce import reduce_session

    files = [
        session / r["file"]
        for r in read_journal(session / "journal.jsonl")
        if r.get("type") == "shot"
    ]
    n = len(files)
    cores = all_cores()

    def decode(f: Path) -> None:
        with rawpy.imread(str(f)) as raw:
            raw.raw_image_visible  # noqa: B018 (open + unpack)

    def bare() -> None:
        for f in files:
            decode(f)

    pool = ThreadPoolExecutor(cores)

    def bare_pool() -> None:
        list(pool.map(decode, files))

    def gonio(k: int, name: str, direct: bool = True) -> Callable[[], None]:
        def go() -> None:
            with libraw_decode(not direct):
                reduce_session(session, out=tmp / name, plot=False, threads=k)

        return go

    out: dict[str, Any] = {}
    for label, k, base in (("one_thread", 1, bare), ("all_cores", cores, bare_pool)):
        with pinned(k):
            st = compare(
                {
                    "gonio": gonio(k, f"g{k}.h5"),
                    "baseline": base,
                    "gonio_libraw": gonio(k, f"l{k}.h5", direct=False),
                },
                repeats=repeats,
                threads=k,
            )
        st = {side: per_frame(v, n) for side, v in st.items()}
        out[label] = {
            "gonio": st["gonio"],
            "baseline": st["baseline"],
            "gonio_libraw": st["gonio_libraw"],
            "speedup": speedup(st["gonio"], st["baseline"]),
            "ratio": st["gonio"]["median"] / st["baseline"]["median"],
            "ratio_libraw_decode": st["gonio_libraw"]["median"] / st["baseline"]["median"],
        }
        if label == "all_cores":
            out[label]["threads"] = cores
    pool.shutdown()
    one = out["one_thread"]
    outputs = [tmp / f"{p}{k}.h5" for k in (1, cores) for p in "gl"]
    same = len({f.read_bytes() for f in outputs}) == 1
    with pinned(1):
        prof = stage_profile(session, tmp / "p.h5", n)
        with libraw_decode(True):
            prof_libraw = stage_profile(session, tmp / "p.h5", n)
    first = read_raw(files[0])
    return {
        "case": f"{first.shape[1]}x{first.shape[0]}, {n} frames",
        "frames": n,
        "frame_size": [first.shape[1], first.shape[0]],
        **out,
        "ratio": one["gonio"]["median"] / one["baseline"]["median"],
        "ratio_worst": one["gonio"]["max"] / one["baseline"]["min"],
        "ratio_all_cores": out["all_cores"]["ratio"],
        "ratio_libraw_decode": one["ratio_libraw_decode"],
        "ratio_libraw_decode_all_cores": out["all_cores"]["ratio_libraw_decode"],
        "target": TARGET,
        "target_met": one["gonio"]["median"] / one["baseline"]["median"] <= TARGET,
        # samples.h5 of one thread and all cores, direct and LibRaw decoding: one file
        "output_identical_1_vs_all_threads": same,
        "profile_one_thread_ms_per_frame": prof,
        "profile_one_thread_ms_per_frame_libraw": prof_libraw,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--session", type=Path, default=None)
    ap.add_argument("--size", action="append", default=None, help="WxH (repeatable)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    sizes = args.size or ["1600x1200", "320x240"]
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.session is not None:
            cases.append(run_case(args.session, tmp, args.repeats))
        else:
            for size in sizes:
                w, h = (int(x) for x in size.lower().split("x"))
                root = tmp / size
                root.mkdir()
                cases.append(run_case(make_session(root, w, h), root, args.repeats))
    doc = {
        "benchmark": "reduce",
        "what": "gonio capture reduce time per RAW frame vs rawpy open+unpack of the same "
        "frames, at equal threads (wall clock, interleaved repetitions); gonio_libraw: the "
        "same reduction with every frame unpacked by LibRaw (GONIO_DIRECT_DNG=0)",
        "units": "seconds per frame",
        "ratio_orientation": "gonio time / rawpy time at one thread each: lower is better, "
        "<= target passes (speedup = rawpy / gonio)",
        "machine": machine(),
        **cases[0],
        "cases": cases,
    }
    print(json.dumps(doc))


if __name__ == "__main__":
    sys.exit(main())
