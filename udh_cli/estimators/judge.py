"""The one judge of a learned answer: "verified" only when independent evidence agrees.

Each piece of evidence is measured by the estimator that has it (:class:`Evidence`); every threshold of the
verdict lives in :class:`~udh_cli.estimators.thresholds.Thresholds`, one reason each; :func:`judge` says whether the answer is verified, by
what, and which checks it failed. Two tiers: an answer is **verified** (one to build a map on) when it also passes
the stricter checks (a finer photometric floor; for a global match, tile levels that accept it); an answer that
passes only the looser ones is **supported**: unverified, with ``verified_by`` naming what supports it, so that a
mosaic may still take it after its own checks. An answer that fails is kept, unverified and with a lower
confidence: the caller (a mosaic, ``udh estimate``'s exit code 3) decides what to do with a doubted answer.
:func:`judge_matched` is the same verdict on an answer RANSAC's matches verify (``auto``'s SIFT opinion).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators.thresholds import THRESHOLDS, Thresholds
from udh_cli.estimators.tiles import TileRefinement, refine_pairs_with_tiles
from udh_cli.estimators.verify import VERIFIER


# Least share of B that A must cover at the network's S x S input for the round trip to say anything.
MIN_NETWORK_OVERLAP = THRESHOLDS.min_network_overlap


@dataclass(frozen=True)
class Evidence:
    """What was measured about one answer; None where a check could not run.

    Attributes:
        alignment: the photometric score of the answer, in [0, 1].
        round_trip: corner error of the answer composed with the network's answer from B back to A, share of
            the network's input side.
        tiles_confirm: whether the tile levels confirmed the answer (None: the stage did not run, or B had no
            room for tiles, so that finding none says nothing).
        match_inliers: cells that support the pair's global match (None: none was made or it found nothing).
        match_disagreement: corner distance between the answer and that match, share of A's longer side.
        is_match: the answer is the global match's own (not refined by anything else).
        match_tile_levels: tile levels that accepted a match's answer, run on it as evidence only (None: not a
            match's answer, or B had no room for tiles).
    """

    alignment: float
    round_trip: float | None = None
    tiles_confirm: bool | None = None
    match_inliers: int | None = None
    match_disagreement: float | None = None
    is_match: bool = False
    match_tile_levels: int | None = None


@dataclass(frozen=True)
class Verdict:
    """``verified`` when no check failed and at least two passed; ``verified_by`` names the strongest evidence
    ("matches" for a match hundreds of cells support, else "alignment"), for a verified answer or a supported one
    (unverified: it failed only the stricter checks); ``failed`` the checks it failed."""

    verified: bool
    verified_by: str | None
    failed: tuple[str, ...]
    confidence: float


def judge(evidence: Evidence, confidence: float, thresholds: Thresholds = THRESHOLDS) -> Verdict:
    """The verdict on an answer of ``confidence`` (in [0, 1]) given ``evidence``."""
    counted_match = evidence.match_inliers is not None and evidence.match_inliers >= thresholds.match_evidence_inliers
    confident_match = counted_match and evidence.match_inliers >= thresholds.confident_inliers
    supported = confident_match and (evidence.is_match or (evidence.match_disagreement or 0.0) <= thresholds.max_match_disagreement)
    floor = thresholds.min_alignment_matched if supported else thresholds.min_alignment_supported
    checks = {"alignment": evidence.alignment >= floor}
    if supported:
        checks["matches"] = True  # hundreds of cells agree on it, as RANSAC's inliers verify SIFT's answers
    if evidence.round_trip is not None:
        checks["round trip"] = bool(evidence.round_trip <= thresholds.max_round_trip)
    if evidence.tiles_confirm is not None and not supported:
        # A match hundreds of cells agree on is not tiled, or is where tiles fail (brighton-beach's trees).
        checks["tiles"] = evidence.tiles_confirm
    if counted_match and evidence.match_disagreement is not None and not evidence.is_match:
        checks["match agrees"] = bool(evidence.match_disagreement <= thresholds.max_match_disagreement)
    failed = tuple(name for name, passed in checks.items() if not passed)
    if failed or len(checks) < 2:
        return Verdict(False, None, failed, confidence * thresholds.unverified_confidence)
    by = "matches" if supported else "alignment"
    if supported:
        confidence = max(confidence, evidence.match_inliers / (evidence.match_inliers + thresholds.confident_inliers))
    stricter = {"fine alignment": evidence.alignment >= thresholds.min_alignment}
    if supported and evidence.match_tile_levels is not None:
        stricter["match tiles"] = evidence.match_tile_levels >= thresholds.min_match_tile_levels
    failed = tuple(name for name, passed in stricter.items() if not passed)
    # Either tier keeps an answer on its side of the mosaic's confidence floor, so the mosaic takes the same answers.
    floor_confidence = thresholds.min_confidence
    below = confidence < floor_confidence
    if failed:  # below every verified answer of the same evidence
        factor = thresholds.unverified_confidence
        return Verdict(False, by, failed, confidence * factor if below else floor_confidence + (confidence - floor_confidence) * factor)
    lift = thresholds.verified_confidence
    return Verdict(True, by, (), confidence if below else lift + (1.0 - lift) * confidence)


def judge_matched(network, pair, b_from_a: np.ndarray, alignment: float, confidence: float,
                  thresholds: Thresholds = THRESHOLDS) -> tuple[dict, Verdict]:
    """The verdict on an answer RANSAC's matches verify, ``b_from_a`` ((3, 3), pixels of the prepared ``pair``)
    with photometric score ``alignment``, and what was measured for it. Verified when something aligns
    (``min_alignment_matched``) and the tile stage of ``network`` (a
    :class:`~udh_cli.estimators.deep.DeepEstimator`; None: no tile check), run on the answer as evidence only,
    accepts ``min_matched_tile_levels`` levels where B has room for tiles; otherwise supported by "matches":
    unverified, and a mosaic takes it as before. The tiles run only where they can decide the verdict. The
    confidence is kept: the verdict changes, not how much the matches say."""
    checks = {"aligns": alignment >= thresholds.min_alignment_matched}
    levels = None
    if checks["aligns"] and network is not None and TileRefinement().can_confirm(pair.b.size, network.network.input_size):
        found = refine_pairs_with_tiles(network.networks.tile, [(pair.a, pair.b)], [b_from_a],
                                        coarse_network=network.networks.tile_coarse)[0]
        levels = found.levels_used
        checks["tiles"] = found.confirms(thresholds.min_matched_tile_levels)
    failed = tuple(name for name, passed in checks.items() if not passed)
    return {"match_tile_levels": levels}, Verdict(not failed, "matches", failed, confidence)


def round_trip_error(b_from_a: np.ndarray, a_from_b: np.ndarray, side: int, grid: int = 5) -> float:
    """Largest error of ``b_from_a @ a_from_b`` (both (3, 3), pixels of S x S images) against the identity at the
    points of a ``grid`` x ``grid`` lattice over B that A covers, as a share of ``side``; inf for a degenerate
    answer or no covered point. Why the covered points, not the frame's corners: where A does not reach, the
    network saw only the pre-warp's border fill, and its 4-point answer there is an extrapolation (right
    consecutive pairs of seneca, overlapping by half, came back 7-16 px off at the corners)."""
    composed = b_from_a @ a_from_b
    if not np.isfinite(composed).all() or abs(composed[2, 2]) < 1e-12:
        return float("inf")
    steps = np.linspace(0.0, side - 1.0, grid)
    points_b = np.array([[x, y] for y in steps for x in steps])
    in_a = geometry.transform_points(a_from_b, points_b)
    covered = np.isfinite(in_a).all(1) & (in_a >= -0.5).all(1) & (in_a <= side - 0.5).all(1)
    if not covered.any():
        return float("inf")
    moved = geometry.transform_points(composed / composed[2, 2], points_b[covered])
    error = float(np.linalg.norm(moved - points_b[covered], axis=1).max())
    return error / side if np.isfinite(error) else float("inf")


def disagreement(b_from_a: np.ndarray, other: np.ndarray, size_a: tuple[int, int]) -> float:
    """Largest corner distance between two ``b_from_a`` (pixels) of an A of ``size_a`` = (w, h), as a share of
    its longer side; inf when either is degenerate."""
    error = float(geometry.corner_errors(b_from_a, other, *size_a).max())
    return error / max(size_a) if np.isfinite(error) else float("inf")


def judge_answers(estimator, pairs, small_a, small_b, fulls, scores, tiled, matched, seen_match,
                  thresholds: Thresholds = THRESHOLDS) -> list:
    """The :func:`judge` of every answer of a :class:`~udh_cli.estimators.deep.DeepEstimator` (None where there is
    none), with the evidence it measured as a dict for the details: the photometric score at 256 px; the round
    trip, the cascade's last round (the refinement network where there is one) on the swapped S x S pair from the
    answer's inverse, one call for all pairs, where the network sees at least :data:`MIN_NETWORK_OVERLAP` of B;
    the tile levels; a global match, and the tile levels run on its answer where they can decide the verdict. Why
    the last round: the refinement network is trained on small residuals; on right answers of turned real pairs its
    round trip stayed under 2.6 px of 128, the coarse network's reached 14 px (docs/estimators.md, "The verdict").

    Args:
        pairs: the prepared pairs; small_a, small_b: (N, S, S) their network inputs.
        fulls: each answer, (3, 3) ``b_from_a`` in the pair's pixels, or None; scores: their confidences.
        tiled: each tile stage's result or None; matched: the global match each answer is, or None;
        seen_match: each pair's global match, kept or not, or None.
    """
    s = estimator.network.input_size
    answered = [i for i, full in enumerate(fulls) if full is not None]
    small = {i: geometry.rescale_homography(fulls[i], pairs[i].a.size, (s, s), pairs[i].b.size, (s, s)) for i in answered}
    seen = [i for i in answered if _overlap(small[i], s) >= thresholds.min_network_overlap]
    back = estimator.predict_small(small_b[seen], small_a[seen], estimator.rounds()[-1:], np.stack([np.linalg.inv(small[i]) for i in seen])) if seen else []
    round_trips = {i: round_trip_error(small[i], a_from_b, s) for i, a_from_b in zip(seen, back)}
    alignments = {i: VERIFIER.score(pairs[i].a, pairs[i].b, fulls[i]) for i in answered}
    # The tile levels as evidence on a match's own answer (kept as the match left it), only where the verdict
    # can turn on them: a confident match that aligns well enough to be verified, with room for tiles in B.
    retile = [i for i in answered if matched[i] is not None and tiled[i] is None and estimator.tiles
              and matched[i].inliers >= thresholds.confident_inliers and alignments[i] >= thresholds.min_alignment
              and TileRefinement().can_confirm(pairs[i].b.size, s)]
    match_tiles = dict(zip(retile, estimator.tile_stage([pairs[i] for i in retile], [small[i] for i in retile]))) if retile else {}
    out = []
    for i, (pair, full) in enumerate(zip(pairs, fulls)):
        if full is None:
            out.append(None)
            continue
        match = seen_match[i]
        can_confirm = tiled[i] is not None and TileRefinement().can_confirm(pair.b.size, s)
        evidence = Evidence(alignment=alignments[i], round_trip=round_trips.get(i),
                            tiles_confirm=tiled[i].confirms(thresholds.confirming_tile_levels) if can_confirm else None,
                            match_inliers=match.inliers if match is not None else None,
                            match_disagreement=disagreement(full, match.b_from_a, pair.a.size) if match is not None else None,
                            is_match=matched[i] is not None and tiled[i] is None,
                            match_tile_levels=match_tiles[i].levels_used if match_tiles.get(i) is not None else None)
        measured = {"alignment": round(evidence.alignment, 3), "round_trip": None if evidence.round_trip is None else round(evidence.round_trip, 4),
                    "match_disagreement": None if evidence.match_disagreement is None else round(evidence.match_disagreement, 4),
                    "match_tile_levels": evidence.match_tile_levels}
        out.append((measured, judge(evidence, scores[i], thresholds)))
    return out


def _overlap(b_from_a: np.ndarray, side: int) -> float:
    """Share of an S x S image B that A covers under ``b_from_a`` (pixels of S x S images)."""
    mask = cv2.warpPerspective(np.ones((side, side), np.float32), b_from_a, (side, side), flags=cv2.INTER_NEAREST)
    return float((mask > 0.5).mean())
