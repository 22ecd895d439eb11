"""``run_mosaic``: frames -> pairs -> parts -> loop closure -> global solve -> canvases -> map -> sidecar.

Each line of :func:`run_mosaic` is one stage, a call into its folder (``inputs/``, ``pairs/``, ``solve/``,
``render/``, ``georef/``, ``outputs/``); this module only wires them.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.config import MosaicConfig, acceptance, check_config, run_estimators, with_workers
from udh_cli.mosaic.georef.gcp import GcpFile, read_gcp_file, undistorted_observations
from udh_cli.mosaic.georef.gcp_scale import infer_gcp_scale
from udh_cli.mosaic.georef.geotiff import has_rasterio
from udh_cli.mosaic.georef.place import georeference
from udh_cli.mosaic.inputs.frames import FrameSet, frames_listed, gps_fixes, open_frames
from udh_cli.mosaic.inputs.lens import Lens, read_cameras
from udh_cli.mosaic.inputs.lens_fit import CAMERA_ESTIMATE, undistort_by_fitted_lens
from udh_cli.mosaic.outputs.files import RunFiles, check_output
from udh_cli.mosaic.outputs.staging import (StagedFiles, check_always_written_are_this_runs, check_outputs_are_not_inputs,
                                            check_sidecar_is_this_outputs, remove_stale_files, remove_stale_staged)
from udh_cli.mosaic.pairs.cache import PairCache
from udh_cli.mosaic.pairs.plan import estimate_sequence
from udh_cli.mosaic.pairs.types import PairResult
from udh_cli.mosaic.pairs.workers import closed_after, open_runner
from udh_cli.mosaic.render.decoded import DECODED_CACHE_BYTES
from udh_cli.mosaic.render.canvases import CanvasPlan, DrawnPart, composite_part, kept_images, on_canvas, plan_canvases, warn_about_earlier_output
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.report_page import write_report_page
from udh_cli.mosaic.sidecar import build_sidecar, relative_to
from udh_cli.mosaic.solve.anchors import solve_anchors
from udh_cli.mosaic.solve.bridges import bridge_by_gps
from udh_cli.mosaic.solve.global_solve import solve_parts
from udh_cli.mosaic.solve.loops import close_loops
from udh_cli.mosaic.solve.parts import Part, chain_parts
from udh_cli.mosaic.solve.truth import load_truth


def run_mosaic(
    source: str | Path,
    output: str | Path,
    config: MosaicConfig = MosaicConfig(),
    reporter: Reporter | None = None,
    estimator: Estimator | None = None,
    fallback: Estimator | None = None,
    ground_truth: str | Path | None = None,
    resume: bool = False,
    cache_dir: str | Path | None = None,
    gcp: str | Path | None = None,
    gcp_image_width: int | None = None,
    camera: str | Path | None = None,
    overwrite: bool = False,
    live: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Mosaic a folder of frames (or a video) into ``output``; returns the sidecar dict (also written).

    ``estimator`` / ``fallback`` override ``config.method`` / ``config.fallback`` with ready instances.
    ``ground_truth`` is a simulator ground-truth file; when ``None``, ``FOLDER/ground_truth.json`` is used
    if present. Raises :class:`UdhError` for unusable input; a failing pair never raises, it splits the run.

    With ``resume``, every finished pair estimate is saved to ``NAME.pairs.json`` beside ``output`` (or in
    ``cache_dir``) after each batch, the file is kept after the run, and the pairs of an earlier file whose
    frames, estimators and settings match are taken from it instead of estimated again (see
    :mod:`.pairs.cache`). With ``cache_dir`` alone the file is written there but not read. Without either,
    no cache file is written.

    ``gcp`` is a ground-control file in OpenDroneMap's format (:mod:`.georef.gcp`; ``gcp_image_width``: the width
    of the images its pixels refer to, when not the frames'): the mosaic is placed on the map by its points,
    else (frames with EXIF GPS) by their GPS, and a world file and a .prj are written beside each part.

    ``camera`` is an OpenSfM/OpenDroneMap ``cameras.json``: every frame, and every ground-control pixel, is
    undistorted by its lens model (:mod:`.inputs.lens`) before anything else; ``"estimate"`` fits one k1 for the
    flight from its own frames first (:mod:`.inputs.lens_fit`).

    Files are replaced or removed only when an earlier run to ``output`` wrote them (:mod:`.outputs.staging`);
    ``overwrite`` replaces any file in the way, and another run's sidecar ``NAME.json``, all the same.

    ``live`` is live mode's record of the flight (:func:`~.live.run.run_live`): the sidecar and the report page carry it.
    """
    reporter = reporter or Reporter(quiet=True)
    source, files = Path(source), RunFiles(Path(output), None if cache_dir is None else Path(cache_dir))
    gcps, lens = _check_inputs(source, files, config, gcp, gcp_image_width, camera, overwrite)
    started = time.perf_counter()
    truth = load_truth(source, ground_truth)
    opinions, spec = run_estimators(config, estimator, fallback)
    for note in dict.fromkeys(line for opinion in opinions for line in opinion.model_notes()):
        reporter.warn(note)  # a model file without its licence or training headings: the sidecar keeps the note
    config = with_workers(config, frames_listed(source, config.every))
    # Opened before the frames are read, so that worker processes start while they are.
    runner = open_runner(opinions, acceptance(config), spec, config.workers, config.scheduler, warn=reporter.warn)
    with closed_after(runner):
        frameset = open_frames(source, config.work_size, config.order, config.every, exclude=files.own_files(), reporter=reporter,
                               lens=lens, keep_decoded_bytes=DECODED_CACHE_BYTES)
        lens = _fit_lens(frameset, reporter) if camera is not None and str(camera) == CAMERA_ESTIMATE else lens
        gcps, gcp_image_width = _gcps_on_frames(gcps, gcp, source, frameset, lens, gcp_image_width, reporter)
        cache = PairCache.open(files.pair_cache, frameset.frames, opinions, acceptance(config), resume, reporter, keep=resume or cache_dir is not None)
        pairs, parts = _pairs_and_parts(frameset, opinions, runner, config, reporter, cache, resume)
    anchors = solve_anchors(frameset, config.gcp_sigma_m, config.gps_sigma_m, reporter, gcps, gcp_image_width)
    solved = solve_parts(frameset, parts, pairs, config.global_solve(), reporter, anchors)
    plan = plan_canvases(frameset, parts, files, config.drawing())
    frameset.drop_decoded(i for part in plan.parts for i in part.frames)  # a frame no part renders is not decoded again
    staged = StagedFiles(files.output, overwrite)  # the images of every part appear together, or none of them does
    try:
        keep = kept_images(plan, wanted=has_rasterio() and (gcps is not None or bool(gps_fixes(frameset.frames))))  # for the GeoTIFFs
        drawn = [composite_part(frameset, part, config.drawing(), reporter, staged, part.number in keep) for part in plan.parts]
        warn_about_earlier_output(files, plan, reporter)
        report = _write_report(frameset, plan, drawn, solved.pairs, solved.loops, truth, config, opinions, reporter, staged, files, gcps,
                               gcp_image_width, cache, started, live)
        del drawn  # the images held for the GeoTIFFs
        published = staged.publish()
    finally:
        staged.discard()  # after a failure; nothing is left to discard after publish()
    remove_stale_files(files, published, [files.output, *(part.file for part in plan.parts)], reporter)
    report["sidecar"] = str(files.sidecar)
    return report


