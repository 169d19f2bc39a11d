"""Simulated sessions for ``benchmarks/adaptive.py``: materials, the dense grid, per-pose data.

One real simulated session per material (the composition root's device opener, virtual
time, the ``perfect`` world, small frames) on the densest regular grid of the benchmark;
every coarser grid of the benchmark is a subset of it (its angles divide the dense
grid's), so its poses' samples are the dense session's samples of those poses: the same
renderer, sensor, brackets and reduction as a session of that grid alone, with the
reference group shot once.  The adaptive design-only driver picks its poses from the
same measured pool.

Run alone to (re)make the sessions: ``python benchmarks/adaptive_sessions.py ROOT [NAME...]``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _refdata() -> Path:
    """``$GONIO_REFDATA``, else ``shared/data`` beside the repository (or beside the
    folder of its work trees)."""
    env = os.environ.get("GONIO_REFDATA")
    if env:
        return Path(env)
    for base in (REPO.parent, REPO.parent.parent):
        if (base / "shared" / "data").is_dir():
            return base / "shared" / "data"
    return REPO.parent / "shared" / "data"


RGL = _refdata() / "rgl"

SIZE = (160, 120)
#: the dense grid (deg): theta_i, theta_o to 80 in 10 deg, phi_o in 22.5 deg
DENSE_THETA = tuple(float(t) for t in range(0, 81, 10))
DENSE_PHI = tuple(22.5 * k for k in range(9))
#: the regular grids of increasing density (theta step, phi step), all subsets of the dense
GRIDS = ((40, 90), (20, 90), (20, 45), (10, 90), (10, 45), (10, 22.5))
SHOT_OVERHEAD_S = 0.5  # the bracket's default download time per frame (plan.BracketPolicy)


@dataclass(frozen=True)
class Material:
    """A benchmark material: the scene's ``[sample.brdf]`` and the ground truth."""

    name: str
    scene_brdf: dict[str, Any]
    spec: str | None = None
    params: dict[str, list[float]] | None = None
    file: Path | None = None

    def truth(self) -> Any:
        import gonio.brdf
        from gonio.fitting.select import parse_model_spec

        if self.file is not None:
            return gonio.brdf.load(self.file)
        name, opts = parse_model_spec(self.spec)
        return gonio.brdf.get_model(name, **opts).bind(
            {k: np.asarray(v, dtype=np.float64) for k, v in self.params.items()}
        )


def materials() -> list[Material]:
    """``lambert+ggx`` (alpha 0.05 and 0.3), ``lambert+beckmann[fresnel=schlick]``, RGL."""
    out = []
    for a in (0.05, 0.3):
        p = {"albedo": [0.5, 0.4, 0.3], "ks": [0.2] * 3, "alpha": [a] * 3}
        out.append(
            Material(f"lambert+ggx(alpha={a})", {"model": "lambert+ggx", "params": p},
                     "lambert+ggx", p)
        )  # fmt: skip
    p = {"albedo": [0.3, 0.35, 0.4], "ks": [0.6] * 3, "alpha": [0.25] * 3, "f0": [0.05] * 3}
    out.append(
        Material("lambert+beckmann[fresnel=schlick]",
                 {"model": "lambert+beckmann", "options": {"fresnel": "schlick"}, "params": p},
                 "lambert+beckmann[fresnel=schlick]", p)
    )  # fmt: skip
    for f in sorted(RGL.glob("*.bsdf")):
        name = f.name.removesuffix("_rgb.bsdf")
        out.append(Material(f"rgl:{name}", {"file": str(f)}, file=f))
    return out


def plan_document(theta: tuple[float, ...], phi: tuple[float, ...], seed: int = 0,
                  size: tuple[int, int] = SIZE) -> dict[str, Any]:  # fmt: skip
    """An isotropic grid plan to theta 80 deg (the budget harness's, without darks)."""
    from gonio.app.budget_harness import harness_plan

    plan = harness_plan((theta, theta, phi), seed=seed, size=size, extras=False)
    plan["darks"] = {"count": 0}
    return plan


def _scene(m: Material, size: tuple[int, int]) -> dict[str, Any]:
    from gonio.app.demo import Material as DemoMaterial
    from gonio.app.demo import scene_document

    scene = scene_document(DemoMaterial(m.name, model="lambert"), *size)
    scene["sample"]["brdf"] = dict(m.scene_brdf)
    return scene


def slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name)


