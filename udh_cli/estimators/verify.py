"""Photometric verification: how well does an estimate align the two images?"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators.pair import ImageLike, PreparedImage
from udh_cli.images import scaled_size


@dataclass(frozen=True)
class Verifier:
    """The one photometric check of an alignment, used by the networks (on their own S x S input), by the
    cascades (``auto``, ``unsupervised+ecc``) and by the mosaic's acceptance test.

    The score is the median, over ``tiles`` x ``tiles`` tiles of the overlap, of the lower of the intensity and
    gradient NCC of B and A warped into B's frame (:func:`alignment_ncc`), at ``side`` px: in [0, 1].

    Attributes:
        side: longer side (px) the images are scored at. 256: enough texture to separate right from wrong,
            a few ms a score.
        tiles: the median over tiles ignores what disagrees in a minority of them: on held-out rho-32 pairs with
            occluders, right answers (under 1 px) scored 0.41 median on the whole overlap and 0.73 tiled, while
            wrong ones (over 10 px) stayed at most 0.51 tiled; on the wrong seneca pairs of the unsupervised
            network, 11 % passed the mosaic's 0.3 check tiled against 40 % whole (and 93 % of its right pairs,
            against 100 %).
        min_overlap: least share of B that A must cover to be judged at all. Real consecutive drone frames can
            overlap that little: two right copr pairs (SIFT reference, 30 and 158 inliers) cover 17 % and
            17.5 %, and at 0.3 they scored 0 and split the mosaic.
    """

    side: int = 256
    tiles: int = 4
    min_overlap: float = 0.15

    def score(self, image_a: ImageLike, image_b: ImageLike, b_from_a: np.ndarray | None, structure: bool = True) -> float:
        """How well ``b_from_a`` aligns two images of any size (arrays, or prepared once and shared); in [0, 1].

        ``structure`` False scores the intensity NCC alone. 0 for no or a degenerate estimate, or an overlap
        below ``min_overlap``.
        """
        if b_from_a is None:
            return 0.0
        prepared_a, prepared_b = PreparedImage.of(image_a, "image A"), PreparedImage.of(image_b, "image B")
        size_a, size_b = prepared_a.size, prepared_b.size
        scale = min(1.0, self.side / max(*size_a, *size_b))
        work_a, work_b = scaled_size(size_a, scale), scaled_size(size_b, scale)
        h = geometry.rescale_homography(b_from_a, size_a, work_a, size_b, work_b)
        return self.score_grey(prepared_a.resized(work_a), prepared_b.resized(work_b), h, structure)

    def score_grey(self, gray_a: np.ndarray, gray_b: np.ndarray, b_from_a: np.ndarray, structure: bool = True) -> float:
        """The score of (H, W) float32 grey images already at the size to score them at; in [0, 1]."""
        on = "both" if structure else "intensity"
        return max(0.0, alignment_ncc(gray_a, gray_b, b_from_a, self.min_overlap, on=on, tiles=self.tiles))


VERIFIER = Verifier()  # the check of auto's answers (Policy.min_score) and of the mosaic's (Acceptance.min_verified)


def gradient_magnitude(gray: np.ndarray) -> np.ndarray:
    """(H, W) float32 -> (H, W) float32 Sobel gradient magnitude: the image's structure without its shading."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    return np.sqrt(gx * gx + gy * gy)


