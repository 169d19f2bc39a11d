"""Per-texel fits (``gonio fit TEXELS.h5 --svbrdf``) against known maps.

The independent reference is the truth the texel files are made from: analytic
lambert+ggx maps (albedo, ks, alpha varying over the sample) evaluated by
``gonio.brdf`` with Gaussian noise of a known sigma per sample, written with
``gonio.texels.save_texels``.  The fitted maps must hold the truth within 3 reported
sigma for >= 95 % of the texel values.  Engines (this process, a real ``dask
scheduler`` + two ``dask worker`` processes, a LocalCluster) must give the same bits.
Exports: Mitsuba 3 loads material.xml and its BSDF, evaluated at texel uvs, must equal
gonio's evaluation of the fitted maps; MaterialX validates material.mtlx against its
standard library.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import h5py
import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.cli import run
from gonio.fitting.svbrdf import SVBRDFOptions, fit_svbrdf, plan_blocks, smooth_maps
from gonio.texels import save_texels

NX, NY, P = 4, 3, 60
REL, FLOOR = 0.02, 2e-3  # sigma = REL f + FLOOR (1/sr), known to the fit


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform in solid angle over theta <= 80 deg."""
    z = math.cos(math.radians(80.0)) + (1 - math.cos(math.radians(80.0))) * rng.random(n)
    phi = 2 * np.pi * rng.random(n)
    s = np.sqrt(1 - z * z)
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)


def truth_maps(nx: int = NX, ny: int = NY) -> dict[str, np.ndarray]:
    """(ny, nx, 3) maps; row 0 at +y, column 0 at -x."""
    yy, xx = np.mgrid[0:ny, 0:nx] / np.array([max(ny - 1, 1), max(nx - 1, 1)])[:, None, None]
    albedo = np.stack([0.2 + 0.4 * xx, 0.3 + 0.3 * yy, np.full(xx.shape, 0.25)], -1)
    ks = (0.1 + 0.2 * yy)[..., None] * np.array([1.0, 0.9, 0.8])
    alpha = np.repeat((0.08 + 0.3 * xx)[..., None], 3, -1)
    return {"albedo": albedo, "ks": ks, "alpha": alpha}


def write_texel_file(path: Path, truth: dict, seed: int = 0, n_poses: int = P) -> Path:
    ny, nx = truth["albedo"].shape[:2]
    t_count = nx * ny
    rng = np.random.default_rng(seed)
    wi = np.empty((t_count, n_poses, 3))
    wo = np.empty((t_count, n_poses, 3))
    for t in range(t_count):
        wi[t] = _directions(rng, n_poses)
        # half the pairs near the mirror direction, so the narrow lobes are sampled
        wo[t] = _directions(rng, n_poses)
        k = n_poses // 2
        h = np.column_stack([0.3 * rng.standard_normal((k, 2)), np.ones(k)])
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        m = 2 * np.sum(wi[t, :k] * h, axis=1, keepdims=True) * h - wi[t, :k]
        good = m[:, 2] > 0.05
        wo[t, :k][good] = m[good]
    p = {k: v.reshape(t_count, 1, 3) for k, v in truth.items()}
    f = get_model("lambert+ggx").eval(
        wi[:, :, None, :], wo[:, :, None, :], {**p, "alpha": p["alpha"][..., :1]}
    )
    sig = REL * f + FLOOR
    y = f + sig * rng.standard_normal(f.shape)
    flags = np.zeros((t_count, n_poses), np.uint32)
    save_texels(
        path, wi=wi, wo=wo, brdf=y, brdf_std=sig, flags=flags,
        pose=np.arange(n_poses, dtype=np.int32), texels=(nx, ny), sample_size=(0.04, 0.03),
        chunk_texels=3,
    )  # fmt: skip
    return path


@pytest.fixture(scope="module")
def texel_file(tmp_path_factory) -> Path:
    return write_texel_file(tmp_path_factory.mktemp("tex") / "texels.h5", truth_maps())


@pytest.fixture(scope="module")
def cli_out(texel_file) -> Path:
    """The CLI in this process (``--workers 0``), blocks of 3 texels."""
    out = texel_file.parent / "svbrdf"
    code = run(
        "fit", str(texel_file), "--svbrdf", "-m", "lambert+ggx", "--workers", "0",
        "--block-texels", "3",
    )  # fmt: skip
    assert code == 0
    return out


