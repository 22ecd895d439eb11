"""Feature matching + RANSAC estimators (SIFT and ORB), with the paper's settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Sequence

import cv2
import numpy as np

from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.base import Estimator
from udh_cli.estimators.pair import PreparedImage
from udh_cli.estimators.recent import RecentCache, pixels_digest


# Recently detected features, least recently used first: (method, settings, pixels' digest) -> (points,
# descriptors, responses), up to FEATURE_CACHE_BYTES of them: a budget rather than a count of images, since
# frames differ tenfold in keypoints. A frame of 10,000 SIFT keypoints holds 1.4 MB (descriptors kept as bytes,
# :class:`_FeatureCache`).
FEATURE_CACHE_BYTES = 256 * 2**20
# Above this many keypoints in an image, exact matching costs seconds (a 1600 px photo has 20,000); the
# kd-trees then take a fraction of it for the same inliers. Below, exact matching is fast and stays exact.
EXACT_MATCH_LIMIT = 5000


class _FeatureCache:
    """Features by key in a :class:`~udh_cli.estimators.recent.RecentCache` of ``budget_bytes``. Float
    descriptors whose values are all whole numbers in 0-255 (OpenCV's SIFT rounds them so) are held as bytes, a
    quarter of the memory, and given back as float32: exactly the same values. Arrays given back are read-only."""

    def __init__(self, budget_bytes: int) -> None:
        self.recent = RecentCache(budget_bytes, self._size)

    @property
    def held_bytes(self) -> int:
        return self.recent.held_bytes

    @staticmethod
    def _size(entry: tuple) -> int:
        points, descriptors, _, responses = entry
        return points.nbytes + responses.nbytes + (descriptors.nbytes if descriptors is not None else 0)

    def get(self, key) -> tuple[np.ndarray, np.ndarray | None, np.ndarray] | None:
        entry = self.recent.get(key)
        return None if entry is None else self._served(entry)

    @staticmethod
    def _served(entry: tuple) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        points, descriptors, dtype, responses = entry
        if descriptors is not None and descriptors.dtype != dtype:
            descriptors = descriptors.astype(dtype)
            descriptors.flags.writeable = False
        return points, descriptors, responses

    def put(self, key, points: np.ndarray, descriptors: np.ndarray | None,
            responses: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Keep the features under ``key``; returns them as :meth:`get` would (another thread may drop them
        from the cache before this one gets them)."""
        held, dtype = descriptors, None if descriptors is None else descriptors.dtype
        if descriptors is not None and descriptors.dtype == np.float32 and descriptors.size and descriptors.min() >= 0 \
                and descriptors.max() <= 255 and np.array_equal(descriptors, np.round(descriptors)):
            held = descriptors.astype(np.uint8)
        for array in (points, held, responses):
            if array is not None:
                array.flags.writeable = False  # shared by every later get
        return self._served(self.recent.put(key, (points, held, dtype, responses)))

    def clear(self) -> None:
        self.recent.clear()


_FEATURE_CACHE = _FeatureCache(FEATURE_CACHE_BYTES)


def keypoint_points(keypoints: Sequence) -> np.ndarray:
    """(N, 2) float64 pixels of OpenCV keypoints."""
    return np.array([k.pt for k in keypoints], np.float64).reshape(-1, 2)


def ratio_test_points(knn: list, points_a: np.ndarray, points_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Lowe's ratio test on two-nearest-neighbour matches (OpenCV DMatch lists, A's descriptors queried in B's;
    ``points_a``, ``points_b``: (N, 2) keypoint pixels, :func:`keypoint_points`): the (M, 2) float64 pixels in A
    and in B of the matches whose best is below ``ratio`` times the second best."""
    good = [pair[0] for pair in knn if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance]
    return (points_a[[m.queryIdx for m in good]].reshape(-1, 2).astype(np.float64, copy=False),
            points_b[[m.trainIdx for m in good]].reshape(-1, 2).astype(np.float64, copy=False))


@dataclass
class FeatureRansacEstimator(Estimator):
    """Detect keypoints, match with Lowe's ratio test, fit ``b_from_a`` with RANSAC.

    Attributes:
        ratio: Lowe's ratio-test threshold; a match is kept when best < ratio * second best.
        ransac_px: RANSAC reprojection threshold in pixels of B (the paper uses 5).
        best_features: keep only the N strongest keypoints per image (the paper uses all on synthetic
            data and the best 50 on aerial data); ``None`` keeps all.
        min_inliers: fewer RANSAC inliers than this is reported as a failure, not returned.
        lmeds_refit: refit the RANSAC inliers with least-median-of-squares. A 5 px RANSAC threshold admits
            loose matches that tilt the least-squares fit; on graf1/graf3 the refit brings the corner
            error from 2-5 px (varying with the ratio) to a steady 1.4-1.7 px.
        matcher: "bf" compares every descriptor pair (exact); "flann" searches randomised kd-trees (float
            descriptors only: SIFT), seeded so that an answer is reproducible: it resets the calling thread's
            OpenCV random generator (``cv2.setRNGSeed(0)``) before each match. On 800-px seneca frames with
            5,000-12,000 SIFT keypoints flann took 0.1-0.7 s a pair against bf's 0.6-3.2 s, with the same
            inlier counts (within 1 %). "auto": bf up to :data:`EXACT_MATCH_LIMIT` keypoints in either image,
            flann beyond (float descriptors; bf for ORB's binary ones).
    """

    ratio: float = 0.75
    ransac_px: float = 5.0
    best_features: int | None = None
    min_inliers: int = 8
    lmeds_refit: bool = True
    matcher: str = "auto"

    norm: ClassVar[int] = cv2.NORM_L2
    verifies_itself: ClassVar[bool] = True  # an answer needs min_inliers matches that agree on it

    def __post_init__(self) -> None:
        if not 0.0 < self.ratio <= 1.0:
            raise UdhError(f"method '{self.name}': ratio {self.ratio} must be in (0, 1]")
        if not self.ransac_px > 0.0:
            raise UdhError(f"method '{self.name}': ransac_px {self.ransac_px} must be positive")
        if self.matcher not in ("bf", "flann", "auto"):
            raise UdhError(f"method '{self.name}': matcher '{self.matcher}' must be bf, flann or auto")
        if self.matcher == "flann" and self.norm != cv2.NORM_L2:
            raise UdhError(f"method '{self.name}': matcher flann needs float descriptors (sift); use bf")
        if self.best_features is not None and self.best_features < 1:  # a negative N would slice off the best ones
            raise UdhError(f"method '{self.name}': best_features {self.best_features} must be at least 1 (or unset for all)")

    def _detector(self):
        raise NotImplementedError

    def _detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """Every keypoint of a grey image: (N, 2) pixels, descriptors and (N,) responses, from
        :data:`_FEATURE_CACHE` when this detector has seen the same pixels recently (:mod:`udh_cli.estimators.recent`:
        detection is most of a feature matcher's time). ``best_features`` is
        applied afterwards (:meth:`_features`), to what an image keeps."""
        key = (self.name, repr(self._cache_settings()), pixels_digest(gray))
        found = _FEATURE_CACHE.get(key)
        if found is None:
            found = _FEATURE_CACHE.put(key, *self._detect_uncached(gray))
        return found

    def _detect_uncached(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        keypoints, descriptors = self._detector().detectAndCompute(gray, None)
        if descriptors is None or len(keypoints) == 0:
            keypoints, descriptors = [], None
        return keypoint_points(keypoints), descriptors, np.array([k.response for k in keypoints], np.float32)

    def _cache_settings(self) -> tuple:
        """The detector's settings (those that change what :meth:`_detect` returns)."""
        return ()

    def _match(self, descriptors_a: np.ndarray, descriptors_b: np.ndarray) -> list:
        """Each descriptor of A's two nearest in B (OpenCV DMatch lists)."""
        matcher = self.matcher
        if matcher == "auto":
            many = max(len(descriptors_a), len(descriptors_b)) > EXACT_MATCH_LIMIT
            matcher = "flann" if many and self.norm == cv2.NORM_L2 else "bf"
        if matcher == "flann":
            cv2.setRNGSeed(0)  # the kd-trees are randomised from OpenCV's (per-thread) generator
            flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})  # 1: FLANN_INDEX_KDTREE
            return flann.knnMatch(descriptors_a, descriptors_b, k=2)
        return cv2.BFMatcher(self.norm).knnMatch(descriptors_a, descriptors_b, k=2)

    def _features(self, image: PreparedImage) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 2) keypoint pixels and descriptors of an image, the ``best_features`` strongest."""
        points, descriptors, responses = self._detect(image.grey_u8())
        if descriptors is None or not len(points):
            return np.zeros((0, 2)), None
        if self.best_features is not None and len(points) > self.best_features:
            # numpy's default sort: ties at the cut fall as when sorting OpenCV's keypoints by their responses
            # directly, so a frame keeps the same keypoints either way.
            strongest = np.argsort(-responses)[: self.best_features]
            points, descriptors = points[strongest], descriptors[strongest]
        return points, descriptors

    def _estimate(self, pair):
        keypoints_a, descriptors_a = self._features(pair.a)  # (N, 2) pixels each
        keypoints_b, descriptors_b = self._features(pair.b)
        if len(keypoints_a) < 4 or len(keypoints_b) < 4:
            raise EstimationFailed(
                f"too few keypoints ({len(keypoints_a)} in A, {len(keypoints_b)} in B); the images may lack texture"
            )
        points_a, points_b = ratio_test_points(self._match(descriptors_a, descriptors_b), keypoints_a, keypoints_b, self.ratio)
        if len(points_a) < max(4, self.min_inliers):
            raise EstimationFailed(f"only {len(points_a)} matches pass the ratio test (need {max(4, self.min_inliers)})")
        points_a, points_b = points_a.astype(np.float32), points_b.astype(np.float32)
        homography, inlier_mask = cv2.findHomography(points_a, points_b, cv2.RANSAC, self.ransac_px)
        inliers = int(inlier_mask.sum()) if inlier_mask is not None else 0
        if homography is None or inliers < self.min_inliers:
            raise EstimationFailed(f"RANSAC kept {inliers} of {len(points_a)} matches (need {self.min_inliers})")
        if self.lmeds_refit:
            keep = inlier_mask.ravel() > 0
            refit, _ = cv2.findHomography(points_a[keep], points_b[keep], cv2.LMEDS)
            if refit is not None and np.isfinite(refit).all():
                homography = refit
        # Confidence: the inlier share, discounted when the support is thin.
        confidence = (inliers / len(points_a)) * min(1.0, inliers / 30.0)
        details = {"keypoints_a": len(keypoints_a), "keypoints_b": len(keypoints_b), "matches": len(points_a), "inliers": inliers}
        return homography, confidence, details


@dataclass
class SiftRansac(FeatureRansacEstimator):
    """SIFT keypoints, L2 ratio-test matching, RANSAC.

    Attributes:
        contrast_threshold: SIFT's DoG contrast threshold. Half OpenCV's default (0.04) finds more
            keypoints in weak texture (aerial fields, sand); with the LMedS refit it gave 1.3 px instead
            of 1.6-4 px on graf1/graf3.
    """

    name: ClassVar[str] = "sift"
    contrast_threshold: float = 0.02

    def _detector(self):
        return cv2.SIFT_create(contrastThreshold=self.contrast_threshold)

    def _cache_settings(self) -> tuple:
        return (self.contrast_threshold,)


@dataclass
class OrbRansac(FeatureRansacEstimator):
    """ORB keypoints, Hamming ratio-test matching, RANSAC.

    Attributes:
        orb_features: how many keypoints ORB detects before ``best_features`` trims them.
    """

    name: ClassVar[str] = "orb"
    norm: ClassVar[int] = cv2.NORM_HAMMING
    orb_features: int = 1000

    def _detector(self):
        return cv2.ORB_create(nfeatures=self.orb_features)

    def _cache_settings(self) -> tuple:
        return (self.orb_features,)
