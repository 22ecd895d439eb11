"""The learned method's stages (estimators/learned.py): the one rule that keeps an offer, what is doubted, the rescues."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from udh_cli.estimators import learned
from udh_cli.estimators.learned import Answer, Batch, Rescue, StageClock, settle, still_doubted
from udh_cli.estimators.matching import CONFIDENT_INLIERS, MatchResult
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.tiles import TileResult

EYE = np.eye(3)


def tiled(levels: int, run: int = 3) -> TileResult:
    return TileResult(EYE, levels, 0.8, 0.5, run)


def match(inliers: int) -> MatchResult:
    return MatchResult(EYE, inliers, inliers + 10, 0)


def test_an_offer_is_kept_by_a_confident_match_then_tile_levels_then_the_score():
    current = Answer(EYE, 0.9, tiled(2))
    confident = Answer(EYE, 0.1, None, match=match(CONFIDENT_INLIERS), seen_match=match(CONFIDENT_INLIERS))
    assert settle(current, confident) is confident  # over more tile levels and a far better score
    weak_match = Answer(EYE, 0.95, tiled(1), match=match(CONFIDENT_INLIERS - 1))
    assert settle(current, weak_match).score == 0.9  # not confident: fewer tile levels lose
    assert settle(current, Answer(EYE, 0.2, tiled(3))).score == 0.2  # more levels win over a better score
    assert settle(current, Answer(EYE, 0.91, tiled(2))).score == 0.91  # as many levels: the better score
    tie = Answer(EYE, 0.9, tiled(2))
    assert settle(current, tie) is not tie  # a tie keeps the answer it would replace
    assert settle(current, None) is current


def test_a_rejected_offer_leaves_the_match_it_saw_as_evidence():
    seen = match(40)
    kept = settle(Answer(EYE, 0.9, tiled(2)), Answer(EYE, 0.3, None, match=seen, seen_match=seen))
    assert kept.score == 0.9 and kept.match is None and kept.seen_match is seen


def test_a_pair_is_doubted_for_a_low_score_or_unconfirmed_tiles_never_for_a_confident_match():
    estimator = SimpleNamespace(search_below=0.5, network=SimpleNamespace(input_size=32))
    image = np.random.default_rng(0).random((96, 128)).astype(np.float32)
    pair = PreparedPair.of(image, image)
    assert still_doubted(estimator, Answer(EYE, 0.4), pair)
    assert not still_doubted(estimator, Answer(EYE, 0.6), pair)
    assert still_doubted(estimator, Answer(EYE, 0.6, tiled(1)), pair)  # one level of three ran
    assert not still_doubted(estimator, Answer(EYE, 0.6, tiled(1, run=1)), pair)  # every level that ran
    assert not still_doubted(estimator, Answer(EYE, 0.4, match=match(CONFIDENT_INLIERS)), pair)


def test_each_rescue_offers_only_for_the_pairs_still_doubted_and_is_timed_only_when_it_ran(monkeypatch):
    offered = []

    def lift(estimator, batch, doubted, answers):
        offered.append(list(doubted))
        return {i: Answer(EYE, 0.8) for i in doubted}

    monkeypatch.setattr(learned, "RESCUES", (Rescue("first", lambda e: True, lift), Rescue("off", lambda e: False, lift),
                                             Rescue("last", lambda e: True, lift)))
    estimator = SimpleNamespace(search_below=0.5, network=SimpleNamespace(input_size=32))
    image = np.random.default_rng(1).random((64, 64)).astype(np.float32)
    pairs = [PreparedPair.of(image, image)] * 3
    batch = Batch.of(pairs, 32)
    clock = StageClock(len(pairs))
    answers = learned.rescued(estimator, batch, [Answer(EYE, 0.2), Answer(EYE, 0.7), Answer(EYE, 0.3)], clock)
    assert offered == [[0, 2]]  # after the first, no pair is doubted: "last" does not run
    assert [a.score for a in answers] == [0.8, 0.7, 0.8]
    assert list(clock.stage_ms) == ["first"]


def test_the_batch_holds_every_pair_at_the_network_side():
    image = np.random.default_rng(2).random((60, 80)).astype(np.float32)
    batch = Batch.of([PreparedPair.of(image, image)] * 2, 32)
    assert batch.small_a.shape == batch.small_b.shape == (2, 32, 32)


@pytest.mark.parametrize("ran", [True, False])
def test_the_clock_names_only_the_stages_that_ran_in_their_order(ran):
    clock = StageClock(4)
    clock.lap("prepare")
    clock.lap("tiles", ran=ran)
    clock.lap("verdict")
    assert list(clock.stage_ms) == (["prepare", "tiles", "verdict"] if ran else ["prepare", "verdict"])
    assert clock.per_pair_ms() >= 0.0
