"""Global matching of dense descriptors (the ``matcher`` network): every cell of A against every cell of B.

Pure numpy and OpenCV, shared by the estimator and by training's validation, so both measure the same thing.
Descriptor cells are 4 px of the described image; cell ``j`` covers pixels ``4j .. 4j+3`` and its centre is
``4j + 1.5`` (the pixel-centre convention of :mod:`udh_cli.geometry`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators.recent import RecentCache, pixels_digest
from udh_cli.estimators.thresholds import THRESHOLDS

MATCH_CELL = 4  # px of the described image per descriptor cell (the matcher's two 2x pools)
# Inlier threshold of the robust fit, px of the described image: a match is a cell (4 px) against a cell, so a
# correct one is up to about a cell off.
FIT_THRESHOLD_PX = 6.0
MIN_MATCHES = 12  # fewer inliers than this and the fit is no answer
# The global match compares every cell with every cell: its cost grows as the side's fourth power (768 px, 4:3:
# 27,648 cells a frame, 7.6e8 pairs of cells: about 98 GFLOP with 64-channel descriptors), so its side is bounded; the guided refinement is not.
MAX_MATCH_SIDE = 768
MIN_DESCRIBED_SIDE = 32  # px: the matcher's smallest input (OnnxMatcher.describe); smaller images get no match
# Lowe's ratio for the global match's cells (mutual_matches). Chosen on consecutive pairs of copr, brighton-beach and
# seneca and on pairs of frames from different flights (docs/estimators.md, "The global match").
DISTINCT_RATIO = 0.95
TEXTURE_FLOOR = 0.01  # grey standard deviation ([0, 1]) under which a cell is flat (textured_cells): 2.5 of 255
GUIDED_RADIUS = 2  # cells either way around the first answer that guided matching searches (8 px at its side)
GUIDED_THRESHOLD_PX = 4.0  # the guided fit's inlier threshold: a cell
# Inliers above which a match needs no second heading, and above which it verifies itself.
CONFIDENT_INLIERS = THRESHOLDS.confident_inliers
HEADINGS = {1: (0,), 2: (0, 180), 4: (0, 180, 90, 270)}  # B's turns global_match tries, in order, by ``headings``
# The second look at a larger side first compares every other cell of A each way (a quarter of the products) and
# compares them all only where that quarter finds this many agreeing cells, a quarter of CONFIDENT_INLIERS. On
# seneca's consecutive pairs, those the second look took to 150 or more found 82-350 on the quarter, and those it
# left under 150 (and copr's frames 0 and 20, which do not overlap) at most 27 (docs/estimators.md).
SCREEN_INLIERS = CONFIDENT_INLIERS // 4
# Descriptors of recently seen images, by the matcher, size, turn and the pixels' digest (recent.py): a frame of
# a mosaic is A in one pair and B in the next, and describing it at both sides costs about as much as the global
# match itself (0.24 s at 384 and 640 px for a 1000 x 750 frame). A frame's descriptors hold 7 MB (64 channels
# at 384 and 640 px) to about 40 MB (turned copies and the second look at 768 px), so this keeps the last 3-20 frames.
DESCRIPTOR_CACHE_BYTES = 128 * 2**20
_DESCRIPTORS = RecentCache(DESCRIPTOR_CACHE_BYTES, lambda features: features.nbytes)


def cell_centres(height: int, width: int) -> np.ndarray:
    """(height * width, 2) centres (x, y), pixels of the described image, of a cell grid, row by row."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) * MATCH_CELL + (MATCH_CELL - 1) / 2


