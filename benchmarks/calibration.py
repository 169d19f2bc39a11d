"""Rig calibration: solve time and accuracy against the number of calibration poses.

For each pose count (subsets of ``rig_calibration_poses``: three quarters board views,
one quarter -- at least six -- mirror views, each taken evenly along the plan's visiting
order, so both approach sides of every joint stay in) and each seed of the
``realistic`` world, at corner level (``gonio.simulator.calibration_views``: the
world's own kinematics and lens, Gaussian corner noise 0.2 px, spot noise 0.15 px):

- the camera is calibrated first on the camera plan (``calibrate_camera``), and that
  calibration is the prior of ``calibrate_rig``, whose solve is timed (``--repeat``
  times; median, min, max over seeds and repetitions);
- accuracy of the parameters: per parameter the median |estimate - truth| / reported
  std over the seeds, and the RMS over parameters and seeds of (estimate - truth) /
  the parameter's expected magnitude (``gonio.rig.calibration.PARAMETERS``);
- accuracy of what a measurement uses, the directions: over the 51 sample poses of
  ``examples/plan.toml`` (the controller's joints, visited in the dry run's order), the
  angle between the world's true wi / wo and those of ``Kinematics.forward`` of the
  calibrated rig (the encoder readings through the calibrated zeros, the approach
  signs), and of the NOMINAL rig (the uncalibrated baseline): max and median, deg.

The top-level ``ratio`` is the nominal rig's direction error over the calibrated rig's
(the worst of wi and wo over the poses, per seed; median over the seeds, with their
min and max) at the default pose count, both measured in this process on one thread.
``--rendered`` also runs the lab's commands on rendered frames (``gonio capture run``
of both plans on the simulated camera, ``gonio calibrate camera``, ``gonio calibrate
rig``) for one world and the full plan (the subsets are corner level only: their moves
are not checked for arm clearance).  Prints one JSON object.

Usage::

    python benchmarks/calibration.py [--poses 12,24,36,48,96] [--seeds 1,2,3,4,5]
                                     [--repeat 2] [--rendered] [--size 480x360]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # one thread: the calibrated and nominal figures alike

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SIGMA_BOARD, SIGMA_SPOT = 0.2, 0.15
SAMPLE = (0.05, 0.05)


def _setup():
    from gonio.rig.calibration_plan import camera_calibration_poses, rig_calibration_poses
    from gonio.rig.config import default_rig_config, default_rig_document
    from gonio.simulator.scene import Board, Camera

    nominal = default_rig_config()
    return {
        "nominal": nominal,
        "doc": tomllib.loads(default_rig_document()),
        "camera": Camera(resolution=(640, 480), focal_length=0.035, fov_deg=26.0),
        "board": Board(),
        "camera_poses": camera_calibration_poses(nominal),
        "rig_poses": rig_calibration_poses(nominal),
    }


def subset(poses: list, n: int) -> list:
    """``n`` poses of the rig plan: a quarter (at least 6) mirror views, the rest board
    views, each spread evenly over the plan's order."""
    boards = [p for p in poses if p.target == "sample"]
    mirrors = [p for p in poses if p.target == "mirror"]
    n_m = min(len(mirrors), max(6, round(n / 4)))
    n_b = min(len(boards), n - n_m)

    def spread(items: list, k: int) -> list:
        if k <= 0:
            return []
        return [items[i] for i in np.unique(np.linspace(0, len(items) - 1, k).round().astype(int))]

    return spread(boards, n_b) + spread(mirrors, n_m)


def _reached(s, world, plan, rng):
    from gonio.rig.calibration_plan import approaches
    from gonio.simulator.calibration_views import simulated_pose

    sides = approaches(plan, s["nominal"].home_rad)
    return [
        simulated_pose(world, s["doc"], p.joints_rad(), side, rng, p.label)
        for p, side in zip(plan, sides, strict=True)
    ]


