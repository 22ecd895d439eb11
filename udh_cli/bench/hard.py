"""``udh bench hard``: real pairs with known motion, every kind of motion, and udh's verdict scored.

The pairs (:func:`build_sets`), one :class:`~udh_cli.bench.pairsets.PairSet` per kind:

* "flight pairs" and "real pairs": the sources' own pairs (:mod:`udh_cli.bench.hard_pairs`) as captured,
  scored against their reference;
* one set per kind of motion of :data:`udh_cli.bench.motions.MOTION_KINDS`: a real pair whose B is warped by a
  known motion drawn for that kind; the truth is the motion composed with the reference.

Pairs are drawn in turn from each source (a flight of 166 pairs does not outweigh one of 17), reproducibly
from ``seed``. Every method sees the same 800-px grey pairs, interleaved by the runner; the result keeps each
answer's confidence and verdict (:mod:`udh_cli.bench.verdicts`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from udh_cli import geometry
from udh_cli.bench import runner
from udh_cli.bench.hard_pairs import FLIGHT_GROUP, MIN_REFERENCE_INLIERS, PAIRS_GROUP, SCORED_SIDE, ReferencePair, find_pairs
from udh_cli.bench.motions import MIN_OVERLAP, MOTION_KINDS, draw_motion, fits, move_pair
from udh_cli.bench.pairsets import PairSet
from udh_cli.bench.verdicts import KindScore, Reliability, kind_scores, reliabilities
from udh_cli.errors import UdhError

KINDS = (FLIGHT_GROUP, PAIRS_GROUP) + MOTION_KINDS
DEFAULT_METHODS = ("unsupervised", "auto", "sift")  # the network alone, the default, and the classical reference
DRAWS_PER_PAIR = 20  # motions tried on a pair before another pair is taken: some leave A too little of B


@dataclass
class HardResult:
    """One ``udh bench hard`` run.

    Attributes:
        runs: one :class:`~udh_cli.bench.runner.MethodRun` per (kind, method); ``set_name`` is the kind.
        scores: failures, verified and verified-but-wrong per kind and method, then per method over all kinds.
        curves: the reliability diagram's bins, one per method, all kinds pooled.
        labels: kind -> the pairs' labels (source, files and the motion laid on them), in run order.
        config: how the run was set up, JSON-ready.
        notes: what the table's footer says (sources, skipped folders, the reference caveat).
    """

    runs: list[runner.MethodRun]
    scores: list[KindScore]
    curves: list[Reliability]
    labels: dict[str, list[str]]
    config: dict[str, Any]
    notes: list[str] = field(default_factory=list)


def _in_turn(pairs: list[ReferencePair], members: list[int], rng: np.random.Generator) -> list[int]:
    """``members`` reordered so that the sources take turns (each source's own pairs shuffled)."""
    by_source: dict[str, list[int]] = {}
    for i in members:
        by_source.setdefault(pairs[i].source, []).append(i)
    queues = [list(rng.permutation(v)) for _, v in sorted(by_source.items())]
    order = []
    while any(queues):
        for queue in queues:
            if queue:
                order.append(int(queue.pop(0)))
    return order


class _Loaded:
    """Reference pairs read once at the scored size, shared by every kind that draws them."""

    def __init__(self, pairs: list[ReferencePair]):
        self.pairs, self.cache = pairs, {}

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if i not in self.cache:
            self.cache[i] = self.pairs[i].load(SCORED_SIDE)
        return self.cache[i]


def _size(image: np.ndarray) -> tuple[int, int]:
    return image.shape[1], image.shape[0]


def build_sets(pairs: list[ReferencePair], count: int, seed: int, kinds: tuple[str, ...] = KINDS) -> tuple[list[PairSet], list[str]]:
    """Up to ``count`` pairs per kind (see the module docstring), and notes on kinds left short."""
    loaded, sets, notes = _Loaded(pairs), [], []
    for k, kind in enumerate(kinds):
        rng = np.random.default_rng([seed, k])
        if kind in (FLIGHT_GROUP, PAIRS_GROUP):
            order = _in_turn(pairs, [i for i, p in enumerate(pairs) if p.group == kind], rng)
            valid = (i for i in order if geometry.is_valid_homography(loaded[i][2], *_size(loaded[i][0])))
            picked = [(i, None) for i in itertools.islice(valid, count)]  # read only the pairs kept
        else:
            order = _in_turn(pairs, list(range(len(pairs))), rng)
            picked = []
            for i in itertools.islice(itertools.cycle(order), 3 * count):  # pairs are reused with new motions
                a, b, reference = loaded[i]
                for _ in range(DRAWS_PER_PAIR):
                    motion = draw_motion(kind, rng)
                    if fits(motion.homography(_size(b)) @ reference, _size(a), _size(b)):
                        picked.append((i, motion))
                        break
                if len(picked) == count:
                    break
        if not picked:
            notes.append(f"{kind}: no pairs (no source gave one that fits)")
            continue
        if len(picked) < count:
            notes.append(f"{kind}: {len(picked)} pairs, fewer than --n {count}")
        sets.append(_pair_set(kind, picked, loaded))
    return sets, notes


def _pair_set(kind: str, picked: list, loaded: _Loaded) -> PairSet:
    images_a, images_b, truths, labels = [], [], [], []
    for i, motion in picked:
        a, b, reference = loaded[i]
        label = f"{loaded.pairs[i].source}/{loaded.pairs[i].label}"
        if motion is not None:
            b, reference = move_pair(b, reference, motion.homography(_size(b)))
            label += f" ({motion.describe()})"
        images_a.append(a)
        images_b.append(b)
        truths.append(reference)
        labels.append(label)
    return PairSet(name=kind, images_a=images_a, images_b=images_b, truths=np.stack(truths), labels=labels)


def run_hard_bench(
    sources: list[Path],
    methods: list[str] | None = None,
    count: int = 20,
    seed: int = 0,
    prefix: str | None = None,
    min_inliers: int = MIN_REFERENCE_INLIERS,
    options: dict[str, dict[str, Any]] | None = None,
    show_progress: bool = True,
) -> HardResult:
    """Benchmark ``methods`` (default :data:`DEFAULT_METHODS`) on ``count`` pairs per kind from ``sources``
    (see :mod:`udh_cli.bench.hard_pairs`; ``prefix`` picks an Oxford folder's image series)."""
    if not sources:
        raise UdhError("no pair sources given; name a pairs CSV, a flight folder or an Oxford folder (or folders of them)")
    if count < 1:
        raise UdhError(f"--n {count}: need at least one pair per kind")
    methods = methods or list(DEFAULT_METHODS)
    jobs = runner.make_jobs(methods, ["image"], [], options)  # unknown methods and missing models fail first
    pairs, notes = find_pairs(sources, prefix, min_inliers)
    sets, short = build_sets(pairs, count, seed)
    runs = runner.run_jobs(jobs, sets, show_progress=show_progress)
    config = {"sources": [str(s) for s in sources], "methods": methods, "n": count, "seed": seed, "prefix": prefix,
              "min_reference_inliers": min_inliers, "scored_side_px": SCORED_SIDE, "min_overlap": MIN_OVERLAP,
              "options": options or {}, "reference_pairs": len(pairs),
              "sources_used": sorted({p.source for p in pairs})}
    notes = notes + short + [
        f"Pairs: {len(pairs)} reference pairs from {', '.join(config['sources_used'])}; seed {seed}. Images are grey and "
        f"shrunk to {SCORED_SIDE} px on the longer side; errors are in those pixels of B.",
        "References of the flights and uav-mountain are SIFT+RANSAC fits, not ground truth (graf's is): errors measure "
        "agreement with them, which favours SIFT, and the moved pairs inherit their error.",
    ]
    return HardResult(runs, kind_scores(runs), reliabilities(runs), {s.name: s.labels for s in sets}, config, notes)
