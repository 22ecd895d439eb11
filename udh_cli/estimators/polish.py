"""A global match's answer polished by the tile stage, where the tiles agree on a better one.

A match many cells support is one or two px off inside the overlap (its cells are 4 px of a 384 or 640-px copy).
Where A reaches far outside B (a pair turned, or seen at another scale) that magnifies to 10-40 px at A's corners,
and the tile stage, pre-warped by the answer and run up to full resolution, is sub-pixel where it agrees with
itself (docs/benchmarks.md, "Turned and scaled pairs: the global match polished by the tiles").
"""

from __future__ import annotations

import numpy as np

from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.estimators.tiles import CONFIRMING_LEVELS, TileResult
from udh_cli.estimators.verify import VERIFIER

MAX_SCORE_LOSS = THRESHOLDS.max_polish_score_loss
MIN_AGREEMENT = THRESHOLDS.min_polish_tile_agreement


def polished_match(pair: PreparedPair, matched: np.ndarray, found: TileResult | None) -> TileResult | None:
    """``found``, the tile stage run from a global match's answer ``matched`` ((3, 3) ``b_from_a``, pixels of
    ``pair``), where it replaces that answer; else None (the match's answer is kept).

    It replaces it where :data:`~udh_cli.estimators.tiles.CONFIRMING_LEVELS` levels accepted it (one accepted level
    moves right matches), most tiles of the finest agreed (:data:`MIN_AGREEMENT`: over surf and trees a few tiles
    agree on a plane of their own) and it aligns about as well (:data:`MAX_SCORE_LOSS`, the photometric score of
    :data:`~udh_cli.estimators.verify.VERIFIER`): two levels can agree on a plane far from a right match.
    """
    if found is None or found.levels_used < CONFIRMING_LEVELS or found.agreeing < MIN_AGREEMENT:
        return None
    before, after = (VERIFIER.score(pair.a, pair.b, h) for h in (matched, found.b_from_a))
    return found if after >= before - MAX_SCORE_LOSS else None
