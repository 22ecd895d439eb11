"""A global match's answer polished by the tile stage: only where two levels accept it and it aligns as well."""

from __future__ import annotations

import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.polish import MAX_SCORE_LOSS, MIN_AGREEMENT, polished_match
from udh_cli.estimators.tiles import TileResult
from udh_cli.estimators.verify import VERIFIER

TRUTH = geometry.translation(6.0, -4.0)


@pytest.fixture(scope="module")
def pair() -> PreparedPair:
    return PreparedPair.of(*warped_pair(TRUTH, seed=5))


@pytest.mark.parametrize("levels, kept", [(3, True), (2, True), (1, False), (0, False)])
def test_a_match_is_polished_only_where_two_tile_levels_accept_it(pair, levels, kept):
    off = geometry.translation(3.0, 0.0) @ TRUTH
    found = TileResult(TRUTH.copy(), levels, 0.75, 0.4, 3)
    assert (polished_match(pair, off, found) is found) == kept
    assert polished_match(pair, off, None) is None


def test_a_polish_that_aligns_worse_than_the_match_is_refused(pair):
    """Two levels agreeing on a plane 8 px off a right match: its score drops by more than MAX_SCORE_LOSS."""
    off = geometry.translation(8.0, 0.0) @ TRUTH
    right, wrong = VERIFIER.score(pair.a, pair.b, TRUTH), VERIFIER.score(pair.a, pair.b, off)
    assert right - wrong > MAX_SCORE_LOSS
    assert polished_match(pair, TRUTH, TileResult(off, 2, 1.0, 0.3, 2)) is None
    assert polished_match(pair, off, TileResult(TRUTH.copy(), 2, 1.0, 0.3, 2)) is not None


def test_a_polish_most_tiles_do_not_agree_on_is_refused(pair):
    off = geometry.translation(3.0, 0.0) @ TRUTH
    assert polished_match(pair, off, TileResult(TRUTH.copy(), 2, MIN_AGREEMENT - 0.1, 0.3, 2)) is None
    assert polished_match(pair, off, TileResult(TRUTH.copy(), 2, MIN_AGREEMENT, 0.3, 2)) is not None
