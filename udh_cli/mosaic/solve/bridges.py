"""Joining the parts of a split run by pairs between frames that GPS puts close together on the ground."""

from __future__ import annotations

from typing import Sequence

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator
from udh_cli.mosaic.inputs.frames import FrameSet, gps_fixes
from udh_cli.mosaic.pairs.cache import PairCache
from udh_cli.mosaic.pairs.estimate import estimate_pairs
from udh_cli.mosaic.pairs.gps import (bridge_candidates, gps_disagreement_m, gps_limit_m, ground_positions, measure_ground_scale, part_map,
                                      placement_error_m)
from udh_cli.mosaic.pairs.types import Acceptance, PairRequest, PairResult
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.parts import Part


def bridge_by_gps(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], opinions: Sequence[Estimator], gps_pairs: int,
                  acceptance: Acceptance, batch_size: int, reporter: Reporter, cache: PairCache, runner) -> list[PairResult]:
    """Pairs between parts (lone frames included) that GPS puts close together on the ground; an estimate that
    disagrees with GPS about the frames' distance is rejected (:mod:`udh_cli.mosaic.pairs.gps`); at most
    ``gps_pairs`` pairs between each two parts."""
    frames = frameset.frames
    if gps_pairs < 1 or len(parts) < 2:
        return []
    fixes = gps_fixes(frames)
    if len(fixes) < 2:
        return []
    try:
        _, positions = ground_positions(fixes)
    except UdhError:  # no pyproj: the georeferencing step says how to install it
        return []
    sizes = [f.size for f in frames]
    scale = measure_ground_scale(positions, [(p.a, p.b, p.b_from_a) for p in pairs if p.ok], sizes)
    if scale is None:
        reporter.warn("the frames carry GPS, but too few pairs worked to measure the ground scale; the parts are not bridged by GPS")
        return []
    known = {(min(p.a, p.b), max(p.a, p.b)) for p in pairs}
    candidates = bridge_candidates(positions, [part.frames for part in parts], known, scale.reach_m, gps_pairs)
    if not candidates:
        return []
    results = estimate_pairs([PairRequest(a, b, "gps") for a, b, _ in candidates], frames, opinions, acceptance,
                             reporter, "GPS bridges between parts", batch_size, cache, runner)
    part_of = {i: k for k, part in enumerate(parts) for i in part.frames}  # frame -> index of its part
    placed = {k: part_map(positions, part.chained, sizes) for k, part in enumerate(parts) if len(part.frames) >= 3}
    for result in results:
        if not result.ok:
            continue
        # Through whichever part GPS places on the map (the larger first): where the estimate puts the other frame.
        checks = sorted([(result.a, result.b, geometry.invert(result.b_from_a)), (result.b, result.a, result.b_from_a)],
                        key=lambda c: -len(parts[part_of[c[0]]].frames))
        through = next(((f, o, h) for f, o, h in checks if placed.get(part_of[f]) is not None), None)
        if through is not None:
            frame, other, frame_from_other = through
            off, limit = placement_error_m(frame_from_other, frame, other, parts[part_of[frame]].chained[frame], placed[part_of[frame]], positions, sizes)
            what = f"places {frames[other].name} {off:.0f} m from its GPS position (limit {limit:.0f} m)"
        else:
            off, limit = gps_disagreement_m(result.b_from_a, result.a, result.b, positions, sizes, scale), gps_limit_m(scale)
            what = f"puts the frames {off:.0f} m further apart or closer than their GPS does (limit {limit:.0f} m)"
        if off > limit:
            result.status, result.b_from_a, result.reason = "rejected", None, what
    reporter.info(f"GPS: {sum(r.ok for r in results)} of {len(results)} pairs between parts joined them "
                  f"(ground scale {scale.metres_per_pixel * 100:.1f} cm per pixel from {scale.pairs_used} pairs, reach {scale.reach_m:.0f} m)")
    return results