def camera_prior(s, world, rng):
    """The corner-level camera calibration of ``world`` as the rig calibration's prior."""
    from gonio.capture.camera_calibration import CalibrationView, calibrate_camera
    from gonio.rig.calibration import CameraPrior
    from gonio.simulator.calibration_views import camera_views

    views = camera_views(
        world,
        s["doc"],
        s["camera"],
        s["board"],
        _reached(s, world, s["camera_poses"], rng),
        SIGMA_BOARD,
        rng,
    )
    cal = calibrate_camera(
        [
            CalibrationView(
                v["label"],
                v["ids"].astype(np.int32),
                v["image_points"],
                v["object_points"],
                s["camera"].resolution,
            )
            for v in views
        ]
    )
    w, h = s["camera"].resolution
    return CameraPrior(
        cal.K,
        cal.dist,
        cal.K_std,
        cal.dist_std,
        rms_px=cal.rms_px,
        width=w,
        height=h,
        covariance=cal.covariance,
    )


def observations(s, world, plan, rng):
    """Board and spot observations of the plan's poses in ``world``."""
    from gonio.rig.calibration_data import BoardObservation, SpotObservation
    from gonio.simulator.calibration_views import board_views, spot_views

    reached = _reached(s, world, plan, rng)
    on_board = [r for r, p in zip(reached, plan, strict=True) if p.target == "sample"]
    on_mirror = [r for r, p in zip(reached, plan, strict=True) if p.target == "mirror"]
    boards = [
        BoardObservation(
            v["label"], v["joints"], v["approach"], v["object_points"], v["image_points"]
        )
        for v in board_views(
            world, s["doc"], s["camera"], s["board"], on_board, SIGMA_BOARD, rng, hidden=SAMPLE
        )
    ]
    spots = [
        SpotObservation(v["label"], v["joints"], v["approach"], v["image_point"])
        for v in spot_views(world, s["doc"], s["camera"], SAMPLE, on_mirror, SIGMA_SPOT, rng)
    ]
    return boards, spots


def measurement_poses(nominal) -> list:
    """The sample poses of examples/plan.toml as the dry run visits them (JointPose)."""
    from gonio.capture.plan import load_plan
    from gonio.capture.schedule import build_schedule
    from gonio.rig.calibration_plan import JointPose
    from gonio.rig.config import JOINT_NAMES
    from gonio.rig.kinematics import Kinematics

    sched = build_schedule(
        load_plan(REPO / "examples" / "plan.toml"), Kinematics(nominal), nominal.park_rad
    )
    out = []
    for st in sched.steps:
        if st["kind"] == "sample" and st.get("joints"):
            out.append(JointPose(*(math.degrees(st["joints"][j]) for j in JOINT_NAMES)))
    return out


