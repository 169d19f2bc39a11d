"""``gonio capture calibrate-noise`` on flat and dark DNGs from the simulator's sensor."""

from __future__ import annotations

import json

import numpy as np

from gonio.cli import run


def test_calibrate_noise_recovers_the_simulated_sensor(tmp_path, capsys):
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.scene import Camera
    from gonio.simulator.sensor import mean_electrons, simulate_raw

    cam = Camera(resolution=(320, 240), fov_deg=40.0, position=(0, 0, 1))  # default sensor
    flats, darks = [], []
    rng = np.random.default_rng(7)
    per_unit = mean_electrons(np.ones((240, 320, 3)), cam, 0.01, cam.f_number).max()
    for level, electrons in enumerate((2000, 10000, 25000)):  # vignetted flats, unclipped
        radiance = electrons / per_unit
        for k in range(2):
            f = simulate_raw(np.full((240, 320, 3), radiance), cam, exposure_time=0.01, seed=rng)
            p = tmp_path / f"flat{level}{k}.dng"
            p.write_bytes(dng_bytes(f))
            flats += ["--flat", str(p)]
    for k in range(2):
        f = simulate_raw(np.zeros((240, 320, 3)), cam, exposure_time=0.01, seed=rng)
        p = tmp_path / f"dark{k}.dng"
        p.write_bytes(dng_bytes(f))
        darks += ["--dark", str(p)]
    out = tmp_path / "noise.json"
    assert (
        run(
            "capture",
            "calibrate-noise",
            *flats,
            *darks,
            "--out",
            str(out),
            "--plot",
            str(tmp_path / "ptc.png"),
        )
        == 0
    )
    model = json.loads(out.read_text())
    s = cam.sensor
    assert model["gain"] == np.float64(model["gain"])
    assert abs(model["gain"] / s.gain_at_base_iso - 1) < 0.03
    assert abs(model["read_noise"] / (s.read_noise * s.gain_at_base_iso) - 1) < 0.05
    assert (tmp_path / "ptc.png").stat().st_size > 1000
    # never overwrites, and an odd number of flats is refused with the reason
    assert run("capture", "calibrate-noise", *flats, "--out", str(out)) == 1
    assert "refusing to overwrite" in capsys.readouterr().err
    assert run("capture", "calibrate-noise", *flats[:2], "--out", str(tmp_path / "n2.json")) == 1
    assert "pairs" in capsys.readouterr().err
