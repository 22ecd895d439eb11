"""How fast a mosaic is, measured against a fixed workload timed in the same run (``udh bench speed``).

The reference workload decodes every frame of the folder and runs OpenCV SIFT on it at
:data:`REFERENCE_SIDE` px longest side on one thread. Dividing by it makes figures from different machines,
and from one machine under different loads, comparable. The mosaic is then run as ``udh mosaic`` would run it, and
the wall time of each of its stages (the ``timings_s`` its sidecar records) is given in seconds and as a
ratio of the reference. Optionally single consecutive pairs are timed too, every method on the same
pairs in one process, interleaved so that load from other jobs falls on all methods alike.
"""

from __future__ import annotations

import os
import platform
import statistics
import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator
from udh_cli.images import IMAGE_SUFFIXES

REFERENCE_SIDE = 800  # longest side, px, of the reference SIFT: the fixed workload that speed figures are divided by
PAIR_METHODS = ("unsupervised", "auto", "sift")  # --methods of the single-pair timing
MOSAIC_NAME = "mosaic.png"  # the name `udh mosaic` writes by default, so that writing costs what it costs there
UNSTAGED = "other"  # wall time outside the mosaic's named stages (setup, estimator loading, the sidecar)


@dataclass(frozen=True)
class ReferenceTiming:
    """The fixed workload: ``frames`` decoded and run through SIFT in ``seconds`` of wall time."""

    seconds: float
    frames: int
    keypoints: int  # total found, to show the work was done (SIFT on a blank frame costs nothing)


@dataclass(frozen=True)
class StageTiming:
    """One stage of the mosaic: wall ``seconds`` and ``ratio`` = seconds / the reference's seconds."""

    name: str
    seconds: float
    ratio: float


@dataclass(frozen=True)
class PairTiming:
    """One method on the timed consecutive pairs.

    Attributes:
        median_ms: median wall time of ``estimate`` per pair, milliseconds.
        sift_ratio: ``median_ms`` over SIFT's on the same pairs (``None`` when sift was not timed).
        answered: pairs with an answer (of ``pairs``).
        stage_ms: median milliseconds per stage of the network's path (``Estimate.details["stage_ms"]``),
            over the pairs where that stage ran; empty for methods that do not report stages.
        stage_pairs: for each key of ``stage_ms``, on how many pairs the stage ran.
        answered_by: how many answers each stage or opinion gave (``Estimate.stage``, e.g. network, sift).
    """

    method: str
    pairs: int
    median_ms: float
    sift_ratio: float | None
    answered: int
    stage_ms: dict[str, float] = field(default_factory=dict)
    stage_pairs: dict[str, int] = field(default_factory=dict)
    answered_by: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class SpeedResult:
    """A speed run: the reference, the mosaic's stages, its wall time and memory, and single pairs.

    Attributes:
        stages: the mosaic's stages in the order they ran, then :data:`UNSTAGED` for the rest of the wall time.
        wall_s: wall time of the whole ``run_mosaic`` call, seconds (the stages sum to it).
        peak_memory_mb: largest resident size of this process and of its largest finished child process, MiB.
        summary: the mosaic sidecar's summary (frames placed, pairs, parts).
    """

    folder: str
    method: str
    workers: int | None
    reference: ReferenceTiming
    stages: list[StageTiming]
    wall_s: float
    peak_memory_mb: dict[str, float]
    summary: dict[str, Any]
    pairs: list[PairTiming]
    machine: dict[str, Any]

    @property
    def ratio(self) -> float:
        """The whole mosaic's wall time over the reference's."""
        return self.wall_s / self.reference.seconds

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "ratio": self.ratio, "reference_side_px": REFERENCE_SIDE}


def frame_files(folder: str | Path) -> list[Path]:
    """The image files directly in ``folder``, sorted by name; raises :class:`UdhError` for fewer than two."""
    folder = Path(folder)
    if not folder.is_dir():
        raise UdhError(f"{folder}: no such folder; give a folder of a flight's frames")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if len(files) < 2:
        raise UdhError(f"{folder}: {len(files)} image file(s); a speed run needs a flight of at least two frames")
    return files


def time_reference(files: Sequence[Path]) -> ReferenceTiming:
    """Decode every file and run SIFT on it at :data:`REFERENCE_SIDE` px, on one OpenCV thread (restored after).
    Files that do not decode are left out of the count, as the mosaic leaves them out."""
    sift = cv2.SIFT_create()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    frames = keypoints = 0
    try:
        started = time.perf_counter()
        for path in files:
            image = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_GRAYSCALE)
            if image is None:
                continue
            scale = REFERENCE_SIDE / max(image.shape)
            size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
            small = cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
            found, _ = sift.detectAndCompute(small, None)
            frames, keypoints = frames + 1, keypoints + len(found)
        seconds = time.perf_counter() - started
    finally:
        cv2.setNumThreads(threads)
    if frames == 0:
        raise UdhError("none of the frames decodes; a speed run needs readable images")
    return ReferenceTiming(seconds, frames, keypoints)


