"""Loop closure: overlapping pairs beyond the chain, estimated from its prediction and checked against it, in rounds."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.estimators import Estimator
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.pairs.cache import PairCache
from udh_cli.mosaic.pairs.estimate import corner_disagreement_px, estimate_pairs
from udh_cli.mosaic.pairs.types import Acceptance, PairRequest, PairResult
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.graph import NEAR_IN_SEQUENCE, overlap_candidates
from udh_cli.mosaic.solve.homographies import pair_points, solve_part
from udh_cli.mosaic.solve.parts import Part


@dataclass(frozen=True)
class LoopClosure:
    """Which overlaps are tried and what contradicts the chain (:class:`~udh_cli.mosaic.config.MosaicConfig` holds them).

    Attributes:
        overlap_min: share of the smaller frame that chained footprints must overlap by to be tried.
        overlap_per_frame: at most this many partners per frame in the first round.
        max_disagreement: a loop pair moving the corners further than this share of the diagonal from the
            prediction is rejected.
        huber_px: the rounds' solves' Huber width, pixels.
        from_prediction: each pair is first confirmed from its prediction by ECC
            (:mod:`udh_cli.mosaic.pairs.confirm`), and only those that fail run the whole cascade.
    """

    overlap_min: float
    overlap_per_frame: int
    max_disagreement: float
    huber_px: float
    from_prediction: bool = True


# Rounds of loop closure at most (fewer when a round accepts nothing new). After each, the pairs are solved
# together, and from that solve the rejected loop pairs are estimated again and frames without a far partner get
# one. Why: over a long survey the chain drifts, so the pairs that close the longest loops (a strip's far end
# against its neighbour) get a prior 100+ px off and fail, and some overlaps do not show in the drifted
# footprints at all. On a simulated 1,988-frame survey all 415 such rejections were wrong (111 px median from
# the truth) and the last strip drifted by up to 850 px; with the rounds its frames were 2.87 px median from the
# truth after the best homography of the plane (26.3 px before).
LOOP_ROUNDS = 4


def close_loops(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], opinions: Sequence[Estimator], settings: LoopClosure,
                acceptance: Acceptance, batch_size: int, reporter: Reporter, cache: PairCache, runner) -> list[PairResult]:
    """Estimate non-consecutive overlapping pairs, pre-warped by the chain, and reject those that contradict it;
    then, from a solve with the accepted ones, estimate the rejected ones again and add a far partner for every
    frame without one (:data:`LOOP_ROUNDS`). Each pair appears once in the result, as last estimated."""
    frames = frameset.frames
    sizes = [f.size for f in frames]
    known = {(min(p.a, p.b), max(p.a, p.b)) for p in pairs}
    # Priors and candidates come from Part.solved: the chain at first, then each round's solve.
    wanted = {k: [(a, b) for a, b, _ in overlap_candidates(part.frames, part.solved, sizes, known, settings.overlap_min, settings.overlap_per_frame)]
              for k, part in enumerate(parts) if len(part.frames) >= 3}  # part index -> the pairs to estimate
    results: dict[tuple[int, int], PairResult] = {}
    for round_number in range(LOOP_ROUNDS):
        requests, requested = [], []
        for k, part in enumerate(parts):
            for a, b in wanted.get(k, []):
                requested.append((a, b))
                prior = geometry.invert(part.solved[b]) @ part.solved[a]
                requests.append(PairRequest(a, b, "overlap", prior / prior[2, 2], settings.from_prediction))
        if not requests:
            break
        stage = "loop-closure pairs" if round_number == 0 else f"loop-closure pairs again, from the solve ({round_number + 1})"
        for result in estimate_pairs(requests, frames, opinions, acceptance, reporter, stage, batch_size, cache, runner):
            if result.ok:
                w, h = frames[result.b].size
                disagreement = corner_disagreement_px(result.b_from_a, result.prior, frames[result.a].size)
                if disagreement > settings.max_disagreement * float(np.hypot(w, h)):
                    result = replace(result, status="rejected", b_from_a=None, reason=(
                        f"moves the corners {disagreement:.0f} px away from the {'chained' if round_number == 0 else 'solved'} "
                        f"prediction (limit {settings.max_disagreement:.0%} of the diagonal)"))
            results[(result.a, result.b)] = result
        retry = {(r.a, r.b) for r in results.values() if r.status == "rejected"}
        if round_number > 0 and all(key in retry for key in requested):
            break  # nothing new accepted: a new solve would predict the same
        if round_number + 1 == LOOP_ROUNDS:
            break
        tried = known | set(results)
        solving = [(k, part) for k, part in enumerate(parts) if k in wanted]
        with reporter.stage("loop-closure solves", len(solving)) as advance:
            for k, part in solving:
                members = set(part.frames)
                used = [p for p in [*pairs, *results.values()] if p.ok and p.a in members and p.b in members]
                # From the previous round's solve, which the pairs it had already hold: nearer this round's answer
                # than the drifted chain is.
                part.solved = solve_part(part.reference, part.solved, sizes, [pair_points(p, sizes[p.a], sizes[p.b]) for p in used], settings.huber_px)
                # The solve also shows overlaps the drifted chain hid: a far partner (the next strip) for every frame
                # that has none yet, one per frame and round, so the work stays about one pair per untied frame.
                tied = {f for p in used if abs(p.b - p.a) > NEAR_IN_SEQUENCE for f in (p.a, p.b)}
                found = [(a, b) for a, b, _ in overlap_candidates(part.frames, part.solved, sizes, tried, settings.overlap_min, 1)
                         if b - a > NEAR_IN_SEQUENCE and not (a in tied and b in tied)]
                wanted[k] = [key for key in wanted[k] if key in retry] + found
                advance(1)
    return list(results.values())
