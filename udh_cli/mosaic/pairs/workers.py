"""Where the mosaic's pair estimates run: in this process, in a pool of local processes, or on a Dask cluster.

A job is one batch of working-size image pairs and the mosaic's opinions (its method, then ``--fallback``): the
first on all of them, each next one on those still doubted; it comes back as the estimates and the acceptance
verdicts, matrices and scores only. Workers build each estimator
once, from its registry name and options, and keep it for every later batch: the networks load once per
worker, not once per pair.

Why Dask (``dask.distributed``) and not Ray: the work is a few thousand independent, short, numpy-in
numpy-out tasks, which Dask's futures serve with no cluster service beyond ``dask scheduler`` and
``dask worker``, both pip-installable anywhere udh is; Ray's actors and object store would add a daemon for
no gain here.
"""

from __future__ import annotations

import os
import re
import sys
import threading
from collections import deque
from contextlib import contextmanager
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.estimators import Estimate, Estimator
from udh_cli.estimators.pair import PreparedPair
from udh_cli.processes import die_with_parent

ImagePair = tuple[np.ndarray, np.ndarray]  # working-size images A and B, as sent to a worker
Judged = tuple[Estimate, "float | None", "str | None"]  # the estimate, its verification score, why it is doubted
# Per pair: the first opinion's judged answer, then each next opinion's while the answers were doubted.
Attempts = list[Judged]
Opinion = tuple[str, dict[str, Any]]  # an estimator by registry name and options


@dataclass(frozen=True)
class EstimatorSpec:
    """How a worker builds the mosaic's opinions, in order: registry names and options; and the acceptance test.

    ``acceptance`` is a :class:`~udh_cli.mosaic.pairs.types.Acceptance`."""

    opinions: tuple[Opinion, ...]
    acceptance: Any = None

    def estimators_key(self) -> str:
        """What the estimators depend on (not the acceptance test, which is applied to their answers)."""
        return repr([(name, sorted(options.items())) for name, options in self.opinions])


def judge_batch(method: Estimator, acceptance, pairs: Sequence[PreparedPair]) -> list[Judged]:
    """Estimate ``pairs`` (working-size images) with ``method`` and judge each answer (:class:`Acceptance`)."""
    estimates = estimate_many_safely(method, list(pairs))
    out = []
    for pair, estimate in zip(pairs, estimates):
        verified, doubt = acceptance.judge(estimate, pair.a, pair.b, method.verifies_itself)
        out.append((estimate, verified, doubt))
    return out


def judge_opinions(opinions: Sequence[Estimator], acceptance, pairs: Sequence[ImagePair],
                   from_prediction: Sequence[bool] | None = None) -> list[Attempts]:
    """One job: the first opinion on every pair, then each next one on the pairs every earlier one left doubted.
    All in the same job, so that a doubted batch never waits in the queue behind other batches for its second
    opinion. Each pair is prepared once (:mod:`udh_cli.estimators.pair`) for every opinion and the acceptance
    test. The pairs marked in ``from_prediction`` (pre-warped loop pairs) are first confirmed from the prediction
    (:mod:`.confirm`), and ask the opinions near their prior (:meth:`~udh_cli.estimators.Estimator.near_prior`)
    only when that is doubted."""
    from udh_cli.mosaic.pairs.confirm import PREDICTION_CHECK  # here: the cascade's modules load when a job runs, not on import

    pairs = [PreparedPair.of(a, b) for a, b in pairs]
    out: list[Attempts] = [[] for _ in pairs]
    confirming = [i for i, marked in enumerate(from_prediction or []) if marked]
    for i, judged in zip(confirming, judge_batch(PREDICTION_CHECK, acceptance, [pairs[i] for i in confirming])):
        out[i].append(judged)
    doubted = [i for i in range(len(pairs)) if not out[i] or out[i][-1][2] is not None]
    marked = set(confirming)
    # A pre-warped pair the prediction did not confirm asks the opinions without their far searches
    # (Estimator.near_prior): a loop pair must land near its prediction to be kept at all.
    prewarped = [i for i in doubted if i in marked]
    for group, asked in (([i for i in doubted if i not in marked], opinions),
                         (prewarped, [opinion.near_prior() for opinion in opinions] if prewarped else [])):
        for opinion in asked:
            if not group:
                break
            for i, judged in zip(group, judge_batch(opinion, acceptance, [pairs[i] for i in group])):
                out[i].append(judged)
            group = [i for i in group if out[i][-1][2] is not None]
    return out