def mutual_matches(features_a: np.ndarray, features_b: np.ndarray, ratio: float = DISTINCT_RATIO,
                   valid_a: np.ndarray | None = None, valid_b: np.ndarray | None = None,
                   rows_a: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between two descriptor grids that are also distinct: an A cell's best B cell
    must be nearer than ``ratio`` times the best B cell outside its 3 x 3 neighbourhood (Lowe's ratio test, with
    the neighbours left out because the descriptors of adjacent cells overlap).

    Why the ratio test: in a featureless region (water, a grey test card, snow) every cell has the same
    descriptor, and mutual nearest neighbours alone still pair them up by the order of ties: a flat grey pair
    gave 361 "agreeing" cells and a confident identity. The ratio test removes those; the cells near the frame's
    border, which differ only by the network's padding, are left to ``valid_a`` / ``valid_b``.

    Args:
        features_a, features_b: (C, h, w) unit descriptors (any h, w each).
        valid_a, valid_b: (h, w) masks of the cells that may be matched (None: all), e.g. :func:`textured_cells`.
        rows_a: (h, w) mask of the cells of A compared at all (None: all), e.g. every other cell each way for a
            quarter of the cost; a B cell's rivals in the mutual test are then these cells alone.

    Returns:
        ``points_a``, ``points_b`` (K, 2) cell centres in pixels of each described image, and ``similarity``
        (K,), the cosine of each match.
    """
    _, ha, wa = features_a.shape
    _, hb, wb = features_b.shape
    flat_a, flat_b = _cells(features_a), _cells(features_b)
    rows = np.arange(ha * wa) if rows_a is None else np.flatnonzero(rows_a)
    best_b, first, second, column_best = _best_rows(flat_a if rows_a is None else flat_a[rows], flat_b, wb)
    distance = lambda cosine: np.sqrt(np.clip(2.0 - 2.0 * cosine, 0.0, None))  # noqa: E731 - unit vectors
    distinct = distance(first) < ratio * distance(second)
    # Mutual: A's best B cell has no A cell more similar to it than this one.
    keep = (first >= column_best[best_b]) & distinct
    if valid_a is not None:
        keep &= valid_a.ravel()[rows]
    if valid_b is not None:
        keep &= valid_b.ravel()[best_b]
    mutual = np.nonzero(keep)[0]
    # Two A cells can tie for a column's maximum (identical neighbourhoods: saturated or repeated patches); one
    # match a B cell, the first A cell, as the argmax of the reverse direction would choose.
    _, first_of_each = np.unique(best_b[mutual], return_index=True)
    mutual = mutual[np.sort(first_of_each)]
    target = best_b[mutual]
    points_b = cell_centres(hb, wb)[target] + MATCH_CELL * _subcell(flat_a[rows[mutual]], flat_b, target, hb, wb)
    return cell_centres(ha, wa)[rows[mutual]], points_b, first[mutual]


def _cells(features: np.ndarray) -> np.ndarray:
    """(C, h, w) descriptors -> (h * w, C) contiguous float32 rows, one a cell, row by row."""
    return np.ascontiguousarray(features.reshape(features.shape[0], -1).T, dtype=np.float32)


def _best_rows(rows: np.ndarray, columns: np.ndarray, width: int,
               block: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For every row descriptor (N, C): the index of its most similar column descriptor (M, C), that similarity,
    and the highest similarity outside the 3 x 3 cells around it on the columns' grid, ``width`` cells wide;
    and for every column, its highest similarity to any row (M,).

    Why blocks of rows, each reduced along its own rows: numpy's argmax down the columns of a 6,912 x 6,912
    matrix took 0.7 s at 384 px (strided reads), and the matrix is never whole in memory. Why the columns'
    maxima and not their argmax: a row and its best column are mutual exactly when the row reaches that
    column's maximum, so one product serves both directions: the same matches in about half the time of a
    second product of the columns against the rows (a seneca pair at 384 px: 0.44-0.59 -> 0.23-0.32 s)."""
    best = np.empty(len(rows), np.int64)
    first = np.empty(len(rows), np.float32)
    second = np.empty(len(rows), np.float32)
    column_best = np.full(len(columns), -np.inf, np.float32)
    for start in range(0, len(rows), block):
        similarity = rows[start : start + block] @ columns.T
        np.maximum(column_best, similarity.max(0), out=column_best)
        index = similarity.argmax(1)
        lines = np.arange(len(index))
        best[start : start + len(index)], first[start : start + len(index)] = index, similarity[lines, index]
        x, y = index % width, index // width
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                near = (x + dx >= 0) & (x + dx < width) & (y + dy >= 0) & ((y + dy) * width + x + dx < columns.shape[0])
                similarity[lines[near], ((y + dy) * width + x + dx)[near]] = -np.inf
        second[start : start + len(index)] = similarity.max(1)
    return best, first, second, column_best


def _subcell(queries: np.ndarray, columns: np.ndarray, peaks: np.ndarray, height: int, width: int) -> np.ndarray:
    """(K, 2) offsets in cells, within +-0.5, of each match's similarity peak: a parabola through the peak and
    its two neighbours along x and along y (none at the grid's edge). ``queries`` (K, C) are the matched A
    descriptors, ``columns`` (h * w, C) B's, ``peaks`` (K,) the matched B cells. Why: a cell is 4 px of the
    described image, 17 px of a 1600-px frame; the peak's shape places the match between cells."""
    px, py = peaks % width, peaks // width
    offsets = np.zeros((len(peaks), 2))
    for axis, (position, size, step) in enumerate(((px, width, 1), (py, height, width))):
        inner = (position > 0) & (position < size - 1)
        q, centre = queries[inner], peaks[inner]
        before, at, after = (np.einsum("kc,kc->k", q, columns[centre + d]) for d in (-step, 0, step))
        curvature = before - 2 * at + after
        with np.errstate(divide="ignore", invalid="ignore"):
            shift = np.where(curvature < 0, 0.5 * (before - after) / curvature, 0.0)
        offsets[inner, axis] = np.clip(np.nan_to_num(shift), -0.5, 0.5)
    return offsets


def fit_matches(points_a: np.ndarray, points_b: np.ndarray, threshold_px: float = FIT_THRESHOLD_PX,
                seed: int = 0) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust homography ``b_from_a`` (3, 3) from (K, 2) matches (OpenCV's MAGSAC++), and the (K,) inlier mask.

    None (and no inliers) when fewer than :data:`MIN_MATCHES` matches agree. ``seed`` fixes OpenCV's RANSAC
    sampling, so that the same matches always give the same answer.
    """
    inliers = np.zeros(len(points_a), bool)
    if len(points_a) < MIN_MATCHES:
        return None, inliers
    cv2.setRNGSeed(seed)
    found, mask = cv2.findHomography(points_a.astype(np.float32), points_b.astype(np.float32), cv2.USAC_MAGSAC,
                                     threshold_px, maxIters=5000, confidence=0.999)
    if found is None or mask is None or not np.isfinite(found).all():
        return None, inliers
    inliers = mask.ravel().astype(bool)
    if inliers.sum() < MIN_MATCHES:
        return None, inliers
    return found / found[2, 2], inliers


# Long side, px, at which frames are described: brighton-beach's consecutive pairs with the untrained encoder
# (corner error at that size, median / under 10 px): 384 px 2.7 px / 71 %, 512 px 3.4 px / 71 %, and 768 px
# with the network's own half-resolution input 5.9 px / 59 %. 384 px costs a 96 x 72 cell grid.
MATCH_SIDE = 384
# Long side, px, of the guided refinement. The matcher after 1,000 steps, consecutive pairs at 800 px against
# SIFT references (median corner error): copr 1.19 -> 0.98 px, seneca 4.49 -> 3.78, brighton-beach 4.99 ->
# 4.38; at 800 px about the same (0.97, 3.52, 4.68) for half again the time.
MATCH_REFINE_SIDE = 640
# Both sides hold for images smaller than them too: on the flight-motion benchmark's 320x240 frames, describing
# at the images' own size instead took the failures from 6.0 to 8.0 % (median 1.33 -> 1.47 px) for a third of
# the time (214 -> 72 ms a pair); a small image has few 4-px cells.


@dataclass
class MatchResult:
    """A global match: ``b_from_a`` (3, 3) in the full images' pixels (None: no answer), its inliers and the
    mutual matches it was fitted to, the turn of B that won (degrees counter-clockwise: 0, 90, 180, 270), and
    the longer side, px, at which the frames were described for it."""

    b_from_a: np.ndarray | None
    inliers: int
    matches: int
    heading: int
    side: int = MATCH_SIDE


@dataclass(frozen=True)
class MatchSettings:
    """How a global match runs (:func:`global_match`'s arguments): the one record of the matcher's settings and
    their check (:meth:`checked`), for ``--method matcher`` and the networks' rescue alike.

    Attributes:
        side: the longer side, px, at which frames are described (64 to :data:`MAX_MATCH_SIDE`).
        headings: B's turns tried (:data:`HEADINGS`: 1 as given, 2 also half a turn, 4 also quarter turns).
        refine_side: the longer side, px, of the guided refinement (64 to 4096; None: none).
        escalate_side: the longer side, px, of a second look when the first is not confident (64 to
            :data:`MAX_MATCH_SIDE`; None: none).
    """

    side: int = MATCH_SIDE
    headings: int = 4
    refine_side: int | None = MATCH_REFINE_SIDE
    escalate_side: int | None = MAX_MATCH_SIDE

    def checked(self, method: str, prefix: str = "") -> "MatchSettings":
        """These settings, or :class:`UdhError` naming ``method``'s options (``prefix`` + the field's name) that are
        out of range."""
        if self.headings not in HEADINGS:
            raise UdhError(f"method '{method}': {prefix}headings ({self.headings}) must be one of {', '.join(map(str, HEADINGS))}")
        if not 64 <= self.side <= MAX_MATCH_SIDE or not (self.refine_side is None or 64 <= self.refine_side <= 4096) \
                or not (self.escalate_side is None or 64 <= self.escalate_side <= MAX_MATCH_SIDE):
            raise UdhError(f"method '{method}': {prefix}side ({self.side}) and {prefix}escalate_side ({self.escalate_side}, or none) "
                           f"must be 64 to {MAX_MATCH_SIDE} px and {prefix}refine_side ({self.refine_side}) 64 to 4096 px or none")
        return self

    def near_prior(self) -> "MatchSettings":
        """B's own heading and the first side only: for a pre-warped pair the other turns and the second look
        search for what the prediction settled."""
        return MatchSettings(self.side, 1, self.refine_side, None)

    def match(self, network, image_a, image_b) -> "MatchResult":
        """:func:`global_match` of two prepared images with these settings."""
        return global_match(network, image_a, image_b, self.side, self.headings, self.refine_side, self.escalate_side)


def match_size(size: tuple[int, int], side: int) -> tuple[int, int]:
    """(w, h) to describe an image of ``size`` at: the longer side ``side``, the aspect kept, both multiples of 4."""
    scale = side / max(size)
    return tuple(max(8, int(round(v * scale / MATCH_CELL)) * MATCH_CELL) for v in size)  # type: ignore[return-value]


def global_match(network, image_a, image_b, side: int = MATCH_SIDE, headings: int = 2, refine_side: int | None = None,
                 escalate_side: int | None = None) -> MatchResult:
    """Match two :class:`~udh_cli.estimators.pair.PreparedImage` s with a matcher
    (:class:`~udh_cli.onnx_model.OnnxMatcher`): describe both at ``side`` px (once per image, kept with it),
    take mutual nearest cells and fit a homography robustly. ``headings`` 2 also matches B turned half a turn
    and keeps the heading with more inliers (a survey's strips alternate direction; the descriptors are
    trained for turns up to 45 degrees); 4 also quarter turns (a turn at a strip's end), each tried only
    while no heading has :data:`CONFIDENT_INLIERS`. ``escalate_side``: when no heading reaches
    :data:`CONFIDENT_INLIERS`, match again at this larger side (at most :data:`MAX_MATCH_SIDE` and the smaller
    frame's longer side), from the best heading so far and its half turn, each only where a quarter of A's cells
    first finds :data:`SCREEN_INLIERS` agreeing cells, and keep whichever found more.
    ``refine_side``: describe both again at that larger side and match every cell of A near where the answer
    puts it (:func:`guided_matches`) for a finer fit; the result keeps the global match's inliers, the evidence
    that it is the right place.

    Why escalate: where two frames overlap by a sliver (a strip's end on seneca, 4-11 %), too few cells of 384 px
    lie in the overlap to reach the threshold however right the match, and four times the cells do (27 -> 229 and
    66 -> 455 cells), while pairs of frames from different flights stayed at most 34 at 768 px (60 pairs;
    docs/estimators.md). Only the pairs that fail at ``side`` pay for it, and those that fail at both sides pay a
    quarter of it (the quarter look)."""
    if headings not in HEADINGS:
        raise ValueError(f"headings must be one of {sorted(HEADINGS)}, not {headings!r}")
    best = _match_at(network, image_a, image_b, side, HEADINGS[headings])
    # Never finer than the smaller frame's own pixels: upsampled cells add no evidence, only correlated matches.
    finer_side = min(escalate_side or 0, MAX_MATCH_SIDE, max(image_a.size), max(image_b.size))
    if best.inliers < CONFIDENT_INLIERS and finer_side > side:
        # The best turn so far and its half turn: a strip's end turns B by half a turn. All four turns placed one
        # more of seneca's frames (167 against 166, the same 11 parts and loops) in 593 s instead of 379 s.
        order = tuple(h for h in (best.heading, (best.heading + 180) % 360) if h in HEADINGS[headings])
        finer = _match_at(network, image_a, image_b, finer_side, order, screened=True)
        if finer.inliers > best.inliers:
            best = finer
    if best.b_from_a is not None and refine_side and refine_side > best.side:
        finer_h = _refined(network, image_a, image_b, best, refine_side)
        if finer_h is not None:
            best = MatchResult(finer_h, best.inliers, best.matches, best.heading, best.side)
    return best


def _match_at(network, image_a, image_b, side: int, turns: tuple[int, ...], screened: bool = False) -> MatchResult:
    """The global match at ``side`` px, trying B turned by each of ``turns`` in order until one is confident;
    ``screened``: each turn only where a quarter of A's cells first finds :data:`SCREEN_INLIERS` agreeing cells."""
    size_a, size_b = match_size(image_a.size, side), match_size(image_b.size, side)
    best = MatchResult(None, 0, 0, 0, side)
    if min(*size_a, *size_b) < MIN_DESCRIBED_SIDE:  # a sliver of a frame (over 12:1 at 384 px): nothing to match
        return best
    features_a, textured_a = _described(network, image_a, size_a, 0), textured_cells(image_a, size_a, 0)
    for heading in turns:
        if best.inliers >= CONFIDENT_INLIERS:
            break
        features_b, textured_b = _described(network, image_b, size_b, heading), textured_cells(image_b, size_b, heading)
        if screened and not _quarter_agrees(features_a, features_b, textured_a, textured_b):
            continue
        points_a, points_b, _ = mutual_matches(features_a, features_b, valid_a=textured_a, valid_b=textured_b)
        found, inliers = fit_matches(points_a, points_b)
        if found is None or inliers.sum() <= best.inliers:
            continue
        full = np.linalg.inv(_to_described(image_b.size, size_b, heading)) @ found @ _to_described(image_a.size, size_a, 0)
        best = MatchResult(full / full[2, 2], int(inliers.sum()), len(points_a), heading, side)
    return best


def _quarter_agrees(features_a: np.ndarray, features_b: np.ndarray, textured_a: np.ndarray, textured_b: np.ndarray) -> bool:
    """Whether every other cell of A each way, a quarter of the products of a whole match, finds
    :data:`SCREEN_INLIERS` cells of B that agree on one homography (descriptors (C, h, w), masks (h, w))."""
    quarter = np.zeros(features_a.shape[1:], bool)
    quarter[::2, ::2] = True
    points_a, points_b, _ = mutual_matches(features_a, features_b, valid_a=textured_a, valid_b=textured_b, rows_a=quarter)
    return int(fit_matches(points_a, points_b)[1].sum()) >= SCREEN_INLIERS


def _to_described(size: tuple[int, int], described: tuple[int, int], heading: int) -> np.ndarray:
    """(3, 3) from an image's pixels to those of its copy resized to ``described`` and turned by ``heading``
    degrees counter-clockwise (``np.rot90`` with k = heading / 90)."""
    out = geometry.resize_matrix(size, described)
    w, h = described
    for _ in range(heading // 90 % 4):  # np.rot90 once: (x, y) of a w-wide image -> (y, w - 1 - x)
        out = np.array([[0.0, 1, 0], [-1.0, 0, w - 1], [0, 0, 1]]) @ out
        w, h = h, w
    return out


def _refined(network, image_a, image_b, coarse: MatchResult, side: int) -> np.ndarray | None:
    """``coarse.b_from_a`` refitted to guided matches of descriptors at ``side`` px; None when too few agree."""
    size_a, size_b = match_size(image_a.size, side), match_size(image_b.size, side)
    a_to, b_to = _to_described(image_a.size, size_a, 0), _to_described(image_b.size, size_b, coarse.heading)
    features_a = _described(network, image_a, size_a, 0)
    features_b = _described(network, image_b, size_b, coarse.heading)
    predicted = b_to @ coarse.b_from_a @ np.linalg.inv(a_to)
    points_a, points_b = guided_matches(features_a, features_b, predicted)
    found, _ = fit_matches(points_a, points_b, GUIDED_THRESHOLD_PX)
    if found is None:
        return None
    full = np.linalg.inv(b_to) @ found @ a_to
    return full / full[2, 2]


def guided_matches(features_a: np.ndarray, features_b: np.ndarray, b_from_a: np.ndarray,
                   radius: int = GUIDED_RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """Each cell of A matched within ``radius`` cells of where ``b_from_a`` (3, 3, in the described images'
    pixels) puts it in B, placed between cells as :func:`mutual_matches` does: (K, 2) points of A and of B.

    Why: at a finer scale there are four times the cells and every frame is alike somewhere; a window
    around a known answer keeps the comparison local and cheap (K x (2r+1)^2 dot products)."""
    _, ha, wa = features_a.shape
    _, hb, wb = features_b.shape
    flat_a, flat_b = _cells(features_a), _cells(features_b)
    centres = cell_centres(ha, wa)
    predicted = geometry.transform_points(b_from_a, centres)
    finite = np.isfinite(predicted).all(1)
    # Cell j spans pixels [4j - 0.5, 4j + 3.5) in the pixel-centre convention.
    cell = np.floor((np.where(finite[:, None], predicted, -1e6) + 0.5) / MATCH_CELL).astype(np.int64)
    inside = finite & (cell[:, 0] >= 0) & (cell[:, 0] < wb) & (cell[:, 1] >= 0) & (cell[:, 1] < hb)
    rows, cell = np.nonzero(inside)[0], cell[inside]
    steps = [(dx, dy) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    similarity = np.full((len(rows), len(steps)), -np.inf, np.float32)
    candidates = np.zeros((len(rows), len(steps)), np.int64)
    for m, (dx, dy) in enumerate(steps):
        x, y = cell[:, 0] + dx, cell[:, 1] + dy
        ok = (x >= 0) & (x < wb) & (y >= 0) & (y < hb)
        candidates[:, m] = np.clip(y, 0, hb - 1) * wb + np.clip(x, 0, wb - 1)
        similarity[ok, m] = np.einsum("kc,kc->k", flat_a[rows[ok]], flat_b[candidates[ok, m]])
    target = candidates[np.arange(len(rows)), similarity.argmax(1)]
    points_b = cell_centres(hb, wb)[target] + MATCH_CELL * _subcell(flat_a[rows], flat_b, target, hb, wb)
    return centres[rows], points_b


def textured_cells(image, size: tuple[int, int], heading: int = 0) -> np.ndarray:
    """(h, w) mask of the descriptor cells of ``image`` described at ``size`` and turned by ``heading`` whose
    12 x 12 px neighbourhood varies by more than :data:`TEXTURE_FLOOR` (standard deviation, grey in [0, 1]).

    Why: where the image is flat the descriptors encode only the distance to the frame's border (the network's
    zero padding), the same in every frame; a flat grey pair matched its border cells 324 times."""
    def make() -> np.ndarray:
        grey = _turned(image, size, heading).astype(np.float32)
        mean = cv2.blur(grey, (12, 12))
        deviation = np.sqrt(np.clip(cv2.blur(grey * grey, (12, 12)) - mean * mean, 0.0, None))
        cells = deviation[MATCH_CELL // 2 :: MATCH_CELL, MATCH_CELL // 2 :: MATCH_CELL]
        return cells[: grey.shape[0] // MATCH_CELL, : grey.shape[1] // MATCH_CELL] > TEXTURE_FLOOR

    return image.derived(("textured cells", size, heading), make)


def _described(network, image, size: tuple[int, int], heading: int) -> np.ndarray:
    """The matcher's descriptors of ``image`` at ``size``, turned by ``heading`` degrees counter-clockwise
    (:func:`_to_described`), made once per image and kept a while for the next pair it is in (:data:`_DESCRIPTORS`)."""
    # The network by its loaded bytes (OnnxMatcher.identity) where it has them, so that a model file rewritten in
    # a long-lived process is never served the old model's descriptors; the image by the pixels it is described
    # from, a digest of 0.4 MB at 384 px rather than of the whole frame.
    network_key = getattr(network, "identity", "") or str(network.path)

    def make() -> np.ndarray:
        key = ("descriptors", network_key, heading, pixels_digest(image.resized(size)))
        return _DESCRIPTORS.get_or_make(key, lambda: network.describe(_turned(image, size, heading)))

    return image.derived(("descriptors", network_key, size, heading), make)


def _turned(image, size: tuple[int, int], heading: int) -> np.ndarray:
    """``image`` resized to ``size`` and turned by ``heading`` degrees counter-clockwise, as :func:`_to_described` maps it."""
    return np.ascontiguousarray(np.rot90(image.resized(size), heading // 90 % 4))
