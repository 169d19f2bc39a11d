"""Reduction time per RAW frame against bare rawpy decoding (open + unpack) of the same frames.

Usage::

    python benchmarks/reduce.py [--session DIR] [--width 1600 --height 1200] [--repeat 3]

Without ``--session`` a simulated session is captured first (virtual servo bus, rendered
DNGs: 8 sample poses, 2 reference poses, 3-frame brackets: 30 frames) in a temporary
directory (it writes its own ``reduction.toml`` when the session is created).  Ten poses,
not a handful, because a session's first frames are decoded before anything can overlap
them and its last pose is measured with nothing left to decode: a lab session has
hundreds of frames, where the per-frame figure is the steady state's.
All timings are medians over ``--repeat`` interleaved runs in this process, after one
warm-up run of each (imports, numba's cached kernel); the reduction includes everything
``gonio capture reduce`` does (journal digest check, decoding, darks, board detection,
HDR merge, calibration, writing samples.h5) except the plot.  The reduction runs with its
default threads (``"threads"`` in the output, this one included: the other decodes ahead
while poses are measured) and with one thread (``ratio_single_thread``).  The baseline is
``rawpy.imread(path)`` + unpack; ``rawpy.imread(BytesIO(bytes))`` + unpack, which is
faster, is reported as a stricter second baseline.  Prints one JSON object.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

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
    # exposures that keep the diffuse reference near half scale at this pixel size
    t = 0.0005 * (480.0 / width) ** 2 * 4
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--session", type=Path, default=None)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1200)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--threads", type=int, default=None, help="reduction threads (default: the default)"
    )
    args = ap.parse_args()

    import rawpy

    from gonio.capture.journal import read_journal, xxh3_bytes
    from gonio.capture.raw import read_file, read_raw
    from gonio.capture.reduce import default_threads, reduce_session

    threads = args.threads or default_threads()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = args.session or make_session(tmp, args.width, args.height)
        files = [
            session / r["file"]
            for r in read_journal(session / "journal.jsonl")
            if r.get("type") == "shot"
        ]

        def bare() -> None:
            for f in files:
                with rawpy.imread(str(f)) as raw:
                    raw.raw_image_visible  # noqa: B018 (open + unpack)

        def bare_bytes() -> None:
            # the fastest bare way we know: one unbuffered read, LibRaw on the buffer
            for f in files:
                with open(f, "rb", buffering=0) as fh:
                    data = fh.readall()
                with rawpy.imread(io.BytesIO(data)) as raw:
                    raw.raw_image_visible  # noqa: B018 (open + unpack)

        def reduction(n: int) -> Callable[[], None]:
            return lambda: reduce_session(session, out=tmp / f"s{n}.h5", plot=False, threads=n)

        runs = {
            "bare": bare,
            "bare_bytes": bare_bytes,
            "reduce": reduction(threads),
            "reduce_1": reduction(1),
        }
        for fn in runs.values():
            fn()  # warm caches and imports for all
        times: dict[str, list[float]] = {k: [] for k in runs}
        for _ in range(args.repeat):  # interleaved, so load changes hit all alike
            for k, fn in runs.items():
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
        same = (tmp / f"s{threads}.h5").read_bytes() == (tmp / "s1.h5").read_bytes()
        with rawpy.imread(str(files[0])) as raw:
            h, w = raw.raw_image_visible.shape
        # where the single-thread time goes, per frame: reading + the journal's digest
        # check, and decoding from those bytes
        t0 = time.perf_counter()
        datas = [read_file(f) for f in files]
        for d in datas:
            xxh3_bytes(d)
        t_hash = (time.perf_counter() - t0) / len(files)
        t0 = time.perf_counter()
        for d in datas:
            read_raw(d)
        t_decode = (time.perf_counter() - t0) / len(files)
    n = len(files)
    per = {k: statistics.median(v) / n for k, v in times.items()}
    print(
        json.dumps(
            {
                "benchmark": "reduce",
                "what": "gonio capture reduce time per RAW frame vs rawpy open+unpack of the same "
                "frames (medians, same run, interleaved)",
                "frames": n,
                "frame_size": [w, h],
                "threads": threads,
                "reduce_s_per_frame": round(per["reduce"], 5),
                "baseline_rawpy_open_unpack_s_per_frame": round(per["bare"], 5),
                "ratio": round(per["reduce"] / per["bare"], 3),
                "reduce_single_thread_s_per_frame": round(per["reduce_1"], 5),
                "ratio_single_thread": round(per["reduce_1"] / per["bare"], 3),
                "baseline_read_bytes_then_open_unpack_s_per_frame": round(per["bare_bytes"], 5),
                "ratio_vs_bytes_baseline": round(per["reduce"] / per["bare_bytes"], 3),
                "ratio_single_thread_vs_bytes_baseline": round(
                    per["reduce_1"] / per["bare_bytes"], 3
                ),
                "single_thread_of_which_read_and_digest_s_per_frame": round(t_hash, 5),
                "single_thread_of_which_read_raw_s_per_frame": round(t_decode, 5),
                "single_thread_rest_per_frame_s": round(per["reduce_1"] - t_hash - t_decode, 5),
                "output_identical_1_vs_n_threads": same,
                "target_ratio": 1.5,
                "repeat": args.repeat,
                "cpu_count": os.cpu_count(),
                "load_average_1min": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    sys.exit(main())
