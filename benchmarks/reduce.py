"""Reduction time per RAW frame against bare rawpy decoding (open + unpack) of the same frames.

Usage::

    python benchmarks/reduce.py [--session DIR] [--width 1600 --height 1200] [--repeat 3]

Without ``--session`` a simulated session is captured first (virtual servo bus, rendered
DNGs: 4 sample poses, 2 reference poses, adaptive brackets) in a temporary directory.
Both timings are medians over ``--repeat`` runs in this process; the reduction includes
everything ``gonio capture reduce`` does (hash check, decoding, darks, board detection,
HDR merge, calibration, writing samples.h5) except the plot.  Prints one JSON object.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import statistics
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

PLAN = """
name = "bench-reduce"
seed = 11
[grid]
theta_i_deg = [20, 40]
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
    from gonio.cli import main

    rig = resources.files("gonio.rig").joinpath("default_rig.toml").read_text()
    (root / "rig.toml").write_text(rig.replace('port = "/dev/ttyUSB0"', 'port = "virtual"'))
    # exposures that keep the diffuse reference near half scale at this pixel size
    t = 0.0005 * (480.0 / width) ** 2 * 4
    (root / "plan.toml").write_text(PLAN.format(t1=t / 4, t2=t, t3=4 * t))
    (root / "scene.toml").write_text(SCENE.format(w=width, h=height))
    try:
        main(
            [
                "capture",
                "run",
                str(root / "plan.toml"),
                "--rig",
                str(root / "rig.toml"),
                "--camera",
                "simulated",
                "--out",
                str(root / "S"),
                "--quiet",
            ]
        )
    except SystemExit as exc:
        if exc.code:
            raise
    return root / "S"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--session", type=Path, default=None)
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1200)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    import rawpy
    from gonio.capture.journal import read_journal
    from gonio.capture.raw import read_raw
    from gonio.capture.reduce import reduce_session

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

        def reduction() -> None:
            reduce_session(session, out=tmp / "samples.h5", plot=False)

        bare()
        reduction()  # warm caches and imports for both
        t_bare, t_red = [], []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            bare()
            t_bare.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            reduction()
            t_red.append(time.perf_counter() - t0)
        with rawpy.imread(str(files[0])) as raw:
            h, w = raw.raw_image_visible.shape
        # where the time goes, per frame: reading + journal hash check, and decoding
        t0 = time.perf_counter()
        for f in files:
            hashlib.sha256(f.read_bytes()).hexdigest()
        t_hash = (time.perf_counter() - t0) / len(files)
        t0 = time.perf_counter()
        for f in files:
            read_raw(f.read_bytes())
        t_decode = (time.perf_counter() - t0) / len(files)
    n = len(files)
    per_bare = statistics.median(t_bare) / n
    per_red = statistics.median(t_red) / n
    print(
        json.dumps(
            {
                "benchmark": "reduce",
                "what": "gonio capture reduce time per RAW frame vs rawpy open+unpack of the same "
                "frames",
                "frames": n,
                "frame_size": [w, h],
                "reduce_s_per_frame": round(per_red, 5),
                "baseline_rawpy_open_unpack_s_per_frame": round(per_bare, 5),
                "ratio": round(per_red / per_bare, 3),
                "of_which_read_and_sha256_s_per_frame": round(t_hash, 5),
                "of_which_read_raw_s_per_frame": round(t_decode, 5),
                "rest_per_frame_s": round(per_red - t_hash - t_decode, 5),
                "target_ratio": 1.5,
                "repeat": args.repeat,
            }
        )
    )


if __name__ == "__main__":
    sys.exit(main())