def _check_inputs(source: Path, files: RunFiles, config: MosaicConfig, gcp: str | Path | None, gcp_image_width: int | None,
                  camera: str | Path | None, overwrite: bool = False) -> tuple[GcpFile | None, Lens | None]:
    """Everything that can be checked before any work: the output, the settings, that no output replaces an
    input, the ground-control file and the lens file; stale temporaries of a killed run are removed."""
    check_output(files.output)
    check_config(config)
    if files.cache_dir is not None and not files.cache_dir.is_dir():
        raise UdhError(f"--cache-dir {files.cache_dir}: no such folder; create it first")
    check_outputs_are_not_inputs(source, files.roles(), files.sidecar)
    check_sidecar_is_this_outputs(files, overwrite)
    check_always_written_are_this_runs(files, overwrite)
    remove_stale_staged(files.output)
    gcps = read_gcp_file(gcp) if gcp is not None else None  # a bad file fails before any work
    lens = read_cameras(camera) if camera is not None and str(camera) != CAMERA_ESTIMATE else None
    if gcp_image_width is not None and gcp_image_width < 1:
        raise UdhError(f"--gcp-image-width {gcp_image_width}: give the width in pixels of the images the GCP file refers to")
    return gcps, lens


def _fit_lens(frameset: FrameSet, reporter: Reporter) -> Lens | None:
    """``--camera estimate``: fit the lens on the flight itself and undistort every frame by it."""
    with reporter.stage("lens", 1) as advance:
        undistort_by_fitted_lens(frameset, reporter)
        advance(1)
    return frameset.lens


