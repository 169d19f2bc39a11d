"""gonio.fitting.agg_text: text drawn as one bitmap per string, where matplotlib puts it.

The reference is matplotlib's own Agg canvas drawing the same figure: the strings' ink
must land on the same pixels up to the whole-pixel rounding of the string's origin (one
pixel), with the same amount of ink (the same glyphs at the same size and hinting).
"""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import ndimage

from gonio.fitting.agg_text import TextCachingCanvas, _TextCachingRenderer


def _draw(canvas_cls, texts) -> np.ndarray:
    fig = Figure(figsize=(4, 3), dpi=100)
    canvas = canvas_cls(fig)
    for x, y, s, kw in texts:
        fig.text(x, y, s, **kw)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return 255 - rgba[..., :3].min(axis=2).astype(float)  # ink: 0 on white


TEXTS = [
    (0.05, 0.85, "theta_i 10.0-20.0° (curve at 15.0°)", {"fontsize": 9}),
    (0.05, 0.65, "10⁻² 10⁻³ 10⁻²", {"fontsize": 7}),
    (0.05, 0.45, "f_r (1/sr)", {"fontsize": 8, "rotation": 90}),
    (0.40, 0.30, "channel B", {"fontsize": 8, "color": "tab:blue"}),
]


def test_same_ink_on_the_same_pixels_as_matplotlib():
    ours, ref = _draw(TextCachingCanvas, TEXTS), _draw(FigureCanvasAgg, TEXTS)
    assert ours.shape == ref.shape
    ink_ours, ink_ref = ours > 64, ref > 64
    assert ink_ref.sum() > 500  # the strings were drawn at all
    grown = np.ones((3, 3), dtype=bool)  # one pixel of placement
    assert np.all(ndimage.binary_dilation(ink_ours, grown)[ink_ref])
    assert np.all(ndimage.binary_dilation(ink_ref, grown)[ink_ours])
    assert abs(ours.sum() / ref.sum() - 1.0) < 0.05


def test_repeated_strings_reuse_their_bitmap_and_mathtext_is_matplotlibs():
    fig = Figure(figsize=(3, 2), dpi=100)
    canvas = TextCachingCanvas(fig)
    for k in range(4):
        fig.text(0.1 + 0.2 * k, 0.5, "10⁻²", fontsize=7)
    fig.text(0.1, 0.2, "$x^2$", fontsize=9)
    canvas.draw()
    renderer = canvas.get_renderer()
    assert isinstance(renderer, _TextCachingRenderer)
    assert [k[0] for k in renderer._text_bitmaps] == ["10⁻²"]  # one bitmap, mathtext none

    math_only = [(0.1, 0.5, "$x^2 + \\alpha$", {"fontsize": 12})]
    assert np.array_equal(_draw(TextCachingCanvas, math_only), _draw(FigureCanvasAgg, math_only))
