"""The one interface that every homography estimator, learned or classical, implements.

Mosaicking, benchmarking and the CLI depend only on :class:`Estimator` and :class:`Estimate`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.pair import ImageLike, PreparedPair
from udh_cli.estimators.thresholds import THRESHOLDS


@dataclass(frozen=True)
class Estimate:
    """The result of estimating one pair.

    Attributes:
        method: the estimator's registry name, e.g. ``"sift"``.
        homography: (3, 3) float64 ``b_from_a`` in pixels of the images as given, h33 = 1;
            ``None`` when the estimator failed.
        confidence: in [0, 1]; what it means is the estimator's own (inlier share, correlation...),
            but 0 always means "do not trust this".
        elapsed_ms: wall time of the estimation itself, without loading models.
        failure: why there is no homography; ``None`` on success.
        details: estimator-specific extras (keypoints, iterations, tile statistics...), JSON-serialisable.
        inliers: RANSAC inliers of a feature matcher's answer (None: not a matcher's answer).
        verification_score: the photometric alignment score the answer was judged by, in [0, 1] (None: not
            judged by the estimator).
        verified: True for a confirmed answer, False for the best found but unconfirmed, None when the
            estimator does not judge its answers (callers then judge by ``confidence``).
        verified_by: what confirmed it: "alignment" (the photometric score) or "matches" (RANSAC's support); on
            an unverified answer, what still supports it (a network's answer that failed only its judge's stricter
            checks), or None.
        stage: which stage or opinion produced the answer, e.g. "network", "sift", "escalated", "mirrored".
    """

    method: str
    homography: np.ndarray | None
    confidence: float
    elapsed_ms: float
    failure: str | None = None
    details: dict[str, Any] = field(default_factory=dict)
    inliers: int | None = None
    verification_score: float | None = None
    verified: bool | None = None
    verified_by: str | None = None
    stage: str | None = None

    @property
    def ok(self) -> bool:
        return self.homography is not None

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict with the stable keys other tools rely on."""
        return {
            "method": self.method,
            "ok": self.ok,
            "homography": None if self.homography is None else self.homography.tolist(),
            "confidence": float(self.confidence),
            "elapsed_ms": float(self.elapsed_ms),
            "failure": self.failure,
            "inliers": self.inliers,
            "verification_score": self.verification_score,
            "verified": self.verified,
            "verified_by": self.verified_by,
            "stage": self.stage,
            "details": self.details,
        }


TYPED_FIELDS = ("inliers", "verification_score", "verified", "verified_by", "stage")  # see Estimate


class Estimator:
    """Base class: estimates ``b_from_a`` between two images of any size, colour or grey, 8 or 16 bit.

    Every entry point takes images as numpy arrays or as :class:`~udh_cli.estimators.pair.PreparedImage`
    (made grey once, shared by every stage; see :mod:`udh_cli.estimators.pair`) and prepares each pair once.
    Subclasses set ``name`` and implement :meth:`_estimate`, which takes a
    :class:`~udh_cli.estimators.pair.PreparedPair` and either returns ``(b_from_a, confidence, details)`` or
    raises :class:`EstimationFailed`; the :data:`TYPED_FIELDS` it puts in ``details`` (a matcher's
    ``inliers``...) become the :class:`Estimate`'s typed fields. Batched (learned) estimators override
    :meth:`estimate_pairs` instead. This class times the call, checks the result (a non-finite, singular or
    folded homography is a failure, never an answer) and packs it into an :class:`Estimate`.

    ``verifies_itself`` says whether an answer was already checked against the images (RANSAC's inlier
    count, a photometric score); callers such as the mosaic add their own check only when it was not.
    """

    name: ClassVar[str] = "base"
    verifies_itself: ClassVar[bool] = False

    def estimate(self, image_a: ImageLike, image_b: ImageLike) -> Estimate:
        """Estimate the homography from ``image_a`` to ``image_b``. Never raises for a failed estimate."""
        return self.estimate_pairs([PreparedPair.of(image_a, image_b)])[0]

    def estimate_many(self, pairs: Sequence[tuple[ImageLike, ImageLike] | PreparedPair]) -> list[Estimate]:
        """Estimate many pairs, each given as ``(image_a, image_b)`` or prepared; learned estimators batch them."""
        return self.estimate_pairs([p if isinstance(p, PreparedPair) else PreparedPair.of(*p) for p in pairs])

    def estimate_pairs(self, pairs: Sequence[PreparedPair]) -> list[Estimate]:
        """Estimate prepared pairs; the one method batched estimators override."""
        return [self._estimate_one(pair) for pair in pairs]

    def _estimate_one(self, pair: PreparedPair) -> Estimate:
        """One prepared pair through :meth:`_estimate`, timed and checked."""
        start = time.perf_counter()
        try:
            homography, confidence, details = self._estimate(pair)
            failure = None
        except EstimationFailed as exc:
            homography, confidence, details, failure = None, 0.0, {}, str(exc)
        elapsed_ms = (time.perf_counter() - start) * 1e3
        typed = {key: details.pop(key) for key in TYPED_FIELDS if key in details}
        return self._checked(homography, confidence, elapsed_ms, failure, details, pair.a.shape, **typed)

    def _estimate(self, pair: PreparedPair) -> tuple[np.ndarray, float, dict]:
        raise NotImplementedError

    def near_prior(self) -> "Estimator":
        """This estimator for a pair whose B is already pre-warped into A's frame by a prediction (a mosaic's
        loop pair, placed by the chain): without the searches that ask what the prediction settled (a shift
        search up to half the frame, a global match's other turns and larger second look); an answer far from
        the prediction is rejected anyway. Estimators without such searches return themselves."""
        return self

    def settings(self) -> dict[str, Any]:
        """The options this estimator runs with, JSON-ready: its dataclass fields shown in its repr (nested
        settings such as a refiner's as dicts). With :attr:`name` and :meth:`model_files` it says what makes
        its answers what they are (the mosaic's pair cache and sidecar record it)."""
        if not dataclasses.is_dataclass(self):
            return {}
        return {f.name: json_ready(getattr(self, f.name, None)) for f in dataclasses.fields(self) if f.repr}

    def model_files(self) -> list[str]:
        """The model files its answers depend on (none for the classical methods)."""
        return []

    def model_notes(self) -> list[str]:
        """One line per thing its model files do not record (a licence, training headings), for the user to read;
        none for the classical methods."""
        return []

    def _checked(self, homography, confidence, elapsed_ms, failure, details, shape_a, **typed: Any) -> Estimate:
        """Pack an answer into an :class:`Estimate`; ``shape_a`` is A's (height, width, ...)."""
        if homography is not None:
            homography = np.asarray(homography, dtype=np.float64)
            if np.isfinite(homography).all() and abs(homography[2, 2]) > 1e-12:
                homography = homography / homography[2, 2]
            if not geometry.is_valid_homography(homography, shape_a[1], shape_a[0]):
                homography, failure = None, "the estimate is degenerate (non-finite, singular or folded)"
        if homography is None:
            confidence = 0.0
            if typed.get("verified"):
                typed["verified"] = False
                typed.pop("verified_by", None)  # nothing verified a failure
        return Estimate(self.name, homography, float(np.clip(confidence, 0.0, 1.0)), elapsed_ms, failure, details, **typed)


def json_ready(value: Any) -> Any:
    """``value`` as JSON types: arrays and tuples as lists, dataclasses as dicts, anything else by its repr."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: json_ready(getattr(value, f.name, None)) for f in dataclasses.fields(value) if f.repr}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def require_ok(estimate: Estimate) -> Estimate:
    """Return ``estimate`` if it succeeded, else raise :class:`UdhError` with its reason."""
    if not estimate.ok:
        raise UdhError(f"{estimate.method} found no homography: {estimate.failure}")
    return estimate


# Below this confidence an answer that carries no verification of its own counts as unverified.
MIN_CONFIDENCE = THRESHOLDS.min_confidence


def is_verified(estimate: Estimate) -> bool:
    """Whether an answer is confirmed: the estimator's own verdict where it gives one (``auto``), else a
    confidence of at least :data:`MIN_CONFIDENCE`."""
    if estimate.verified is not None:
        return estimate.verified
    return estimate.confidence >= MIN_CONFIDENCE