def _maps(out: Path) -> dict:
    with h5py.File(out / "svbrdf.h5", "r") as f:
        return {
            "params": {k: f[f"params/{k}"][()] for k in f["params"]},
            "std": {k: f[f"std/{k}"][()] for k in f["std"]},
            **{k: f[k][()] for k in ("cost", "rms_residual", "n_samples", "success")},
            "attrs": dict(f.attrs),
        }


# ------------------------------------------------------------------ accuracy


def test_maps_within_three_sigma_of_truth(cli_out, capsys):
    truth = truth_maps()
    d = _maps(cli_out)
    assert d["attrs"]["schema"] == "gonio.svbrdf"
    assert list(d["attrs"]["texels"]) == [NX, NY]
    assert d["success"].all() and (d["n_samples"] == P).all()
    z_all, rel = [], {}
    for k, t in truth.items():
        v, s = d["params"][k], d["std"][k]
        assert v.shape == (NY, NX, 3)
        z = np.abs(v - t) / s
        z_all.append(z[..., :1] if k == "alpha" else z)  # alpha: one value per texel
        rel[k] = float(np.median(np.abs(v / t - 1)))
    frac = float(np.mean(np.concatenate([z.ravel() for z in z_all]) < 3))
    print(f"within 3 sigma: {frac:.3f}; median relative error {rel}")
    assert frac >= 0.95
    assert all(r < 0.05 for r in rel.values())
    # the sigmas are the data's: residuals over them have RMS ~ 1
    assert 0.7 < float(np.median(d["rms_residual"])) < 1.3


