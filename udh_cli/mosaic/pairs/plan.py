"""Which pairs a run estimates first: each frame with the next, and a bridge over each broken link."""

from __future__ import annotations

from typing import Sequence

from udh_cli.estimators import Estimator
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.pairs.cache import PairCache
from udh_cli.mosaic.pairs.estimate import estimate_pairs
from udh_cli.mosaic.pairs.types import Acceptance, PairRequest, PairResult
from udh_cli.mosaic.report import Reporter


def estimate_sequence(frameset: FrameSet, opinions: Sequence[Estimator], acceptance: Acceptance, batch_size: int, reporter: Reporter,
                      cache: PairCache, runner) -> list[PairResult]:
    """Consecutive pairs, then a bridge over each broken link (i-1 -> i+1 and i -> i+2)."""
    frames = frameset.frames
    args = (frames, opinions, acceptance, reporter)
    pairs = estimate_pairs([PairRequest(i, i + 1, "consecutive") for i in range(len(frames) - 1)], *args, "consecutive pairs", batch_size, cache, runner)
    broken = [p for p in pairs if not p.ok]
    for pair in broken:
        reporter.warn(f"pair {frames[pair.a].name} -> {frames[pair.b].name} failed ({pair.reason}); trying to bridge it")
    bridges = sorted({(a, b) for p in broken for a, b in ((p.a - 1, p.b), (p.a, p.b + 1)) if a >= 0 and b < len(frames)})
    if bridges:
        pairs += estimate_pairs([PairRequest(a, b, "bridge") for a, b in bridges], *args, "bridging gaps", batch_size, cache, runner)
    return pairs