def alignment_ncc(gray_a: np.ndarray, gray_b: np.ndarray, b_from_a: np.ndarray, min_overlap: float = 0.3,
                  on: str = "intensity", tiles: int = 1) -> float:
    """Normalised cross-correlation between B and A warped into B's frame, over their overlap.

    Args:
        gray_a, gray_b: (H, W) float32 grey images.
        b_from_a: (3, 3) homography between them, pixels.
        min_overlap: below this share of B covered by A, the answer is 0: a small overlap can correlate
            well by chance (a diverged ECC on occluded patches scored high on slivers of overlap).
        on: "intensity" compares the grey values; "gradient" compares gradient magnitudes (of the warped A
            and of B); "both" is the lower of the two, from one warp. Smooth, low-texture scenes (fields,
            water) keep a high intensity NCC under a wrong shift (wrong pairs of the seneca flight scored up
            to 0.9), their gradients do not (at most 0.47 at 256 px).
        tiles: 1 correlates the whole overlap; N > 1 splits the overlap's bounding box into N x N tiles and
            takes the median of the tiles' NCC (tiles at least half inside the overlap). The median ignores
            what disagrees in a minority of tiles: occluders, moving water, a passing car.

    Returns:
        NCC in [-1, 1]; gain and bias changes do not lower it. 0 for a non-finite H or too little overlap.
    """
    if on not in ("intensity", "gradient", "both"):
        raise ValueError(f"on={on!r}: use 'intensity', 'gradient' or 'both'")
    if not np.isfinite(b_from_a).all():
        return 0.0
    size = (gray_b.shape[1], gray_b.shape[0])
    warped = cv2.warpPerspective(gray_a, b_from_a, size, flags=cv2.INTER_LINEAR)
    mask = cv2.warpPerspective(np.ones_like(gray_a), b_from_a, size, flags=cv2.INTER_NEAREST) > 0.5
    if mask.mean() < min_overlap:
        return 0.0
    scores = []
    if on != "gradient":
        scores.append(_tiled_ncc(warped, gray_b, mask, tiles))
    if on != "intensity":
        inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # Sobel reads one pixel around
        scores.append(_tiled_ncc(gradient_magnitude(warped), gradient_magnitude(gray_b), inner, tiles))
    return min(scores)


def _tiled_ncc(x: np.ndarray, y: np.ndarray, mask: np.ndarray, tiles: int) -> float:
    """NCC of two (H, W) images over ``mask``: whole (``tiles`` 1), or the median over a ``tiles`` x ``tiles``
    grid on the mask's bounding box of the tiles at least half inside the mask (0 when none is)."""
    if tiles <= 1:
        return _ncc(x[mask], y[mask])
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return 0.0
    row_edges = np.linspace(rows[0], rows[-1] + 1, tiles + 1).astype(int)
    col_edges = np.linspace(cols[0], cols[-1] + 1, tiles + 1).astype(int)
    # The six masked moments of every tile in one pass (np.add.reduceat over the tile edges), instead of a
    # correlation per tile: the score runs several times per estimate and this was most of its time.
    r0, r1, c0, c1 = row_edges[0], row_edges[-1], col_edges[0], col_edges[-1]
    x, y, m = x[r0:r1, c0:c1], y[r0:r1, c0:c1], mask[r0:r1, c0:c1].astype(np.float64)
    xm, ym = x * m, y * m
    moments = np.stack([m, xm, ym, xm * x, ym * y, xm * y])
    sums = np.add.reduceat(np.add.reduceat(moments, row_edges[:-1] - r0, axis=1), col_edges[:-1] - c0, axis=2)
    count, sx, sy, sxx, syy, sxy = sums.reshape(6, -1)
    area = np.outer(np.diff(row_edges), np.diff(col_edges)).ravel()
    # A sliver of overlap leaves some tiles empty (area 0; reduceat's sums there are not theirs): left out.
    used = (area > 0) & (count >= 0.5 * area)
    if not used.any():
        return 0.0
    count, sx, sy, sxx, syy, sxy = (v[used] for v in (count, sx, sy, sxx, syy, sxy))
    var_x, var_y = sxx - sx * sx / count, syy - sy * sy / count
    flat = (var_x <= 1e-10 * count) | (var_y <= 1e-10 * count)  # constant tiles (up to rounding): NCC 0
    ncc = np.where(flat, 0.0, (sxy - sx * sy / count) / np.sqrt(np.where(flat, 1.0, var_x * var_y)))
    return float(np.median(ncc))


def _ncc(x: np.ndarray, y: np.ndarray) -> float:
    """NCC of two equal-length 1-D samples; 0 when either is constant."""
    x, y = x.astype(np.float64), y.astype(np.float64)
    x, y = x - x.mean(), y - y.mean()
    denominator = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / denominator) if denominator > 1e-12 else 0.0
