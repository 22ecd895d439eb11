"""Run estimators over pair sets: every method on the same pairs, interleaved, timed after a warm-up.

Methods are created by name through :func:`udh_cli.estimators.registry.create_estimator` and called
only through :meth:`Estimator.estimate_many`, so a newly registered method needs no change here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from udh_cli.bench import metrics
from udh_cli.bench.pairsets import PairSet
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimate, Estimator, create_estimator

BATCH = 32  # pairs per estimate_many call: big enough for batched (learned) estimators, small for the bar
WARMUP_PAIRS = 3  # pairs each method runs untimed first (lazy model loading, caches, allocation)
INPUTS = ("patch", "full")  # what a synthetic pair can show a method; real pairs show the given "image"


@dataclass
class Job:
    """One method shown one kind of input: a row of the table per pair set."""

    method: str
    input: str  # "patch", "full" or "image"
    estimator: Estimator

    @property
    def label(self) -> str:
        return self.method if self.input != "full" else f"{self.method} (full)"


@dataclass
class MethodRun:
    """Per-pair results and the summary of one job on one pair set.

    Attributes:
        mace, rmse: (N,) pixel errors at the scored corners (no answer scored as no motion).
        answered: (N,) bool.
        elapsed_ms: (N,) the estimator's own time per pair (``Estimate.elapsed_ms``).
        failures: (N,) the reason for each missing answer, ``""`` where there is an answer.
        wall_ms_per_pair: wall-clock time of all this job's ``estimate_many`` calls over N, milliseconds.
        sift_ratio: median time over SIFT's median time on the same set and input (``None`` without SIFT).
        confidence: (N,) each answer's ``Estimate.confidence`` (0 for no answer).
        verdicts: (N,) int8, each answer's ``Estimate.verified``: 1 True, 0 False, -1 None (the method does not judge).
    """

    set_name: str
    rho: float | None
    method: str
    input: str
    mace: np.ndarray
    rmse: np.ndarray
    answered: np.ndarray
    elapsed_ms: np.ndarray
    failures: list[str]
    wall_ms_per_pair: float
    summary: metrics.Summary
    sift_ratio: float | None = None
    confidence: np.ndarray | None = None
    verdicts: np.ndarray | None = None

    @property
    def label(self) -> str:
        return self.method if self.input != "full" else f"{self.method} (full)"


def parse_methods(text: str) -> list[str]:
    """``"sift, orb,ecc"`` -> ``["sift", "orb", "ecc"]``, without duplicates; an empty list is an error."""
    names = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    if not names:
        raise UdhError("--methods is empty; name at least one method, e.g. --methods sift,orb,ecc")
    return names


def make_jobs(
    methods: list[str], inputs: list[str], full_methods: list[str], options: dict[str, dict[str, Any]] | None = None
) -> list[Job]:
    """Create every estimator up front, so that an unknown method or a missing model fails before any work.

    Args:
        methods: registry names.
        inputs: the inputs each method gets: ``["image"]`` for real pairs, a subset of ``INPUTS`` for
            synthetic ones. ``"full"`` applies only to ``full_methods`` (the classical methods, as in
            the paper); every method gets ``"patch"`` when it is listed, and ``full_methods`` fall back to
            ``"full"`` only when it is not.
        options: per-method keyword options for :func:`create_estimator`, e.g. ``{"ecc": {"iterations": 200}}``.
    """
    options = options or {}
    unknown = [name for name in options if name not in methods]
    if unknown:
        raise UdhError(f"options given for {', '.join(unknown)}, which is not among --methods")
    jobs = []
    for name in methods:
        try:
            estimator = create_estimator(name, **options.get(name, {}))
        except UdhError as exc:
            if str(exc).startswith("unknown method"):
                raise
            about = str(exc) if str(exc).startswith(f"method '{name}'") else f"method '{name}': {exc}"
            raise UdhError(f"{about} (in udh bench, options reach a method as -O "
                           f"{name}.KEY=VALUE, e.g. -O {name}.model=PATH; or leave it out of --methods)") from None
        for kind in inputs:
            if kind == "full" and name not in full_methods:
                continue
            jobs.append(Job(name, kind, estimator))
        if not any(job.method == name for job in jobs):  # full-only mode: learned methods still get patches
            jobs.append(Job(name, "patch", estimator))
    return jobs


def _safe_estimate_many(estimator: Estimator, pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[Estimate]:
    """``estimate_many``, but a crash costs only the pairs it crashes on: they come back as failures."""
    try:
        results = estimator.estimate_many(pairs)
        if len(results) == len(pairs):
            return list(results)
    except Exception:  # noqa: BLE001 - retry one by one to find which pairs crash
        pass
    results = []
    for a, b in pairs:
        start = time.perf_counter()
        try:
            results.extend(estimator.estimate_many([(a, b)]))
        except Exception as exc:  # noqa: BLE001 - a crash on one pair is a failure of that pair
            elapsed = (time.perf_counter() - start) * 1e3
            results.append(Estimate(estimator.name, None, 0.0, elapsed, f"crashed: {type(exc).__name__}: {exc}"))
    return results


def warm_up(jobs: list[Job], pair_set: PairSet) -> None:
    """Run every job untimed on the first pairs; a crash here is a setup problem and stops the run."""
    index = range(min(WARMUP_PAIRS, len(pair_set)))
    for job in jobs:
        try:
            job.estimator.estimate_many(pair_set.inputs(job.input, index))
        except UdhError as exc:
            raise UdhError(f"method '{job.method}' ({job.input} input) failed to start: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - report it as a setup error, in one line
            raise UdhError(f"method '{job.method}' ({job.input} input) crashed on its warm-up pairs: "
                           f"{type(exc).__name__}: {exc}") from None


def run_jobs(jobs: list[Job], pair_sets: list[PairSet], show_progress: bool = True) -> list[MethodRun]:
    """Run every job on every set, interleaving the jobs batch by batch so that load from other
    processes falls on all methods alike. Returns one :class:`MethodRun` per (set, job)."""
    for pair_set in pair_sets:
        if any(job.input == "full" for job in jobs) and pair_set.full_a is None:
            raise UdhError(f"{pair_set.name}: the pairs have no full frames; use --mode patch or regenerate them")
        if len(pair_set) == 0:
            raise UdhError(f"{pair_set.name}: no pairs to run")
    warm_up(jobs, pair_sets[0])
    total = sum(len(s) for s in pair_sets) * len(jobs)
    progress = Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("eta"), TimeRemainingColumn(), console=Console(stderr=True), disable=not show_progress,
    )
    runs: list[MethodRun] = []
    with progress:
        task = progress.add_task("bench", total=total)
        for pair_set in pair_sets:
            estimates: dict[int, list[Estimate]] = {k: [] for k in range(len(jobs))}
            wall = np.zeros(len(jobs))
            for start in range(0, len(pair_set), BATCH):
                index = range(start, min(start + BATCH, len(pair_set)))
                for k, job in enumerate(jobs):
                    progress.update(task, description=f"{pair_set.name}: {job.label}")
                    began = time.perf_counter()
                    estimates[k].extend(_safe_estimate_many(job.estimator, pair_set.inputs(job.input, index)))
                    wall[k] += time.perf_counter() - began
                    progress.advance(task, len(index))
            runs.extend(_score(job, pair_set, estimates[k], wall[k]) for k, job in enumerate(jobs))
    add_sift_ratios(runs)
    return runs


def _score(job: Job, pair_set: PairSet, estimates: list[Estimate], wall_s: float) -> MethodRun:
    scored = [pair_set.to_scored_frame(job.input, i, e.homography) for i, e in enumerate(estimates)]
    mace, rmse, answered = metrics.pair_errors(scored, pair_set.truths, pair_set.sizes_a(), pair_set.no_motion())
    elapsed = np.array([e.elapsed_ms for e in estimates], dtype=np.float64)
    return MethodRun(
        set_name=pair_set.name, rho=pair_set.rho, method=job.method, input=job.input, mace=mace, rmse=rmse,
        answered=answered, elapsed_ms=elapsed, failures=[(e.failure or "no answer") if not e.ok else "" for e in estimates],
        wall_ms_per_pair=1e3 * wall_s / len(pair_set), summary=metrics.summarize(mace, rmse, answered, elapsed),
        confidence=np.array([e.confidence for e in estimates], dtype=np.float64),
        verdicts=np.array([-1 if e.verified is None else int(e.verified) for e in estimates], dtype=np.int8),
    )


def add_sift_ratios(runs: list[MethodRun]) -> None:
    """Set each run's time ratio to SIFT on the same set: SIFT with the same input if it ran, else any SIFT."""
    for run in runs:
        sift = [r for r in runs if r.method == "sift" and r.set_name == run.set_name]
        same_input = [r for r in sift if r.input == run.input]
        reference = (same_input or sift or [None])[0]
        if reference is not None and reference.summary.time_median_ms > 0:
            run.sift_ratio = run.summary.time_median_ms / reference.summary.time_median_ms
