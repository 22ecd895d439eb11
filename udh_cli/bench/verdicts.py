"""Scoring udh's own verdicts: which answers it called verified, which of those are wrong, and how well its
confidence predicts being right (the reliability diagram's bins).

A pair is **right** when there is an answer within ``FAIL_PX`` (10 px) of the truth, and a **failure**
otherwise (:func:`udh_cli.bench.metrics.failures`). An answer is **verified** by the rule ``udh estimate``
reports (:func:`udh_cli.estimators.base.is_verified`): the method's own verdict where it gives one
(``Estimate.verified``), else a confidence of at least its floor (``MIN_CONFIDENCE``). **Verified but wrong**
is a verified answer that is a failure: the answers a map would be built on, and should not be.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from udh_cli.bench import metrics
from udh_cli.bench.runner import MethodRun
from udh_cli.estimators.base import MIN_CONFIDENCE as VERIFIED_CONFIDENCE

RELIABILITY_BINS = 10  # equal confidence bins over [0, 1]; 1.0 falls in the last
ALL_KINDS = "all kinds"


def verified(run: MethodRun) -> np.ndarray:
    """(N,) bool: answers udh reports as verified, :func:`~udh_cli.estimators.base.is_verified` over the run's arrays."""
    judged = np.asarray(run.verdicts)
    by_confidence = (judged == -1) & (np.asarray(run.confidence) >= VERIFIED_CONFIDENCE)
    return np.asarray(run.answered, bool) & ((judged == 1) | by_confidence)


def right(run: MethodRun, fail_px: float = metrics.FAIL_PX) -> np.ndarray:
    """(N,) bool: an answer within ``fail_px`` of the truth."""
    return ~metrics.failures(run.mace, run.answered, fail_px)


@dataclass(frozen=True)
class KindScore:
    """One method on one kind of motion (or :data:`ALL_KINDS`). Counts of pairs; the median error in px."""

    kind: str
    method: str
    pairs: int
    failures: int
    verified: int
    verified_wrong: int
    median_px: float

    @property
    def failure_rate(self) -> float:
        return self.failures / self.pairs

    @property
    def verified_wrong_rate(self) -> float:
        """Share of all pairs that are verified but wrong (what a map built on verified answers risks)."""
        return self.verified_wrong / self.pairs

    @property
    def wrong_among_verified(self) -> float:
        """Share of the verified answers that are wrong (the target: under 3 %); NaN without any."""
        return self.verified_wrong / self.verified if self.verified else float("nan")

    def to_dict(self) -> dict:
        return {**asdict(self), "failure_rate": self.failure_rate, "verified_wrong_rate": self.verified_wrong_rate,
                "wrong_among_verified": self.wrong_among_verified}


def score(kind: str, method: str, mace: np.ndarray, is_right: np.ndarray, is_verified: np.ndarray) -> KindScore:
    """A :class:`KindScore` from per-pair arrays of equal length N (errors in px, two bool masks)."""
    return KindScore(kind, method, len(mace), int((~is_right).sum()), int(is_verified.sum()),
                     int((is_verified & ~is_right).sum()), float(np.median(mace)))


def kind_scores(runs: list[MethodRun]) -> list[KindScore]:
    """One score per run (a kind of motion, a method), then one per method over all kinds pooled."""
    scores = [score(r.set_name, r.method, r.mace, right(r), verified(r)) for r in runs]
    for method in dict.fromkeys(r.method for r in runs):
        mine = [r for r in runs if r.method == method]
        scores.append(score(ALL_KINDS, method, np.concatenate([r.mace for r in mine]),
                            np.concatenate([right(r) for r in mine]), np.concatenate([verified(r) for r in mine])))
    return scores


@dataclass(frozen=True)
class Reliability:
    """Confidence against the fraction right, for one method: ``bins`` equal bins over [0, 1].

    Attributes:
        counts: (bins,) pairs per bin.
        fraction_right: (bins,) share of a bin's pairs that are right; NaN for an empty bin.
        mean_confidence: (bins,) mean confidence of a bin's pairs; NaN for an empty bin.
    """

    method: str
    counts: np.ndarray
    fraction_right: np.ndarray
    mean_confidence: np.ndarray

    @property
    def edges(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, len(self.counts) + 1)

    def to_dict(self) -> dict:
        clean = [None if not np.isfinite(v) else float(v) for v in self.fraction_right]
        return {"method": self.method, "edges": self.edges.tolist(), "counts": self.counts.tolist(),
                "fraction_right": clean,
                "mean_confidence": [None if not np.isfinite(v) else float(v) for v in self.mean_confidence]}


def reliability(method: str, confidence: np.ndarray, is_right: np.ndarray, bins: int = RELIABILITY_BINS) -> Reliability:
    """Bin ``confidence`` (N,) in [0, 1] into ``bins`` equal bins and count the right answers of each."""
    confidence = np.clip(np.asarray(confidence, np.float64), 0.0, 1.0)
    index = np.minimum((confidence * bins).astype(int), bins - 1)
    counts = np.bincount(index, minlength=bins)
    hits = np.bincount(index, weights=np.asarray(is_right, np.float64), minlength=bins)
    sums = np.bincount(index, weights=confidence, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return Reliability(method, counts, np.where(counts > 0, hits / counts, np.nan), np.where(counts > 0, sums / counts, np.nan))


def reliabilities(runs: list[MethodRun]) -> list[Reliability]:
    """One :class:`Reliability` per method, over every kind of motion pooled."""
    curves = []
    for method in dict.fromkeys(r.method for r in runs):
        mine = [r for r in runs if r.method == method]
        curves.append(reliability(method, np.concatenate([r.confidence for r in mine]), np.concatenate([right(r) for r in mine])))
    return curves