def test_output_files_and_png_ranges(cli_out):
    from gonio.fitting.svbrdf_output import read_png_map

    doc = json.loads((cli_out / "maps.json").read_text())
    d = _maps(cli_out)
    for name in ("albedo.png", "ks.png", "alpha.png", "albedo_std.png", "residual.png"):
        assert (cli_out / name).is_file()
    for name in ("preview.png", "material.xml", "material.mtlx", "mtlx_base_color.png"):
        assert (cli_out / name).is_file()
    # a 16-bit PNG over its stated range gives the map back to 1/65535 of the range
    for png, ref in (("albedo.png", d["params"]["albedo"]), ("alpha.png", d["params"]["alpha"])):
        e = doc["maps"][png]
        back = read_png_map(cli_out / png, e)
        ref = ref if back.ndim == 3 else ref[..., 0]
        lo, hi = e["range"]
        assert np.max(np.abs(back - ref)) <= (hi - lo) / 65535 * 0.51
    import cv2

    img = cv2.imread(str(cli_out / "albedo.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint16 and img.shape == (NY, NX, 3)


# ------------------------------------------------------------------ engines


@pytest.mark.slow
def test_real_cluster_and_local_cluster_identical_to_single_process(dask_cluster, texel_file):
    address, _ = dask_cluster
    o = SVBRDFOptions(model="lambert+ggx")
    ref = fit_svbrdf(texel_file, o, workers=0, block_texels=3)
    runs = {
        "scheduler": fit_svbrdf(texel_file, o, scheduler=address, block_texels=3),
        "local": fit_svbrdf(texel_file, o, workers=2, block_texels=5),  # other blocks too
    }
    for engine, r in runs.items():
        assert not r.failed_blocks, engine
        for k in ref.param_names:
            assert r.params[k].tobytes() == ref.params[k].tobytes(), (engine, k)
            assert r.std[k].tobytes() == ref.std[k].tobytes(), (engine, k)
        for k in ("cost", "rms_residual", "n_samples", "success"):
            assert getattr(r, k).tobytes() == getattr(ref, k).tobytes(), (engine, k)


def _corrupt_block(src: Path, dst: Path, t0: int) -> None:
    """Copy ``src`` with ``brdf`` gzip-compressed and the chunk holding texel t0 damaged
    (its bytes overwritten): reading that hyperslab fails, the others read fine."""
    import shutil

    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        data = f["brdf"][()]
        chunks = f["brdf"].chunks
        del f["brdf"]
        f.create_dataset("brdf", data=data, chunks=chunks, compression="gzip")
        ds = f["brdf"]
        info = ds.id.get_chunk_info_by_coord((t0 // chunks[0] * chunks[0], 0, 0))
        offset, size = info.byte_offset, info.size
    with open(dst, "r+b") as fh:
        fh.seek(offset)
        fh.write(b"\xff" * size)


def test_failed_block_named_others_kept(texel_file, tmp_path, capsys):
    with h5py.File(texel_file, "r") as f:
        ct = f["brdf"].chunks[0]
    bad = tmp_path / "texels.h5"
    _corrupt_block(texel_file, bad, t0=ct)  # the second chunk
    out = tmp_path / "out"
    code = run(
        "fit", str(bad), "--svbrdf", "-m", "lambert+ggx", "--workers", "0",
        "--block-texels", str(ct), "--out", str(out), "--no-plots",
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    name = f"texels {ct}-{min(2 * ct, NX * NY) - 1}"
    assert name in err and str(bad) in err and "Traceback" not in err
    d = _maps(out)
    ok = d["success"].ravel()
    lost = np.zeros(NX * NY, bool)
    lost[ct : 2 * ct] = True
    assert not ok[lost].any() and ok[~lost].all()
    assert np.isnan(d["params"]["albedo"].reshape(-1, 3)[lost]).all()
    assert name in json.loads(d["attrs"]["failed_blocks"])


# ------------------------------------------------------------------ bad input


def test_not_a_texel_file_refused(tmp_path, capsys):
    junk = tmp_path / "texels.h5"
    junk.write_bytes(b"not an HDF5 file\n")
    assert run("fit", str(junk), "--svbrdf", "--workers", "0") == 1
    err = capsys.readouterr().err
    assert str(junk) in err and "error:" in err and "Traceback" not in err
    assert not (tmp_path / "svbrdf").exists()
    other = tmp_path / "samples.h5"
    with h5py.File(other, "w") as f:
        f.attrs["schema"] = "gonio.samples"
    assert run("fit", str(other), "--svbrdf", "--workers", "0", "--out", str(tmp_path / "o")) == 1
    err = capsys.readouterr().err
    assert str(other) in err and "Traceback" not in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("model", ["lambert+ggx", "auto"])
def test_unreachable_scheduler_named_before_any_texel_is_fitted(
    texel_file, tmp_path, capsys, monkeypatch, model
):
    """``--scheduler`` where nothing listens: exit 1, the address named, no output folder,
    and no texel fitted first (neither the cost probe nor the ``auto`` vote)."""
    import socket

    import gonio.fitting

    # every texel fit (probe, vote, block) goes through gonio.fitting.fit: count them
    fitted = []
    real = gonio.fitting.fit
    monkeypatch.setattr(gonio.fitting, "fit", lambda *a, **k: fitted.append(a) or real(*a, **k))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"  # closed again: nothing listens
    out = tmp_path / "o"
    code = run(
        "fit", str(texel_file), "--svbrdf", "-m", model, "--scheduler", address,
        "--connect-timeout", "1", "--out", str(out),
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 1
    assert address in err and "error:" in err and "Traceback" not in err
    assert fitted == [] and not out.exists()


def test_unknown_model_refused_before_work(texel_file, tmp_path, capsys):
    out = tmp_path / "o"
    assert run("fit", str(texel_file), "--svbrdf", "-m", "lambert+ggz", "--out", str(out)) == 1
    err = capsys.readouterr().err
    assert "'ggz'" in err and "Traceback" not in err and not out.exists()
    assert run("fit", str(texel_file), "--smooth", "1", "--out", str(out)) == 2  # usage


def test_existing_output_needs_force(cli_out, texel_file, capsys):
    before = (cli_out / "svbrdf.h5").read_bytes()
    assert run("fit", str(texel_file), "--svbrdf", "--workers", "0") == 1
    assert "--force" in capsys.readouterr().err
    assert (cli_out / "svbrdf.h5").read_bytes() == before


# ------------------------------------------------------------------ exports


@pytest.mark.mitsuba
def test_mitsuba_export_matches_gonio_evaluation(cli_out, tmp_path):
    """mi.load_file(material.xml); its BSDF at each texel's uv (u = (x + w/2)/w,
    v = (y + h/2)/h) and 30 direction pairs against gonio's lambert+ggx at that texel's
    fitted (unquantised) parameters: relative RMSE (16-bit textures, float32)."""
    os.environ.setdefault("DRJIT_CACHE_DIR", str(tmp_path / "drjit"))
    from gonio.mitsuba_oracle import load_mitsuba

    mi, _ = load_mitsuba("scalar")
    b = mi.load_file(str(cli_out / "material.xml"))
    d = _maps(cli_out)
    m = get_model("lambert+ggx")
    rng = np.random.default_rng(5)
    num = den = 0.0
    w, h = d["attrs"]["sample_size"]
    for r in range(NY):
        for c in range(NX):
            # texel centre in the sample frame, then its uv (independent of the module)
            x = -w / 2 + (c + 0.5) * w / NX
            y = h / 2 - (r + 0.5) * h / NY
            u, v = (x + w / 2) / w, (y + h / 2) / h
            p = {k: d["params"][k][r, c] for k in ("albedo", "ks")}
            bound = m.bind({**p, "alpha": d["params"]["alpha"][r, c, 0]})
            for _ in range(30):
                ti, to, po = rng.uniform(0, 1.4), rng.uniform(0, 1.4), rng.uniform(0, 2 * np.pi)
                wi = np.array([np.sin(ti), 0, np.cos(ti)], np.float32).astype(np.float64)
                wo = np.array(
                    [np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], np.float32
                ).astype(np.float64)
                si = mi.SurfaceInteraction3f()
                si.wi = mi.Vector3f(*wi)
                si.uv = mi.Point2f(u, v)
                val = b.eval(mi.BSDFContext(), si, mi.Vector3f(*wo))
                theirs = np.array([val[0], val[1], val[2]], dtype=np.float64)
                ours = bound.eval(wi[None], wo[None])[0] * wo[2]  # Mitsuba: f cos(theta_o)
                num += float(np.sum((theirs - ours) ** 2))
                den += float(np.sum(ours**2))
    rmse = math.sqrt(num / den)
    print(f"Mitsuba vs gonio relative RMSE {rmse:.2e}")
    assert rmse < 1e-3


@pytest.mark.mitsuba
def test_mitsuba_render_of_the_export_matches_gonio(cli_out, tmp_path):
    """A Mitsuba render (``direct`` integrator, a point light) of material.xml on the
    sample's rectangle (Mitsuba's own uv over it) against gonio's lambert+ggx at the
    fitted maps.  Mitsuba's camera rays at a 4 x 4 grid in each pixel find the surface
    points; gonio takes each point's texel by the texel convention (from the point, not
    from any uv), the directions to the light and the camera, and averages over the
    grid.  Pixels whose grid spans two texels (the nearest texture lookup mixes them by
    area) or leaves the sample are left out.  Relative RMSE stated; the same comparison
    with the texel rows taken upside down must be far off (the test sees orientation)."""
    os.environ.setdefault("DRJIT_CACHE_DIR", str(tmp_path / "drjit"))
    from gonio.mitsuba_oracle import load_mitsuba

    mi, _ = load_mitsuba("scalar")
    d = _maps(cli_out)
    w, h = (float(v) for v in d["attrs"]["sample_size"])
    width, height, spp = 40, 30, 256
    camera = np.array([0.012, -0.05, 0.08])
    light = np.array([-0.01, 0.03, 0.07])
    intensity = 1.0e-3  # W/sr
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": {
                "type": "perspective",
                "fov": 35.0,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=camera.tolist(), target=[0, 0, 0], up=[0, 1, 0]
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": width,
                    "height": height,
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },
                "sampler": {"type": "independent", "sample_count": spp},
            },
            "sample": {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().scale([w / 2, h / 2, 1.0]),
                "bsdf": mi.load_file(str(cli_out / "material.xml")),
            },
            "light": {
                "type": "point",
                "position": light.tolist(),
                "intensity": {"type": "rgb", "value": [intensity] * 3},
            },
        }
    )
    image = np.array(mi.render(scene, spp=spp), dtype=np.float64)[..., :3]
    sensor = scene.sensors()[0]
    m = get_model("lambert+ggx")
    grid = (np.arange(4) + 0.5) / 4

    def radiance(p: np.ndarray, row: int, col: int) -> np.ndarray:
        wi, wo = light - p, camera - p
        r2 = float(wi @ wi)
        wi, wo = wi / np.sqrt(r2), wo / np.linalg.norm(wo)
        params = {k: d["params"][k][row, col] for k in ("albedo", "ks")}
        f = m.bind({**params, "alpha": d["params"]["alpha"][row, col, 0]}).eval(wi[None], wo[None])
        return f[0] * wi[2] * intensity / r2

    ours, theirs, flipped = [], [], []
    for y in range(height):
        for x in range(width):
            points, texels, inside = [], set(), True
            # the grid for the average, the pixel's corners for its footprint's texels
            for a, b in [(a, b) for b in grid for a in grid] + [(0, 0), (1, 0), (0, 1), (1, 1)]:
                ray, _ = sensor.sample_ray(
                    0.0, 0.5, mi.Point2f((x + a) / width, (y + b) / height), mi.Point2f(0.5)
                )
                si = scene.ray_intersect(ray)
                if not si.is_valid():
                    inside = False
                    break
                p = np.array([si.p[0], si.p[1], si.p[2]], dtype=np.float64)
                col = int(np.floor((p[0] + w / 2) / w * NX))
                row = int(np.floor((h / 2 - p[1]) / h * NY))
                texels.add((row, col))
                if 0 < a < 1:
                    points.append(p)
            if not inside or len(texels) != 1:
                continue
            row, col = texels.pop()
            if not (0 <= row < NY and 0 <= col < NX):
                continue
            ours.append(np.mean([radiance(p, row, col) for p in points], axis=0))
            flipped.append(np.mean([radiance(p, NY - 1 - row, col) for p in points], axis=0))
            theirs.append(image[y, x])
    ours, theirs, flipped = np.array(ours), np.array(theirs), np.array(flipped)
    assert len(ours) > 200, len(ours)  # most of the sample's pixels are compared

    def rel_rmse(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean((theirs - a) ** 2) / np.mean(a**2)))

    err, err_flipped = rel_rmse(ours), rel_rmse(flipped)
    print(f"Mitsuba render vs gonio: relative RMSE {err:.2e} over {len(ours)} pixels "
          f"(texel rows upside down: {err_flipped:.2e})")  # fmt: skip
    # measured 1.8e-3 over 308 pixels (mean signed error 4e-5: the rest is Mitsuba's
    # Monte Carlo over each pixel, 256 samples, and the 16-bit textures)
    assert err < 5e-3
    assert err_flipped > 10 * err


def test_materialx_document_valid_and_textures_decode(cli_out):
    import MaterialX as mx

    from gonio.fitting.svbrdf_output import read_png_map

    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(cli_out / "material.mtlx"))
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.importLibrary(lib)
    ok, why = doc.validate()
    assert ok, why
    shader = doc.getNode("SR_gonio_svbrdf")
    assert shader.getCategory() == "standard_surface"
    ior = shader.getInputValue("specular_IOR")
    d = _maps(cli_out)
    ks = d["params"]["ks"]
    f0 = ((ior - 1) / (ior + 1)) ** 2
    assert f0 == pytest.approx(ks.max(), rel=1e-4)  # F0 = the largest ks (module doc)
    entries = json.loads((cli_out / "maps.json").read_text())["maps"]
    spec = read_png_map(cli_out / "mtlx_specular_color.png", entries["mtlx_specular_color.png"])
    np.testing.assert_allclose(spec, ks / f0, atol=2e-5)
    rough = read_png_map(
        cli_out / "mtlx_specular_roughness.png", entries["mtlx_specular_roughness.png"]
    )
    np.testing.assert_allclose(rough**2, d["params"]["alpha"][..., 0], atol=1e-4)
    err = json.loads((cli_out / "maps.json").read_text())["exports"]["materialx"]
    print(f"MaterialX mapping relative RMSE {err['relative_rmse']}")


