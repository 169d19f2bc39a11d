"""Every ``gonio`` command fed broken input, as a demanding user would.

For each case the real entry point runs in a subprocess (``python -m gonio ...``) and
must: exit with the expected non-zero status (2 for click usage errors, 1 for gonio
errors), print a message naming the file, field or value and what was expected, print
no Python traceback, and leave the disk exactly as it was (an existing output is
byte-identical, no partial output appears).

The broken inputs are what users really produce: missing files, directories where files
are expected, empty files, a ``.toml`` that is not TOML, TOML with a wrong field type or
an unknown key, garbage with the right extension (DNG, RGL .bsdf, HDF5), an HDF5 file
that is not a samples file, out-of-range and non-finite numbers, unknown names, a serial
port that does not exist, and outputs that already exist.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "examples"
PRECIOUS = b"precious: must survive\n"
NOPORT = "/dev/ttyNOPE"


@dataclass(frozen=True)
class Case:
    """One broken invocation and what the user must see."""

    id: str
    args: tuple[str, ...]
    code: int
    expect: tuple[str, ...]  # substrings of stderr (case-insensitive)
    needs_rgl: bool = False


def case(id, args, code, *expect, rgl=False) -> Case:
    return Case(id, tuple(args.split()), code, tuple(expect), rgl)


RUN = "capture run {ex}/plan.toml --camera simulated --out {tmp}/S"
VRUN = RUN + " --rig {bad}/rig_virtual.toml"
NOISE = "capture calibrate-noise --flat {bad}/garbage.dng --flat {bad}/garbage.dng"

# Placeholders: {bad} broken input files, {ex} examples/, {tmp} the case's own folder
# (holding keep.* outputs and keepdir/ with a fit.json), {rgl} a real RGL .bsdf file.
CASES = [
    # -- gonio brdf ------------------------------------------------------------------
    case("brdf-list-extra", "brdf list extra", 2, "unexpected extra argument (extra)"),
    case("info-missing", "brdf info {bad}/nope.bsdf", 2, "nope.bsdf", "does not exist"),
    case("info-dir", "brdf info {bad}/adir", 2, "adir", "is a directory"),
    case("info-empty", "brdf info {bad}/empty.bsdf", 1, "empty.bsdf", "0 bytes", "expected"),
    case("info-garbage", "brdf info {bad}/garbage.bsdf", 1, "garbage.bsdf", "expected an rgl"),
    case("info-garbage-merl", "brdf info {bad}/garbage.binary", 1, "garbage.binary", "merl"),
    case("info-toml", "brdf info {bad}/bad.toml", 1, "bad.toml", "unrecognised"),
    case("info-h5", "brdf info {bad}/other.h5", 1, "other.h5", "unrecognised"),
    case("info-truncated", "brdf info {bad}/trunc.bsdf", 1, "trunc.bsdf", "truncated", rgl=True),
    case("info-theta-text", "brdf info {rgl} --theta-i-deg abc", 2, "'abc'", "degrees", rgl=True),
    case("info-theta-range", "brdf info {rgl} --theta-i-deg 95", 2, "'95'", "[0, 90)", rgl=True),
    case("albedo-unknown", "brdf albedo nosuch", 1, "unknown brdf model 'nosuch'", "lambert"),
    case("albedo-bounds", "brdf albedo lambert -p albedo=2", 1, "'albedo'", "= 2", "[0, 1]"),
    case("albedo-param", "brdf albedo lambert -p foo=1", 1, "'foo'", "parameters are: albedo"),
    case("albedo-no-value", "brdf albedo lambert -p albedo", 2, "name=value", "'albedo'"),
    case("albedo-nan-text", "brdf albedo lambert -p albedo=x", 2, "albedo", "'x'", "number"),
    case("albedo-rgb", "brdf albedo lambert -p albedo=1,2", 2, "albedo", "1 value or 3"),
    case("albedo-theta", "brdf albedo lambert --theta-i 100", 2, "--theta-i", "[0, 90]", "100"),
    case("albedo-garbage", "brdf albedo {bad}/garbage.bsdf", 1, "garbage.bsdf", "expected"),
    case("plot-unknown", "brdf plot gxx -o {tmp}/new.png", 1, "unknown brdf model 'gxx'"),
    case("plot-exists", "brdf plot lambert -o {tmp}/keep.png", 2, "keep.png", "exists", "--force"),
    case("plot-suffix", "brdf plot lambert -o {tmp}/a.xyz", 2, "'.xyz'", ".png"),
    case("plot-dir", "brdf plot lambert -o {tmp}/keepdir", 2, "keepdir", "is a directory"),
    case("plot-phi-nan", "brdf plot lambert --phi-i nan -o {tmp}/n.png", 2, "--phi-i", "nan"),
    case("plot-bounds", "brdf plot ggx -p alpha=2 -o {tmp}/keep.png", 1, "'alpha'", "bounds"),
    case("convert-garbage", "brdf convert {bad}/garbage.bsdf {tmp}/n.binary", 1, "garbage.bsdf"),
    case(
        "convert-exists",
        "brdf convert {rgl} {tmp}/keep.binary",
        1,
        "keep.binary",
        "--force",
        rgl=True,
    ),
    case("convert-suffix", "brdf convert {rgl} {tmp}/n.txt", 2, "n.txt", ".binary", rgl=True),
    case(
        "convert-no-folder", "brdf convert {rgl} {tmp}/no/n.binary", 2, "does not exist", rgl=True
    ),
    # -- gonio sim ---------------------------------------------------------------------
    case(
        "render-not-toml",
        "sim render {bad}/bad.toml --out {tmp}/a.dng",
        1,
        "bad.toml",
        "not a valid toml",
    ),
    case(
        "render-empty",
        "sim render {bad}/empty.toml --out {tmp}/a.dng",
        1,
        "empty.toml",
        "'camera'",
        "required",
    ),
    case("render-dir", "sim render {bad}/adir --out {tmp}/a.dng", 2, "adir", "is a directory"),
    case(
        "render-missing",
        "sim render {bad}/nope.toml --out {tmp}/a.dng",
        1,
        "nope.toml",
        "not found",
    ),
    case(
        "render-type",
        "sim render {bad}/scene_type.toml --out {tmp}/a.dng",
        1,
        "camera.exposure_time",
        "'fast'",
    ),
    case(
        "render-unknown-key",
        "sim render {bad}/scene_key.toml --out {tmp}/a.dng",
        1,
        "'bogus_key'",
        "not permitted",
    ),
    case(
        "render-brdf-model",
        "sim render {bad}/scene_model.toml --out {tmp}/a.dng",
        1,
        "scene_model.toml",
        "sample.brdf",
        "'nosuch'",
    ),
    case(
        "render-brdf-file",
        "sim render {bad}/scene_file.toml --out {tmp}/a.dng",
        1,
        "scene_file.toml",
        "nope.bsdf",
        "does not exist",
    ),
    case(
        "render-exists", "sim render {ex}/scene.toml --out {tmp}/keep.dng", 1, "keep.dng", "--force"
    ),
    case(
        "render-truth-exists",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --truth {tmp}/keep.h5",
        1,
        "keep.h5",
        "--force",
    ),
    case(
        "render-truth-folder",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --truth {tmp}/no/t.h5",
        2,
        "--truth",
        "does not exist",
    ),
    case(
        "render-suffix", "sim render {ex}/scene.toml --out {tmp}/a.txt", 2, "--out", ".dng", "a.txt"
    ),
    case(
        "render-preview-suffix",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --preview {tmp}/p.txt",
        2,
        "--preview",
        "p.txt",
    ),
    case("render-iso", "sim render {ex}/scene.toml --out {tmp}/a.dng --iso -5", 2, "--iso", "-5"),
    case(
        "render-f-nan",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --f-number nan",
        2,
        "--f-number",
        "nan",
    ),
    case(
        "render-exposure",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --exposure-time 0",
        2,
        "--exposure-time",
        "positive",
    ),
    case(
        "render-tolerance",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --tolerance -1",
        2,
        "--tolerance",
        "-1",
    ),
    case(
        "render-strategy",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --strategy fast",
        2,
        "'fast'",
        "auto",
    ),
    # issue 14: huge exposures, huge renders, pickled albedo maps
    case(
        "render-exposure-huge",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --exposure-time 1e308",
        2,
        "--exposure-time",
        "at most 3600",
    ),
    case(
        "render-scene-exposure-huge",
        "sim render {bad}/scene_exposure.toml --out {tmp}/a.dng",
        1,
        "scene_exposure.toml",
        "camera.exposure_time",
        "less than or equal to 3600",
    ),
    case(
        "render-scene-exposure-inf",
        "sim render {bad}/scene_exposure_inf.toml --out {tmp}/a.dng",
        1,
        "scene_exposure_inf.toml",
        "camera.exposure_time",
        "finite",
    ),
    case(
        "render-huge",
        "sim render {bad}/scene_huge.toml --out {tmp}/a.dng",
        1,
        "scene_huge.toml",
        "camera.resolution",
        "20000 x 20000",
        "GB of memory",
    ),
    case(
        "render-memory-limit",
        "sim render {ex}/scene.toml --out {tmp}/a.dng --max-memory-gb 0.01",
        1,
        "scene.toml",
        "640 x 480",
        "0.01 GB allowed",
    ),
    case(
        "render-albedo-pickle",
        "sim render {bad}/scene_pickle.toml --out {tmp}/a.dng",
        1,
        "scene_pickle.toml",
        "sample.albedo_map",
        "pickled.npy",
        "python objects",
    ),
    case("bus-ids-text", "sim bus --servos a,b", 2, "--servos", "'a,b'", "integers"),
    case("bus-id-range", "sim bus --servos 1,300", 2, "--servos", "0..252", "300"),
    case("bus-id-dup", "sim bus --servos 1,1", 2, "--servos", "duplicate"),
    case("bus-no-ids", "sim bus --servos ,", 2, "--servos", "at least one"),
    case(
        "bus-positions", "sim bus --servos 1,2 --positions 1", 2, "--positions", "1 positions for 2"
    ),
    case("bus-baud", "sim bus --baud 12345", 2, "--baud", "'12345'", "1000000"),
    case("bus-fault-rate", "sim bus --fault-rate 2", 2, "--fault-rate", "0<=x<=1"),
    case("bus-time-scale", "sim bus --time-scale 0", 2, "--time-scale", "0.001<=x<=1000000"),
    case("bus-model", "sim bus --model XZ999", 2, "'XZ999'", "XM430-W350"),
    case("bus-rig-not-toml", "sim bus --rig {bad}/bad.toml", 1, "bad.toml", "not a valid toml"),
    case("bus-rig-fields", "sim bus --rig {bad}/empty.toml", 1, "empty.toml", "'servos'"),
    case("bus-rig-missing", "sim bus --rig {bad}/nope.toml", 2, "nope.toml", "does not exist"),
    # -- gonio rig ---------------------------------------------------------------------
    case("scan-no-port", f"rig scan --port {NOPORT}", 1, NOPORT, "cannot open serial port"),
    case("scan-dir-port", "rig scan --port {bad}/adir", 1, "adir", "cannot open serial port"),
    case(
        "scan-file-port", "rig scan --port {bad}/bad.toml", 1, "bad.toml", "cannot open serial port"
    ),
    case(
        "scan-baud", f"rig scan --port {NOPORT} --baud 12345", 1, "baud rate 12345", "not supported"
    ),
    case("scan-no-option", "rig scan", 2, "--port"),
    case("status-no-port", f"rig status --port {NOPORT}", 1, NOPORT, "cannot open serial port"),
    case(
        "status-not-toml", "rig status --config {bad}/bad.toml", 1, "bad.toml", "not a valid toml"
    ),
    case(
        "status-empty",
        "rig status --config {bad}/empty.toml",
        1,
        "empty.toml",
        "'servos'",
        "required",
    ),
    case("status-dir", "rig status --config {bad}/adir", 2, "adir", "is a directory"),
    case("status-missing", "rig status --config {bad}/nope.toml", 1, "nope.toml", "not found"),
    case(
        "status-type",
        "rig status --config {bad}/rig_type.toml",
        1,
        "bus.baud_rate",
        "'fast'",
        "integer",
    ),
    case("status-id", "rig status --config {bad}/rig_id.toml", 1, "servos.0.id", "252", "999"),
    case(
        "status-model", "rig status --config {bad}/rig_model.toml", 1, "servos.0.model", "'XZ999'"
    ),
    case(
        "status-unknown-key",
        "rig status --config {bad}/rig_key.toml",
        1,
        "'bogus'",
        "not permitted",
    ),
    case("move-no-port", f"rig move --port {NOPORT} --theta-i 30 --theta-o 30", 1, NOPORT),
    case(
        "move-theta-range",
        f"rig move --port {NOPORT} --theta-i 200 --theta-o 30",
        2,
        "--theta-i",
        "[0, 90]",
        "200",
    ),
    case(
        "move-theta-nan",
        f"rig move --port {NOPORT} --theta-i 30 --theta-o nan",
        2,
        "--theta-o",
        "nan",
    ),
    case(
        "move-phi-inf",
        f"rig move --port {NOPORT} --theta-i 30 --theta-o 30 --phi-o inf",
        2,
        "--phi-o",
        "inf",
    ),
    case("move-missing", f"rig move --port {NOPORT} --theta-i 30", 2, "--theta-o"),
    case("move-config", "rig move --config {bad}/bad.toml --theta-i 1 --theta-o 1", 1, "bad.toml"),
    case("home-no-port", f"rig home --port {NOPORT}", 1, NOPORT, "cannot open serial port"),
    case("home-config", "rig home --config {bad}/rig_type.toml", 1, "bus.baud_rate"),
    case("off-no-port", f"rig off --port {NOPORT}", 1, NOPORT, "cannot open serial port"),
    case("off-config", "rig off --config {bad}/empty.toml", 1, "empty.toml", "'servos'"),
    # -- gonio capture -----------------------------------------------------------------
    case("plan-not-toml", "capture plan {bad}/bad.toml", 1, "bad.toml", "not a valid toml"),
    case("plan-empty", "capture plan {bad}/empty.toml", 1, "empty.toml", "'grid'", "required"),
    case("plan-dir", "capture plan {bad}/adir", 2, "adir", "is a directory"),
    case("plan-missing", "capture plan {bad}/nope.toml", 1, "nope.toml", "not found"),
    case("plan-type", "capture plan {bad}/plan_type.toml", 1, "bracket.iso", "'high'"),
    case("plan-kind", "capture plan {bad}/plan_kind.toml", 1, "grid.kind", "'cubic'", "spherical"),
    case("plan-range", "capture plan {bad}/plan_range.toml", 1, "theta_i_deg", "[0, 90]", "400"),
    case("plan-step", "capture plan {bad}/plan_step.toml", 1, "theta_o_deg.step", "greater than 0"),
    case("plan-settle", "capture plan {bad}/plan_settle.toml", 1, "'settle_s'", "60"),
    case("plan-exposure-inf", "capture plan {bad}/plan_inf.toml", 1, "exposure_time_s", "finite"),
    case(
        "plan-too-large",
        "capture plan {bad}/plan_huge.toml",
        1,
        "plan_huge.toml",
        "too large",
        "972,002 poses > limits.max_poses",
        "972,000 grid poses",
    ),
    case(
        "plan-rig", "capture plan {ex}/plan.toml --rig {bad}/rig_id.toml", 1, "rig_id.toml", "999"
    ),
    case(
        "plan-plot-exists",
        "capture plan {ex}/plan.toml --plot {tmp}/keep.png",
        2,
        "keep.png",
        "--force",
    ),
    case(
        "plan-plot-folder",
        "capture plan {ex}/plan.toml --plot {tmp}/no/p.png",
        2,
        "--plot",
        "does not exist",
    ),
    case(
        "plan-plot-suffix",
        "capture plan {ex}/plan.toml --plot {tmp}/p.txt",
        2,
        "--plot",
        "p.txt",
        ".png",
    ),
    case(
        "run-nonempty-out",
        "capture run {ex}/plan.toml --camera simulated --out {tmp}/keepdir",
        1,
        "keepdir",
        "not an empty directory",
    ),
    case(
        "run-out-file",
        "capture run {ex}/plan.toml --camera simulated --out {tmp}/keep.h5",
        2,
        "keep.h5",
        "is a file",
    ),
    case(
        "run-not-toml",
        "capture run {bad}/bad.toml --camera simulated --out {tmp}/S",
        1,
        "bad.toml",
        "not a valid toml",
    ),
    case(
        "run-rig",
        "capture run {ex}/plan.toml --rig {bad}/bad.toml --camera simulated --out {tmp}/S",
        1,
        "bad.toml",
    ),
    case(
        "run-scene",
        VRUN + " --scene {bad}/bad.toml",
        1,
        "bad.toml",
        "toml",
    ),
    case(
        "run-scene-type",
        VRUN + " --scene {bad}/scene_type.toml",
        1,
        "scene_type.toml",
        "camera.exposure_time",
        "'fast'",
    ),
    case(
        "run-no-port",
        RUN + " --rig {bad}/rig_noport.toml --quiet",
        1,
        NOPORT,
        "cannot open serial port",
    ),
    case(
        "run-sim-speed",
        VRUN + " --sim-speed -1",
        2,
        "--sim-speed",
        "-1",
    ),
    case(
        "run-sim-speed-nan",
        VRUN + " --sim-speed nan",
        2,
        "--sim-speed",
        "nan",
    ),
    case(
        "run-camera",
        "capture run {ex}/plan.toml --camera webcam --out {tmp}/S",
        2,
        "'webcam'",
        "simulated",
    ),
    case("resume-missing", "capture resume {tmp}/nope", 2, "nope", "does not exist"),
    case(
        "resume-not-session",
        "capture resume {bad}/adir --camera simulated",
        1,
        "adir",
        "no manifest.json",
    ),
    case(
        "resume-corrupt",
        "capture resume {bad}/sess_corrupt --camera simulated",
        1,
        "manifest.json",
        "cannot read",
    ),
    case(
        "resume-schema",
        "capture resume {bad}/sess_empty --camera simulated",
        1,
        "manifest.json",
        "schema_version",
    ),
    case("resume-sim-speed", "capture resume {bad}/adir --sim-speed 0", 2, "--sim-speed", "0"),
    case("inspect-file", "capture inspect {bad}/bad.toml", 2, "bad.toml", "is a file"),
    case("inspect-not-session", "capture inspect {bad}/adir", 1, "adir", "no manifest.json"),
    case(
        "inspect-corrupt", "capture inspect {bad}/sess_corrupt", 1, "manifest.json", "cannot read"
    ),
    case("reduce-not-session", "capture reduce {bad}/adir", 1, "adir", "no manifest.json"),
    case("reduce-corrupt", "capture reduce {bad}/sess_corrupt", 1, "manifest.json", "cannot read"),
    case("reduce-grid", "capture reduce {bad}/adir --grid 0", 2, "--grid", "1<=x<=20"),
    case("reduce-threads", "capture reduce {bad}/adir --threads 0", 2, "--threads", "1<=x<=64"),
    case(
        "reduce-noise-garbage",
        "capture reduce {bad}/sess_corrupt --noise {bad}/garbage.h5",
        1,
        "garbage.h5",
        "noise model",
    ),
    case(
        "noise-garbage",
        NOISE + " --out {tmp}/n.json",
        1,
        "garbage.dng",
        "raw file",
    ),
    case(
        "noise-empty",
        "capture calibrate-noise --flat {bad}/empty.h5 --flat {bad}/empty.h5 --out {tmp}/n.json",
        1,
        "empty.h5",
        "empty",
    ),
    case(
        "noise-missing",
        "capture calibrate-noise --flat {bad}/nope.dng --out {tmp}/n.json",
        2,
        "nope.dng",
        "does not exist",
    ),
    case(
        "noise-exists",
        NOISE + " --out {tmp}/keep.json",
        1,
        "keep.json",
        "exists",
    ),
    # -- gonio fit ---------------------------------------------------------------------
    case(
        "fit-garbage-h5",
        "fit {bad}/garbage.h5 --out {tmp}/F",
        1,
        "garbage.h5",
        "not a readable hdf5",
    ),
    case("fit-empty-h5", "fit {bad}/empty.h5 --out {tmp}/F", 1, "empty.h5", "hdf5"),
    case(
        "fit-other-h5",
        "fit {bad}/other.h5 --out {tmp}/F",
        1,
        "other.h5",
        "'schema'",
        "gonio.samples",
    ),
    case("fit-h5-field", "fit {bad}/nobrdf.h5 --out {tmp}/F", 1, "nobrdf.h5", "'brdf'", "missing"),
    case("fit-h5-type", "fit {bad}/textwi.h5 --out {tmp}/F", 1, "textwi.h5", "'wi'", "numbers"),
    case("fit-h5-version", "fit {bad}/version.h5 --out {tmp}/F", 1, "'schema_version'", "'one'"),
    case(
        "fit-h5-no-samples", "fit {bad}/nosamples.h5 --out {tmp}/F", 1, "nosamples.h5", "no samples"
    ),
    case("fit-h5-non-unit", "fit {bad}/nonunit.h5 --out {tmp}/F", 1, "nonunit.h5", "'wo'", "unit"),
    case("fit-h5-float-flags", "fit {bad}/floatflags.h5 --out {tmp}/F", 1, "'flags'", "integers"),
    case("fit-toml", "fit {bad}/bad.toml --out {tmp}/F", 1, "bad.toml", "unrecognised"),
    case("fit-garbage-bsdf", "fit {bad}/garbage.bsdf --out {tmp}/F", 1, "garbage.bsdf", "expected"),
    case("fit-dir", "fit {bad}/adir --out {tmp}/F", 1, "adir", "no samples.h5, .bsdf or .binary"),
    case("fit-missing", "fit {bad}/nope.h5 --out {tmp}/F", 2, "nope.h5", "does not exist"),
    case("fit-model", "fit {rgl} -m nosuch --out {tmp}/F", 1, "'nosuch'", "lambert", rgl=True),
    case(
        "fit-candidates",
        "fit {rgl} --candidates lambert,nosuch --out {tmp}/F",
        1,
        "'nosuch'",
        rgl=True,
    ),
    case(
        "fit-algorithm",
        "fit {rgl} --algorithm NOPE --out {tmp}/F",
        1,
        "'NOPE'",
        "LD_LBFGS",
        rgl=True,
    ),
    case("fit-f-scale", "fit {rgl} --f-scale -1 --out {tmp}/F", 2, "--f-scale", "-1", rgl=True),
    case("fit-loss", "fit {bad}/garbage.h5 --loss l3 --out {tmp}/F", 2, "'l3'", "weighted_l2"),
    case(
        "fit-out-exists",
        "fit {rgl} -m lambert --out {tmp}/keepdir",
        1,
        "keepdir",
        "fit.json",
        "--force",
        rgl=True,
    ),
    case("fit-out-file", "fit {rgl} --out {tmp}/keep.h5", 2, "keep.h5", "is a file", rgl=True),
    # -- gonio demo --------------------------------------------------------------------
    case("demo-model", "demo --material nosuch --out {tmp}/D", 1, "unknown brdf model 'nosuch'"),
    case("demo-bounds", "demo --material lambert_albedo=5 --out {tmp}/D", 1, "'albedo'", "[0, 1]"),
    case(
        "demo-number", "demo --material lambert_albedo=abc --out {tmp}/D", 1, "albedo=abc", "number"
    ),
    case("demo-param", "demo --material lambert_foo=1 --out {tmp}/D", 1, "'foo'", "albedo"),
    case(
        "demo-file-missing",
        "demo --material {bad}/nope.bsdf --out {tmp}/D",
        1,
        "nope.bsdf",
        "no such file",
    ),
    case(
        "demo-file-garbage",
        "demo --material {bad}/garbage.bsdf --out {tmp}/D",
        1,
        "garbage.bsdf",
        "expected",
    ),
    case(
        "demo-rgl",
        "demo --material rgl:nosuch --out {tmp}/D",
        1,
        "nosuch_rgb.bsdf",
        "not found",
        "gonio_refdata",
    ),
    case("demo-out-nonempty", "demo --out {tmp}/keepdir", 1, "keepdir", "not empty"),
    case("demo-out-file", "demo --out {tmp}/keep.h5", 2, "keep.h5", "is a file"),
    case("demo-resolution", "demo --resolution 0 0 --out {tmp}/D", 2, "--resolution", "8<=x"),
    case("demo-fit-model", "demo --model nosuch --out {tmp}/D", 1, "unknown brdf model 'nosuch'"),
    case("demo-poses", "demo --poses 5 --out {tmp}/D", 2, "--poses", "10<=x<=5000"),
]


def _sed(src: Path | str, old: str, new: str) -> str:
    text = src.read_text() if isinstance(src, Path) else src
    assert old in text, f"{old!r} not in {src}: update this test's broken input"
    return text.replace(old, new, 1)


def _huge_plan(plan: Path) -> str:
    """The issue's 972 000-pose dry run: 90 x 90 x 120, no symmetry reductions."""
    text = plan.read_text()
    for old, new in (
        ("theta_i_deg = [0, 20, 40, 60]", "theta_i_deg = {start=0, stop=89, step=1}"),
        ("stop = 70, step = 10", "stop = 89, step = 1"),
        ("phi_o_deg = [0, 90, 180]", "phi_o_deg = {start=0, stop=357, step=3}"),
        ("isotropic = true", "isotropic = false"),
        ("reciprocity = true", "reciprocity = false"),
    ):
        text = _sed(text, old, new)
    return text


