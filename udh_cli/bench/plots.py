"""The benchmark's two figures, drawn with OpenCV (no plotting library):

* :func:`percentile_plot`: error against the percentile of pairs, best first, one panel per set
  (the paper's figure 4);
* :func:`speed_accuracy_plot`: mean error against time per pair, both on log axes (the paper's figure 5).

Both return (H, W, 3) uint8 BGR images.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from udh_cli.bench import metrics
from udh_cli.bench.runner import MethodRun

FONT = cv2.FONT_HERSHEY_SIMPLEX
TEXT = (40, 40, 40)
GRID = (225, 225, 225)
GRID_MINOR = (242, 242, 242)
# Tableau-10 colours in BGR: distinct for up to ten methods and legible in grey print.
PALETTE = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23)]
MARKERS = ("circle", "square", "triangle", "diamond")


def _colour(method: str, methods: list[str]) -> tuple[int, int, int]:
    return PALETTE[methods.index(method) % len(PALETTE)]


def _text(canvas, text, org, scale=0.45, colour=TEXT, thickness=1, align="left", valign="baseline"):
    """Put text with its anchor at ``org``: align left/centre/right, valign baseline/middle/top."""
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    x = org[0] - (w if align == "right" else w // 2 if align == "centre" else 0)
    y = org[1] + (h // 2 if valign == "middle" else h if valign == "top" else 0)
    cv2.putText(canvas, text, (int(x), int(y)), FONT, scale, colour, thickness, cv2.LINE_AA)


def _vertical_text(canvas, text, centre, scale=0.5):
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    tile = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(tile, text, (2, h + 2), FONT, scale, TEXT, 1, cv2.LINE_AA)
    tile = cv2.rotate(tile, cv2.ROTATE_90_COUNTERCLOCKWISE)
    y0, x0 = centre[1] - tile.shape[0] // 2, centre[0] - tile.shape[1] // 2
    region = canvas[y0 : y0 + tile.shape[0], x0 : x0 + tile.shape[1]]
    np.minimum(region, tile[: region.shape[0], : region.shape[1]], out=region)


def _number(value: float) -> str:
    if value == 0:
        return "0"
    return f"{value:g}" if 1e-3 <= abs(value) < 1e5 else f"1e{int(round(math.log10(value)))}"


def _log_limits(values: np.ndarray, floor: float, ceiling: float) -> tuple[float, float]:
    """Decade-aligned limits that hold the finite positive ``values``, within [floor, ceiling]."""
    v = values[np.isfinite(values) & (values > 0)]
    lo = max(floor, float(v.min())) if len(v) else floor
    hi = min(ceiling, float(v.max())) if len(v) else ceiling
    lo, hi = 10 ** math.floor(math.log10(lo)), 10 ** math.ceil(math.log10(hi))
    return (lo, hi * 10) if hi <= lo else (lo, hi)


class Axes:
    """A plot area on ``canvas`` at pixel rectangle ``(left, top, width, height)``; ``*log`` axes are log10."""

    def __init__(self, canvas, rect, xlim, ylim, xlog=False, ylog=False):
        self.canvas, self.rect = canvas, rect
        self.xlim, self.ylim, self.xlog, self.ylog = xlim, ylim, xlog, ylog

    def _unit(self, values, lim, log):
        values = np.asarray(values, dtype=np.float64)
        if log:
            values, lim = np.log10(np.clip(values, 1e-12, None)), (math.log10(lim[0]), math.log10(lim[1]))
        return (values - lim[0]) / (lim[1] - lim[0])

    def to_px(self, xs, ys) -> np.ndarray:
        """(N, 2) int32 pixel positions of data points, clamped to the plot area."""
        left, top, width, height = self.rect
        u = np.clip(self._unit(xs, self.xlim, self.xlog), 0, 1)
        v = np.clip(self._unit(ys, self.ylim, self.ylog), 0, 1)
        return np.stack([left + u * width, top + (1 - v) * height], -1).round().astype(np.int32)

    def _ticks(self, lim, log):
        if log:
            decades = range(round(math.log10(lim[0])), round(math.log10(lim[1])) + 1)
            major = [10.0**d for d in decades]
            minor = [m * 10.0**d for d in decades for m in range(2, 10) if m * 10.0**d < lim[1]]
            return major, minor
        step = 10 ** math.floor(math.log10((lim[1] - lim[0]) / 4))
        step *= 2 if (lim[1] - lim[0]) / step > 10 else 1
        first = math.ceil(lim[0] / step) * step
        return list(np.arange(first, lim[1] + step / 2, step)), []

    def draw_frame(self, xlabel: str, ylabel: str, title: str = "") -> None:
        """Grid, ticks with labels, axis labels and a title."""
        left, top, width, height = self.rect
        c = self.canvas
        xmajor, xminor = self._ticks(self.xlim, self.xlog)
        ymajor, yminor = self._ticks(self.ylim, self.ylog)
        for x in xminor:
            px = self.to_px([x], [self.ylim[0]])[0, 0]
            cv2.line(c, (px, top), (px, top + height), GRID_MINOR, 1)
        for y in yminor:
            py = self.to_px([self.xlim[0]], [y])[0, 1]
            cv2.line(c, (left, py), (left + width, py), GRID_MINOR, 1)
        for x in xmajor:
            px = self.to_px([x], [self.ylim[0]])[0, 0]
            cv2.line(c, (px, top), (px, top + height), GRID, 1)
            cv2.line(c, (px, top + height), (px, top + height + 5), TEXT, 1)
            _text(c, _number(x), (px, top + height + 9), align="centre", valign="top")
        for y in ymajor:
            py = self.to_px([self.xlim[0]], [y])[0, 1]
            cv2.line(c, (left, py), (left + width, py), GRID, 1)
            cv2.line(c, (left - 5, py), (left, py), TEXT, 1)
            _text(c, _number(y), (left - 8, py), align="right", valign="middle")
        cv2.rectangle(c, (left, top), (left + width, top + height), TEXT, 1)
        _text(c, xlabel, (left + width // 2, top + height + 42), scale=0.5, align="centre")
        _vertical_text(c, ylabel, (left - 52, top + height // 2))
        if title:
            _text(c, title, (left + width // 2, top - 10), scale=0.55, align="centre", thickness=1)

    def polyline(self, xs, ys, colour, thickness=2, dashed=False) -> None:
        points = self.to_px(xs, ys)
        if not dashed:
            cv2.polylines(self.canvas, [points.reshape(-1, 1, 2)], False, colour, thickness, cv2.LINE_AA)
            return
        _dashed(self.canvas, points, colour, thickness)

    def hline(self, y, colour, label="") -> None:
        left, _, width, _ = self.rect
        py = int(self.to_px([self.xlim[0]], [y])[0, 1])
        _dashed(self.canvas, np.array([[left, py], [left + width, py]]), colour, 1, dash=6)
        if label:
            _text(self.canvas, label, (left + 6, py - 4), scale=0.4, colour=colour)


def _dashed(canvas, points: np.ndarray, colour, thickness, dash: int = 9) -> None:
    """A dashed polyline through ``points`` (N, 2): the dash pattern runs on along the whole curve."""
    points = points.astype(np.float64)
    steps = np.hypot(*np.diff(points, axis=0).T)
    run = np.concatenate([[0.0], np.cumsum(steps)])
    if run[-1] == 0:
        return
    samples = np.arange(0.0, run[-1] + 1, 1.0)
    xs, ys = np.interp(samples, run, points[:, 0]), np.interp(samples, run, points[:, 1])
    on = (samples // dash) % 2 == 0
    start = None
    for i in range(len(samples) + 1):
        if i < len(samples) and on[i]:
            start = i if start is None else start
        elif start is not None:
            seg = np.stack([xs[start:i], ys[start:i]], -1).round().astype(np.int32)
            cv2.polylines(canvas, [seg.reshape(-1, 1, 2)], False, colour, thickness, cv2.LINE_AA)
            start = None


def _marker(canvas, centre, shape, colour, size=6, filled=True) -> None:
    x, y = int(centre[0]), int(centre[1])
    thickness = -1 if filled else 2
    if shape == "circle":
        cv2.circle(canvas, (x, y), size, colour, thickness, cv2.LINE_AA)
        return
    if shape == "square":
        pts = [(x - size, y - size), (x + size, y - size), (x + size, y + size), (x - size, y + size)]
    elif shape == "triangle":
        pts = [(x, y - size - 1), (x + size + 1, y + size), (x - size - 1, y + size)]
    else:  # diamond
        pts = [(x, y - size - 1), (x + size + 1, y), (x, y + size + 1), (x - size - 1, y)]
    pts = np.array(pts, np.int32).reshape(-1, 1, 2)
    if filled:
        cv2.fillPoly(canvas, [pts], colour, cv2.LINE_AA)
    else:
        cv2.polylines(canvas, [pts], True, colour, 2, cv2.LINE_AA)


def _legend(canvas, origin, entries, line_height=22) -> None:
    """Entries ``(label, colour, style)``; style is ``"line"``, ``"dashed"`` or ``("marker", shape, filled)``."""
    x, y = origin
    for label, colour, style in entries:
        cy = y + line_height // 2
        if style == "line":
            cv2.line(canvas, (x, cy), (x + 28, cy), colour, 2, cv2.LINE_AA)
        elif style == "dashed":
            _dashed(canvas, np.array([[x, cy], [x + 28, cy]]), colour, 2, dash=6)
        else:
            _marker(canvas, (x + 14, cy), style[1], colour, filled=style[2])
        _text(canvas, label, (x + 36, cy), valign="middle")
        y += line_height


def _methods(runs: list[MethodRun]) -> list[str]:
    return list(dict.fromkeys(r.method for r in runs))


def _sets(runs: list[MethodRun]) -> list[str]:
    return list(dict.fromkeys(r.set_name for r in runs))


def percentile_plot(runs: list[MethodRun], panel_size: tuple[int, int] = (380, 330)) -> np.ndarray:
    """Error (MACE, log scale) against the percentile of pairs, best first: one panel per set, one curve per
    method and input (dashed: full-frame input). No answers are scored as no motion, as in the table."""
    methods, sets = _methods(runs), _sets(runs)
    errors = np.concatenate([r.mace for r in runs])
    ylim = _log_limits(errors, 1e-2, 1e3)  # wilder errors are drawn at the top edge
    margin_left, margin_top, gap, margin_bottom, legend_width = 80, 50, 90, 70, 190
    pw, ph = panel_size
    width = margin_left + len(sets) * pw + (len(sets) - 1) * gap + 30 + legend_width
    height = margin_top + ph + margin_bottom
    canvas = np.full((height, width, 3), 255, np.uint8)
    for k, name in enumerate(sets):
        axes = Axes(canvas, (margin_left + k * (pw + gap), margin_top, pw, ph), (0, 100), ylim, ylog=True)
        axes.draw_frame("percentile of pairs (best first)", "MACE (px)", title=name)
        axes.hline(metrics.FAIL_PX, (120, 120, 120), f"failure: > {metrics.FAIL_PX:g} px")
        for run in (r for r in runs if r.set_name == name):
            percent, ordered = metrics.percentile_profile(run.mace)
            ordered = np.where(np.isfinite(ordered), ordered, ylim[1])
            axes.polyline(percent, ordered, _colour(run.method, methods), dashed=run.input == "full")
    entries = [(m, _colour(m, methods), "line") for m in methods]
    if any(r.input == "full" for r in runs):
        entries += [("", (255, 255, 255), "line"), ("full 320x240 input", TEXT, "dashed"), ("patch input", TEXT, "line")]
    _legend(canvas, (width - legend_width, margin_top + 4), entries)
    return canvas


def speed_accuracy_plot(runs: list[MethodRun], size: tuple[int, int] = (560, 420)) -> np.ndarray:
    """Mean MACE against median time per pair, both log10: colour = method, marker = set, hollow = full-frame
    input. Points of one method and input are joined across sets."""
    methods, sets = _methods(runs), _sets(runs)
    times = np.array([r.summary.time_median_ms for r in runs])
    errors = np.array([r.summary.mace_mean for r in runs])
    xlim = _log_limits(times, 1e-3, 1e6)
    ylim = _log_limits(errors, 1e-2, 1e5)
    margin_left, margin_top, margin_bottom, legend_width = 80, 50, 70, 210
    pw, ph = size
    canvas = np.full((margin_top + ph + margin_bottom, margin_left + pw + 30 + legend_width, 3), 255, np.uint8)
    axes = Axes(canvas, (margin_left, margin_top, pw, ph), xlim, ylim, xlog=True, ylog=True)
    axes.draw_frame("median time per pair (ms, log)", "mean MACE (px, log)", title="speed vs accuracy")
    axes.hline(metrics.FAIL_PX, (120, 120, 120), f"{metrics.FAIL_PX:g} px")
    groups = dict.fromkeys((r.method, r.input) for r in runs)
    for method, kind in groups:
        members = [r for r in runs if r.method == method and r.input == kind]
        colour = _colour(method, methods)
        xs = [r.summary.time_median_ms for r in members]
        ys = [r.summary.mace_mean if math.isfinite(r.summary.mace_mean) else ylim[1] for r in members]
        if len(members) > 1:
            axes.polyline(xs, ys, colour, thickness=1, dashed=kind == "full")
        for run, point in zip(members, axes.to_px(xs, ys)):
            _marker(canvas, point, MARKERS[sets.index(run.set_name) % len(MARKERS)], colour, filled=kind != "full")
    entries = [(m, _colour(m, methods), "line") for m in methods] + [("", (255, 255, 255), "line")]
    entries += [(name, TEXT, ("marker", MARKERS[k % len(MARKERS)], True)) for k, name in enumerate(sets)]
    if any(r.input == "full" for r in runs):
        entries += [("", (255, 255, 255), "line"), ("hollow: full input", TEXT, ("marker", "circle", False))]
    _legend(canvas, (margin_left + pw + 30, margin_top + 4), entries)
    return canvas
