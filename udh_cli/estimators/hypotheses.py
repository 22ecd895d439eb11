"""Starts the networks cannot reach from the identity: turns of B over the whole circle, and shifts up to half
the frame. Each hypothesis is a view of the pair (A and B cropped, resized or turned to S x S) with the exact map
from its answer back to the whole S x S images; every view of every pair goes through the first round of the
cascade in one onnxruntime call, is scored on the whole images, and the best few per pair finish the cascade.

Conventions: ``b_from_a`` of the whole S x S images is ``after @ h_view @ before``, with ``h_view`` the answer
between the view's images (:class:`Hypotheses`). Angles are degrees counter-clockwise on screen
(``cv2.getRotationMatrix2D``), about the centre of the S x S image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.flight_motion import PREWARP_BORDER

FINALISTS = 3  # hypotheses of a pair that get the whole cascade after screening
# Turns tried over the whole circle: 30 degrees apart, so the nearest is at most 15 degrees from any heading,
# inside the coarse networks' reach (the flight network is trained with turns of up to 30 degrees).
HEADING_COUNT = 12


@dataclass
class Hypotheses:
    """Views of N pairs, ``per_pair`` each, pair-major.

    Attributes:
        views_a, views_b: (N * per_pair, S, S) grey in [0, 1].
        after, before: (N * per_pair, 3, 3): the whole S x S ``b_from_a`` is ``after @ h_view @ before``.
        labels: (N * per_pair,) what each view tried (degrees of a turn, or an index of a shift).
        per_pair: views per pair.
    """

    views_a: np.ndarray
    views_b: np.ndarray
    after: np.ndarray
    before: np.ndarray
    labels: np.ndarray
    per_pair: int

    def whole(self, index: int, view_h: np.ndarray) -> np.ndarray:
        """The answer of view ``index`` as ``b_from_a`` of the whole S x S images; NaN when degenerate."""
        h = self.after[index] @ view_h @ self.before[index]
        return h / h[2, 2] if np.isfinite(h).all() and abs(h[2, 2]) > 1e-12 else np.full((3, 3), np.nan)


def turn_matrix(degrees: float, side: int) -> np.ndarray:
    """(3, 3) turn of an S x S image about its centre by ``degrees`` counter-clockwise on screen, pixels."""
    centre = ((side - 1) / 2, (side - 1) / 2)
    return np.vstack([cv2.getRotationMatrix2D(centre, float(degrees), 1.0), [0.0, 0.0, 1.0]])


def heading_angles(count: int, skip: Sequence[float] = ()) -> list[float]:
    """``count`` turns evenly over the circle, without those in ``skip`` (already tried), degrees."""
    return [360.0 * k / count for k in range(count) if not any(abs((360.0 * k / count - s) % 360.0) < 1e-6 for s in skip)]


def heading_hypotheses(small_a: np.ndarray, small_b: np.ndarray, angles: Sequence[float]) -> Hypotheses:
    """B (N, S, S) turned by each of ``angles`` against A as it is: the corners a turn leaves empty repeat
    the border, as the cascade's pre-warps do."""
    n, s = small_a.shape[0], small_a.shape[-1]
    turns = [turn_matrix(angle, s) for angle in angles]
    views_b = np.stack([cv2.warpAffine(b, turn[:2], (s, s), flags=cv2.INTER_LINEAR, borderMode=PREWARP_BORDER)
                        for b in small_b for turn in turns])
    after = np.stack([np.linalg.inv(turn) for _ in range(n) for turn in turns])  # b_from_turned
    return Hypotheses(np.repeat(small_a, len(turns), 0), views_b, after, np.repeat(np.eye(3)[None], n * len(turns), 0),
                      np.tile(np.asarray(angles, np.float64), n), len(turns))


def shift_hypotheses(pairs, side: int, steps: int) -> Hypotheses:
    """For each prepared pair, the two windows that overlap under each shift of a (2 * steps + 1)^2 grid up to
    half the frame (the identity left out), cropped from the full images and resized to S x S."""
    grid = np.linspace(-0.5, 0.5, 2 * steps + 1)
    shifts = [(fx, fy) for fy in grid for fx in grid if (fx, fy) != (0.0, 0.0)]
    views_a, views_b, after, before = [], [], [], []
    for pair in pairs:
        a, b = pair.a.grey, pair.b.grey
        whole_a, whole_b = geometry.resize_matrix(pair.a.size, (side, side)), geometry.resize_matrix(pair.b.size, (side, side))
        for fx, fy in shifts:
            # B shows A's content moved by -shift: A's window starts where B's ends, and the other way.
            ax0, ay0, ax1, ay1 = _window(a.shape, max(0.0, fx), max(0.0, fy), 1 + min(0.0, fx), 1 + min(0.0, fy))
            bx0, by0, bx1, by1 = _window(b.shape, max(0.0, -fx), max(0.0, -fy), 1 - max(0.0, fx), 1 - max(0.0, fy))
            views_a.append(cv2.resize(a[ay0:ay1, ax0:ax1], (side, side), interpolation=cv2.INTER_AREA))
            views_b.append(cv2.resize(b[by0:by1, bx0:bx1], (side, side), interpolation=cv2.INTER_AREA))
            crop_from_a = geometry.resize_matrix((ax1 - ax0, ay1 - ay0), (side, side)) @ geometry.translation(-ax0, -ay0)
            crop_from_b = geometry.resize_matrix((bx1 - bx0, by1 - by0), (side, side)) @ geometry.translation(-bx0, -by0)
            # whole-S b_from_a = whole_b . crop_from_b^-1 . H_crop . crop_from_a . whole_a^-1
            after.append(whole_b @ np.linalg.inv(crop_from_b))
            before.append(crop_from_a @ np.linalg.inv(whole_a))
    labels = np.tile(np.arange(len(shifts), dtype=np.float64), len(pairs))
    return Hypotheses(np.stack(views_a), np.stack(views_b), np.stack(after), np.stack(before), labels, len(shifts))