def test_specular_albedo_against_direct_quadrature():
    """The directional albedo E of the standard_surface closed form (integrated over half
    vectors) against a plain quadrature over incident directions (broad lobe)."""
    from gonio.fitting.svbrdf_export import _specular_albedo, standard_surface_eval

    alpha, ior = 0.6, 1.8
    for theta_o in (0.2, 0.9, 1.3):
        wo = np.array([[np.sin(theta_o), 0, np.cos(theta_o)]])
        x, wq = np.polynomial.legendre.leggauss(200)
        mu = 0.5 * (x + 1)
        phi = (np.arange(400) + 0.5) / 400 * 2 * np.pi
        mm, pp = np.meshgrid(mu, phi, indexing="ij")
        s = np.sqrt(1 - mm**2)
        wi = np.stack([s * np.cos(pp), s * np.sin(pp), mm], -1).reshape(-1, 3)
        f = standard_surface_eval(
            wi, np.repeat(wo, len(wi), 0), np.zeros(1), np.ones(1), math.sqrt(alpha), ior
        )[:, 0]
        direct = np.sum(f * wi[:, 2] * np.repeat(wq * 0.5, 400)) * 2 * np.pi / 400
        ours = float(_specular_albedo(np.cos(theta_o), alpha, ior, n=96))
        assert ours == pytest.approx(direct, rel=2e-3), theta_o


