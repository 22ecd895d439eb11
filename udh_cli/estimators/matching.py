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

MATCH_CELL = 4  # px of the described image per descriptor cell (the matcher's two 2x pools)
# Inlier threshold of the robust fit, px of the described image: a match is a cell (4 px) against a cell, so a
# correct one is up to about a cell off.
FIT_THRESHOLD_PX = 6.0
MIN_MATCHES = 12  # fewer inliers than this and the fit is no answer
# Inliers above which a match needs no second heading, and above which it verifies itself, as RANSAC verifies
# SIFT's answers. With an untrained encoder, on consecutive pairs of copr, brighton-beach and seneca: right
# answers had 185-4,000 inliers, pairs of frames six or more apart (no shared ground) 0-65 (one 151).
CONFIDENT_INLIERS = 150


def cell_centres(height: int, width: int) -> np.ndarray:
    """(height * width, 2) centres (x, y), pixels of the described image, of a cell grid, row by row."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) * MATCH_CELL + (MATCH_CELL - 1) / 2


def mutual_matches(features_a: np.ndarray, features_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours between two descriptor grids.

    Args:
        features_a, features_b: (C, h, w) unit descriptors (any h, w each).

    Returns:
        ``points_a``, ``points_b`` (K, 2) cell centres in pixels of each described image, and ``similarity``
        (K,), the cosine of each match.
    """
    c, ha, wa = features_a.shape
    _, hb, wb = features_b.shape
    similarity = features_a.reshape(c, -1).T.astype(np.float32) @ features_b.reshape(c, -1).astype(np.float32)
    best_b = similarity.argmax(1)
    best_a = similarity.argmax(0)
    mutual = np.nonzero(best_a[best_b] == np.arange(len(best_b)))[0]
    target = best_b[mutual]
    points_b = cell_centres(hb, wb)[target] + MATCH_CELL * _subcell(similarity, mutual, target, hb, wb)
    return cell_centres(ha, wa)[mutual], points_b, similarity[mutual, target]


def _subcell(similarity: np.ndarray, rows: np.ndarray, peaks: np.ndarray, height: int, width: int) -> np.ndarray:
    """(K, 2) offsets in cells, within +-0.5, of each match's similarity peak: a parabola through the peak and
    its two neighbours along x and along y (none at the grid's edge). Why: a cell is 4 px of the described
    image, 17 px of a 1600-px frame; the peak's shape places the match between cells."""
    px, py = peaks % width, peaks // width
    offsets = np.zeros((len(peaks), 2))
    for axis, (position, size, step) in enumerate(((px, width, 1), (py, height, width))):
        inner = (position > 0) & (position < size - 1)
        r, centre = rows[inner], peaks[inner]
        before, at, after = similarity[r, centre - step], similarity[r, centre], similarity[r, centre + step]
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


@dataclass
class MatchResult:
    """A global match: ``b_from_a`` (3, 3) in the full images' pixels (None: no answer), its inliers and the
    mutual matches it was fitted to, and the heading of B that won (0 or 180 degrees)."""

    b_from_a: np.ndarray | None
    inliers: int
    matches: int
    heading: int


def match_size(size: tuple[int, int], side: int) -> tuple[int, int]:
    """(w, h) to describe an image of ``size`` at: the longer side ``side``, the aspect kept, both multiples of 4."""
    scale = side / max(size)
    return tuple(max(8, int(round(v * scale / MATCH_CELL)) * MATCH_CELL) for v in size)  # type: ignore[return-value]


def global_match(network, image_a, image_b, side: int = MATCH_SIDE, headings: int = 2) -> MatchResult:
    """Match two :class:`~udh_cli.estimators.pair.PreparedImage` s with a matcher
    (:class:`~udh_cli.onnx_model.OnnxMatcher`): describe both at ``side`` px (once per image, kept with it),
    take mutual nearest cells and fit a homography robustly. ``headings`` 2 also matches B turned half a turn
    and keeps the heading with more inliers (a survey's strips alternate direction; the descriptors are
    trained for turns up to 45 degrees)."""
    size_a, size_b = match_size(image_a.size, side), match_size(image_b.size, side)
    features_a = _described(network, image_a, size_a, turned=False)
    best = MatchResult(None, 0, 0, 0)
    for heading in ((0, 180) if headings == 2 else (0,)):
        if best.inliers >= CONFIDENT_INLIERS:
            break
        features_b = _described(network, image_b, size_b, turned=heading == 180)
        points_a, points_b, _ = mutual_matches(features_a, features_b)
        found, inliers = fit_matches(points_a, points_b)
        if found is None or inliers.sum() <= best.inliers:
            continue
        if heading == 180:  # undo the turn: a point (x, y) of the turned B is (w-1-x, h-1-y) of B
            w, h = size_b
            found = np.array([[-1.0, 0, w - 1], [0, -1.0, h - 1], [0, 0, 1]]) @ found
        full = np.linalg.inv(geometry.resize_matrix(image_b.size, size_b)) @ found @ geometry.resize_matrix(image_a.size, size_a)
        best = MatchResult(full / full[2, 2], int(inliers.sum()), len(points_a), heading)
    return best


def _described(network, image, size: tuple[int, int], turned: bool) -> np.ndarray:
    """The matcher's descriptors of ``image`` at ``size`` (turned half a turn or not), made once per image."""
    def make() -> np.ndarray:
        grey = image.resized(size)
        return network.describe(np.ascontiguousarray(grey[::-1, ::-1]) if turned else grey)

    return image.derived(("descriptors", str(network.path), size, turned), make)
