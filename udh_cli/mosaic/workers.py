"""Where the mosaic's pair estimates run: in this process, in a pool of local processes, or on a Dask cluster.

A job is one batch of working-size image pairs for one method (the first method or the fallback); it comes
back as the estimates and the acceptance verdicts, matrices and scores only. Workers build each estimator
once, from its registry name and options, and keep it for every later batch: the networks load once per
worker, not once per pair.

Why Dask (``dask.distributed``) and not Ray: the work is a few thousand independent, short, numpy-in
numpy-out tasks, which Dask's futures serve with no cluster service beyond ``dask scheduler`` and
``dask worker``, both pip-installable anywhere udh is; Ray's actors and object store would add a daemon for
no gain here.
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.estimators import Estimate, Estimator

ImagePair = tuple[np.ndarray, np.ndarray]
Judged = tuple[Estimate, "float | None", "str | None"]  # the estimate, its verification score, why it is doubted


@dataclass(frozen=True)
class EstimatorSpec:
    """How a worker builds the mosaic's estimators: registry names and options, and the acceptance test.

    ``acceptance`` is a :class:`~udh_cli.mosaic.pairwise.Acceptance`."""

    method: str
    options: dict[str, Any] = field(default_factory=dict)
    fallback: str | None = None
    acceptance: Any = None

    def key(self) -> str:
        return repr((self.method, sorted(self.options.items()), self.fallback, self.acceptance))


def judge_batch(method: Estimator, acceptance, pairs: Sequence[ImagePair]) -> list[Judged]:
    """Estimate ``pairs`` (working-size images) with ``method`` and judge each answer (:class:`Acceptance`)."""
    estimates = estimate_many_safely(method, list(pairs))
    out = []
    for (image_a, image_b), estimate in zip(pairs, estimates):
        verified, doubt = acceptance.judge(estimate, image_a, image_b, method.verifies_itself)
        out.append((estimate, verified, doubt))
    return out


def estimate_many_safely(method: Estimator, pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[Estimate]:
    """``estimate_many``, but an estimator that raises (a bug, a runtime error) fails only its own pairs.

    Estimators report failures as estimates and never raise by contract; this keeps one broken pair from
    stopping a run of hundreds.
    """
    try:
        return method.estimate_many(pairs)
    except UdhError:
        raise  # a problem the user must fix (a missing model...): stop with its message
    except Exception:  # noqa: BLE001 - retry one by one so that only the offending pairs fail
        out = []
        for a, b in pairs:
            try:
                out.append(method.estimate(a, b))
            except UdhError:
                raise
            except Exception as exc:  # noqa: BLE001
                out.append(Estimate(method.name, None, 0.0, 0.0, f"the estimator raised {type(exc).__name__}: {exc}"))
        return out


_WORKER_ESTIMATORS: dict[str, tuple[Estimator, Estimator | None]] = {}


def _worker_estimators(spec: EstimatorSpec) -> tuple[Estimator, Estimator | None]:
    """The spec's estimators, built once per worker process."""
    from udh_cli.estimators import create_estimator

    key = spec.key()
    if key not in _WORKER_ESTIMATORS:
        import cv2

        cv2.setNumThreads(1)  # one worker per core: OpenCV's own threads would fight the other workers
        method = create_estimator(spec.method, **spec.options)
        fallback = create_estimator(spec.fallback) if spec.fallback else None
        _WORKER_ESTIMATORS[key] = (method, fallback)
    return _WORKER_ESTIMATORS[key]


def judge_on_worker(spec: EstimatorSpec, attempt: int, pairs: Sequence[ImagePair]) -> list[Judged]:
    """A worker's job: ``attempt`` 0 runs the first method, 1 the fallback."""
    method, fallback = _worker_estimators(spec)
    return judge_batch(method if attempt == 0 else fallback, spec.acceptance, pairs)