@pytest.fixture(scope="module")
def bad(tmp_path_factory) -> Path:
    """A folder of broken inputs, written once per worker."""
    import h5py
    import numpy as np

    d = tmp_path_factory.mktemp("bad")
    rng = np.random.default_rng(1)
    (d / "adir").mkdir()
    (d / "bad.toml").write_text("this is [not toml = =\n")
    for name in ("empty.toml", "empty.bsdf", "empty.h5"):
        (d / name).write_bytes(b"")
    for name in ("garbage.dng", "garbage.bsdf", "garbage.binary", "garbage.h5"):
        (d / name).write_bytes(rng.bytes(3000))
    with h5py.File(d / "other.h5", "w") as f:  # valid HDF5, not a samples file
        f["x"] = np.arange(3)
    with h5py.File(d / "nobrdf.h5", "w") as f:  # a samples file missing a dataset
        f.attrs.update(schema="gonio.samples", schema_version=1, channels=["R", "G", "B"])
        f["wi"] = np.tile([0.0, 0.0, 1.0], (4, 1))
        f["wo"] = np.tile([0.0, 0.0, 1.0], (4, 1))
    refdata = Path(os.environ.get("GONIO_REFDATA", REPO.parent / "shared" / "data"))
    with h5py.File(d / "textwi.h5", "w") as f:  # a field of the wrong type
        f.attrs.update(schema="gonio.samples", schema_version=1, channels=["R", "G", "B"])
        f["wi"] = np.array([b"a"] * 4)
        f["wo"] = np.tile([0.0, 0.0, 1.0], (4, 1))
        f["brdf"] = np.ones((4, 3))
    with h5py.File(d / "version.h5", "w") as f:
        f.attrs.update(schema="gonio.samples", schema_version="one")
    for name, wo, flags in (  # issue 14.8
        ("nosamples.h5", np.zeros((0, 3)), np.zeros(0, np.uint32)),
        ("nonunit.h5", np.tile([0.0, 0.0, 2.0], (4, 1)), np.zeros(4, np.uint32)),
        ("floatflags.h5", np.tile([0.0, 0.0, 1.0], (4, 1)), np.zeros(4)),
    ):
        with h5py.File(d / name, "w") as f:
            f.attrs.update(schema="gonio.samples", schema_version=1, channels=["R", "G", "B"])
            f["wi"] = np.tile([0.0, 0.0, 1.0], (len(wo), 1))
            f["wo"] = wo
            f["brdf"] = np.ones((len(wo), 3))
            f["flags"] = flags
    np.save(d / "pickled.npy", np.array([{"x": 1}, None], dtype=object), allow_pickle=True)
    rgl = refdata / "rgl" / "paper_white_rgb.bsdf"
    if rgl.is_file():
        (d / "trunc.bsdf").write_bytes(rgl.read_bytes()[:1000])
    scene, rig, plan = EXAMPLES / "scene.toml", EXAMPLES / "rig.toml", EXAMPLES / "plan.toml"
    docs = {
        "scene_type.toml": _sed(scene, "exposure_time = ", 'exposure_time = "fast" # '),
        "scene_exposure.toml": _sed(scene, "exposure_time = ", "exposure_time = 1e308 # "),
        "scene_exposure_inf.toml": _sed(scene, "exposure_time = ", "exposure_time = inf # "),
        "scene_huge.toml": _sed(scene, "resolution = [640, 480]", "resolution = [20000, 20000]"),
        "scene_pickle.toml": _sed(
            scene, "[sample]\n", f"[sample]\nalbedo_map = '{d / 'pickled.npy'}'\n"
        ),
        "plan_settle.toml": _sed(plan, "settle_s = 0.2", "settle_s = 1e308"),
        "plan_inf.toml": _sed(plan, "exposure_time_s = 0.02", "exposure_time_s = inf"),
        "plan_huge.toml": _huge_plan(plan),
        "scene_key.toml": "bogus_key = 1\n" + scene.read_text(),
        "scene_model.toml": _sed(scene, 'model = "lambert+ggx"', 'model = "nosuch"'),
        "scene_file.toml": _sed(scene, 'model = "lambert+ggx"', 'file = "nope.bsdf"\n# '),
        "rig_type.toml": _sed(rig, "baud_rate = 1000000", 'baud_rate = "fast"'),
        "rig_id.toml": _sed(rig, "id = 1\n", "id = 999\n"),
        "rig_model.toml": _sed(rig, 'model = "XM430-W350"', 'model = "XZ999"'),
        "rig_key.toml": "bogus = 1\n" + rig.read_text(),
        "rig_virtual.toml": _sed(rig, 'port = "/dev/ttyUSB0"', 'port = "virtual"'),
        "rig_noport.toml": _sed(rig, 'port = "/dev/ttyUSB0"', f'port = "{NOPORT}"'),
        "plan_type.toml": _sed(plan, "iso = 100", 'iso = "high"'),
        "plan_kind.toml": _sed(plan, '\nkind = "spherical"', '\nkind = "cubic"'),
        "plan_range.toml": _sed(plan, "theta_i_deg = [0, 20, 40, 60]", "theta_i_deg = [0, 400]"),
        "plan_step.toml": _sed(plan, "stop = 70, step = 10", "stop = 70, step = 0"),
    }
    for name, text in docs.items():
        (d / name).write_text(text)
    (d / "sess_corrupt").mkdir()
    (d / "sess_corrupt" / "manifest.json").write_text('{"schema_version": 1, ')
    (d / "sess_empty").mkdir()
    (d / "sess_empty" / "manifest.json").write_text("{}")
    return d


