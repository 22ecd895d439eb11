"""Live mode's run: the quick look in this process, refreshes in a second one, the final mosaic at the end
(:mod:`.follow` follows the folder, :mod:`.quicklook` draws each frame as it lands)."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator
from udh_cli.files import record_written
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.live.follow import FollowConfig, check_followed_folder, follow_mosaic
from udh_cli.mosaic.inputs.lens_fit import CAMERA_ESTIMATE
from udh_cli.mosaic.config import MosaicConfig, acceptance, check_config, mosaic_method_options
from udh_cli.mosaic.outputs.files import RunFiles, check_output
from udh_cli.mosaic.run import run_mosaic
from udh_cli.mosaic.outputs.staging import check_outputs_are_not_inputs
from udh_cli.mosaic.live.quicklook import QuickLook
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.pairs.workers import check_main_guard
from udh_cli.mosaic.report_page import rewrite_report_page
from udh_cli.mosaic.sidecar import relative_to
from udh_cli.processes import die_with_parent


def run_live(folder: str | Path, output: str | Path, config: MosaicConfig = MosaicConfig(), follow: FollowConfig = FollowConfig(),
             reporter: Reporter | None = None, cache_dir: str | Path | None = None, quick_look: bool = True, **options: Any) -> dict[str, Any]:
    """Live mode (:mod:`.follow`): mosaic ``folder`` while frames are still being written into it, until the
    flight ends; returns the final sidecar.

    Each new frame is placed on its predecessor and drawn into ``NAME.live.jpg`` at once (``quick_look``,
    :mod:`.quicklook`). Every ``follow.refresh_every`` frames the mosaic itself is rewritten by a whole run in a
    second process, so that new frames do not wait for it. The pair cache is always on (``NAME.pairs.json``,
    kept afterwards), so each refresh estimates only what is new. ``options`` go to every :func:`run_mosaic`
    call (``ground_truth``, ``gcp``, ...)."""
    reporter = reporter or Reporter(quiet=True)
    output = Path(output)
    check_output(output)
    check_config(config)
    if config.workers is None:  # the quick look needs the other core; each refresh estimates its new pairs in one process
        config = replace(config, workers=1)
    check_followed_folder(Path(folder))  # before the networks load
    check_main_guard("live mode's refresh")
    if str(options.get("camera")) == CAMERA_ESTIMATE:  # each refresh would fit another k1 and estimate every pair again
        raise UdhError("--camera estimate cannot follow a flight as it is written: fit the lens once on a finished flight "
                       "(it writes NAME.cameras.json) and give that file, or the camera's own cameras.json")
    files = RunFiles(output, None if cache_dir is None else Path(cache_dir))
    check_outputs_are_not_inputs(Path(folder), files.live_roles(), files.sidecar)
    cache_file = files.pair_cache

    def run(source: Path, live: dict[str, Any] | None = None) -> dict[str, Any]:
        reporter.timings_s.clear()  # each run's stage times are its own, as its total is
        return _live_run(source, output, config, cache_file, reporter, {**options, "live": live})

    look = None
    if quick_look:
        method_options = mosaic_method_options(config.method, config.method_options)
        opinions = [create_estimator(config.method, **method_options)]
        if config.fallback:
            opinions.append(create_estimator(config.fallback, **config.fallback_options))
        look = QuickLook(output, opinions, acceptance(config), config.work_size)

    def on_frames(paths: list[Path]) -> None:
        for path in paths:
            try:
                record = look.add(path)
            except Exception as exc:  # noqa: BLE001 - the quick look is a convenience: it never ends the flight
                reporter.warn(f"live: {path.name} could not be drawn in the quick look ({type(exc).__name__}: {exc}); the flight goes on")
                continue
            if not record["placed"]:
                reporter.warn(f"live: {path.name} is not in the quick look ({record.get('failure')}); the mosaic will try it again")

    # spawn, not fork: the networks' onnxruntime sessions and their threads do not survive a fork
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                             initializer=die_with_parent, initargs=(os.getpid(),)) as refresher:
        def start_refresh(source: Path):
            return refresher.submit(_refresh_in_worker, source, output, config, cache_file, options)

        report = follow_mosaic(folder, output, run, follow, reporter, exclude=lambda: {p.resolve() for p in files.own_files()},
                               on_frames=on_frames if look is not None else None, start_refresh=start_refresh)
    if report["live"]["final"] == "the last refresh":  # written before the flight ended; a final run wrote its own
        _publish_last_refresh(report, Path(folder), files)
    return report


def _publish_last_refresh(report: dict[str, Any], folder: Path, files: RunFiles) -> None:
    """Write the sidecar and report page of the refresh that became the final mosaic again, from its ``report``:
    with the flight's ``live`` record, and naming ``folder``, not the staging folder (gone now) it read the frames from."""
    report["source"] = relative_to(folder, files.sidecar.parent)
    sidecar = {key: value for key, value in report.items() if key != "sidecar"}  # the path, added once it was written
    atomic_write_bytes(files.sidecar, (json.dumps(sidecar, indent=1) + "\n").encode())
    rewrite_report_page(sidecar, files.sidecar.parent)
    record_written(*[p for p in (files.sidecar, files.report_page) if p.is_file()], run=files.output.name)  # the next run's to replace


def _refresh_in_worker(source: Path, output: Path, config: MosaicConfig, cache_file: Path, options: dict[str, Any]) -> dict[str, Any]:
    """A refresh in the refresher process, which ignores Ctrl-C while idle (:func:`~udh_cli.processes.die_with_parent`,
    or it would print a traceback): while it refreshes, Ctrl-C stops it as it stops the main run, so that the
    flight's end never waits for a whole refresh."""
    idle = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return _live_run(source, output, config, cache_file, None, options)
    finally:
        signal.signal(signal.SIGINT, idle)


def _live_run(source: Path, output: Path, config: MosaicConfig, cache_file: Path, reporter: Reporter | None, options: dict[str, Any]) -> dict[str, Any]:
    """One run of live mode: the cache is kept from the first run on, and read once there is one."""
    return run_mosaic(source, output, config, reporter, resume=cache_file.is_file(), cache_dir=cache_file.parent, **options)
