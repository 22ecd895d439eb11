"""The reliability diagram of ``udh bench hard``, drawn as :mod:`udh_cli.bench.plots` draws (OpenCV only):
confidence bins on x, the fraction of right answers on y, one line per method, each point labelled with its
bin's count of pairs. A method whose confidence means what it says follows the diagonal."""

from __future__ import annotations

import numpy as np

from udh_cli.bench.plots import Axes, _colour, _legend, _marker, _text
from udh_cli.bench.verdicts import Reliability

DIAGONAL = (150, 150, 150)


def reliability_plot(curves: list[Reliability], size: tuple[int, int] = (560, 420), title: str = "reliability") -> np.ndarray:
    """(H, W, 3) uint8 BGR: each method's fraction right per confidence bin, at the bin's mean confidence;
    empty bins are left out and the line joins the others. Counts are written beside the points."""
    methods = [c.method for c in curves]
    margin_left, margin_top, margin_bottom, legend_width = 80, 50, 70, 230
    pw, ph = size
    canvas = np.full((margin_top + ph + margin_bottom, margin_left + pw + 30 + legend_width, 3), 255, np.uint8)
    axes = Axes(canvas, (margin_left, margin_top, pw, ph), (0.0, 1.0), (0.0, 1.0))
    axes.draw_frame("confidence (bins of 0.1)", "fraction right (<= 10 px)", title=title)
    axes.polyline([0.0, 1.0], [0.0, 1.0], DIAGONAL, thickness=1, dashed=True)
    for k, curve in enumerate(curves):
        colour = _colour(curve.method, methods)
        filled = curve.counts > 0
        xs, ys = curve.mean_confidence[filled], curve.fraction_right[filled]
        if len(xs) > 1:
            axes.polyline(xs, ys, colour)
        for point, count in zip(axes.to_px(xs, ys), curve.counts[filled]):
            _marker(canvas, point, "circle", colour, size=4)
            # Methods' labels sit at different heights so that points that coincide stay readable.
            _text(canvas, str(int(count)), (int(point[0]) + 6, int(point[1]) - 6 + 14 * (k % 3)), scale=0.38, colour=colour)
    entries = [(f"{c.method} ({int(c.counts.sum())} pairs)", _colour(c.method, methods), "line") for c in curves]
    entries += [("", (255, 255, 255), "line"), ("calibrated", DIAGONAL, "dashed")]
    _legend(canvas, (margin_left + pw + 30, margin_top + 4), entries)
    _text(canvas, "numbers: pairs per bin", (margin_left + pw + 30, margin_top + 20 + 22 * len(entries)), scale=0.4)
    return canvas