def estimate_many_safely(method: Estimator, pairs: list[PreparedPair]) -> list[Estimate]:
    """``estimate_many``, but an estimator that raises (a bug, a runtime error) fails only its own pairs.

    Estimators report failures as estimates and never raise by contract; this keeps one broken pair from
    stopping a run of hundreds.
    """
    try:
        return method.estimate_pairs(pairs)
    except UdhError:
        raise  # a problem the user must fix (a missing model...): stop with its message
    except Exception:  # noqa: BLE001 - retry one by one so that only the offending pairs fail
        out = []
        for pair in pairs:
            try:
                out.append(method.estimate_pairs([pair])[0])
            except UdhError:
                raise
            except Exception as exc:  # noqa: BLE001
                out.append(Estimate(method.name, None, 0.0, 0.0, f"the estimator raised {type(exc).__name__}: {exc}"))
        return out


# The estimators a worker process has built, newest last; a long-lived Dask worker serving runs with other
# settings keeps only the last few, and the lock keeps two of its threads from building the same one twice.
_WORKER_ESTIMATORS: dict[str, tuple[Estimator, ...]] = {}
_WORKER_LOCK = threading.Lock()
_KEPT_SPECS = 2


def _worker_estimators(spec: EstimatorSpec) -> tuple[Estimator, ...]:
    """The spec's estimators, built once per worker process."""
    from udh_cli.estimators import create_estimator

    key = spec.estimators_key()
    with _WORKER_LOCK:
        if key not in _WORKER_ESTIMATORS:
            import cv2

            cv2.setNumThreads(1)  # one worker per core: OpenCV's own threads would fight the other workers
            _WORKER_ESTIMATORS[key] = tuple(create_estimator(name, **options) for name, options in spec.opinions)
            while len(_WORKER_ESTIMATORS) > _KEPT_SPECS:
                _WORKER_ESTIMATORS.pop(next(iter(_WORKER_ESTIMATORS)))
        return _WORKER_ESTIMATORS[key]


def warm_up_worker(spec: EstimatorSpec) -> None:
    """Build ``spec``'s estimators in this worker before its first batch (:class:`PoolRunner`)."""
    _worker_estimators(spec)


def judge_on_worker(spec: EstimatorSpec, pairs: Sequence[ImagePair], from_prediction: Sequence[bool] | None = None) -> list[Attempts]:
    """A worker's job: :func:`judge_opinions` with the spec's estimators."""
    return judge_opinions(_worker_estimators(spec), spec.acceptance, list(pairs), from_prediction)


class LocalRunner:
    """Runs each job in this process as soon as it is submitted, with the given estimator instances."""

    window = 1  # one job at a time, so an interrupt loses only the batch it stopped

    def __init__(self, opinions: Sequence[Estimator], acceptance):
        self.opinions, self.acceptance = tuple(opinions), acceptance

    def submit(self, pairs: Sequence[ImagePair], from_prediction: Sequence[bool] | None = None) -> Future:
        done: Future = Future()
        done.set_result(judge_opinions(self.opinions, self.acceptance, pairs, from_prediction))
        return done

    def result(self, future: Future) -> list[Attempts]:
        return future.result()

    def close(self, abort: bool = False) -> None:
        pass


_MAIN_GUARD = re.compile(r"""__name__\s*==\s*['"]__main__['"]|['"]__main__['"]\s*==\s*__name__""")


def unguarded_script() -> str | None:
    """The main script's path when it has no ``if __name__ == "__main__":`` guard, else None.

    Why: a spawned worker imports the main script again, and one without the guard runs its top level there,
    so each worker would start the mosaic once more and die while starting its own pool, which the pool only
    reports as a worker that died. Interactive sessions and notebooks have no script and need no guard.
    """
    main = sys.modules.get("__main__")
    path, spec = getattr(main, "__file__", None), getattr(main, "__spec__", None)
    if not path or (spec is not None and spec.name.split(".")[-1] == "__main__"):  # `python -m package`: never run again there
        return None
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:  # a frozen or vanished script: nothing to tell by
        return None
    return None if _MAIN_GUARD.search(text) else str(path)


