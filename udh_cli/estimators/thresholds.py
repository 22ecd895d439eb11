"""Every threshold of "is this answer right?", in one table with one reason each.

The judge (:mod:`.judge`), the cascade's :class:`~udh_cli.estimators.refined.Policy`, the tile stage, the global
match, :func:`~udh_cli.estimators.base.is_verified` and the mosaic's
:class:`~udh_cli.mosaic.pairs.types.Acceptance` and loop confirmation all read their defaults from
:data:`THRESHOLDS`. Where two of them ask the same question they share one entry; where the reasons differ, each has
its own. Measurements: docs/estimators.md, "Where each threshold comes from".

A leaf module: it imports nothing of udh, so that any layer can read it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Thresholds:
    """Every threshold of a verdict, one reason each (measurements: docs/estimators.md, "Where each threshold comes from").

    Attributes:
        min_alignment: least photometric score (the lower of intensity and gradient NCC,
            :data:`~udh_cli.estimators.verify.VERIFIER`) of a verified answer: the one measure that told answers
            10-20 px off from right ones on real pairs.
        min_alignment_supported: the same floor for a supported answer, and the mosaic's alignment check
            (``Acceptance.min_verified``) for methods that do not verify themselves: wrong answers' gradient NCC
            stays below it.
        min_alignment_matched: the supported floor for an answer hundreds of cells support, and the verified floor
            for an answer RANSAC's matches verify: right pairs over surf score barely above 0, yet 0 means nothing
            aligns.
        min_match_tile_levels: tile levels that must accept a global match's answer for it to be verified: cells
            at 384 px can agree on an answer tens of px off under strong perspective, the tiles are independent
            evidence.
        max_round_trip: largest error of ``b_from_a @ a_from_b`` against the identity where A covers B, as a
            share of the network's input side: it catches gross errors (a wrong heading, no overlap), not a few
            pixels.
        match_evidence_inliers: fewest cells of a global match for it to count as an opinion at all: above what
            frames of different flights reach.
        max_match_disagreement: largest corner distance between the answer and a global match that counts, as a
            share of A's longer side: about two cells of the match.
        unverified_confidence: factor on the confidence of an answer that fails a check, so that it ranks below
            the answers that passed on its side of the mosaic's floor (confidence 0 stays for "no answer").
        verified_confidence: a verified answer's confidence c becomes ``v + (1 - v) * c``, so that the
            reliability diagram shows how often verified answers are right (one under the mosaic's floor keeps
            its score).
        min_confidence: least confidence of an answer that carries no verification of its own to count as
            verified, and the mosaic's floor (``Acceptance.min_confidence``): it drops only what an estimator
            itself calls hopeless.
        network_search_below: a network's own score (``deep.NETWORK_CHECK``) under which its answer is doubted
            and the searches run: a cheap trigger, the verdict comes after.
        min_network_overlap: least share of B that A must cover at the network's S x S input for its own score
            and the round trip to say anything.
        confident_inliers: agreeing cells above which a global match needs no second heading and verifies
            itself, as RANSAC verifies SIFT's answers: well above what frames of different flights reach.
        confirming_tile_levels: tile levels that must accept a network's answer for it to count as confirmed:
            answers one level accepted were mostly far off.
        min_matched_tile_levels: tile levels that must accept an answer RANSAC's matches verify (``auto``'s SIFT
            opinion) for it to stay verified, where B has room for tiles: SIFT's matches agree on answers 10-30 px
            off under parallax and strong perspective, the tiles are evidence independent of the matches.
        min_cascade_score: photometric score below which a cascade (``Policy.min_score``) doubts its answer and
            a loop pair's prediction is not confirmed: nothing else stands between a cheap answer and the map.
        trusted_inliers: RANSAC inliers (SIFT's, ORB's) at which a cascade's opinion is verified by its matches:
            occluders and surf lower the photometric score of right answers, never the agreement of matches.
        min_prediction_start: photometric score under which a loop pair's chained prediction is not refined:
            that far off, ECC from it fails after spending its budget.
        max_prediction_move: largest corner move, as a share of A's diagonal, of ECC confirming a prediction:
            beyond it ECC left the prediction's basin.
        max_polish_score_loss: most the photometric score of a global match's answer may drop when the tile stage
            polishes it (:mod:`.polish`): right answers moved by a few px change it by less, a polish far off a right
            match by more (docs/benchmarks.md, "Turned and scaled pairs: the global match polished by the tiles").
        min_polish_tile_agreement: least share of the finest accepted tile level's tiles that must agree for that
            polish: over surf and trees fewer agree, and their polish loosened a network-only mosaic's loops; the
            polishes that turned a failure into a right answer agreed more (the same section).
    """

    min_alignment: float = 0.55
    min_alignment_supported: float = 0.3
    min_alignment_matched: float = 0.02
    min_match_tile_levels: int = 1
    max_round_trip: float = 0.1
    match_evidence_inliers: int = 40
    max_match_disagreement: float = 0.02
    unverified_confidence: float = 0.5
    verified_confidence: float = 0.5
    min_confidence: float = 0.2
    network_search_below: float = 0.5
    min_network_overlap: float = 0.3
    confident_inliers: int = 150
    confirming_tile_levels: int = 2
    min_matched_tile_levels: int = 2
    min_cascade_score: float = 0.7
    trusted_inliers: int = 20
    min_prediction_start: float = 0.2
    max_prediction_move: float = 0.03
    max_polish_score_loss: float = 0.05
    min_polish_tile_agreement: float = 0.6


THRESHOLDS = Thresholds()