def _gcps_on_frames(gcps: GcpFile | None, gcp: str | Path | None, source: Path, frameset: FrameSet, lens: Lens | None,
                    gcp_image_width: int | None, reporter: Reporter) -> tuple[GcpFile | None, int | None]:
    """The ground-control observations of the frames that were read, undistorted with them, and the width of the
    images the file's pixels refer to (given, or read from the frames; None: the frames' own); none at all fails."""
    if gcps is None:
        return None, gcp_image_width
    names = {f.name for f in frameset.frames}
    missing = sorted({o.image for o in gcps.observations} - names)
    if len(missing) == len({o.image for o in gcps.observations}):
        raise UdhError(f"{gcp}: none of the images it names is among the frames of {source} (e.g. {missing[0]})")
    if missing:
        reporter.warn(f"{gcp}: {len(missing)} image(s) it names are not among the frames, their observations are skipped: {', '.join(missing[:5])}")
    gcp_scale = infer_gcp_scale(gcps, frameset.frames, gcp_image_width, str(gcp))
    gcp_image_width = gcp_scale.image_width
    reporter.info(f"{Path(gcp).name}: its pixels are {gcp_scale.reason}")
    if lens is not None:  # the points were measured on the distorted frames
        gcps = undistorted_observations(gcps, lens, {f.name: f.size for f in frameset.frames}, gcp_image_width)
    return gcps, gcp_image_width


def _pairs_and_parts(frameset: FrameSet, opinions, runner, config: MosaicConfig, reporter: Reporter, cache: PairCache,
                     resume: bool) -> tuple[list[PairResult], list[Part]]:
    """Every pair estimate of the run (consecutive, bridges, GPS bridges, loop closure), by ``runner``
    (:mod:`.pairs.workers`), and the parts they chain into; the pair cache is saved after them, and an
    interruption says how to go on from it."""
    batch = (acceptance(config), config.batch_size)
    try:
        pairs = estimate_sequence(frameset, opinions, *batch, reporter, cache, runner)
        parts = chain_parts(frameset, pairs)
        bridged = bridge_by_gps(frameset, parts, pairs, opinions, config.gps_pairs, *batch, reporter, cache, runner)
        pairs += bridged
        if any(p.ok for p in bridged):
            parts = chain_parts(frameset, pairs)
        pairs += close_loops(frameset, parts, pairs, opinions, config.loop_closure(), *batch, reporter, cache, runner)
    except KeyboardInterrupt:
        if cache.entries and cache.keep:
            reporter.warn(f"interrupted: the finished pair estimates are kept in {cache.path}; add --resume to the same command to go on from them")
        elif cache.entries:
            reporter.warn("interrupted: run with --resume to keep the pair estimates, so that a rerun goes on from them")
        raise
    cache.save(prune=True)
    if resume:
        reporter.info(f"{cache.hits} of {cache.requests} pair estimates taken from {cache.path}")
    return pairs, parts


def _write_report(frameset: FrameSet, plan: CanvasPlan, drawn: list[DrawnPart], pairs: list[PairResult], loops: dict[str, Any],
                  truth: dict | None, config: MosaicConfig, opinions, reporter: Reporter, staged: StagedFiles, files: RunFiles,
                  gcps: GcpFile | None, gcp_image_width: int | None, cache: PairCache, started: float,
                  live: dict[str, Any] | None) -> dict[str, Any]:
    """The sidecar, with the map placement, staged last beside the images (a run that fails while writing leaves
    the earlier run's files, all of them, and never new images beside an old sidecar); returns its content."""
    on_map = on_canvas(plan)
    report = build_sidecar(frameset, plan, drawn, on_map, pairs, loops, truth, config, opinions, reporter, files.sidecar.parent)
    if gcps is not None or gps_fixes(frameset.frames):
        with reporter.stage("georeferencing", 1) as advance:  # world files and the north-up GeoTIFFs
            images = {part.plan.number: part.image for part in drawn if part.image is not None}
            placement = georeference(frameset, on_map, staged, reporter, files, gcps, gcp_image_width, config.gcp_sigma_m > 0, images,
                                     threads=config.workers)
            advance(1)
        for entry in report["parts"]:
            entry.update(placement.parts.get(entry["part"], {}))
        if placement.map is not None:
            report["map"] = placement.map
        if any(entry.get("georeference") for entry in report["parts"]):  # not timed where nothing was placed on the map
            report["timings_s"]["georeferencing"] = reporter.timings_s["georeferencing"]
    report["pair_cache"] = relative_to(cache.path, files.sidecar.parent) if cache.keep else None
    report["summary"]["pairs_from_cache"] = cache.hits
    report["timings_s"]["total"] = time.perf_counter() - started
    if frameset.lens_fit is not None and frameset.lens is not None:  # the fitted lens, for the next run and for ODM
        atomic_write_bytes(staged.path_for(files.cameras), (json.dumps(frameset.lens.to_cameras_json(), indent=1) + "\n").encode())
        report["camera"]["file"] = files.cameras.name
    report["report_page"] = files.report_page.name
    if live is not None:  # the last key, where a last refresh published as the final mosaic has it too
        report["live"] = live
    write_report_page(report, staged, files)  # NAME.report.html, from the same results as the sidecar
    atomic_write_bytes(staged.path_for(files.sidecar), (json.dumps(report, indent=1) + "\n").encode())
    return report
