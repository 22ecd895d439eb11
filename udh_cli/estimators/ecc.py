"""ECC (enhanced correlation coefficient) photometric alignment, OpenCV's MOTION_HOMOGRAPHY."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.base import Estimator


HAS_MASKED_ECC = hasattr(cv2, "findTransformECCWithMask")  # recent OpenCV only (5.0.0 on the development machine)


@dataclass
class EccEstimator(Estimator):
    """Maximise the correlation coefficient between B and A warped by ``b_from_a``.

    ECC is invariant to gain and bias, precise near the answer, and diverges far from it.

    Attributes:
        iterations: the most iterations OpenCV may run (the paper uses 1000).
        eps: stop when the correlation improves by less than this.
        init: initial ``b_from_a`` in pixels of the given images; ``None`` starts at the identity.
        gauss_filt_size: Gaussian blur OpenCV applies before aligning (odd, pixels).
        min_correlation: a final correlation coefficient below this is reported as a failure.
    """

    name: ClassVar[str] = "ecc"
    iterations: int = 1000
    eps: float = 1e-6
    init: np.ndarray | None = None
    gauss_filt_size: int = 5
    min_correlation: float = 0.3

    def __post_init__(self) -> None:
        if self.iterations < 1:  # OpenCV would stop at once and report a meaningless correlation
            raise UdhError(f"method '{self.name}': iterations {self.iterations} must be at least 1")

    def _estimate(self, pair):
        return self.refine(pair.a.grey, pair.b.grey, self.init)

    def refine(self, gray_a: np.ndarray, gray_b: np.ndarray, b_from_a: np.ndarray | None, mask_b: np.ndarray | None = None):
        """Run ECC from ``b_from_a`` (or the identity); returns ``(b_from_a, correlation, details)``.

        ``gray_a``, ``gray_b``: (H, W) float32 images (grey, or any normalisation of it such as local contrast).
        ``mask_b``: (H_B, W_B) bool, the pixels of B that may count (all when None). Needs OpenCV's
        ``findTransformECCWithMask`` (:data:`HAS_MASKED_ECC`).
        """
        if float(gray_a.std()) < 1e-4 or float(gray_b.std()) < 1e-4:
            raise EstimationFailed("an image is constant; ECC needs texture")
        if mask_b is not None:
            if np.shape(mask_b) != gray_b.shape:
                raise ValueError(f"mask_b has shape {np.shape(mask_b)}; image B is {gray_b.shape}")
            mask_b = (np.asarray(mask_b) > 0).astype(np.uint8)
        start = np.eye(3) if b_from_a is None else np.asarray(b_from_a, dtype=np.float64)
        # findTransformECC(template, input, warp) finds warp with input(warp(x)) ~ template(x): with
        # template B and input A, warp is a_from_b, the inverse of our convention.
        warp = geometry.invert(start).astype(np.float32)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.iterations, self.eps)
        try:
            if mask_b is None:
                correlation, warp = cv2.findTransformECC(
                    gray_b, gray_a, warp, cv2.MOTION_HOMOGRAPHY, criteria, None, self.gauss_filt_size
                )
            else:
                everywhere_a = np.ones(gray_a.shape, np.uint8)
                correlation, warp = cv2.findTransformECCWithMask(
                    gray_b, gray_a, mask_b, everywhere_a, warp, cv2.MOTION_HOMOGRAPHY, criteria, self.gauss_filt_size
                )
        except cv2.error as exc:
            raise EstimationFailed(f"ECC did not converge ({_opencv_reason(exc)})") from None
        if not np.isfinite(correlation) or correlation < self.min_correlation:
            raise EstimationFailed(f"ECC converged to a poor alignment (correlation {correlation:.2f})")
        return geometry.invert(warp.astype(np.float64)), float(correlation), {"correlation": float(correlation)}


def _opencv_reason(exc: cv2.error) -> str:
    """The human part of an OpenCV error, without its version, source path, code and function name."""
    text = " ".join(str(exc).split())
    match = re.search(r"error: \(-?\d+:[^)]*\)\s*(.*?)(?:\s+in function '[^']*')?\s*$", text)
    reason = match.group(1) if match and match.group(1) else text
    return reason.rstrip(".") or "OpenCV error"