def _angle_deg(a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def direction_errors(s, world, config, poses, rng) -> dict[str, float]:
    """Max and median angle (deg) between the world's true wi, wo and ``config``'s
    forward kinematics of the encoder readings, over ``poses``."""
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.world_kinematics import NominalRig, true_poses

    kin = Kinematics(config)
    rig = NominalRig.of(s["doc"])
    ids = {sv.id: sv.joint for sv in rig.servos}
    ei, eo = [], []
    for r in _reached(s, world, poses, rng):
        truth = true_poses(world, rig, r["servo_states"])
        # the readings as this config's encoders give them (its zeros)
        joints = {
            ids[i]: config.servo_for(ids[i]).joint_rad(pulses)
            for i, (pulses, _) in r["servo_states"].items()
        }
        wi, wo = kin.forward(joints, r["approach"])
        ei.append(_angle_deg(wi, truth.wi))
        eo.append(_angle_deg(wo, truth.wo))
    ei, eo = np.asarray(ei), np.asarray(eo)
    return {
        "wi_max_deg": float(ei.max()),
        "wi_median_deg": float(np.median(ei)),
        "wo_max_deg": float(eo.max()),
        "wo_median_deg": float(np.median(eo)),
        "worst_deg": float(max(ei.max(), eo.max())),
    }


def _summary(values: list[float], digits: int = 4) -> dict[str, float]:
    return {
        "median": round(statistics.median(values), digits),
        "min": round(min(values), digits),
        "max": round(max(values), digits),
    }


def corner_curve(s, counts, seeds, repeat, eval_poses):
    """The curve at corner level: one entry per pose count."""
    from gonio.errors import GonioError
    from gonio.rig.calibration import INTRINSIC_NAMES, PARAMETERS, calibrate_rig
    from gonio.simulator.world import draw_world

    curve, baseline = [], {}
    for n in counts:
        plan = subset(s["rig_poses"], n)
        times, z, rel, dirs, refused = [], {}, [], [], None
        for seed in seeds:
            world = draw_world("realistic", seed)
            rng = np.random.default_rng([seed, 15])
            prior = camera_prior(s, world, rng)
            boards, spots = observations(s, world, plan, rng)
            try:
                for _ in range(repeat):
                    t0 = time.perf_counter()
                    cal = calibrate_rig(s["nominal"], boards, spots, prior)
                    times.append(time.perf_counter() - t0)
            except GonioError as exc:  # too few views, a parameter left undetermined
                lines = str(exc).splitlines()
                names = [ln.split(":")[0].strip() for ln in lines[1:] if ln.startswith("  ")]
                refused = lines[0] + (" " + ", ".join(names) if names else "")
                break
            K, dist = world.intrinsics(s["camera"])
            truth = {
                **world.truth_parameters(s["doc"]),
                **dict(
                    zip(INTRINSIC_NAMES, [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist], strict=True)
                ),
            }
            for name in cal.names:
                v, sd = cal.estimate(name)
                z.setdefault(name, []).append(abs(v - truth[name]) / sd)
                if name in PARAMETERS:
                    rel.append((v - truth[name]) / PARAMETERS[name].magnitude)
            eval_rng = np.random.default_rng([seed, 16])
            dirs.append(direction_errors(s, world, cal.config, eval_poses, eval_rng))
            if seed not in baseline:
                eval_rng = np.random.default_rng([seed, 16])
                baseline[seed] = direction_errors(s, world, s["nominal"], eval_poses, eval_rng)
        entry = {
            "poses": n,
            "board_poses": sum(p.target == "sample" for p in plan),
            "mirror_poses": sum(p.target == "mirror" for p in plan),
        }
        if refused is not None:
            entry["refused"] = refused
        else:
            entry.update(
                {
                    "solve_s": _summary(times, 3),
                    "param_rms_error_over_magnitude": round(
                        float(np.sqrt(np.mean(np.square(rel)))), 5
                    ),
                    "abs_z_median": {k: round(float(np.median(v)), 2) for k, v in z.items()},
                    "abs_z_worst": max(
                        ((k, round(float(np.max(v)), 2)) for k, v in z.items()),
                        key=lambda kv: kv[1],
                    ),
                    "directions_deg": {
                        k: _summary([d[k] for d in dirs], 5)
                        for k in ("wi_max_deg", "wi_median_deg", "wo_max_deg", "wo_median_deg")
                    },
                    "worst_direction_deg": [round(d["worst_deg"], 5) for d in dirs],
                }
            )
        curve.append(entry)
    return curve, baseline


def rendered(s, seed: int, size: tuple[int, int]) -> dict:
    """The lab's commands on rendered frames (full plans) for one world."""
    from gonio.cli import run
    from gonio.rig.calibration_plan import write_plan
    from gonio.rig.config import load_rig_config, virtual_rig_document
    from gonio.simulator.scene import Camera
    from gonio.simulator.world import draw_world

    w, h = size
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(sys.stderr):
        root = Path(tmp)
        rig = root / "rig.toml"
        rig.write_text(virtual_rig_document())
        write_plan(root / "cam.toml", s["camera_poses"], kind="camera", width=w, height=h)
        write_plan(root / "rig_plan.toml", s["rig_poses"], kind="rig", width=w, height=h)
        world = ["--camera", "simulated", "--world", "realistic", "--world-seed", str(seed)]
        t0 = time.perf_counter()
        for plan, out in (("cam.toml", "CS"), ("rig_plan.toml", "RS")):
            if run(
                "capture",
                "run",
                str(root / plan),
                "--rig",
                str(rig),
                *world,
                "--out",
                str(root / out),
                "--quiet",
            ):
                raise SystemExit(f"capture run {plan} failed")
        t_shoot = time.perf_counter() - t0
        if run("calibrate", "camera", str(root / "CS"), "--calibration", str(root / "c.toml")):
            raise SystemExit("calibrate camera failed")
        t1 = time.perf_counter()
        if run(
            "calibrate",
            "rig",
            str(root / "RS"),
            "--rig",
            str(rig),
            "--camera-calibration",
            str(root / "c.toml"),
            "--out",
            str(root / "rc.toml"),
        ):
            raise SystemExit("calibrate rig failed")
        t_cal = time.perf_counter() - t1
        config = load_rig_config(root / "rc.toml")
    world_ = draw_world("realistic", seed)
    cam = Camera(resolution=size, focal_length=0.035, fov_deg=26.0)
    K, dist = world_.intrinsics(cam)
    truth = {
        **world_.truth_parameters(s["doc"]),
        **dict(
            zip(
                ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"),
                [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist],
                strict=True,
            )
        ),
    }
    rec = config.calibration
    z = {
        n: round((e.value - truth[n]) / e.std, 2)
        for n, e in {**rec.parameters, **rec.intrinsics}.items()
    }
    poses = measurement_poses(s["nominal"])
    cal_dirs = direction_errors(s, world_, config, poses, np.random.default_rng([seed, 16]))
    nom_dirs = direction_errors(s, world_, s["nominal"], poses, np.random.default_rng([seed, 16]))
    return {
        "seed": seed,
        "size": list(size),
        "poses": len(s["rig_poses"]),
        "shoot_s": round(t_shoot, 1),
        "calibrate_s": round(t_cal, 2),
        "rms_px": {k: round(v, 4) for k, v in rec.rms_px.items()},
        "z": z,
        "max_abs_z": max(abs(v) for v in z.values()),
        "calibrated_worst_direction_deg": round(cal_dirs["worst_deg"], 5),
        "nominal_worst_direction_deg": round(nom_dirs["worst_deg"], 5),
        "ratio": round(nom_dirs["worst_deg"] / cal_dirs["worst_deg"], 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", default="12,24,36,48,96", help="pose counts of the curve")
    ap.add_argument("--default-poses", type=int, default=96, help="pose count of `ratio`")
    ap.add_argument("--seeds", default="1,2,3,4,5", help="realistic-world seeds")
    ap.add_argument("--repeat", type=int, default=2, help="solves timed per seed and count")
    ap.add_argument("--rendered", action="store_true", help="also run on rendered frames")
    ap.add_argument("--size", default="480x360", help="rendered frame size, WxH")
    args = ap.parse_args()
    counts = sorted({int(x) for x in args.poses.split(",")} | {args.default_poses})
    seeds = [int(x) for x in args.seeds.split(",")]
    t0 = time.perf_counter()
    s = _setup()
    eval_poses = measurement_poses(s["nominal"])
    curve, baseline = corner_curve(s, counts, seeds, args.repeat, eval_poses)
    default = next(e for e in curve if e["poses"] == args.default_poses)
    if "refused" in default:
        raise SystemExit(f"the default pose count is refused: {default['refused']}")
    nominal_worst = [baseline[seed]["worst_deg"] for seed in seeds]
    ratios = [b / c for b, c in zip(nominal_worst, default["worst_direction_deg"], strict=True)]
    out = {
        "benchmark": "calibration",
        "figure": (
            f"worst wi/wo direction error over the {len(eval_poses)} poses of "
            f"examples/plan.toml after calibrating with {args.default_poses} poses (deg, "
            "median over seeds)"
        ),
        "calibrated_worst_direction_deg": round(
            statistics.median(default["worst_direction_deg"]), 5
        ),
        "baseline": "the nominal (uncalibrated) rig's worst direction error (deg, median)",
        "nominal_worst_direction_deg": round(statistics.median(nominal_worst), 4),
        "ratio": round(statistics.median(ratios), 1),
        "ratio_over_seeds": {"min": round(min(ratios), 1), "max": round(max(ratios), 1)},
        "solve_s_at_default": default["solve_s"],
        "seeds": seeds,
        "noise_px": {"board": SIGMA_BOARD, "spot": SIGMA_SPOT},
        "nominal_directions_deg": {
            k: _summary([baseline[seed][k] for seed in seeds], 4)
            for k in ("wi_max_deg", "wi_median_deg", "wo_max_deg", "wo_median_deg")
        },
        "curve": curve,
    }
    if args.rendered:
        w, h = (int(x) for x in args.size.lower().split("x"))
        out["rendered"] = rendered(s, seeds[0], (w, h))
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