def cascade_headings(estimator, small_a: np.ndarray, small_b: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """The cascade of every coarse network of a :class:`~udh_cli.estimators.deep.DeepEstimator` (its
    ``networks.first``), from B as given and (``headings`` 2) from B turned half a turn: the best-scoring answer of
    each pair, (N, 3, 3) ``b_from_a`` of the S x S images, and its score. With one network and one heading this is
    the plain cascade."""
    n, s = len(small_a), estimator.network.input_size
    half_turn = np.array([[-1.0, 0.0, s - 1.0], [0.0, -1.0, s - 1.0], [0.0, 0.0, 1.0]])  # its own inverse
    views = [(small_b, np.eye(3))]
    if estimator.headings == 2:
        views.append((np.ascontiguousarray(small_b[:, ::-1, ::-1]), half_turn))
    later = estimator.rounds()[estimator.iterations:]  # the refinement rounds, shared by every candidate
    stacked_b = np.concatenate([view for view, _ in views])
    stacked_a = np.concatenate([small_a] * len(views))
    coarse_answers = np.concatenate([estimator.predict_small(stacked_a, stacked_b, [coarse] * estimator.iterations)
                                     for coarse in estimator.networks.first])
    # Every coarse network's answers share the refinement rounds: one call a round for all of them.
    copies = len(estimator.networks.first)
    answers = coarse_answers if not later else estimator.predict_small(
        np.concatenate([stacked_a] * copies), np.concatenate([stacked_b] * copies), later, start=coarse_answers)
    candidates = [undo @ answers[(c * len(views) + k) * n : (c * len(views) + k + 1) * n]  # per coarse network and view,
                  for c in range(copies) for k, (_, undo) in enumerate(views)]  # (N, 3, 3) answers in the unturned B
    if len(candidates) == 1:
        found = candidates[0]
        return found, [estimator.score(sa, sb, h) for sa, sb, h in zip(small_a, small_b, found)]
    found, scores = [], []
    for i in range(n):
        ranked = [(estimator.score(small_a[i], small_b[i], c[i]), -k, c[i]) for k, c in enumerate(candidates)]
        score, _, h = max(ranked, key=lambda c: (c[0], c[1]))
        found.append(h / h[2, 2] if np.isfinite(h).all() and abs(h[2, 2]) > 1e-12 else h)
        scores.append(score)
    return np.stack(found), scores


def best_hypotheses(estimator, hypotheses: Hypotheses, small_a: np.ndarray, small_b: np.ndarray,
                    finalists: int = FINALISTS) -> tuple[np.ndarray, list[float], list[float]]:
    """Screen every view with the cascade's first round (one call for all), keep the ``finalists`` best-scoring
    of each pair, finish the cascade on them and keep each pair's best.

    ``estimator`` is a :class:`~udh_cli.estimators.deep.DeepEstimator` (its ``predict_small``, ``rounds`` and
    ``score``); ``small_a``, ``small_b`` (N, S, S) the whole images the answers are scored on. Returns (N, 3, 3)
    ``b_from_a`` of the whole S x S images, their scores, and the label of the view each came from.

    Why screen: a third of the passes of running the cascade on every view. On copr's consecutive pairs the
    shift search's answers were the same at a quarter of the time; seneca's run went from 170 to 104 s.
    """
    rounds = estimator.rounds()
    screened = estimator.predict_small(hypotheses.views_a, hypotheses.views_b, rounds[:1])
    per_pair, kept = hypotheses.per_pair, min(finalists, hypotheses.per_pair)
    chosen = []
    for p in range(len(small_a)):
        indices = range(p * per_pair, (p + 1) * per_pair)
        ranked = sorted(indices, key=lambda i: (-estimator.score(small_a[p], small_b[p], hypotheses.whole(i, screened[i])), i))
        chosen += ranked[:kept]
    finished = estimator.predict_small(hypotheses.views_a[chosen], hypotheses.views_b[chosen], rounds[1:], start=screened[chosen])
    best_h, best_scores, best_labels = [], [], []
    for p in range(len(small_a)):  # the finalists come in runs of `kept` per pair, in pair order
        candidates = []
        for k in range(p * kept, (p + 1) * kept):
            h = hypotheses.whole(chosen[k], finished[k])
            candidates.append((estimator.score(small_a[p], small_b[p], h), -chosen[k], h))
        score, negative_index, h = max(candidates, key=lambda c: (c[0], c[1]))  # ties: the earlier view
        best_h.append(h)
        best_scores.append(score)
        best_labels.append(float(hypotheses.labels[-negative_index]))
    return np.stack(best_h), best_scores, best_labels


def _window(shape: tuple[int, ...], fx0: float, fy0: float, fx1: float, fy1: float) -> tuple[int, int, int, int]:
    """Pixel window ``(x0, y0, x1, y1)`` of an image of ``shape`` from fractions of its width and height."""
    height, width = shape[:2]
    x0, x1 = int(round(fx0 * width)), max(int(round(fx0 * width)) + 1, int(round(fx1 * width)))
    y0, y1 = int(round(fy0 * height)), max(int(round(fy0 * height)) + 1, int(round(fy1 * height)))
    return x0, y0, x1, y1
