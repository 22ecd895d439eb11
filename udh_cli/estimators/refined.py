"""Beyond the paper: a network's estimate, refined photometrically and verified, with second opinions.

Both methods here are a :class:`Cascade` of estimator instances (a start, an ECC refiner, second opinions and
a :class:`Policy` that chooses between them), composed by the ``build()`` of their registered option records,
:class:`UnsupervisedEccOptions` and :class:`AutoOptions`:

* ``unsupervised+ecc``: the unsupervised network (several rounds), then coarse-to-fine ECC
  (:class:`udh_cli.estimators.refine.PyramidEcc`), scored by how well the aligned images agree: the lower of their
  intensity and gradient NCC over tiles (:data:`~udh_cli.estimators.verify.VERIFIER`).
* ``auto``: the same, and while the answer is doubted (a score below ``min_score``, or ECC diverged from it)
  it asks for second opinions, each refined the same way: ``fallback`` (SIFT), then the network's full
  cascade, then the cascade on mirrored, flipped and swapped copies of the pair (``views``). It keeps
  whichever answer verifies best, with two exceptions for the fallback's RANSAC matches: an answer at least
  ``trusted_inliers`` of them agree on is kept at once, and when no answer verifies photometrically the one
  the matches support is kept. An answer that aligns nothing at all (score 0, not matched) is a failure.
  An answer the matches verify stays verified only when the one judge agrees
  (:func:`~udh_cli.estimators.judge.judge_matched`: it aligns at all, and the network's tile levels accept it);
  otherwise it is returned supported: unverified, ``verified_by`` "matches".
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple, Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.base import Estimate, Estimator, json_ready
from udh_cli.estimators.judge import judge_matched
from udh_cli.models_catalog import has_refinement_stage
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.registry import create_estimator
from udh_cli.estimators.views import VIEWS, ViewEstimator
from udh_cli.estimators.refine import PyramidEcc
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.estimators.verify import VERIFIER

CLEAR_DROP = 0.05  # a refinement that lowers the score by more than this is discarded
# See fallback_options. At this contrast 800-px drone frames have 5,000-12,000 SIFT keypoints: flann matches them
# 4-6x faster than bf (seneca's auto mosaic spent 1.9 s a pair in bf matching), and best_features bounds the
# count on large photos.
FALLBACK_OPTIONS: dict[str, dict[str, Any]] = {"sift": {"contrast_threshold": 0.002, "best_features": 10000, "matcher": "flann"}}
# How far (pixels of A) ECC may move a corner of an answer that matches verify. A fixed distance, not a share of
# the image: on river1/river2 (1024x768, 1,460 SIFT inliers, a moving river) ECC pulled corners 9.8 px away.
NEAR_PX = 2.0


LEARNED_STARTS = ("unsupervised", "supervised")  # the networks a cascade can start from


@dataclass(frozen=True)
class Policy:
    """How a :class:`Cascade` judges answers and chooses between them.

    Attributes:
        min_score: an answer scoring below this is doubted: the lower of the intensity and gradient NCC at
            256 px (:data:`~udh_cli.estimators.verify.VERIFIER`; ``THRESHOLDS.min_cascade_score``).
        trusted_inliers: an opinion with at least this many RANSAC inliers (SIFT's, ORB's) is verified by its
            matches: kept whatever its photometric score, with its matcher's confidence if that is higher, and
            no further opinion is asked; ECC may polish it by up to :data:`NEAR_PX` at each corner. With fewer
            inliers the opinions go on, and the matched answer is kept only if none verifies photometrically.
            Why: occluders, surf and moving water lower the photometric score of right answers, never the
            agreement of that many matches (``THRESHOLDS.trusted_inliers``).
    """

    min_score: float = THRESHOLDS.min_cascade_score
    trusted_inliers: int = THRESHOLDS.trusted_inliers

    def __post_init__(self) -> None:
        if not 0.0 < self.min_score <= 1.0:
            raise UdhError(f"min_score ({self.min_score}) must be in (0, 1]")
        if self.trusted_inliers < 4:
            raise UdhError(f"trusted_inliers ({self.trusted_inliers}) must be at least 4, the matches a homography needs")

    def doubted(self, score: float, details: dict) -> bool:
        """An answer needs a second opinion when it scores low, or when its refinement failed (ECC diverged,
        did not converge, or left a degenerate homography): a start outside ECC's basin is rarely right, yet a
        wrong network answer on a smooth pair can still score above ``min_score`` (held-out rho 32: one such
        pair at 11.5 px scored 0.73; SIFT's answer scored 0.94). ``details`` at the top level describe the
        first answer; the second opinions are under their own keys."""
        return score < self.min_score or "refine_failure" in details


class Matched(NamedTuple):
    """An opinion's answer that RANSAC's matches support: ``b_from_a`` (3, 3), pixels of the pair; its confidence
    (the higher of its photometric score and its matcher's confidence); the stage it came from; its photometric
    score alone, in [0, 1]."""

    b_from_a: np.ndarray
    confidence: float
    stage: str
    alignment: float


@dataclass(frozen=True)
class Opinion:
    """A second opinion of a :class:`Cascade`, asked while the answer held is doubted.

    Attributes:
        key: where its findings go in the estimate's details ("fallback", "escalated", "mirrored"...).
        estimator: who gives it.
        stage: what the estimate's ``stage`` says when it wins (the fallback's method name, "escalated"...).
    """

    key: str
    estimator: Estimator
    stage: str


@dataclass
class Cascade(Estimator):
    """A start, refined photometrically and verified; while the answer is doubted, second opinions in order,
    each refined and verified the same way, and the answer the :class:`Policy` prefers is kept.

    Attributes:
        name: the registry name it is built for ("auto", "unsupervised+ecc").
        start: the first estimator (a network).
        refiner: the ECC pyramid and its iteration budget.
        opinions: the second opinions, cheapest first.
        policy: how answers are judged and chosen.
        tiles_from: the network whose tile stage is evidence on an answer the matches verify (None: none).

    Its confidence is the NCC score of the aligned images (or, for an answer matches verify, the higher of that
    and the matcher's confidence).
    """

    verifies_itself: ClassVar[bool] = True
    name: str = "cascade"  # a default only because Estimator.name is one; build() always names it
    start: Estimator | None = None
    refiner: PyramidEcc = field(default_factory=PyramidEcc)
    opinions: tuple[Opinion, ...] = ()
    policy: Policy = field(default_factory=Policy)
    tiles_from: Estimator | None = None

    def __post_init__(self) -> None:
        if self.start is None:
            raise ValueError("Cascade: give the estimator that starts it (start=...)")

    def settings(self) -> dict[str, Any]:
        def described(estimator: Estimator) -> dict[str, Any]:
            return {"method": estimator.name, **estimator.settings()}

        return {"start": described(self.start), "refiner": json_ready(self.refiner), "policy": json_ready(self.policy),
                "opinions": [{"key": o.key, **described(o.estimator)} for o in self.opinions]}

    def model_files(self) -> list[str]:
        inner = [self.start, *(opinion.estimator for opinion in self.opinions)]
        return sorted({path for estimator in inner for path in estimator.model_files()})

    def model_notes(self) -> list[str]:
        inner = [self.start, *(opinion.estimator for opinion in self.opinions)]
        return list(dict.fromkeys(line for estimator in inner for line in estimator.model_notes()))

    def near_prior(self) -> "Cascade":
        """The same cascade with its start and every opinion :meth:`~Estimator.near_prior`."""
        opinions = tuple(Opinion(o.key, o.estimator.near_prior(), o.stage) for o in self.opinions)
        return dataclasses.replace(self, start=self.start.near_prior(), opinions=opinions)

    def estimate_pairs(self, pairs: Sequence[PreparedPair]) -> list[Estimate]:
        if not pairs:
            return []
        started = time.perf_counter()
        first = self.start.estimate_pairs(pairs)
        first_ms = (time.perf_counter() - started) * 1e3 / len(pairs)
        return [self._finish(pair, start, first_ms) for pair, start in zip(pairs, first)]

    def _refine_and_score(self, pair: PreparedPair, start: Estimate) -> tuple[np.ndarray | None, float, dict]:
        """Refine ``start`` photometrically and keep whichever of the two verifies better."""
        if not start.ok:
            return None, 0.0, {"start_failure": start.failure}
        start_score = VERIFIER.score(pair.a, pair.b, start.homography)
        details = {"start_method": start.method, "start_score": start_score}
        try:
            refined, correlation = self.refiner.refine(pair.a, pair.b, start.homography)
            if not geometry.is_valid_homography(refined, *pair.a.size):
                raise EstimationFailed("refinement left a degenerate homography")
            details["ecc_correlation"] = correlation
        except EstimationFailed as exc:
            details["refine_failure"] = str(exc)
            return start.homography, start_score, details
        refined_score = VERIFIER.score(pair.a, pair.b, refined)
        # The score (NCC at 256 px) cannot rank sub-pixel differences: preferring the start whenever it
        # scored higher undid good refinements (sim flight 0.24 -> 0.50 px). Only a clear drop means ECC
        # wandered off.
        if refined_score < start_score - CLEAR_DROP:
            details["refinement_kept"] = False
            return start.homography, start_score, details
        return refined, refined_score, details

    @staticmethod
    def _near(refined: np.ndarray | None, start: np.ndarray, shape_a: tuple[int, ...]) -> bool:
        """Whether ``refined`` moved no corner of A by more than :data:`NEAR_PX` from ``start``."""
        if refined is None:
            return False
        height, width = shape_a[:2]
        return float(geometry.corner_errors(refined, start, width, height).max()) <= NEAR_PX

    def _finish(self, pair: PreparedPair, start: Estimate, first_ms: float) -> Estimate:
        started = time.perf_counter()
        policy = self.policy
        homography, score, details = self._refine_and_score(pair, start)
        details["score"] = score
        doubted = policy.doubted(score, details)
        # Second opinions, cheapest first, each only while the answer held is still doubted: SIFT settles most
        # doubtful clean pairs, so the longer cascade runs where it fails too (and on occluded pairs, whose
        # right answers also score low). Cascade first was as accurate at rho 45 but worse at rho 32.
        supported: Matched | None = None  # a feature method's answer, with its matches' support but not trusted outright
        for opinion in self.opinions:
            if not doubted:
                break
            found = opinion.estimator.estimate_pairs([pair])[0]
            other, other_score, other_details = self._refine_and_score(pair, found)
            matched = found.ok and found.inliers is not None
            if matched and not self._near(other, found.homography, pair.a.shape):
                # Matches agreeing on one answer say more than a photometric score that occluders, surf or a
                # wrong shift of a smooth scene can fool: ECC's polish stands only if it stays by them.
                other, other_score = found.homography, other_details.get("start_score", 0.0)
                other_details["refinement_kept"] = False
            details[opinion.key] = {"method": opinion.estimator.name, "score": other_score, **other_details}
            if matched:
                supported = Matched(other, max(other_score, found.confidence), opinion.stage, other_score)
                if found.inliers >= policy.trusted_inliers:
                    homography, score, doubted = supported.b_from_a, supported.confidence, False
                    details["used"], details["verified_by"] = opinion.stage, "matches"
                    break
            if other_score > score:
                homography, score = other, other_score
                details["used"] = opinion.stage
                doubted = policy.doubted(other_score, other_details)
        if doubted and supported is not None:
            # Nothing verified photometrically: a low score does not tell right from wrong (held-out occluded
            # pairs: right SIFT answers with 9-19 inliers scored 0.00-0.25, wrong mirrored views up to 0.36),
            # RANSAC's support does.
            homography, score = supported.b_from_a, supported.confidence
            details["used"], details["verified_by"] = supported.stage, "matches"
        failure = None if homography is not None else (start.failure or "no estimate")
        if homography is not None and score <= 0.0 and "verified_by" not in details:
            # No evidence at all: a score of 0 means constant tiles, too little overlap or anti-correlation.
            homography, failure = None, "no answer aligns the images (they may lack texture or not overlap)"
        # False: the best answer found, unconfirmed (a low score or a diverged ECC, and no matches agree on it).
        verified = homography is not None and (not doubted or "verified_by" in details)
        verified_by = details.pop("verified_by", "alignment" if verified else None)
        if verified and verified_by == "matches":
            measured, verdict = judge_matched(self.tiles_from, pair, homography, supported.alignment, score)
            verified = verdict.verified
            details.update(measured, verdict_failed=list(verdict.failed))
        stage = details.pop("used", "network")
        elapsed = first_ms + (time.perf_counter() - started) * 1e3
        return self._checked(homography, score, elapsed, failure, details, pair.a.shape, verified=verified,
                             verification_score=score, verified_by=verified_by, stage=stage)


# The start network's options where a cascade's differ from the network's own (refine_rounds: see build): one round
# of each network and no tile stage are enough ahead of ECC, which refines to full resolution (docs/estimators.md, "Why the settings").
NETWORK_DEFAULTS: dict[str, Any] = {"iterations": 1, "search": 0, "tiles": False}


@dataclass
class UnsupervisedEccOptions:
    """The options of ``unsupervised+ecc``; :meth:`build` composes its :class:`Cascade`.

    Attributes:
        initial: the network that starts it: "unsupervised" or "supervised" (:data:`LEARNED_STARTS`).
        network: that network's options (the fields of :class:`~udh_cli.estimators.deep.DeepEstimator`, e.g.
            ``{"search": 2}``, ``-O network.search=2``), over :data:`NETWORK_DEFAULTS` and the network's own
            defaults. ``refine_rounds`` unset: one round when the network has a refinement stage. ``judged`` is
            the cascade's: it judges after ECC (:class:`Policy`).
        refiner: the ECC pyramid and its iteration budget.
        escalate: when the answer is still doubted after the fallback, rerun the network with its own default
            (longer) cascade, sharing its loaded networks: it rescues large-motion pairs at the cost of the few
            doubted ones.
        fallback: registry name of the first second opinion (None: none).
        fallback_options: the fallback's options; None: :data:`FALLBACK_OPTIONS` for its name. As the fallback,
            SIFT keeps keypoints of a tenth of its own default contrast, so that the faint texture of dark or
            smooth patches survives next to bright occluders.
        views: the last opinions: the network (its longer cascade when it escalates) on these copies of the
            pair (:data:`~udh_cli.estimators.views.VIEWS`).
        min_score, trusted_inliers: the :class:`Policy`.

    The measurements behind these settings are in ``docs/estimators.md`` ("Why the settings").
    """

    name: ClassVar[str] = "unsupervised+ecc"
    initial: str = "unsupervised"
    network: dict[str, Any] = field(default_factory=dict, metadata={"options_of": "unsupervised", "set_here": ("judged",)})
    refiner: PyramidEcc = field(default_factory=PyramidEcc)
    escalate: bool = False
    fallback: str | None = None
    fallback_options: dict[str, Any] | None = None
    views: tuple[str, ...] = ()
    min_score: float = Policy.min_score
    trusted_inliers: int = Policy.trusted_inliers

    def build(self) -> Cascade:
        """The :class:`Cascade` these options describe (networks and fallback loaded once here)."""
        if self.initial not in LEARNED_STARTS:
            raise UdhError(f"method '{self.name}': initial '{self.initial}' must be a network: {', '.join(LEARNED_STARTS)}")
        if not isinstance(self.network, dict) or "judged" in self.network:
            raise UdhError(f"method '{self.name}': network takes the network's options (but judged, the cascade's) as a JSON object, "
                           f"e.g. -O 'network={{\"search\": 2}}' or -O network.search=2, not {self.network!r}")
        if self.fallback_options is not None and not isinstance(self.fallback_options, dict):
            raise UdhError(f"method '{self.name}': fallback_options takes the fallback's options as a JSON object, "
                           f"e.g. -O 'fallback_options={{\"ratio\": 0.8}}', not {self.fallback_options!r}")
        if not isinstance(self.refiner, PyramidEcc):
            raise UdhError(f"method '{self.name}': refiner takes a PyramidEcc (udh_cli.estimators.refine), not {self.refiner!r}; "
                           "its settings are not command-line options")
        if isinstance(self.views, str) or not all(isinstance(view, str) for view in self.views):
            raise UdhError(f"method '{self.name}': views takes a list of names ({', '.join(VIEWS)}), not {self.views!r}")
        try:
            policy = Policy(self.min_score, self.trusted_inliers)
        except UdhError as exc:
            raise UdhError(f"method '{self.name}': {exc}") from None
        # A model given alone runs alone, as with the network's own method, and so does a network with no
        # shipped refinement stage (supervised): refine_rounds then stays the network's own default (0).
        chosen = {**NETWORK_DEFAULTS, **self.network}
        if chosen.get("refine_rounds") is None and has_refinement_stage(self.initial, chosen.get("model"), chosen.get("refine_model")):
            chosen["refine_rounds"] = 1
        try:
            network = create_estimator(self.initial, **chosen, judged=False)  # the cascade judges after ECC (Policy)
        except UdhError as exc:
            raise UdhError(f"method '{self.name}', its network: {exc}") from None
        opinions = []
        if self.fallback:
            options = FALLBACK_OPTIONS.get(self.fallback, {}) if self.fallback_options is None else self.fallback_options
            fallback = create_estimator(self.fallback, **options)
            opinions.append(Opinion("fallback", fallback, fallback.name))
        longer = network.with_default_rounds() if self.escalate else None
        if longer is not None and len(longer.rounds()) <= len(network.rounds()):
            longer = None  # the first run is already as long: rerunning it would only repeat its answer
        if longer is not None:
            opinions.append(Opinion("escalated", longer, "escalated"))
        opinions += [Opinion(view, ViewEstimator(longer or network, view), view) for view in self.views]
        return Cascade(self.name, network, self.refiner, tuple(opinions), policy, tiles_from=network)


@dataclass
class AutoOptions(UnsupervisedEccOptions):
    """The options of ``auto``, the verified combination: network + ECC; while the answer is doubted, SIFT
    (+ ECC), the full cascade, then the cascade on mirrored, flipped and swapped views; SIFT's RANSAC matches
    verify its answers (module docstring)."""

    name: ClassVar[str] = "auto"
    fallback: str | None = "sift"
    escalate: bool = True
    views: tuple[str, ...] = VIEWS
