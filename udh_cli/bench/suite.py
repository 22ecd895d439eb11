"""The two benchmarks as library calls, one per ``udh bench`` command.

Each call checks its methods first (an unknown method or a missing model stops it before any work),
then builds the pairs, runs every method on them and returns a :class:`BenchResult`;
:func:`udh_cli.bench.report.write_outputs` writes the files.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from udh_cli.bench import runner
from udh_cli.bench.pairsets import check_pairs_memory, held_out_sources, load_sets, save_sets, synthetic_set
from udh_cli.bench.real_pairs import load_real_pairs
from udh_cli.bench.report import BenchResult
from udh_cli.errors import UdhError
from udh_cli.files import check_replaceable
from udh_cli.estimators.registry import parse_method_options
from udh_cli.estimators import estimator_names
from udh_cli.images import check_output_path
from udh_cli.synthetic import SOURCE_SIZE

MODES = ("patch", "full", "both")  # what the classical methods are shown on synthetic pairs
FULL_METHODS = ("sift", "orb", "ecc")  # methods shown the full frames in "full"/"both" mode, as in the paper
PAPER_RHOS = (16.0, 32.0, 45.0)  # the paper's 85 / 75 / 65 % overlap
FULL_FRAME = (0, 0, *SOURCE_SIZE)  # an uncropped full-input window


def default_methods() -> str:
    """Every registered method, comma-separated: new estimators join the benchmark by registering."""
    return ",".join(estimator_names())


def parse_rhos(text: str) -> list[float]:
    """``"16,32,45"`` -> ``[16.0, 32.0, 45.0]``."""
    try:
        rhos = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UdhError(f"--rho {text!r}: give pixel values separated by commas, e.g. 16,32,45") from None
    if not rhos or any(not 0 <= r <= 56 for r in rhos):
        raise UdhError(f"--rho {text!r}: each value must be between 0 and 56 px (128-px patches in a 320x240 image)")
    return list(dict.fromkeys(rhos))


def bench_options(items: list[str] | None, methods: str | None) -> dict[str, dict[str, Any]]:
    """``-O`` items for the methods compared (``methods``: the ``--methods`` text, None for every registered
    one): :func:`udh_cli.estimators.registry.parse_method_options`, so a bare ``KEY=VALUE`` reaches every
    compared method that takes it."""
    return parse_method_options(items, runner.parse_methods(methods or default_methods()))


def _inputs_for(mode: str) -> list[str]:
    if mode not in MODES:
        raise UdhError(f"--mode {mode!r}: choose one of {', '.join(MODES)}")
    return ["patch", "full"] if mode == "both" else [mode]


def _run_flight_bench(images, count, seed, methods, options, show_progress) -> BenchResult:
    """The flight-motion benchmark: whole frames, every method on them (see :func:`run_synthetic_bench`)."""
    from udh_cli.bench.pairsets import flight_set
    from udh_cli.flight_motion import MotionConfig, source_size

    methods = methods or runner.parse_methods(default_methods())
    jobs = runner.make_jobs(methods, ["image"], [], options)
    sources, where = held_out_sources(images, size_for=source_size)
    sets = [flight_set(sources, count, seed)]
    motion = MotionConfig()
    config = {"images": where, "motion": "flight", "n": count, "seed": seed, "methods": methods, "options": options or {},
              "motion_ranges": {"max_heading": motion.max_heading, "scale_range": list(motion.scale_range),
                                "max_shift": motion.max_shift, "perspective": motion.perspective, "min_overlap": motion.min_overlap}}
    runs = runner.run_jobs(jobs, sets, show_progress=show_progress)
    notes = [f"Pairs: whole 320x240 frames with flight motion (turns up to {motion.max_heading:g} degrees, scale "
             f"{motion.scale_range[0]:.2f}-{motion.scale_range[1]:.2f}, shifts up to {motion.max_shift:g} of the frame, overlap "
             f"at least {motion.min_overlap:g}), from {where}; seed {seed}."]
    return BenchResult("synthetic", runs, config, notes)


def run_synthetic_bench(
    images: Path | None = None,
    rhos: list[float] = list(PAPER_RHOS),
    count: int = 500,
    seed: int = 0,
    illumination: bool = True,
    occluders: bool = False,
    methods: list[str] | None = None,
    mode: str = "both",
    full_methods: list[str] = list(FULL_METHODS),
    options: dict[str, dict[str, Any]] | None = None,
    save_pairs: Path | None = None,
    load_pairs: Path | None = None,
    show_progress: bool = True,
    motion: str = "paper",
    overwrite: bool = False,
) -> BenchResult:
    """Benchmark ``methods`` on synthetic pairs from held-out images (see :mod:`udh_cli.bench.pairsets`).

    With ``load_pairs``, the saved set replaces ``images``, ``rhos``, ``count``, ``seed`` and
    ``illumination``. ``mode`` says whether ``full_methods`` see the patches, the full frames, or both.
    ``motion`` "flight" draws whole 320x240 frames with real flight motion instead (every method sees them;
    ``rhos``, ``mode``, ``occluders`` and saving do not apply). An existing ``save_pairs`` file is replaced only
    when udh wrote it, or with ``overwrite`` (:func:`udh_cli.files.check_replaceable`).
    """
    if motion not in ("paper", "flight"):
        raise UdhError(f"--motion {motion}: choose paper or flight")
    if load_pairs is None and count >= 1:
        check_pairs_memory(count, 1 if motion == "flight" else len(rhos))
    if motion == "flight":
        if save_pairs is not None or load_pairs is not None:
            raise UdhError("--save-pairs and --load-pairs hold the paper-motion pairs; the flight-motion set is drawn "
                           "again from --seed (the same seed gives the same pairs)")
        return _run_flight_bench(images, count, seed, methods, options, show_progress)
    methods = methods or runner.parse_methods(default_methods())
    jobs = runner.make_jobs(methods, _inputs_for(mode), full_methods, options)
    with_full = any(job.input == "full" for job in jobs)
    if save_pairs is not None and load_pairs is None:
        check_output_path(save_pairs, (".npz",))  # before the pairs are drawn
        check_replaceable(save_pairs, overwrite)
    if load_pairs is not None:
        sets, meta = load_sets(load_pairs)
        config = {"pairs_loaded_from": str(load_pairs), **meta}
    else:
        if count < 1:
            raise UdhError(f"--n {count}: need at least one pair")
        sources, where = held_out_sources(images)
        meta = {"images": where, "rhos": rhos, "n": count, "seed": seed, "illumination": illumination,
                "occluders": occluders, "generator": "udh_cli.synthetic.make_pairs, chunks of 64 pairs from default_rng([seed, chunk])"}
        sets = [synthetic_set(sources, rho, count, seed, illumination, with_full=with_full, occluders=occluders)
                for rho in rhos]
        if save_pairs is not None:
            save_sets(save_pairs, sets, meta, overwrite)
        config = dict(meta)
    config.update({"methods": methods, "mode": mode, "full_methods": [m for m in full_methods if m in methods],
                   "options": options or {}})
    runs = runner.run_jobs(jobs, sets, show_progress=show_progress)
    notes = [f"Pairs: {config.get('images', config.get('pairs_loaded_from'))}; illumination "
             f"{'on' if config.get('illumination', True) else 'off'}; occluders {'on' if config.get('occluders') else 'off'}; "
             f"seed {config.get('seed', 'n/a')}."]
    if with_full:
        cropped = ", ".join(f"{s.name}: {100 * np.mean(np.any(s.full_window != FULL_FRAME, axis=1)):.0f} %" for s in sets)
        notes.append(f"Full input: A's frame is cropped around the patch where the true homography would put the "
                     f"horizon inside it (pairs cropped: {cropped}).")
    if with_full and config.get("illumination", True):
        notes.append("Full frames get their own illumination draw from the generator's distribution "
                     "(the generator does not keep the patches' draws).")
    return BenchResult("synthetic", runs, config, notes)


def run_pairs_bench(
    source: Path,
    methods: list[str] | None = None,
    h_column: str = "H",
    prefix: str | None = None,
    options: dict[str, dict[str, Any]] | None = None,
    show_progress: bool = True,
) -> BenchResult:
    """Benchmark ``methods`` on real pairs listed in a CSV or an Oxford/HPatches folder (see
    :mod:`udh_cli.bench.real_pairs`). Every method is shown the images as given."""
    methods = methods or runner.parse_methods(default_methods())
    jobs = runner.make_jobs(methods, ["image"], [], options)
    pair_set = load_real_pairs(source, h_column=h_column, prefix=prefix)
    runs = runner.run_jobs(jobs, [pair_set], show_progress=show_progress)
    notes = [f"Pairs: {source} ({len(pair_set)}: {', '.join(pair_set.labels[:6])}{', ...' if len(pair_set) > 6 else ''})."]
    if any(word in h_column.lower() for word in ("sift", "reference", "ransac")):
        notes.append(f"Column {h_column} holds SIFT+RANSAC reference homographies, not ground truth: "
                     "errors measure agreement with that reference, which favours feature-based methods.")
    config = {"source": str(source), "h_column": h_column, "prefix": prefix, "methods": methods, "options": options or {}}
    return BenchResult("pairs", runs, config, notes)