def dense_session(root: Path, m: Material, seed: int = 0, size: tuple[int, int] = SIZE,
                  theta: tuple[float, ...] = DENSE_THETA,
                  phi: tuple[float, ...] = DENSE_PHI) -> Path:  # fmt: skip
    """Capture and reduce the dense grid of ``m`` into ``root/slug`` (reused when done)."""
    import tomli_w

    from gonio.app.simulation import run_simulated_session
    from gonio.capture.manifest import load_manifest
    from gonio.capture.reduce import reduce_session
    from gonio.capture.reduction_config import resolve_setup
    from gonio.rig.config import virtual_rig_document

    d = root / slug(m.name)
    session = d / "session"
    if (session / "samples.h5").is_file():
        return session
    d.mkdir(parents=True, exist_ok=True)
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "scene.toml").write_text(tomli_w.dumps(_scene(m, size)))
    (d / "plan.toml").write_text(tomli_w.dumps(plan_document(theta, phi, seed, size)))
    if session.exists():
        import shutil

        shutil.rmtree(session)
    from gonio.app.devices import device_opener
    from gonio.capture.sessions import SessionStopped, resume_session
    from gonio.errors import GonioError

    try:
        run_simulated_session(session, d / "plan.toml", d / "rig.toml", "virtual",
                              world="perfect", world_seed=seed, quiet=True)  # fmt: skip
    except SessionStopped:
        # a loaded machine can starve the virtual bus (no status packet): the rig parks
        # and the session resumes, as in a lab
        for attempt in range(8):
            try:
                resume_session(session, device_opener(time_scale="virtual"))
                break
            except GonioError:
                if attempt == 7:
                    raise
    setup = dataclasses.replace(resolve_setup(session, load_manifest(session)), grid=6)
    reduce_session(session, setup=setup, plot=False)
    return session


@dataclass
class MeasuredPool:
    """A dense session as a pool of measured poses.

    Attributes
    ----------
    samples
        All samples (``gonio.dataset.BRDFSamples``) with ``pose`` (N,) their pose index.
    pose_ids
        (P,) the sample poses' indices.
    wi, wo
        (P, 3) each pose's requested directions (sample frame).
    joints
        Per pose the joint angles (rad).
    exposure_s
        (P,) total exposure of each pose's bracket (s); ``frames`` (P,) its frame count.
    kinematics, park
        The rig's kinematics and park joints (for travel times).
    """

    samples: Any
    pose_ids: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    joints: list[dict[str, float]]
    exposure_s: np.ndarray
    frames: np.ndarray
    kinematics: Any
    park: dict[str, float]
    reference_time_s: float

    def subset(self, poses: Any) -> Any:
        """The samples of the poses at positions ``poses`` (indices into ``pose_ids``)."""
        keep = np.isin(self.samples.pose, self.pose_ids[np.asarray(poses, dtype=int)])
        return _take(self.samples, keep)


def _take(s: Any, keep: np.ndarray) -> Any:
    """The samples ``keep`` of ``s`` (per-sample arrays cut, the rest kept)."""
    n = len(s.wi)
    kw = {}
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if isinstance(v, np.ndarray) and v.shape[:1] == (n,):
            v = v[keep]
        elif isinstance(v, dict) and f.name == "budget":
            v = {k: (a[keep] if isinstance(a, np.ndarray) and a.shape[:1] == (n,) else a)
                 for k, a in v.items()}  # fmt: skip
        kw[f.name] = v
    return type(s)(**kw)


def load_pool(session: Path) -> MeasuredPool:
    """The dense session's samples, per-pose directions, joints and shots."""
    from gonio.capture.journal import read_journal
    from gonio.dataset import load_samples
    from gonio.rig.config import load_rig_config
    from gonio.rig.kinematics import Kinematics

    samples = load_samples(session / "samples.h5")
    recs = read_journal(session / "journal.jsonl")
    shots: dict[int, list[dict]] = {}
    for r in recs:
        if r.get("type") == "shot":
            shots.setdefault(int(r["pose"]), []).append(r)
    ids = np.unique(samples.pose[samples.pose >= 0])
    ids = np.array([i for i in ids if i in shots and shots[i][0]["kind"] == "sample"])
    wi = np.array([shots[i][0]["wi_requested"] for i in ids], dtype=np.float64)
    wo = np.array([shots[i][0]["wo_requested"] for i in ids], dtype=np.float64)
    joints = [dict(shots[i][0]["joints"]) for i in ids]
    expo = np.array([sum(s["exposure_time"] for s in shots[i]) for i in ids])
    frames = np.array([len(shots[i]) for i in ids])
    ref = [r for k, v in shots.items() if v[0]["kind"] == "reference" for r in v]
    ref_time = sum(s["exposure_time"] + SHOT_OVERHEAD_S for s in ref)
    man = json.loads((session / "manifest.json").read_text())
    del man
    cfg = load_rig_config(session.parent / "rig.toml")
    kin = Kinematics(cfg)
    return MeasuredPool(samples, ids, wi, wo, joints, expo, frames, kin,
                        dict(cfg.park_rad), ref_time)  # fmt: skip


