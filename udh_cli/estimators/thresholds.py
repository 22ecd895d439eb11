"""Every threshold of "is this answer right?", in one table with one reason each.

The judge (:mod:`.judge`), the cascade's :class:`~udh_cli.estimators.refined.Policy`, the tile stage, the global
match, :func:`~udh_cli.estimators.base.is_verified` and the mosaic's
:class:`~udh_cli.mosaic.pairs.types.Acceptance` and loop confirmation all read their defaults from
:data:`THRESHOLDS`. Where two of them ask the same question they share one entry; where the reasons differ, each has
its own. Measurements: docs/estimators.md ("The verdict", "The global match") and docs/mosaic.md.

A leaf module: it imports nothing of udh, so that any layer can read it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Thresholds:
    """Every threshold of a verdict, one reason each (measurements: docs/estimators.md, "The verdict").

    Attributes:
        min_alignment: least photometric score (the lower of intensity and gradient NCC over 4 x 4 tiles at
            256 px, :data:`~udh_cli.estimators.verify.VERIFIER`) of a verified answer: the one measure that told
            answers 10-20 px off from right ones on the hard real-pair benchmark, however many cells matched them
            (docs/estimators.md, "The verdict").
        min_alignment_supported: the same floor for a supported answer, and the mosaic's own alignment check
            (``Acceptance.min_verified``) for methods that do not verify themselves: wrong seneca answers' gradient
            NCC stayed below it 95 % of the time.
        min_alignment_matched: the supported floor for an answer hundreds of cells support: right consecutive
            brighton-beach pairs that 330-440 cells matched scored 0.026-0.058 (surf, moving water), yet 0 means
            that nothing aligns (no overlap, or flat tiles only).
        min_match_tile_levels: tile levels that must accept a global match's answer for it to be verified: cells
            at 384 px agree on homographies tens of px off at A's corners under strong perspective, and the tiles,
            up to full resolution, are evidence independent of the cells and of the score.
        max_round_trip: largest error of ``b_from_a @ a_from_b`` against the identity where A covers B, as a share
            of the network's input side (12.8 px of 128): the network re-run from B to A must come back to A. On
            right consecutive pairs of seneca and brighton-beach at 800 px it came back up to 0.085 of the side
            (the network at 128 px on half-overlapping frames), on right turned pairs up to 0.02: it catches gross
            errors (a wrong heading, no overlap, a network stuck on one answer), not a few pixels.
        match_evidence_inliers: fewest cells of a global match for it to count as an opinion at all: pairs of
            frames from different flights reached up to 34 (docs/estimators.md, "The global match").
        max_match_disagreement: largest corner distance between the answer and a global match that counts, as a
            share of A's longer side (16 px of 800): a cell of the match is 4 px at 384 px, 8 px of 800.
        unverified_confidence: factor on the confidence of an answer that fails a check, so that it ranks below
            the answers that passed on its side of the mosaic's floor (confidence 0 stays for "no answer").
        verified_confidence: a verified answer's confidence c becomes ``v + (1 - v) * c``: verified answers are
            right far more often than the network's score says, and the reliability diagram should show it (one
            scored under the mosaic's floor keeps its score, so that the floor still decides).
        min_confidence: least confidence of an answer that carries no verification of its own to count as
            verified, and the mosaic's floor (``Acceptance.min_confidence``): low on purpose, it drops only what an
            estimator itself calls hopeless (docs/mosaic.md).
        network_search_below: a network's own score (``deep.NETWORK_CHECK``) under which its answer is doubted
            and the searches run (``DeepEstimator.search_below``): a cheap trigger, the verdict comes after.
        min_network_overlap: least share of B that A must cover at the network's S x S input for its own score
            (``deep.NETWORK_CHECK``) and the round trip to say anything: below it the network sees mostly the
            pre-warp's border.
        confident_inliers: agreeing cells above which a global match needs no second heading and verifies
            itself, as RANSAC verifies SIFT's answers: frames of different flights reached at most 27, right
            consecutive pairs 185 and more (docs/estimators.md, "The global match").
        confirming_tile_levels: tile levels that must accept a network's answer for it to count as confirmed:
            answers one level accepted were mostly over 20 px off on seneca (docs/estimators.md).
        min_cascade_score: photometric score below which a cascade (``Policy.min_score``) doubts its answer and a
            loop pair's chained prediction is not confirmed: stricter than ``min_alignment_supported`` because
            nothing but this check stands between a cheap answer and the map; wrong answers' gradients stayed
            below it, right ones above.
        trusted_inliers: RANSAC inliers (SIFT's, ORB's) at which a cascade's opinion is verified by its matches:
            occluders, surf and moving water lower the photometric score of right answers, never the agreement
            of 20 matches.
        min_prediction_start: photometric score under which a loop pair's chained prediction is not refined: that
            far off, ECC from it fails after spending its budget (docs/mosaic.md).
        max_prediction_move: largest corner move, as a share of A's diagonal, of ECC confirming a prediction: a
            move beyond it means ECC left the prediction's basin.
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
    min_cascade_score: float = 0.7
    trusted_inliers: int = 20
    min_prediction_start: float = 0.2
    max_prediction_move: float = 0.03


THRESHOLDS = Thresholds()