def stage_timings(timings_s: dict[str, float], wall_s: float, reference_s: float) -> list[StageTiming]:
    """The sidecar's ``timings_s`` (its ``total`` left out) as stages with ratios to ``reference_s``, and the
    wall time no stage claims as :data:`UNSTAGED`."""
    named = [(name, float(seconds)) for name, seconds in timings_s.items() if name != "total"]
    rest = max(0.0, wall_s - sum(seconds for _, seconds in named))
    return [StageTiming(name, seconds, seconds / reference_s) for name, seconds in named + [(UNSTAGED, rest)]]


def peak_memory_mb() -> dict[str, float]:
    """Peak resident memory of this process (``self``) and of its largest finished child (``children``), MiB."""
    import resource

    to_mb = 1 / 1024 if platform.system() != "Darwin" else 1 / 2**20  # ru_maxrss is KiB on Linux, bytes on macOS
    return {"self": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * to_mb,
            "children": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * to_mb}


def machine() -> dict[str, Any]:
    """Where the run was measured: the CPU's name beside the benchmarks' usual environment."""
    from udh_cli.bench.report import environment

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as handle:
            cpu = next((line.split(":", 1)[1].strip() for line in handle if line.startswith("model name")), cpu)
    except OSError:  # not Linux: platform's name is the best there is
        pass
    return {"cpu": cpu or "unknown", **environment()}


def time_pairs(files: Sequence[Path], count: int, estimators: dict[str, Estimator]) -> list[PairTiming]:
    """Time ``estimate`` on the first ``count`` consecutive pairs of ``files`` (the images as stored) for
    every estimator (by method name), interleaved pair by pair in a rotating order, after one untimed warm-up
    pair each."""
    from udh_cli.images import read_image

    count, methods = min(count, len(files) - 1), list(estimators)
    images = [read_image(path) for path in files[: count + 1]]
    for estimator in estimators.values():  # model loading and first-call allocation stay out of the times
        estimator.estimate(images[0], images[1])
    times: dict[str, list[float]] = {name: [] for name in methods}
    answered_by: dict[str, Counter] = {name: Counter() for name in methods}
    stages: dict[str, dict[str, list[float]]] = {name: {} for name in methods}
    for i in range(count):
        for name in methods[i % len(methods):] + methods[: i % len(methods)]:
            started = time.perf_counter()
            estimate = estimators[name].estimate(images[i], images[i + 1])
            times[name].append((time.perf_counter() - started) * 1e3)
            if estimate.ok:
                answered_by[name][estimate.stage or name] += 1
            for stage, ms in (estimate.details.get("stage_ms") or {}).items():
                stages[name].setdefault(stage, []).append(ms)
    medians = {name: statistics.median(values) for name, values in times.items()}
    sift = medians.get("sift")
    return [PairTiming(name, count, medians[name], medians[name] / sift if sift else None, sum(answered_by[name].values()),
                       {stage: statistics.median(ms) for stage, ms in stages[name].items()},
                       {stage: len(ms) for stage, ms in stages[name].items()}, dict(answered_by[name]))
            for name in methods]


def run_speed_bench(
    folder: str | Path,
    method: str | None = None,
    workers: int | None = None,
    method_options: dict[str, dict[str, Any]] | None = None,
    pairs: int = 0,
    pair_methods: Sequence[str] = PAIR_METHODS,
    mosaic_dir: str | Path | None = None,
    progress: bool = False,
) -> SpeedResult:
    """Time the reference workload, then ``run_mosaic`` on ``folder``, then (``pairs`` > 0) single pairs.

    Args:
        method: the mosaic's method (default: the mosaic's); ``workers``: its local processes (default: its own choice).
        method_options: ``{method: {key: value}}`` for the mosaic's method and the timed pairs' methods.
        mosaic_dir: where the mosaic is written (as :data:`MOSAIC_NAME`); ``None``: a temporary folder, removed after.
        progress: show the mosaic's progress bars on stderr.
    """
    from udh_cli.estimators import create_estimator
    from udh_cli.mosaic import DEFAULT_METHOD, MosaicConfig, Reporter, run_mosaic

    files = frame_files(folder)
    method, method_options = method or DEFAULT_METHOD, method_options or {}
    config = MosaicConfig(method=method, method_options=method_options.get(method, {}), workers=workers)
    # Made first, so that an unknown method or a bad option fails before any work.
    pair_estimators = {name: create_estimator(name, **method_options.get(name, {})) for name in pair_methods} if pairs > 0 else {}
    load_at_start = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    reference = time_reference(files)
    with tempfile.TemporaryDirectory(prefix="udh-speed-") as scratch:
        output = Path(mosaic_dir or scratch) / MOSAIC_NAME
        output.parent.mkdir(parents=True, exist_ok=True)
        started = time.perf_counter()
        report = run_mosaic(folder, output, config, Reporter(quiet=not progress, progress=progress))
        wall = time.perf_counter() - started
    memory = peak_memory_mb()
    timed_pairs = time_pairs(files, pairs, pair_estimators) if pair_estimators else []
    return SpeedResult(folder=str(folder), method=config.method, workers=workers, reference=reference,
                       stages=stage_timings(report["timings_s"], wall, reference.seconds), wall_s=wall,
                       peak_memory_mb=memory, summary=report["summary"], pairs=timed_pairs,
                       machine={**machine(), "load_average_1min_at_start": load_at_start})