def session_time_s(pool: MeasuredPool, batches: list[list[int]]) -> float:
    """Estimated session time (s) of measuring ``batches`` of pool positions in turn.

    Travel (each batch ordered for the least servo travel from where the rig is, by the
    plan scheduler's own ordering, :func:`gonio.capture.ordering.order_poses`) plus the
    exposures and the download of every frame (``shot_overhead_s`` each) plus the
    reference group (shot once).  A regular grid is one batch.
    """
    from gonio.capture.ordering import move_time_matrix, order_poses, tour_time

    t = pool.reference_time_s
    here = pool.park
    for b in batches:
        if not len(b):
            continue
        js = [pool.joints[k] for k in b]
        D = move_time_matrix(js, pool.kinematics.move_time, start=here)
        tour = order_poses(D, start=0)
        t += tour_time(D, tour)
        here = js[tour[-1] - 1]
        t += float(np.sum(pool.exposure_s[b]) + SHOT_OVERHEAD_S * np.sum(pool.frames[b]))
    return t


def grid_positions(pool: MeasuredPool, theta_step: float, phi_step: float) -> list[int]:
    """Pool positions of the regular grid (theta_i, theta_o every ``theta_step``, phi_o
    every ``phi_step`` deg): the dense poses whose requested angles lie on it."""
    ti = np.degrees(np.arccos(np.clip(pool.wi[:, 2], -1, 1)))
    to = np.degrees(np.arccos(np.clip(pool.wo[:, 2], -1, 1)))
    dphi = np.degrees(
        np.arctan2(pool.wo[:, 1], pool.wo[:, 0]) - np.arctan2(pool.wi[:, 1], pool.wi[:, 0])
    )
    dphi = np.abs((dphi + 180.0) % 360.0 - 180.0)
    # a pose at theta 0 has any azimuth: it lies on every azimuth grid
    on_phi = (np.abs(np.round(dphi / phi_step) * phi_step - dphi) < 0.5) | (ti < 0.5) | (to < 0.5)

    def on(t: np.ndarray) -> np.ndarray:
        return np.abs(np.round(t / theta_step) * theta_step - t) < 0.5

    return [int(k) for k in np.flatnonzero(on(ti) & on(to) & on_phi)]


if __name__ == "__main__":
    root = Path(sys.argv[1])
    want = set(sys.argv[2:])
    for m in materials():
        if want and m.name not in want:
            continue
        s = dense_session(root, m)
        p = load_pool(s)
        print(m.name, len(p.pose_ids), "poses", len(p.samples.wi), "samples", flush=True)


def adaptive_session(root: Path, m: Material, *, seed_poses: int = 24, batch_poses: int = 8,
                     max_poses: int = 48, seed: int = 0,
                     size: tuple[int, int] = SIZE) -> Path:  # fmt: skip
    """A real adaptive session of ``m`` (A1's engine, ``run_session`` with an
    ``[adaptive]`` plan and :class:`gonio.app.adaptive_advisor.FitAdvisor`, whose choices
    are :mod:`gonio.fitting.design`'s), reduced as the dense sessions are."""
    import tomli_w

    from gonio.app.adaptive_advisor import FitAdvisor
    from gonio.app.simulation import simulated_run
    from gonio.capture.manifest import load_manifest
    from gonio.capture.plan import load_plan
    from gonio.capture.reduce import reduce_session
    from gonio.capture.reduction_config import resolve_setup
    from gonio.capture.sessions import run_session
    from gonio.rig.config import load_rig_config, virtual_rig_document

    d = root / ("adaptive_" + slug(m.name))
    session = d / "session"
    if (session / "samples.h5").is_file():
        return session
    d.mkdir(parents=True, exist_ok=True)
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "scene.toml").write_text(tomli_w.dumps(_scene(m, size)))
    plan = plan_document(DENSE_THETA, DENSE_PHI, seed, size)
    del plan["grid"]
    plan["adaptive"] = {
        "seed_poses": seed_poses,
        "batch_poses": batch_poses,
        "max_poses": max_poses,
        "pool_step_deg": 10.0,
    }
    (d / "plan.toml").write_text(tomli_w.dumps(plan))
    if session.exists():
        import shutil

        shutil.rmtree(session)
    p = load_plan(d / "plan.toml")
    sim = simulated_run(p, d / "plan.toml", None, "virtual", "perfect", seed)
    run_session(session, p, load_rig_config(d / "rig.toml"), sim.opener,
                camera_backend="simulated", simulation=sim.simulation,
                attachments=sim.attachments, advisor=lambda plan: FitAdvisor(plan))  # fmt: skip
    setup = dataclasses.replace(resolve_setup(session, load_manifest(session)), grid=6)
    reduce_session(session, setup=setup, plot=False)
    return session