def _snapshot(*roots: Path) -> dict[str, str]:
    """Every file and folder under ``roots`` with the sha256 of its bytes."""
    snap = {}
    for root in roots:
        for p in sorted(root.rglob("*")):
            snap[str(p)] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return snap


# Run as the user does, in a fresh interpreter (``python -m gonio``): every sim bus case
# (a bus that wrongly starts would serve forever: the subprocess can be timed out) and one
# or two per command.  The rest run in-process through the same entry point,
# ``gonio.cli.main``, which saves ~0.5 s of imports per case.
SUBPROCESS = {
    "info-garbage", "albedo-bounds", "plot-exists", "convert-no-folder",
    "render-truth-folder", "render-exists", "scan-no-port", "status-type",
    "move-theta-nan", "home-no-port", "off-no-port", "plan-plot-suffix",
    "run-sim-speed-nan", "run-no-port", "resume-corrupt", "inspect-corrupt",
    "reduce-noise-garbage", "noise-garbage", "fit-h5-field", "fit-out-exists",
    "demo-fit-model", "demo-out-nonempty",
}  # fmt: skip
SUBPROCESS |= {c.id for c in CASES if c.args[:2] == ("sim", "bus")}
assert SUBPROCESS <= {c.id for c in CASES}


def _run_subprocess(args: list[str], cwd: Path) -> tuple[int, str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "COLUMNS": "200"}
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "gonio", *args],
            capture_output=True,
            text=True,
            timeout=60,
            env=env,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"gonio {' '.join(args)} did not refuse the input: still running ({exc})")
    return proc.returncode, proc.stderr