class LocalRunner:
    """Runs every job at once, in this process, with the given estimator instances."""

    window = 1  # a job runs when submitted: one at a time, so an interrupt loses only the batch it stopped

    def __init__(self, estimator: Estimator, fallback: Estimator | None, acceptance):
        self.methods = (estimator, fallback)
        self.acceptance = acceptance

    def submit(self, attempt: int, pairs: Sequence[ImagePair]) -> Future:
        done: Future = Future()
        done.set_result(judge_batch(self.methods[attempt], self.acceptance, pairs))
        return done

    def close(self) -> None:
        pass


class PoolRunner:
    """Runs jobs in ``workers`` local processes (one onnxruntime and OpenCV thread each)."""

    def __init__(self, spec: EstimatorSpec, workers: int):
        import multiprocessing

        self.spec = _single_threaded(spec)
        self.window = 2 * workers  # a batch queued behind each running one keeps every worker busy
        # spawn, not fork: a forked onnxruntime or OpenCV thread pool can hang its child.
        self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))

    def submit(self, attempt: int, pairs: Sequence[ImagePair]) -> Future:
        return self.pool.submit(judge_on_worker, self.spec, attempt, list(pairs))

    def close(self) -> None:
        self.pool.shutdown(cancel_futures=True)


class DaskRunner:
    """Runs jobs on a Dask cluster (``dask.distributed``): ``scheduler`` is its address, e.g. ``tcp://host:8786``."""

    def __init__(self, spec: EstimatorSpec, scheduler: str):
        try:
            from distributed import Client
        except ImportError:
            raise UdhError("--scheduler needs Dask: pip install 'dask[distributed]' (from the udh checkout: pip install '.[cluster]')") from None
        try:
            self.client = Client(scheduler, timeout=10)
        except (OSError, TimeoutError) as exc:
            raise UdhError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc}); start one with `dask scheduler` "
                           f"and workers with `dask worker {scheduler}`") from None
        self.spec = _single_threaded(spec)
        self.window = 2 * max(1, sum(self.client.nthreads().values()))

    def submit(self, attempt: int, pairs: Sequence[ImagePair]) -> Future:
        return self.client.submit(judge_on_worker, self.spec, attempt, list(pairs), pure=False)

    def close(self) -> None:
        self.client.close()


def _single_threaded(spec: EstimatorSpec) -> EstimatorSpec:
    """The spec with one onnxruntime thread where the method takes ``threads``: a worker per core, not threads."""
    from udh_cli.estimators.registry import estimator_options

    if "threads" in estimator_options(spec.method) and spec.options.get("threads") is None:
        return EstimatorSpec(spec.method, {**spec.options, "threads": 1}, spec.fallback, spec.acceptance)
    return spec


def open_runner(estimator: Estimator, fallback: Estimator | None, acceptance, spec: EstimatorSpec | None, workers: int,
                scheduler: str | None) -> LocalRunner | PoolRunner | DaskRunner:
    """The runner for a mosaic: Dask with a ``scheduler``, a process pool with ``workers`` > 1, else local.
    Without a ``spec`` (estimators given as instances, not by name) only the local runner can run them."""
    if spec is None or (workers <= 1 and scheduler is None):
        return LocalRunner(estimator, fallback, acceptance)
    if scheduler is not None:
        return DaskRunner(spec, scheduler)
    return PoolRunner(spec, min(workers, os.cpu_count() or 1))


def in_order(jobs: Sequence[Callable[[], Future]], window: int):
    """Start ``jobs`` keeping up to ``window`` in flight, and yield ``(index, future)`` in submission order,
    each once it is done."""
    started: deque[tuple[int, Future]] = deque()
    next_job = 0
    while next_job < len(jobs) or started:
        while next_job < len(jobs) and len(started) < window:
            started.append((next_job, jobs[next_job]()))
            next_job += 1
        index, future = started.popleft()
        future.result()
        yield index, future
