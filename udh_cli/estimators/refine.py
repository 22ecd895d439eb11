"""Photometric refinement: coarse-to-fine ECC from an initial homography, on a bounded budget.

ECC maximises the correlation coefficient, so it is invariant to gain and bias between the images; aligning
their local contrast makes it invariant to light that changes across them too.
It is precise near the answer and diverges far from it; a network's estimate gives it that start.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import EstimationFailed
from udh_cli.estimators.ecc import HAS_MASKED_ECC, EccEstimator
from udh_cli.estimators.pair import ImageLike, PreparedImage
from udh_cli.images import scaled_size


ROBUST_MIN_SHARE = 0.2  # the robust pass needs this share of B's pixels to agree
ROBUST_MAX_MOVE_PX = 3.0  # pixels of the finest level: further, the robust pass is not a polish and is dropped


@dataclass
class PyramidEcc:
    """Refine ``b_from_a`` with ECC over an image pyramid.

    Attributes:
        work_side: the longer side (pixels) of the finest level; larger images are downscaled first,
            and the result is rescaled exactly to the originals.
        levels: pyramid levels, each half the size of the next.
        iterations: ECC iterations per level, coarsest first (a bounded budget).
        blur: side of the Gaussian OpenCV applies to both images before aligning, per level, coarsest first
            (1: none): blur widens ECC's basin, and the finest level aligns unblurred because blur biases the
            optimum under strong perspective.
        eps: ECC's convergence threshold (the least gain in correlation an iteration must make): 3e-4 keeps the
            errors of 1e-5 at about 70 % of the time.
        max_move: the largest corner move from the start, as a share of A's diagonal, that counts as
            refining; ECC that goes further has diverged (a refinement corrects a close guess).
        contrast_sigma: ECC aligns the images' local contrast (:func:`udh_cli.images.local_contrast`, mean and
            deviation over this many pixels of each level) instead of their grey values (0): ECC's one gain
            and bias cannot model light that changes across the image.
        robust_k: after the pyramid, ECC runs once more at the finest level on the pixels of B whose residual is
            under this many robust deviations (:meth:`_robust_pass`), so that occluders, moving water and
            glints stop pulling the fit; 0 turns it off, and so does an OpenCV without
            ``findTransformECCWithMask``.
        robust_iterations: the robust pass's iteration budget (it starts from a converged answer).
        clean_side, clean_correlation: when the level before the finest correlates at ``clean_correlation`` or
            more (clean texture, no surf or moving water), the finest level and the robust pass run at
            ``clean_side`` pixels (longer side) instead of ``work_side``: as accurate there, and faster. None:
            always ``work_side``; images no larger than ``clean_side`` are aligned as before either way.

    The measurements behind these settings are in ``docs/estimators.md`` ("Why the settings").
    """

    work_side: int = 480  # 640 px is half again as slow and no more accurate (docs/estimators.md, "Why the settings")
    levels: int = 3
    iterations: tuple[int, ...] = (20, 15, 10)  # from the cascade's start, (40, 30, 20) cost 25 % more time for the same failures
    blur: tuple[int, ...] = (3, 3, 1)
    eps: float = 3e-4
    max_move: float = 0.25
    contrast_sigma: float = 2.0
    robust_k: float = 2.0
    robust_iterations: int = 10
    clean_side: int | None = 400  # clean texture aligns as accurately here; fewer pixels lost pairs over surf
    clean_correlation: float = 0.9  # above the coarse correlation of pairs over surf or moving water

    def __post_init__(self) -> None:
        if len(self.iterations) < self.levels or len(self.blur) < self.levels:
            raise ValueError(f"PyramidEcc: {self.levels} levels need as many iterations and blur sizes "
                             f"(got {len(self.iterations)} and {len(self.blur)})")
        if any(size < 1 or size % 2 == 0 for size in self.blur):
            raise ValueError(f"PyramidEcc: blur sizes {self.blur} must be odd and positive")
        if self.clean_side is not None and self.clean_side < 1:
            raise ValueError(f"PyramidEcc: clean_side ({self.clean_side}) must be a positive side in pixels, or None")
        if not (self.contrast_sigma >= 0 and self.robust_k >= 0 and self.robust_iterations >= 1):
            raise ValueError(f"PyramidEcc: contrast_sigma ({self.contrast_sigma}) and robust_k ({self.robust_k}) must be "
                             f"0 (off) or more, robust_iterations ({self.robust_iterations}) at least 1")

    def refine(self, image_a: ImageLike, image_b: ImageLike, b_from_a: np.ndarray) -> tuple[np.ndarray, float]:
        """Returns the refined ``b_from_a`` (pixels of the given images) and the final correlation.

        The images are arrays or prepared ones (:mod:`udh_cli.estimators.pair`), whose pyramid levels are then
        made once and shared with the other stages. Raises :class:`EstimationFailed` when ECC diverges at the
        finest level.
        """
        prepared_a, prepared_b = PreparedImage.of(image_a, "image A"), PreparedImage.of(image_b, "image B")
        size_a, size_b = prepared_a.size, prepared_b.size
        longest = max(*size_a, *size_b)
        scale = min(1.0, self.work_side / longest)
        current = np.asarray(b_from_a, dtype=np.float64)
        correlation = float("nan")
        budgets = list(self.iterations)[-self.levels :]
        blurs = list(self.blur)[-self.levels :]
        for level, budget, blur in zip(range(self.levels - 1, -1, -1), budgets, blurs):
            s = scale / (2**level)
            if level == 0 and self.clean_side is not None and correlation >= self.clean_correlation:
                s = min(s, self.clean_side / longest)  # clean texture aligns as well at fewer pixels
            work_a, work_b = scaled_size(size_a, s), scaled_size(size_b, s)
            if self.contrast_sigma > 0:
                small_a, small_b = prepared_a.contrast(work_a, self.contrast_sigma), prepared_b.contrast(work_b, self.contrast_sigma)
            else:
                small_a, small_b = prepared_a.resized(work_a), prepared_b.resized(work_b)
            start = geometry.rescale_homography(current, size_a, work_a, size_b, work_b)
            ecc = EccEstimator(iterations=budget, eps=self.eps, gauss_filt_size=blur, min_correlation=0.0)
            try:
                refined, correlation, _ = ecc.refine(small_a, small_b, start)
            except EstimationFailed:
                if level == 0:
                    raise
                correlation = float("nan")  # the clean-texture rule reads the level just before the finest only
                continue  # a coarse level may lack texture; the finer ones still get their chance
            current = geometry.rescale_homography(refined, work_a, size_a, work_b, size_b)
        if self.robust_k > 0 and HAS_MASKED_ECC:
            current, correlation = self._robust_pass(small_a, small_b, size_a, size_b, current, correlation, blurs[-1])
        start = np.asarray(b_from_a, dtype=np.float64)
        moved = float(geometry.corner_errors(current, start, *size_a).max())
        if not moved <= self.max_move * float(np.hypot(*size_a)):
            raise EstimationFailed(f"ECC moved a corner {moved:.0f} px from its start: it diverged")
        return current, correlation

    def _robust_pass(self, small_a: np.ndarray, small_b: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int],
                     current: np.ndarray, correlation: float, blur: int) -> tuple[np.ndarray, float]:
        """ECC once more at the finest level, on the pixels of B whose residual is under ``robust_k`` robust
        deviations (1.4826 x the median absolute residual): occluders, moving water and glints no longer pull.

        ``small_a``, ``small_b``: the finest level's (normalised) images; ``size_a``, ``size_b``: the originals'
        (width, height).
        Keeps ``current`` when too few pixels agree, ECC fails, or the pass moves a corner over
        :data:`ROBUST_MAX_MOVE_PX` (it polishes a converged answer, it does not search).
        """
        work_a, work_b = (small_a.shape[1], small_a.shape[0]), (small_b.shape[1], small_b.shape[0])
        start = geometry.rescale_homography(current, size_a, work_a, size_b, work_b)
        warped = cv2.warpPerspective(small_a, start, work_b, flags=cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.ones_like(small_a), start, work_b, flags=cv2.INTER_NEAREST) > 0.5
        if inside.mean() < ROBUST_MIN_SHARE:
            return current, correlation
        residual = np.abs(warped - small_b)
        agree = inside & (residual <= self.robust_k * 1.4826 * float(np.median(residual[inside])))
        if agree.mean() < ROBUST_MIN_SHARE:
            return current, correlation
        ecc = EccEstimator(iterations=self.robust_iterations, eps=self.eps, gauss_filt_size=blur, min_correlation=0.0)
        try:
            refined, robust_correlation, _ = ecc.refine(small_a, small_b, start, mask_b=agree)
        except EstimationFailed:
            return current, correlation
        if not float(geometry.corner_errors(refined, start, *work_a).max()) <= ROBUST_MAX_MOVE_PX:
            return current, correlation
        return geometry.rescale_homography(refined, work_a, size_a, work_b, size_b), robust_correlation