def check_main_guard(what: str) -> None:
    """Refuse to start worker processes from a script without the ``__main__`` guard (:func:`unguarded_script`)."""
    script = unguarded_script()
    if script is not None:
        raise UdhError(f"{what} starts worker processes, which import {script} again: put the call under "
                       "'if __name__ == \"__main__\":' in that script, or use workers=1")


class PoolRunner:
    """Runs jobs in ``workers`` local processes (one onnxruntime and OpenCV thread each)."""

    def __init__(self, spec: EstimatorSpec, workers: int):
        import multiprocessing

        check_main_guard(f"workers={workers}")
        self.spec = _single_threaded(spec)
        self.window = 2 * workers  # a batch queued behind each running one keeps every worker busy
        # spawn, not fork: a forked onnxruntime or OpenCV thread pool can hang its child.
        self.pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=die_with_parent, initargs=(os.getpid(),))
        # Start every worker now, each building its estimators, while this process reads the frames: starting one
        # (Python, onnxruntime, the networks) is slow, and the first pairs would otherwise wait for it.
        # A warm-up's error is left to the first batch, which meets it again and says it.
        for _ in range(workers):
            self.pool.submit(warm_up_worker, self.spec)

    def submit(self, pairs: Sequence[ImagePair], from_prediction: Sequence[bool] | None = None) -> Future:
        return self.pool.submit(judge_on_worker, self.spec, list(pairs), from_prediction)

    def result(self, future: Future) -> list[Attempts]:
        from concurrent.futures.process import BrokenProcessPool

        try:
            return future.result()
        except BrokenProcessPool:
            raise UdhError("a worker process died (out of memory?); run again with fewer --workers or a smaller --work-size, "
                           "and --resume to keep the pairs already estimated") from None

    def close(self, abort: bool = False) -> None:
        # On an interrupt the batches still running are abandoned: their pairs are estimated again on --resume.
        self.pool.shutdown(wait=not abort, cancel_futures=True)


class DaskRunner:
    """Runs jobs on a Dask cluster (``dask.distributed``): ``scheduler`` is its address, e.g. ``tcp://host:8786``."""

    def __init__(self, spec: EstimatorSpec, scheduler: str, timeout_s: float = 10.0):
        try:
            from distributed import Client
        except ImportError:
            raise UdhError("--scheduler needs Dask: pip install 'dask[distributed]' (from the udh checkout: pip install '.[cluster]')") from None
        try:
            _handshake(scheduler, timeout_s)
            self.client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError, ValueError) as exc:
            raise UdhError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc}); start one with `dask scheduler` "
                           f"and workers with `dask worker {scheduler}`") from None
        self.scheduler = scheduler
        self.spec = _single_threaded(spec)
        self.window = 2 * max(1, sum(self.client.nthreads().values()))

    def submit(self, pairs: Sequence[ImagePair], from_prediction: Sequence[bool] | None = None) -> Future:
        # The images go straight to a worker, not into the task graph through the scheduler.
        images = self.client.scatter(list(pairs), direct=True)
        return self.client.submit(judge_on_worker, self.spec, images, from_prediction, pure=False)

    def result(self, future: Future) -> list[Attempts]:
        try:
            return future.result()
        except UdhError:
            raise
        except Exception as exc:  # noqa: BLE001 - a lost worker or connection: one line, and how to go on
            raise UdhError(f"--scheduler {self.scheduler}: the cluster failed a batch ({type(exc).__name__}: {exc}); "
                           f"check the workers, and run again with --resume to keep the pairs already estimated") from None

    def close(self, abort: bool = False) -> None:
        self.client.close()