def _run_in_process(args: list[str], capsys) -> tuple[int, str]:
    from gonio.cli import main

    capsys.readouterr()
    try:
        main(args)
        code = 0
    except SystemExit as exc:
        code = 0 if exc.code is None else exc.code
    except BaseException:  # what a user would see as a traceback
        import traceback

        pytest.fail(f"gonio {' '.join(args)} raised:\n{traceback.format_exc()}")
    return code, capsys.readouterr().err


@pytest.mark.parametrize("c", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_refused_clearly_and_harmlessly(
    c: Case, bad, tmp_path, request, capsys, monkeypatch
):
    subs = {"bad": str(bad), "ex": str(EXAMPLES), "tmp": str(tmp_path), "rgl": ""}
    if c.needs_rgl:
        subs["rgl"] = str(request.getfixturevalue("rgl_file")("paper_white"))
    for name in ("keep.png", "keep.binary", "keep.dng", "keep.h5", "keep.json"):
        (tmp_path / name).write_bytes(PRECIOUS)
    (tmp_path / "keepdir").mkdir()
    (tmp_path / "keepdir" / "fit.json").write_bytes(PRECIOUS)
    # "_" joins a --material spec's words, which the whitespace split above would part.
    args = [a.format(**subs).replace("lambert_", "lambert ") for a in c.args]
    before = _snapshot(tmp_path, bad)

    if c.id in SUBPROCESS:
        code, err = _run_subprocess(args, tmp_path)
    else:
        monkeypatch.chdir(tmp_path)
        monkeypatch.setenv("MPLBACKEND", "Agg")
        code, err = _run_in_process(args, capsys)

    assert "Traceback" not in err, f"traceback for gonio {' '.join(args)}:\n{err}"
    assert code == c.code, f"gonio {' '.join(args)} exited {code}, expected {c.code}:\n{err}"
    flat = " ".join(err.split()).lower()  # rich and click wrap long lines
    for s in c.expect:
        assert s.lower() in flat, f"{s!r} not in the message of gonio {' '.join(args)}:\n{err}"
    assert _snapshot(tmp_path, bad) == before, f"gonio {' '.join(args)} changed files on disk"


@pytest.fixture(scope="module")
def flats(tmp_path_factory) -> list[str]:
    """Three pairs of small simulated flat fields: enough for a photon-transfer fit."""
    import numpy as np

    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.scene import Camera
    from gonio.simulator.sensor import mean_electrons, simulate_raw

    d = tmp_path_factory.mktemp("flats")
    cam = Camera(resolution=(64, 48), fov_deg=40.0, position=(0, 0, 1))
    rng = np.random.default_rng(7)
    per_unit = mean_electrons(np.ones((48, 64, 3)), cam, 0.01, cam.f_number).max()
    args = []
    for level, electrons in enumerate((2000, 10000, 25000)):
        for k in range(2):
            f = simulate_raw(
                np.full((48, 64, 3), electrons / per_unit), cam, exposure_time=0.01, seed=rng
            )
            p = d / f"flat{level}{k}.dng"
            p.write_bytes(dng_bytes(f))
            args += ["--flat", str(p)]
    return args


@pytest.mark.parametrize(
    "plot, expect",
    [("keep.png", ("keep.png", "exists")), ("p.txt", ("p.txt", ".png"))],
    ids=["plot-exists", "plot-suffix"],
)
def test_calibrate_noise_checks_its_plot_path_first(plot, expect, flats, tmp_path, capsys):
    (tmp_path / "keep.png").write_bytes(PRECIOUS)
    before = _snapshot(tmp_path)
    args = ["capture", "calibrate-noise", *flats, "--out", str(tmp_path / "n.json")]
    code, err = _run_in_process([*args, "--plot", str(tmp_path / plot)], capsys)
    assert code in (1, 2) and "Traceback" not in err
    assert all(s in err for s in expect), err
    assert _snapshot(tmp_path) == before
