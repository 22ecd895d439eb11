"""Benchmark figures: pure functions from per-pair errors and times to the numbers the paper reports.

Scoring rules (the table footer repeats them):

* The error of a pair is measured at the four corners of image A (for synthetic pairs, the 128x128 patch),
  in pixels of B, with :func:`udh_cli.geometry.mace` (the mean corner distance) and
  :func:`udh_cli.geometry.corner_rmse` (the paper's 4-point RMSE).
* A pair the method gives **no answer** for is scored as if the method had answered "no motion" (the
  identity, which is what a caller falls back to). Its error therefore stays finite and it is **included**
  in every statistic: a method cannot look accurate by refusing the hard pairs.
* A pair is a **failure** when there is no answer or its MACE exceeds ``FAIL_PX`` (10 px). Failures
  are counted in the failure rate and also stay in the means, medians and percentile buckets with their
  error.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from udh_cli import geometry

FAIL_PX = 10.0  # a MACE above this is a failure, as in the issue ("an error over 10 px")
BUCKETS = ((0, 30), (30, 60), (60, 100))  # the paper's percentile buckets, in percent of pairs (best first)


def pair_errors(
    estimates: list[np.ndarray | None], truths: np.ndarray, sizes_a: list[tuple[int, int]], fallbacks: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pair MACE and RMSE, with the no-answer rule applied.

    Args:
        estimates: N ``b_from_a`` (3, 3) or ``None`` for no answer.
        truths: (N, 3, 3) true ``b_from_a``.
        sizes_a: N ``(width, height)`` of image A, whose corners are measured.
        fallbacks: N (3, 3) homographies scored in place of a missing answer (the identity).

    Returns:
        ``(mace, rmse, answered)``: (N,) float64 pixels, (N,) float64 pixels, (N,) bool.
    """
    n = len(estimates)
    mace = np.empty(n)
    rmse = np.empty(n)
    answered = np.array([h is not None for h in estimates], dtype=bool)
    for i, (estimate, truth, (w, h), fallback) in enumerate(zip(estimates, truths, sizes_a, fallbacks)):
        scored = np.asarray(estimate if estimate is not None else fallback, dtype=np.float64)
        mace[i] = float(geometry.mace(scored, np.asarray(truth, np.float64), w, h))
        rmse[i] = float(geometry.corner_rmse(scored, np.asarray(truth, np.float64), w, h))
    # A valid homography can still send a corner absurdly far; keep it, but never as NaN.
    mace[~np.isfinite(mace)] = np.inf
    rmse[~np.isfinite(rmse)] = np.inf
    return mace, rmse, answered


def failures(mace: np.ndarray, answered: np.ndarray, fail_px: float = FAIL_PX) -> np.ndarray:
    """(N,) bool: no answer, or a MACE above ``fail_px``."""
    return ~np.asarray(answered, bool) | ~(np.asarray(mace) <= fail_px)


def bucket_means(errors: np.ndarray, buckets: tuple[tuple[int, int], ...] = BUCKETS) -> list[float]:
    """Mean error of each percentile bucket of the pairs sorted best first.

    Bucket ``(lo, hi)`` holds the sorted pairs with index in ``[round(lo*N/100), round(hi*N/100))``, so the
    buckets split the pairs exactly (10 pairs: 3, 3 and 4). An empty bucket gives NaN.
    """
    ordered = np.sort(np.asarray(errors, dtype=np.float64))
    n = len(ordered)
    means = []
    for lo, hi in buckets:
        part = ordered[int(round(lo * n / 100)) : int(round(hi * n / 100))]
        means.append(float(part.mean()) if len(part) else float("nan"))
    return means


def percentile_profile(errors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The curve of the paper's figure 4: ``(percent, error)``, errors sorted best first.

    ``percent[i]`` is the centre of pair ``i``'s share of the set, ``100 (i + 0.5) / N``.
    """
    ordered = np.sort(np.asarray(errors, dtype=np.float64))
    percent = 100.0 * (np.arange(len(ordered)) + 0.5) / max(len(ordered), 1)
    return percent, ordered


@dataclass(frozen=True)
class Summary:
    """The figures reported for one method on one set of pairs. Errors in pixels, times in milliseconds."""

    pairs: int
    mace_mean: float
    mace_median: float
    rmse_mean: float
    bucket_0_30: float
    bucket_30_60: float
    bucket_60_100: float
    mace_p95: float
    failure_rate: float  # share of pairs, 0..1: no answer or MACE > FAIL_PX
    no_answer_rate: float  # share of pairs, 0..1, with no answer at all
    time_median_ms: float
    time_mean_ms: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def summarize(
    mace: np.ndarray, rmse: np.ndarray, answered: np.ndarray, elapsed_ms: np.ndarray, fail_px: float = FAIL_PX
) -> Summary:
    """All reported figures from per-pair arrays of equal length N (see :func:`pair_errors`)."""
    mace = np.asarray(mace, dtype=np.float64)
    if len(mace) == 0:
        raise ValueError("no pairs to summarise")
    buckets = bucket_means(mace)
    elapsed_ms = np.asarray(elapsed_ms, dtype=np.float64)
    return Summary(
        pairs=len(mace),
        mace_mean=float(mace.mean()),
        mace_median=float(np.median(mace)),
        rmse_mean=float(np.mean(rmse)),
        bucket_0_30=buckets[0],
        bucket_30_60=buckets[1],
        bucket_60_100=buckets[2],
        mace_p95=float(np.percentile(mace, 95)),
        failure_rate=float(failures(mace, answered, fail_px).mean()),
        no_answer_rate=float((~np.asarray(answered, bool)).mean()),
        time_median_ms=float(np.median(elapsed_ms)),
        time_mean_ms=float(np.mean(elapsed_ms)),
    )