def _handshake(scheduler: str, timeout_s: float) -> None:
    """Connect to ``scheduler`` and exchange Dask's handshake within ``timeout_s`` seconds, or raise TimeoutError.

    Why: ``distributed``'s connect bounds the TCP connection but not the handshake after it, so a server that
    accepts and never answers would hold the run for ever. It runs on a thread of its own, whose event loop is
    its own even when the caller's thread runs one (a notebook). It connects as ``Client`` does: with the client
    role's TLS settings from Dask's config (``distributed.comm.tls.*``), so that a ``tls://`` scheduler accepts it."""
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    connection_args = Security().get_connection_args("client")

    async def exchange() -> None:
        comm = await asyncio.wait_for(connect(scheduler, timeout=timeout_s, **connection_args), timeout_s)
        await comm.close()

    failure: list[BaseException] = []

    def run() -> None:
        try:
            asyncio.run(exchange())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            failure.append(exc)

    thread = threading.Thread(target=run, name="udh-dask-handshake", daemon=True)
    thread.start()
    thread.join(timeout_s + 5)  # wait_for ends the exchange at timeout_s; this only guards a loop that never returns
    if thread.is_alive():
        raise TimeoutError(f"no handshake within {timeout_s:g} s")
    if failure:
        exc = failure[0]
        if isinstance(exc, asyncio.TimeoutError):
            raise TimeoutError(f"no handshake within {timeout_s:g} s")
        if isinstance(exc, (OSError, ValueError, TimeoutError)):
            raise exc
        raise OSError(f"the handshake failed ({type(exc).__name__}: {exc})")


def _single_threaded(spec: EstimatorSpec) -> EstimatorSpec:
    """The spec with one onnxruntime thread for each method that takes ``threads``: a worker per core, not threads."""
    from dataclasses import replace

    from udh_cli.estimators.registry import with_option_default

    return replace(spec, opinions=tuple((name, with_option_default(name, options, "threads", 1, none_is_unset=True)) for name, options in spec.opinions))


# workers=None: one process per core, at most MAX_AUTO_WORKERS, for a flight of POOL_MIN_FRAMES frames or more.
# Why: a pool pays for its start (spawning, imports, loading the networks) only over enough pairs (docs/mosaic.md,
# "Both cores, or a cluster"), and each worker holds its own networks and feature cache (up to about 0.5 GB).
MAX_AUTO_WORKERS = 4
POOL_MIN_FRAMES = 30


def available_cores() -> int:
    """The cores this process may run on (a container or ``taskset`` may allow fewer than the machine has)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def automatic_workers(frames: int) -> int:
    """Local processes for a flight of ``frames`` frames when none are asked for (see :data:`POOL_MIN_FRAMES`)."""
    return min(available_cores(), MAX_AUTO_WORKERS) if frames >= POOL_MIN_FRAMES else 1


def open_runner(opinions: Sequence[Estimator], acceptance, spec: EstimatorSpec | None, workers: int,
                scheduler: str | None, warn: Callable[[str], None] = lambda message: None) -> LocalRunner | PoolRunner | DaskRunner:
    """The runner for a mosaic: Dask with a ``scheduler``, a process pool with ``workers`` > 1, else local.
    Without a ``spec`` (estimators given as instances, not by name) only the local runner can run them."""
    if spec is None and (workers > 1 or scheduler is not None):
        warn("the estimators were given as objects, not by name: pairs are estimated in this process (no --workers, no --scheduler)")
    if scheduler is not None and spec is not None:
        if workers > 1:
            warn(f"--workers {workers} is ignored with --scheduler: the cluster's workers estimate the pairs")
        return DaskRunner(spec, scheduler)
    workers = min(workers, available_cores())
    if spec is None or workers <= 1:
        return LocalRunner(opinions, acceptance)
    return PoolRunner(spec, workers)


@contextmanager
def closed_after(runner: LocalRunner | PoolRunner | DaskRunner) -> Iterator[None]:
    """Close ``runner`` when the block ends; abandon its batches in flight when it ends by an error or interrupt."""
    try:
        yield
    except BaseException:
        runner.close(abort=True)
        raise
    runner.close()


def in_order(jobs: Sequence[Callable[[], Future]], window: int):
    """Start ``jobs`` keeping up to ``window`` in flight, and yield ``(index, future)`` in submission order; the
    caller waits for each (``runner.result``) before the next job starts."""
    window = max(1, window)
    started: deque[tuple[int, Future]] = deque()
    next_job = 0
    while next_job < len(jobs) or started:
        while next_job < len(jobs) and len(started) < window:
            started.append((next_job, jobs[next_job]()))
            next_job += 1
        yield started.popleft()