# ------------------------------------------------------------------ pieces


def test_plan_blocks_cover_and_align():
    for n, cost, ct in ((100, 0.01, 16), (7, 1.0, 4), (1000, 0.001, 64), (5, 0.0, 1)):
        blocks = plan_blocks(n, cost, ct)
        assert blocks[0][0] == 0 and blocks[-1][1] == n
        assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:], strict=False))
        size = blocks[0][1] - blocks[0][0]
        assert size % ct == 0 or ct % size == 0
    assert plan_blocks(100, 0.01, 16)[0] == (0, 96)  # 100 texels of 10 ms: ~1 s, 6 chunks


def test_smooth_closed_form_two_texels_and_fill():
    """1 x 2 map, precisions w1, w2, lam * median(w) = k: (w1 + k) p1 - k p2 = w1 x1 and
    -k p1 + (w2 + k) p2 = w2 x2 (Cramer's rule); a texel without a fit is filled."""
    model = get_model("lambert+ggx")
    x = np.array([0.2, 0.6])
    s = np.array([0.01, 0.02])
    w = 1 / s**2
    lam = 0.7
    k = lam * np.median(w)
    det = (w[0] + k) * (w[1] + k) - k * k
    p1 = (w[0] * x[0] * (w[1] + k) + k * w[1] * x[1]) / det
    p2 = ((w[0] + k) * w[1] * x[1] + k * w[0] * x[0]) / det
    params = {"albedo": x.reshape(1, 2, 1)}
    out = smooth_maps(params, {"albedo": s.reshape(1, 2, 1)}, lam, model)
    np.testing.assert_allclose(out["albedo"].ravel(), [p1, p2], rtol=1e-12)
    assert smooth_maps(params, {"albedo": s.reshape(1, 2, 1)}, 0.0, model)["albedo"][0, 1, 0] == 0.6
    holes = {"albedo": np.array([0.3, np.nan, 0.5]).reshape(1, 3, 1)}
    sd = {"albedo": np.array([0.01, np.nan, 0.01]).reshape(1, 3, 1)}
    filled = smooth_maps(holes, sd, 1.0, model)["albedo"].ravel()
    assert filled[1] == pytest.approx(0.4)  # the mean of its neighbours (symmetric)


