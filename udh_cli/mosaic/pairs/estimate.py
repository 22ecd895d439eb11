"""Pairwise estimation for the mosaic: batched through the estimators at the working size, each pair asked of the
mosaic's opinions in order (its method, then ``--fallback``) until one is accepted, and rescaled exactly to
full resolution (types: :mod:`.types`)."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.estimators import Estimator
from udh_cli.mosaic.inputs.frames import Frame
from udh_cli.mosaic.pairs.types import Acceptance, PairRequest, PairResult, full_resolution, work_inputs
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.pairs.workers import DaskRunner, LocalRunner, PoolRunner, in_order


def estimate_pairs(
    requests: Sequence[PairRequest],
    frames: Sequence[Frame],
    opinions: Sequence[Estimator],
    acceptance: Acceptance,
    reporter: Reporter,
    stage: str,
    batch_size: int = 16,
    cache: Any = None,
    runner: LocalRunner | PoolRunner | DaskRunner | None = None,
) -> list[PairResult]:
    """Estimate every request with the first of ``opinions``; a failed or doubtful (see :class:`Acceptance`) pair
    is asked of the next. Batches of up to ``batch_size`` pairs (:func:`even_batch_size`) go to ``estimate_pairs``
    so learned methods batch them.

    ``runner`` (:mod:`.workers`) runs the batches: in this process (the default, with ``opinions``), in a
    process pool or on a Dask cluster, several at once, each with the estimators it builds from their names
    (``opinions`` are then not used); results are taken in batch order, so they are the same either way.

    With a ``cache`` (a :class:`~udh_cli.mosaic.pairs.cache.PairCache`, which depends on this stage's types, so it
    is not imported here), a request whose key the cache holds is
    taken from it, and every finished batch is added to it and saved, so an interrupt loses at most the
    batches in flight. Batches are cut from ``requests`` the same way with or without cached pairs, so a
    resumed run hands the estimator the same batches as an uninterrupted one.
    """
    runner = runner or LocalRunner(opinions, acceptance)
    results = [PairResult(r.a, r.b, r.kind, prior=r.prior) for r in requests]
    batches = []
    size = even_batch_size(len(requests), batch_size, runner.window)
    with reporter.stage(stage, len(requests)) as advance:
        for start in range(0, len(requests), size):
            batch = []
            for i in range(start, min(start + size, len(requests))):
                cached = cache.lookup(requests[i]) if cache is not None else None
                if cached is None:
                    batch.append(i)
                else:
                    results[i] = cached
                    advance(1)
            if batch:
                batches.append(batch)
        inputs = {}

        def job(batch: list[int]):
            def submit():
                for i in batch:
                    inputs[i] = work_inputs(requests[i], frames)
                return runner.submit([inputs[i][:2] for i in batch], [requests[i].from_prediction for i in batch])
            return submit

        for index, future in in_order([job(b) for b in batches], window=runner.window):
            batch = batches[index]
            for i, attempts in zip(batch, runner.result(future)):
                _apply(i, attempts, requests, results, frames, inputs[i][2])
                del inputs[i]
            advance(len(batch))
            if cache is not None:
                for i in batch:
                    cache.add(requests[i], results[i])
                cache.save()
    return results


def even_batch_size(count: int, largest: int, window: int) -> int:
    """Pairs per batch for ``count`` pairs run ``window`` batches at a time: at most ``largest``, and few enough
    that the pairs make two batches per slot of the window. Why: a last batch larger than the others, or fewer
    batches than workers (a later loop round's few pairs), keeps one worker busy while the others wait
    (docs/benchmarks.md, "Speed"). An estimate does not depend on the batch it is in (tests/mosaic/pairs)."""
    return max(1, min(largest, math.ceil(count / (2 * max(1, window)))))


def _apply(i: int, attempts, requests: Sequence[PairRequest], results: list[PairResult], frames: Sequence[Frame], undo) -> None:
    """Record request ``i``'s judged attempts (:func:`.workers.judge_opinions`: the first opinion's, then each
    next one's while the answers were doubted); ``undo`` maps the estimate back to full resolution."""
    result = results[i]
    for estimate, verified, doubt in attempts:
        result.estimates.append(estimate)
        result.verified = verified
        if doubt is None:
            result.b_from_a = full_resolution(estimate, requests[i], frames, undo)
            result.status, result.reason, result.method = "ok", None, estimate.method
        else:
            result.reason = f"{estimate.method}: {doubt}"


def corner_disagreement_px(b_from_a: np.ndarray, other_b_from_a: np.ndarray, size_a: tuple[int, int]) -> float:
    """Mean distance in B's pixels between where two homographies put A's corners."""
    return float(geometry.mace(b_from_a, other_b_from_a, *size_a))
