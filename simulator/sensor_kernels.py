"""Fused numba kernels of the sensor model's arithmetic: the mean electrons, quantisation.

Why hand-written: :func:`gonio.simulator.sensor.simulate_mosaic` is some fifteen numpy
passes over the frame around its two noise draws (the mean's six products, the fixed
patterns' gain, dark charge, offset, hot pixels and clip, the saturation guard; after the
draws the full well, gain, black level, rounding, clipping and the cast), each streaming
a float64 temporary through memory: at 1600 x 1200 those passes cost about a third of a
frame.  These two kernels do them per site in registers, in the numpy code's operation
order (``* +``, ``min``/``max``/``rint``: the same bits).

The noise draws are the frame's reproducible contract (the same seed gives the same bytes
as before these kernels): the Poisson draw stays numpy's (``rng.poisson(mu)``, whole
array), because numpy's C Poisson sampler is faster than numba's port of it below 10
electrons, where most sites of a frame are (measured: a realistic 320 x 240 frame holds
73 % of its sites below 10 e-; 320 x 240 sites: numpy 3.3-5.1 ms, numba 4.6-5.8 ms).  The
read noise is drawn inside :func:`quantise_read` from the same generator, site by site
after the Poisson draw: numba's ``Generator.normal`` is a port of numpy's ziggurat that
consumes the same bits and returns the same numbers as ``rng.normal(0, read_noise, n)``
(held equal in ``tests/simulator/test_sensor_kernels.py``), 3x faster (320 x 240 sites:
0.43-0.49 ms against 1.24-1.33 ms), and no (N,) temporary.
``tests/simulator/test_sensor_kernels.py`` holds the kernel path equal to the numpy path.
:func:`shot_sites` is the simulated camera's per-shot radiance at the sites (drift, room
light, clamp), held equal to its numpy path in ``tests/simulator/test_render_kernels.py``.

IEEE-strict as :mod:`gonio.simulator.render_kernels` (``fastmath=False``,
``error_model="numpy"``, ``cache=True``).  ``GONIO_NUMBA=0`` keeps the sensor on numpy
(the reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["mean_electrons", "quantise", "quantise_read", "shot_sites"]

_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}


@njit(**_JIT)
def mean_electrons(
    sites, c0, vignette, pitch2, t, ppj, qe, gain_map, dark, dark_offset, hot, pattern,
    poisson_max, out_mu, out_over,
):  # fmt: skip
    """Mean electrons per site with the fixed patterns and the saturation guard.

    Parameters
    ----------
    sites
        (N,) radiance at the colour filters' sites, W/(sr m^2), finite and >= 0.
    c0
        ``pi / (4 N^2)``; ``vignette`` (N,) cos^4 or (0,); ``pitch2`` pixel area, m^2;
        ``t`` exposure, s; ``ppj``, ``qe`` (N,) photons per joule and quantum efficiency.
    gain_map, dark_offset, hot
        (N,) PRNU gain, DSNU offset (e-) and the hot pixels' dark current (e-/s, 0
        elsewhere), or (0,) each; ``dark`` the uniform dark charge, e-.
    pattern
        The camera has fixed patterns (``FixedPattern.apply``: clipped at 0 e-).
    poisson_max
        Means above this, or not finite, are flagged in ``out_over`` and set to 0 (they
        saturate at the full well without a draw).
    out_mu, out_over
        (N,) the means, e-, and the saturation flags.

    Returns
    -------
    bool
        Whether any site was flagged.
    """
    n = sites.shape[0]
    has_vig = vignette.shape[0] == n
    has_gain = gain_map.shape[0] == n
    has_off = dark_offset.shape[0] == n
    has_hot = hot.shape[0] == n
    any_over = False
    for i in range(n):
        # sensor._expose_numpy's products in its order
        m = sites[i] * c0
        if has_vig:
            m = m * vignette[i]
        m = m * pitch2
        m = m * t
        m = m * ppj[i]
        m = m * qe[i]
        if pattern:
            # FixedPattern.apply: gain, + dark, + offset, + hot charge, clip at 0
            if has_gain:
                m = m * gain_map[i]
            m = m + dark
            if has_off:
                m = m + dark_offset[i]
            if has_hot and hot[i] != 0.0:
                m = m + hot[i] * t
            m = max(m, 0.0)
        else:
            m = m + dark
        over = not m <= poisson_max
        if over:
            any_over = True
            m = 0.0
        out_over[i] = over
        out_mu[i] = m
    return any_over


@njit(**_JIT)
def quantise(counts, read, over, full_well, gain, black, white, out):
    """Digital numbers (N,) uint16 into ``out``: the Poisson ``counts`` (N,) plus the read
    noise ``read`` (N,) e- (or (0,): none), at most the full well (``over`` sites at it),
    times ``gain`` DN/e-, plus ``black``, rounded half to even, clipped to [0, ``white``]."""
    has_read = read.shape[0] == counts.shape[0]
    for i in range(counts.shape[0]):
        v = float(counts[i])
        if has_read:
            v = v + read[i]
        v = min(v, full_well)
        if over[i]:
            v = full_well
        v = v * gain
        v = v + black
        v = np.rint(v)
        v = min(max(v, 0.0), white)
        out[i] = np.uint16(v)


@njit(**_JIT)
def quantise_read(counts, rng, read_noise, over, full_well, gain, black, white, out):
    """:func:`quantise` with the read noise drawn here: ``rng.normal(0, read_noise)`` per
    site in order, which is ``rng.normal(0, read_noise, N)`` number for number (``rng``
    a ``numpy.random.Generator``, advanced as that call advances it)."""
    for i in range(counts.shape[0]):
        v = float(counts[i])
        v = v + rng.normal(0.0, read_noise)
        v = min(v, full_well)
        if over[i]:
            v = full_well
        v = v * gain
        v = v + black
        v = np.rint(v)
        v = min(max(v, 0.0), white)
        out[i] = np.uint16(v)


@njit(**_JIT)
def shot_sites(direct, diffuse, channel, k_direct, k_diffuse, out):
    """A shot's radiance at the colour filters' sites into ``out`` (N,), W/(sr m^2):
    :meth:`gonio.simulator.camera.SimulatedCamera.site_radiance`'s numpy arithmetic per
    site in its order (one pass instead of six over the frame, ~0.3 ms of a 320 x 240
    shot): ``direct * k_direct[c]`` (``direct`` (0,): light off, 0), plus ``diffuse *
    k_diffuse[c]`` (``diffuse`` (0,): none), ``c = channel[i]``; then
    ``np.maximum(v, 0)`` (NaN kept, -0 made +0) and ``np.nan_to_num`` (NaN 0, inf the
    largest float)."""
    has_direct = direct.shape[0] > 0
    has_diffuse = diffuse.shape[0] > 0
    big = np.finfo(np.float64).max
    for i in range(out.shape[0]):
        c = channel[i]
        v = direct[i] * k_direct[c] if has_direct else 0.0
        if has_diffuse:
            v = v + diffuse[i] * k_diffuse[c]
        if not v > 0.0:  # below 0, -0 (numpy's maximum gives +0) and NaN (then 0)
            v = 0.0
        elif v == np.inf:
            v = big
        out[i] = v
