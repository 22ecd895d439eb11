"""The learned method as a composition of stages over immutable answers, as ``auto`` is a composition of estimators.

A batch of pairs goes through the cascade of networks and the tile stage (:func:`first_answers`); each pair's
:class:`Answer` is then doubted or not (:func:`still_doubted`), and the rescue stages, cheapest first
(:data:`RESCUES`: the heading search, the global match, the large-motion search), each take the doubted pairs'
answers and return offers; one rule, :func:`settle`, keeps an offer or the answer it would replace. The verdict
is :mod:`~udh_cli.estimators.judge`'s. ``estimator`` is always a :class:`~udh_cli.estimators.deep.DeepEstimator`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable, NamedTuple, Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.estimators.base import Estimate
from udh_cli.estimators.hypotheses import best_hypotheses, cascade_headings, heading_angles, heading_hypotheses, shift_hypotheses
from udh_cli.estimators.judge import judge_answers
from udh_cli.estimators.matching import CONFIDENT_INLIERS, MatchResult
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.polish import polished_match
from udh_cli.estimators.tiles import TileRefinement, TileResult


SEARCH_FINALISTS = 3  # large-motion search: hypotheses of a pair that get the whole cascade after screening
HEADING_FINALISTS = 2  # heading search: turns of a pair that get the whole cascade after screening


@dataclass(frozen=True)
class Answer:
    """One pair's answer as it passes from stage to stage.

    Attributes:
        small_h: (3, 3) ``b_from_a`` of the S x S images.
        score: its photometric score on the S x S images (``estimator.score``), in [0, 1].
        tiled: the tile stage's result from it (None: the stage did not run, the answer is degenerate, or it is a
            confident global match, kept untiled).
        match: the global match this answer is (None: not a match's answer).
        heading: the turn of B, degrees, the heading search found it from (None: not the heading search's).
        searched: found by the large-motion search.
        seen_match: the pair's global match, kept or not, as evidence for the verdict (None: none made or found).
    """

    small_h: np.ndarray
    score: float
    tiled: TileResult | None = None
    match: MatchResult | None = None
    heading: float | None = None
    searched: bool = False
    seen_match: MatchResult | None = None

    @property
    def confident_match(self) -> bool:
        """Whether this is a global match many cells support (:data:`~udh_cli.estimators.matching.CONFIDENT_INLIERS`)."""
        return self.match is not None and self.match.inliers >= CONFIDENT_INLIERS

    def rank(self) -> tuple[bool, int, float]:
        """What an offer must beat (:func:`settle`): a confident match, then tile levels accepted, then the score."""
        return self.confident_match, self.tiled.levels_used if self.tiled else 0, self.score


def settle(current: Answer, offer: Answer | None) -> Answer:
    """The one rule of the rescues: ``offer`` replaces ``current`` when it ranks higher (:meth:`Answer.rank`).

    A match many cells support first: a doubted cascade answer that one tile level accepted can be hundreds of px
    off where a match of a thousand cells is right (docs/estimators.md, "The global match"). Then tile levels (they
    confirm precise answers), then the score. A rejected offer still leaves the global match it saw, as evidence.
    """
    if offer is None:
        return current
    return offer if offer.rank() > current.rank() else replace(current, seen_match=offer.seen_match)


@dataclass(frozen=True)
class Batch:
    """The pairs of one call and their network inputs: ``small_a``, ``small_b`` (N, S, S) grey in [0, 1]."""

    pairs: Sequence[PreparedPair]
    small_a: np.ndarray
    small_b: np.ndarray

    @classmethod
    def of(cls, pairs: Sequence[PreparedPair], side: int) -> "Batch":
        small_a, small_b = (np.stack(images) for images in zip(*(pair.square(side) for pair in pairs)))
        return cls(pairs, small_a, small_b)


class StageClock:
    """A batch's stage times, ms: each stage's time divided by the batch size, for the stages that ran only (an
    absent key says "skipped" where a rounded 0.0 could not)."""

    def __init__(self, size: int) -> None:
        self.size, self.stage_ms = size, {}
        self.start = self.last = time.perf_counter()

    def lap(self, name: str, ran: bool = True) -> None:
        """End stage ``name`` now (timed when it ``ran``) and start the next."""
        now = time.perf_counter()
        if ran:
            self.stage_ms[name] = round((now - self.last) * 1e3 / self.size, 2)
        self.last = now

    def per_pair_ms(self) -> float:
        """The whole batch's time so far divided by its size, ms."""
        return (self.last - self.start) * 1e3 / self.size


def first_answers(estimator, batch: Batch, clock: StageClock) -> list[Answer]:
    """The cascade of the coarse networks from every heading (stage "network"), then the tile stage ("tiles")."""
    small_h, scores = cascade_headings(estimator, batch.small_a, batch.small_b)
    clock.lap("network")
    tiled = estimator.tile_stage(batch.pairs, small_h) if estimator.tiles else [None] * len(batch.pairs)
    clock.lap("tiles", ran=bool(estimator.tiles))
    return [Answer(h, score, found) for h, score, found in zip(small_h, scores, tiled)]


def still_doubted(estimator, answer: Answer, pair: PreparedPair) -> bool:
    """A low score, or (with tiles) an answer the tile levels did not confirm although B had room for tiles (on real
    flights: a start too far off for the tiles); never a match many cells support."""
    return (answer.score < estimator.search_below or _unconfirmed(estimator, answer.tiled, pair)) and not answer.confident_match


def _unconfirmed(estimator, tiled: TileResult | None, pair: PreparedPair) -> bool:
    """Whether the tile stage ran on ``pair`` (``tiled``: its result, None when it did not) and did not confirm the
    answer (:meth:`TileResult.confirms`), although B had room for tiles."""
    return tiled is not None and not tiled.confirms() and TileRefinement().can_confirm(pair.b.size, estimator.network.input_size)


def _retiled(estimator, pair: PreparedPair, small_h: np.ndarray) -> TileResult | None:
    """The tile stage on one offered answer, where the estimator has the stage."""
    return estimator.tile_stage([pair], [small_h])[0] if estimator.tiles else None


def heading_offers(estimator, batch: Batch, doubted: list[int], answers: Sequence[Answer]) -> dict[int, Answer]:
    """The heading search's answer for each doubted pair, tiled: B's small copy turned by ``heading_search`` angles
    over the whole circle (those the cascade tried left out), screened in one call, the best finishing the cascade
    (:func:`~udh_cli.estimators.hypotheses.best_hypotheses`)."""
    tried = (0.0, 180.0) if estimator.headings == 2 else (0.0,)
    small_a, small_b = batch.small_a[doubted], batch.small_b[doubted]
    turns = heading_hypotheses(small_a, small_b, heading_angles(estimator.heading_search, tried))
    found, scores, angles = best_hypotheses(estimator, turns, small_a, small_b, HEADING_FINALISTS)
    return {i: Answer(h, score, _retiled(estimator, batch.pairs[i], h), heading=angle, seen_match=answers[i].seen_match)
            for i, h, score, angle in zip(doubted, found, scores, angles)}


def match_offers(estimator, batch: Batch, doubted: list[int], answers: Sequence[Answer]) -> dict[int, Answer]:
    """The global match of each doubted pair where it found a valid answer; tiled unless many cells support it."""
    s, offers = estimator.network.input_size, {}
    for i in doubted:
        pair = batch.pairs[i]
        found = estimator.match_settings.match(estimator.networks.matcher, pair.a, pair.b)
        if found.b_from_a is None:
            continue
        h = geometry.rescale_homography(found.b_from_a, pair.a.size, (s, s), pair.b.size, (s, s))
        if not geometry.is_valid_homography(h, s, s):  # a folded fit is no answer, however many cells agree
            continue
        # A match hundreds of cells agree on is kept as the guided matching left it, not tiled: the tile stage is
        # less precise than it on the flights' pairs (docs/estimators.md, "The global match"); with polish_matches
        # it takes the tiles' answer where they agree on it (polish.py: better on turned pairs, looser loops).
        confident = found.inliers >= CONFIDENT_INLIERS
        tiled = _retiled(estimator, pair, h) if not confident or estimator.polish_matches else None
        if confident and tiled is not None:
            tiled = polished_match(pair, found.b_from_a, tiled)
        offers[i] = Answer(h, estimator.score(batch.small_a[i], batch.small_b[i], h), tiled, match=found, seen_match=found)
    return offers


def search_offers(estimator, batch: Batch, doubted: list[int], answers: Sequence[Answer]) -> dict[int, Answer]:
    """The large-motion search's answer for each doubted pair, tiled: the network run from each shift of a
    (2 * search + 1)^2 grid up to half the frame (:func:`~udh_cli.estimators.hypotheses.shift_hypotheses`), the
    best-scoring kept."""
    shifts = shift_hypotheses([batch.pairs[i] for i in doubted], estimator.network.input_size, estimator.search)
    found, scores, _ = best_hypotheses(estimator, shifts, batch.small_a[doubted], batch.small_b[doubted], SEARCH_FINALISTS)
    return {i: Answer(h, score, _retiled(estimator, batch.pairs[i], h), searched=True, seen_match=answers[i].seen_match)
            for i, h, score in zip(doubted, found, scores)}


class Rescue(NamedTuple):
    """A rescue of doubted pairs: its stage name (a key of ``details["stage_ms"]``), whether an estimator runs it,
    and its offers (``offers(estimator, batch, doubted indices, answers) -> {index: offered Answer}``)."""

    name: str
    runs: Callable[[object], bool]
    offers: Callable[[object, Batch, list[int], Sequence[Answer]], dict[int, Answer]]


# Cheapest first: a few network passes (the heading search) before describing both frames (the global match), and
# the shift search, whose answers only the score and the tiles judge, last.
RESCUES = (
    Rescue("headings", lambda estimator: bool(estimator.heading_search), heading_offers),
    Rescue("match", lambda estimator: estimator.networks.matcher is not None, match_offers),
    Rescue("search", lambda estimator: bool(estimator.search), search_offers),
)


def rescued(estimator, batch: Batch, answers: list[Answer], clock: StageClock) -> list[Answer]:
    """Every rescue of :data:`RESCUES` the estimator runs, in order, on the pairs still doubted; one stage each."""
    for name, runs, offers in RESCUES:
        doubted = [i for i, (answer, pair) in enumerate(zip(answers, batch.pairs)) if still_doubted(estimator, answer, pair)]
        ran = runs(estimator) and bool(doubted)
        if ran:
            offered = offers(estimator, batch, doubted, answers)
            answers = [settle(answer, offered.get(i)) for i, answer in enumerate(answers)]
        clock.lap(name, ran)
    return answers


def final_homography(estimator, answer: Answer, pair: PreparedPair) -> np.ndarray | None:
    """The answer as ``b_from_a`` in the pair's pixels: the tile stage's where it ran; None when degenerate."""
    full = estimator.full_resolution(answer.small_h, pair)
    return full if full is None or answer.tiled is None else answer.tiled.b_from_a


def judged(estimator, batch: Batch, answers: Sequence[Answer], fulls: Sequence[np.ndarray | None]) -> list:
    """:func:`~udh_cli.estimators.judge.judge_answers` on every answer (``fulls``: each as :func:`final_homography`
    gives it): ``(measured, Verdict)`` each, None where there is no answer; all None when the estimator does not judge."""
    if not estimator.judged:
        return [None] * len(answers)
    return judge_answers(estimator, batch.pairs, batch.small_a, batch.small_b, list(fulls), [a.score for a in answers],
                         [a.tiled for a in answers], [a.match for a in answers], [a.seen_match for a in answers])


def packed(estimator, pair: PreparedPair, answer: Answer, full: np.ndarray | None, verdict, stage_ms: dict,
           per_pair_ms: float, precision: str) -> Estimate:
    """The :class:`Estimate` of one answer, its details and the stage that found it; ``verdict`` is the judge's
    ``(measured, Verdict)`` or None."""
    failure = None if full is not None else "the network's 4-point output gives a degenerate homography"
    details = {"iterations": estimator.iterations, "refine_rounds": estimator.refine_rounds, "searched": answer.searched,
               "precision": precision, "provider": estimator.network.provider, "stage_ms": stage_ms}
    match, refined = answer.match, answer.tiled
    if answer.heading is not None:
        details["heading"] = answer.heading
    if match is not None:
        details.update(matched=True, match_inliers=match.inliers, match_heading=match.heading, match_side=match.side)
    if full is not None and refined is not None:  # a confident match only where polish_matches polished it
        details.update(tile_levels=refined.levels_used, tile_agreement=round(refined.agreeing, 3),
                       tile_residual_px=None if np.isnan(refined.residual_px) else round(refined.residual_px, 3))
    stage = ("tiles" if details.get("tile_levels") else "search" if answer.searched else "heading" if answer.heading is not None
             else "match" if match is not None else "network")
    confidence, verified, verified_by = (answer.score, None, None) if not estimator.judged else (0.0, False, None)
    if verdict is not None:
        details.update(verdict_failed=list(verdict[1].failed), **verdict[0])
        confidence, verified, verified_by = verdict[1].confidence, verdict[1].verified, verdict[1].verified_by
    return estimator._checked(full, confidence, per_pair_ms, failure, details, pair.a.shape, stage=stage, verified=verified,
                              verified_by=verified_by, verification_score=verdict[0]["alignment"] if verdict else None,
                              inliers=match.inliers if match else None)