@pytest.mark.slow
def test_model_auto_chooses_by_the_texels(texel_file):
    """--model auto: the texels' own selections find the truth's model, which is then
    fitted per texel (the same maps as asking for it)."""
    r = fit_svbrdf(texel_file, SVBRDFOptions(model="auto"), workers=0, block_texels=6)
    assert r.model == "lambert+ggx"
    assert r.selection[0]["model"] == "lambert+ggx" and r.selection[0]["texels"] >= 7
    ref = fit_svbrdf(texel_file, SVBRDFOptions(model="lambert+ggx"), workers=0, block_texels=4)
    for k in ref.param_names:
        assert r.params[k].tobytes() == ref.params[k].tobytes()


def test_nothing_to_fit_or_a_smoothing_past_its_bound_is_an_error(tmp_path, capsys):
    """Every texel's BRDF 0: no texel can be fitted, so nothing is written and the exit
    is 1 (it wrote 11 files of NaN maps, "0 of 16 converged", exit 0); --smooth beyond
    1e6 is a usage error (1e20 gave all-zero maps, "converged")."""
    rng = np.random.default_rng(5)
    t_count, n = 4, 12
    wi = np.stack([_directions(rng, n) for _ in range(t_count)])
    wo = np.stack([_directions(rng, n) for _ in range(t_count)])
    (tmp_path / "zero").mkdir()
    path = save_texels(
        tmp_path / "zero" / "texels.h5", wi=wi, wo=wo, brdf=np.zeros((t_count, n, 3)),
        brdf_std=np.full((t_count, n, 3), FLOOR), flags=np.zeros((t_count, n), np.uint32),
        pose=np.arange(n, dtype=np.int32), texels=(2, 2), sample_size=(0.04, 0.03),
    )  # fmt: skip
    out = tmp_path / "o"
    code = run("fit", str(path), "--svbrdf", "-m", "lambert", "--workers", "0", "--out", str(out))
    err = capsys.readouterr().err
    assert code == 1 and "no texel could be fitted" in err and not out.exists()
    args = ["fit", str(path), "--svbrdf", "-m", "lambert", "--workers", "0", "--smooth", "1e20"]
    assert run(*args, "--out", str(out)) == 2
    assert "--smooth" in capsys.readouterr().err and not out.exists()
