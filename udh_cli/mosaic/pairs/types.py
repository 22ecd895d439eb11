"""What the mosaic's pair stage works with: a request, its result, the acceptance test, and the working images.

Its own module so that the pair stage (:mod:`.estimate`), the pair cache (:mod:`.cache`), the solve and
the reports all depend on these types, and none of them on another.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import Estimate
from udh_cli.estimators.pair import ImageLike
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.estimators.verify import VERIFIER
from udh_cli.mosaic.inputs.frames import Frame


# The revision of what makes a pair accepted: these rules, and what an estimator calls confirmed (the tile
# stage's CONFIRMING_LEVELS). A pair cache records it, so that --resume never reuses decisions made under other
# rules. 2: answers their method marks unconfirmed are doubted, and two tile levels confirm. 3: loop pairs are
# first confirmed from the chain's prediction (confirm.py's settings). 4: answers RANSAC's matches verify stay verified
# only where the judge's tile levels agree (judge_matched).
ACCEPTANCE_REVISION = 4


@dataclass(frozen=True)
class Acceptance:
    """When a pair estimate is accepted; below either threshold it is doubted (fallback, bridge, split).

    Attributes:
        min_confidence: the estimator's own confidence (its meaning differs between methods). One floor for
            all, low on purpose: it only drops what an estimator itself calls hopeless; the alignment check below
            and RANSAC's inliers tell right from wrong, not the confidence (docs/mosaic.md, "Stages").
        min_verified: a photometric check for the methods that do not verify their answers themselves
            (the networks, ECC; not SIFT/ORB, whose answers are RANSAC-verified, nor auto): the lower of the
            intensity and gradient NCC of the aligned working images (:data:`udh_cli.estimators.verify.VERIFIER`).
            Not for every method: right SIFT pairs over surf and sand score under it. 0 turns the check off (not
            the rule below).

    An answer its own method marks unconfirmed with nothing supporting it (``Estimate.verified`` False and no
    ``verified_by``: a network's tile levels did not confirm it) is doubted whatever these say, unless the method
    verifies itself (``auto`` keeps its best unconfirmed answer and says so). An answer the network's judge left
    unverified but supported (``verified_by`` set: it failed only the judge's stricter checks) is judged here like a
    verified one: the joint solve cross-checks every pair. An answer its matches verify or support (``verified_by``
    "matches": a network's global match that hundreds of cells support) skips the photometric check, as SIFT's
    RANSAC-verified ones do. Why: without it most of a network-only mosaic's accepted pairs on a low-texture
    flight were over 20 px off (docs/benchmarks.md, "2026-11-25, later: confirmed network answers").
    """

    min_confidence: float = THRESHOLDS.min_confidence
    min_verified: float = THRESHOLDS.min_alignment_supported

    def judge(self, estimate: Estimate, image_a: ImageLike, image_b: ImageLike,
              verified_by_method: bool = False) -> tuple[float | None, str | None]:
        """``(verification score or None when not computed, reason for doubt or None when accepted)``."""
        if not estimate.ok:
            return None, estimate.failure
        if estimate.confidence < self.min_confidence:
            return None, f"confidence {estimate.confidence:.2f} < {self.min_confidence}"
        if verified_by_method or estimate.verified_by == "matches":
            return None, None  # RANSAC's support verified or supports it (SIFT, ORB, a network's global match)
        if estimate.verified is False and estimate.verified_by is None:  # nothing supports it (the networks' tile stage)
            return None, f"{estimate.method}: its answer is unconfirmed (for a network: its tile levels did not agree on it)"
        if self.min_verified <= 0:
            return None, None
        verified = VERIFIER.score(image_a, image_b, estimate.homography)
        if verified < self.min_verified:
            return verified, f"alignment check {verified:.2f} < {self.min_verified} (intensity/gradient NCC)"
        return verified, None


@dataclass
class PairRequest:
    """A pair to estimate: ``b_from_a`` between frames ``a`` and ``b``.

    ``prior`` is a full-resolution ``b_from_a`` predicted by chaining (overlap pairs): B is then warped
    into A's frame first and only the residual is estimated, so that methods with a small capture range
    (the learned ones) can close loops between frames far apart in the sequence. With ``from_prediction`` the
    prior is first confirmed and refined cheaply (:mod:`.confirm`), and the opinions run only if that fails.
    """

    a: int
    b: int
    kind: str
    prior: np.ndarray | None = None
    from_prediction: bool = False


@dataclass(frozen=True)
class PairVerdict:
    """What the global solve found of one pair: its consistency (rms px before and after the solve, and whether it
    closes a loop) and, for a pair the others contradict, why it is rejected."""

    consistency_px: dict[str, Any]
    rejected_because: str | None = None


@dataclass
class PairResult:
    """The outcome of one pair.

    Attributes:
        a, b, kind: as requested.
        estimates: every attempt, first method then fallback; homographies in working-size pixels
            (of the pre-warped B when ``prior`` was used).
        b_from_a: the accepted homography, full-resolution pixels; ``None`` when the pair failed.
        status: ``"ok"``, ``"failed"`` (no method gave a confident estimate) or ``"rejected"`` (an
            estimate disagreed with the chained prediction, or with the global solve).
        reason: why it is not ``"ok"``.
        method: the method whose estimate was accepted.
        prior: the chained prediction that was used, full resolution.
        consistency_px: filled by the solve: {"before": rms px, "after": rms px}.
        verified: the accepted (or last doubted) estimate's alignment check, see :class:`Acceptance`.
    """

    a: int
    b: int
    kind: str
    estimates: list[Estimate] = field(default_factory=list)
    b_from_a: np.ndarray | None = None
    status: str = "failed"
    reason: str | None = None
    method: str | None = None
    prior: np.ndarray | None = None
    consistency_px: dict[str, float | None] = field(default_factory=dict)
    verified: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def judged(self, verdict: PairVerdict) -> PairResult:
        """A copy with the global solve's ``verdict``: its consistency figures, and rejected where it says why."""
        if verdict.rejected_because is None:
            return replace(self, consistency_px=verdict.consistency_px)
        return replace(self, consistency_px=verdict.consistency_px, status="rejected", b_from_a=None, reason=verdict.rejected_because)

    @property
    def confidence(self) -> float:
        return max((e.confidence for e in self.estimates if e.ok), default=0.0)

    def to_json(self) -> dict[str, Any]:
        return {
            "a": self.a,
            "b": self.b,
            "kind": self.kind,
            "status": self.status,
            "reason": self.reason,
            "method": self.method,
            "confidence": self.confidence,
            "verified": self.verified,
            "b_from_a": None if self.b_from_a is None else self.b_from_a.tolist(),
            "prewarped": self.prior is not None,
            "consistency_px": self.consistency_px,
            "estimates": [e.to_json() for e in self.estimates],
        }


def work_inputs(request: PairRequest, frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The two working images for a request, and how to undo what was done to them.

    Returns ``(image_a, image_b, (after, before))``: an estimate ``H`` between the returned images becomes
    the working-size ``b_from_a = after @ H @ before``. With a ``prior``, B is warped into A's frame and
    both are cropped to the window where the warped B has real pixels: the empty border of a pre-warped
    image would otherwise mislead photometric methods (ECC, NCC verification) and the networks.
    """
    fa, fb = frames[request.a], frames[request.b]
    identity = np.eye(3)
    if request.prior is None:
        return fa.work, fb.work, (identity, identity)
    prior_work = geometry.rescale_homography(request.prior, fa.size, fa.work_size, fb.size, fb.work_size)
    # B rendered in A's frame: pixel x of the warped image shows B at prior_work(x).
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped_b = cv2.warpPerspective(fb.work, prior_work, fa.work_size, flags=flags)
    covered = cv2.warpPerspective(np.ones_like(fb.work), prior_work, fa.work_size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    window = covered_window(covered > 0)
    if window is None:
        return fa.work, warped_b, (prior_work, identity)
    x0, y0, x1, y1 = window
    after = prior_work @ geometry.translation(x0, y0)
    return fa.work[y0:y1, x0:x1], warped_b[y0:y1, x0:x1], (after, geometry.translation(-x0, -y0))


MIN_WINDOW = 48  # px; a smaller overlap window is not worth estimating on its own


def covered_window(covered: np.ndarray, max_uncovered: float = 0.02) -> tuple[int, int, int, int] | None:
    """An axis-aligned window ``(x0, y0, x1, y1)`` of ``covered`` (H, W) bool with at most ``max_uncovered``
    of its pixels uncovered: the bounding box, shrunk from its emptiest side until it is nearly full.

    Every share is read from one integral image (exact counts, so the same window as averaging the pixels):
    the shrinking takes up to a few hundred steps, each of which averaged the whole window."""
    mask = np.ascontiguousarray(covered).view(np.uint8)
    x0, y0, width, height = cv2.boundingRect(mask)
    if width == 0 or height == 0:
        return None
    sums = cv2.integral(mask, sdepth=cv2.CV_64F)

    def share(x0: int, y0: int, x1: int, y1: int) -> float:
        count = sums[y1, x1] - sums[y0, x1] - sums[y1, x0] + sums[y0, x0]
        return float(count) / ((x1 - x0) * (y1 - y0))

    x1, y1 = x0 + width, y0 + height
    while x1 - x0 >= MIN_WINDOW and y1 - y0 >= MIN_WINDOW:
        if 1.0 - share(x0, y0, x1, y1) <= max_uncovered:
            return x0, y0, x1, y1
        step_x, step_y = max(1, (x1 - x0) // 50), max(1, (y1 - y0) // 50)
        empty = {"top": 1 - share(x0, y0, x1, y0 + 1), "bottom": 1 - share(x0, y1 - 1, x1, y1),
                 "left": 1 - share(x0, y0, x0 + 1, y1), "right": 1 - share(x1 - 1, y0, x1, y1)}
        side = max(empty, key=empty.get)
        if side == "top":
            y0 += step_y
        elif side == "bottom":
            y1 -= step_y
        elif side == "left":
            x0 += step_x
        else:
            x1 -= step_x
    return None


def full_resolution(estimate: Estimate, request: PairRequest, frames: Sequence[Frame], undo: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The estimate as a full-resolution ``b_from_a`` (undoing the pre-warp, the crop and the working scale)."""
    fa, fb = frames[request.a], frames[request.b]
    after, before = undo
    work_b_from_a = after @ estimate.homography @ before
    return geometry.rescale_homography(work_b_from_a, fa.work_size, fa.size, fb.work_size, fb.size)
