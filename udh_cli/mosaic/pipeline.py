"""``run_mosaic``: frames -> pairwise estimates -> chaining -> loop closure -> global solve -> canvas.

Each step is one call into a module of this package; this file only wires them and writes the outputs.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from udh_cli import __version__, geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import DEFAULT_METHOD, Estimator, create_estimator
from udh_cli.estimators.registry import estimator_options
from udh_cli.images import atomic_write_bytes, check_output_path, write_image
from udh_cli.mosaic import composite as compositing
from udh_cli.mosaic.frames import ORDERS, FrameSet, open_frames
from udh_cli.mosaic.gains import EXPOSURES, exposure_gains, mean_gain
from udh_cli.mosaic.seams import SEAM_FINDERS, find_seams
from udh_cli.mosaic.small import draw_small
from udh_cli.mosaic.graph import NEAR_IN_SEQUENCE, chain_to_reference, connected_parts, overlap_candidates, reference_frame
from udh_cli.mosaic.outputs import (SIDECAR_FORMAT, StagedFiles, cameras_path, check_outputs_are_not_inputs, output_paths, preview_path, remove_stale_staged,
                                   sidecar_path, stale_part_files)
from udh_cli.mosaic.gcp import fit_gcps, gcp_anchors, read_gcp_file, undistorted_observations
from udh_cli.mosaic.gcp_scale import check_gcp_fit, infer_gcp_scale, residual_lines
from udh_cli.mosaic.map_files import georeference_mosaic_file, pam_path
from udh_cli.mosaic.report_page import report_page_path, write_report_page
from udh_cli.mosaic.lens import read_cameras
from udh_cli.mosaic.lens_fit import CAMERA_ESTIMATE, frames_focal, undistort_by_fitted_lens
from udh_cli.mosaic.geotiff import MosaicImage, cog_path, has_rasterio, write_cog, write_combined_cog, write_tiled_tiff
from udh_cli.mosaic.workers import EstimatorSpec, automatic_workers, open_runner
from udh_cli.mosaic.gps_pairs import (bridge_candidates, gps_disagreement_m, gps_limit_m, ground_positions, measure_ground_scale, part_map,
                                      placement_error_m)
from udh_cli.mosaic.georef import MIN_GPS_FRAMES, georeference_part, projection_text, world_file_path, world_file_text
from udh_cli.mosaic.pair_cache import PairCache, cache_path, estimator_identity
from udh_cli.mosaic.pairs import Acceptance, PairRequest, PairResult
from udh_cli.mosaic.quicklook import live_picture_path, live_record_path
from udh_cli.mosaic.pairwise import corner_disagreement_px, estimate_pairs
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.cameras import CameraSolution, solve_cameras
from udh_cli.mosaic.rectify import keep_reference_view, rectifying_homography
from udh_cli.mosaic.solve import Anchors, pair_points, pair_rms_px, solve_part, solve_with_rejection, summarise
from udh_cli.mosaic.truth import corner_errors_vs_truth, map_shape_errors, summarise_truth
from udh_cli.simulate import GROUND_TRUTH_FILE, load_ground_truth

OUTPUT_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")


@dataclass(frozen=True)
class MosaicConfig:
    """Every choice of a mosaic run; the CLI's options and defaults come from here.

    Attributes:
        method: registered estimator name for every pair.
        fallback: registered estimator name of the second opinion, asked about the pairs ``method`` fails or
            doubts (:func:`.workers.judge_opinions`); ``None`` for none.
        method_options: keyword options for ``create_estimator(method, ...)``, e.g. ``{"model": "x.onnx"}``.
        fallback_options: the same for ``fallback``.
        work_size: longest side, pixels, of the copies the estimators see.
        order: frame order in a folder: ``"name"`` or ``"time"`` (EXIF capture time).
        every: for a video, keep every N-th frame.
        min_confidence: estimates below this confidence count as failures (then fallback, then split).
        min_verified: estimates whose photometric alignment check (see
            :class:`~udh_cli.mosaic.pairs.Acceptance`) is below this count as failures too; 0: no check.
        overlap_min: non-consecutive frames whose chained footprints overlap by this share of the smaller
            frame are estimated too (loop closure).
        overlap_per_frame: at most this many loop-closure partners per frame (bounds the work).
        gps_pairs: when the frames carry GPS and the run splits, at most this many pairs between each two
            parts that GPS puts close together are estimated (:mod:`.gps_pairs`); 0: off. Off by default:
            joining a long flight's parts can chain homographies further than one plane per frame holds
            (measured in docs/mosaic.md).
        gps_sigma_m: with GPS in the frames, the fixes join the global solve as anchors of this standard
            error in metres (:class:`~udh_cli.mosaic.solve.Anchors`): they bound the projective drift of long
            chains that loop closures alone leave. 0: off, the solve uses the pairs alone.
        gcp_sigma_m: with ground-control points (``run_mosaic(gcp=...)``), their observations join the global
            solve as anchors of this standard error in metres, so that the mosaic bends to them instead of only
            being placed by them afterwards; 0: off.
        workers: local processes estimating pairs at once (:mod:`.workers`; 1: in this process; None: one per
            core, at most 4, for 30 frames or more, :func:`.workers.automatic_workers`, which is what the command
            line does). 1 by default here: a pool spawns processes that import the calling script again, so a
            script needs ``if __name__ == "__main__":`` first.
        scheduler: a Dask scheduler's address (``tcp://host:8786``): pairs are estimated on its workers.
        exposure: exposure compensation of each part (:mod:`.gains`: ``blocks``, ``channels``, ``gain``, ``none``).
        seams: where one frame gives way to the next (:mod:`.seams`: ``dp``, ``graphcut``, ``central``); with
            ``blend`` ``feather`` the frames are averaged and there are no seams.
        preview: also write a small JPEG preview beside the mosaic.
        solve: the global solve's model (:data:`SOLVES`): ``homography``, a free homography per frame
            (:mod:`.solve`), or ``camera``, a pinhole camera per frame over one flat ground, all sharing one
            focal length (:mod:`.cameras`): the map is then drawn on that ground. The camera model starts from
            the homography solve's answer.
    """

    method: str = DEFAULT_METHOD
    fallback: str | None = None
    method_options: dict[str, Any] = field(default_factory=dict)
    fallback_options: dict[str, Any] = field(default_factory=dict)
    work_size: int = 800
    order: str = "name"
    every: int = 1
    min_confidence: float = Acceptance.min_confidence
    min_verified: float = Acceptance.min_verified
    overlap_min: float = 0.3
    overlap_per_frame: int = 3
    gps_pairs: int = 0
    gps_sigma_m: float = 0.0
    gcp_sigma_m: float = 0.0
    workers: int | None = 1
    scheduler: str | None = None
    max_disagreement: float = 0.1
    huber_px: float = 2.0
    outlier_px: float = 5.0
    blend: str = "multiband"  # hard seams blended band by band: no ghosts where parallax defeats the homographies
    exposure: str = "channels"
    seams: str = "dp"
    max_frame_scale: float = 3.0
    # Without anchors, draw on the plane the frames look down on rather than in the reference frame's view
    # (rectify.py). Off by default: it helped simulated nadir surveys but put copr's ground-control checkpoints
    # 3.99 m from the map instead of 2.10 m (docs/mosaic.md).
    rectify: bool = False
    max_size: int | None = None
    max_canvas_bytes: int = compositing.DEFAULT_MAX_CANVAS_BYTES
    batch_size: int = 16
    preview: bool = True
    solve: str = "homography"


@dataclass
class Part:
    """A connected run of frames mosaicked on its own: its frames, reference, homographies and canvas."""

    number: int
    frames: list[int]
    reference: int
    chained: dict[int, np.ndarray]
    solved: dict[int, np.ndarray]  # the chain at first, then each loop round's solve, then the global solve's
    tree: set[int]
    canvas: compositing.Canvas | None = None
    file: Path | None = None
    preview: Path | None = None
    dropped: dict[int, str] = field(default_factory=dict)  # frame -> why it was taken out of the part
    rectified: bool = False  # solved on the ground's plane (rectify.py, cameras.py) rather than in the reference frame's view
    cameras: CameraSolution | None = None  # the camera-model solve's answer (--solve camera)
    focal_source: str | None = None  # where the camera-model solve's focal length came from


def check_output(output: Path) -> None:
    """Fail before any work when the mosaic could not be written."""
    if output.suffix.lower() not in OUTPUT_SUFFIXES:
        raise UdhError(f"{output}: unknown image type '{output.suffix}'; use .png or .tif (they keep the alpha channel)")
    longest, limit = len(os.fsencode(longest_derived_name(output))), _name_max(output.parent)
    if limit is not None and longest > limit:
        raise UdhError(f"{output}: the name is too long for this file system: the files a run writes beside it (NAME.part12.preview.jpg, "
                       f"hidden temporary names) need {longest} bytes where {limit} are allowed; shorten the name to at most "
                       f"{max(1, len(os.fsencode(output.stem)) - (longest - limit))} bytes before its suffix")
    check_output_path(output)  # folder exists and is writable, and the name is not a folder


MAX_PART_DIGITS = 4  # the name check makes room for part numbers up to 9999


def longest_derived_name(output: Path) -> str:
    """The longest file name a run writing ``output`` may create, temporary ones included: a part's preview,
    staged (``.NAME.partK.preview.xxxxxxxx.staged.jpg``) and written through a temporary file of
    :func:`udh_cli.images.atomic_write_bytes` (``.<that name>.xxxxxxxx.part``)."""
    part = output.with_name(f"{output.stem}.part{'9' * MAX_PART_DIGITS}{output.suffix}")
    finals = [output, part, preview_path(output), preview_path(part), sidecar_path(output), pam_path(part)]
    written = [f".{f.stem}.{'0' * 8}.staged{f.suffix}" for f in finals] + [cache_path(output).name]  # see StagedFiles.path_for
    return max((f".{name}.{'x' * 8}.part" for name in written), key=lambda name: len(os.fsencode(name)))


def _name_max(folder: Path) -> int | None:
    """The longest file name (bytes) ``folder``'s file system takes; None when the folder does not exist."""
    try:
        if not folder.is_dir():
            return None
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):  # no pathconf (Windows) or no answer: the usual limit
        return 255


def check_config(config: MosaicConfig) -> None:
    """Fail before any work on a setting that could only fail later (a typo in --blend, a zero size)."""
    if config.blend not in compositing.BLENDS:
        raise UdhError(f"unknown blend '{config.blend}'; choose one of: {', '.join(compositing.BLENDS)}")
    if config.exposure not in EXPOSURES:
        raise UdhError(f"unknown exposure compensation '{config.exposure}'; choose one of: {', '.join(EXPOSURES)}")
    if config.seams not in SEAM_FINDERS:
        raise UdhError(f"unknown seam finder '{config.seams}'; choose one of: {', '.join(SEAM_FINDERS)}")
    if config.order not in ORDERS:
        raise UdhError(f"unknown order '{config.order}'; choose one of: {', '.join(ORDERS)}")
    if config.work_size < 32:
        raise UdhError(f"--work-size {config.work_size}: give at least 32 pixels")
    if config.max_size is not None and config.max_size < 16:
        raise UdhError(f"--max-size {config.max_size}: give at least 16 pixels")
    if not 0.0 <= config.min_confidence <= 1.0:
        raise UdhError(f"--min-confidence {config.min_confidence}: give a value in [0, 1]")
    if not 0.0 <= config.min_verified <= 1.0:
        raise UdhError(f"--min-verified {config.min_verified}: give a value in [0, 1]")
    if not config.max_frame_scale > 1.0:
        raise UdhError(f"--max-frame-scale {config.max_frame_scale}: give a factor above 1 (frames drawn that many times larger or smaller than the reference are reported)")
    if config.workers is not None and config.workers < 1:
        raise UdhError(f"--workers {config.workers}: give at least 1 (pairs estimated in this process)")
    if not (config.gps_sigma_m >= 0 and math.isfinite(config.gps_sigma_m)):
        raise UdhError(f"--gps-sigma {config.gps_sigma_m}: give the GPS fixes' error in metres (e.g. 3), or 0 for off")
    if not (config.gcp_sigma_m >= 0 and math.isfinite(config.gcp_sigma_m)):
        raise UdhError(f"--gcp-sigma {config.gcp_sigma_m}: give the ground-control points' error in metres (e.g. 0.05), or 0 for off")
    if config.gps_sigma_m > 0 and importlib.util.find_spec("pyproj") is None:  # fail before the pairs, not after
        raise UdhError("--gps-sigma needs pyproj to put the GPS fixes on a map: pip install pyproj (or pip install '.[geo]')")
    if config.solve not in SOLVES:
        raise UdhError(f"--solve {config.solve}: choose one of {', '.join(SOLVES)}")
    if config.every < 1 or config.overlap_per_frame < 0 or config.gps_pairs < 0:
        raise UdhError("--every must be at least 1, and --overlap-pairs and --gps-pairs at least 0")


SOLVES = ("homography", "camera")  # the global solve's models (MosaicConfig.solve)
MOSAIC_SEARCH = 2  # the learned methods' large-motion search, on for mosaics unless the user sets it


def mosaic_method_options(method: str, given: dict[str, Any]) -> dict[str, Any]:
    """``given`` plus the mosaic's defaults for ``method``: the learned methods search for large motion.

    Why: consecutive frames of real flights move further than the synthetic pairs the networks were trained
    on (median corner motion 37-70 px at the networks' 128x128 input on copr, brighton-beach and seneca,
    against at most 45 in training). On copr the search took the median pair error from 14.3 to 2.6 px
    (at 128x128, against the SIFT reference).
    """
    options = dict(given)
    if "search" in estimator_options(method) and "search" not in options:
        options["search"] = MOSAIC_SEARCH
    return options


def acceptance(config: MosaicConfig) -> Acceptance:
    """The run's pair-acceptance thresholds."""
    return Acceptance(config.min_confidence, config.min_verified)


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
) -> dict[str, Any]:
    """Mosaic a folder of frames (or a video) into ``output``; returns the sidecar dict (also written).

    ``estimator`` / ``fallback`` override ``config.method`` / ``config.fallback`` with ready instances.
    ``ground_truth`` is a simulator ground-truth file; when ``None``, ``FOLDER/ground_truth.json`` is used
    if present. Raises :class:`UdhError` for unusable input; a failing pair never raises, it splits the run.

    With ``resume``, every finished pair estimate is saved to ``NAME.pairs.json`` beside ``output`` (or in
    ``cache_dir``) after each batch, the file is kept after the run, and the pairs of an earlier file whose
    frames, estimators and settings match are taken from it instead of estimated again (see
    :mod:`.pair_cache`). With ``cache_dir`` alone the file is written there but not read. Without either,
    no cache file is written.

    ``gcp`` is a ground-control file in OpenDroneMap's format (:mod:`.gcp`; ``gcp_image_width``: the width of
    the images its pixels refer to, when not the frames'): the mosaic is placed on the map by its points,
    else (frames with EXIF GPS) by their GPS, and a world file and a .prj are written beside each part.

    ``camera`` is an OpenSfM/OpenDroneMap ``cameras.json``: every frame, and every ground-control pixel, is
    undistorted by its lens model (:mod:`.lens`) before anything else; ``"estimate"`` fits one k1 for the flight
    from its own frames first (:mod:`.lens_fit`).
    """
    reporter = reporter or Reporter(quiet=True)
    source, output = Path(source), Path(output)
    check_output(output)
    check_config(config)
    pair_cache_file = cache_path(output) if cache_dir is None else Path(cache_dir) / cache_path(output).name
    if cache_dir is not None and not Path(cache_dir).is_dir():
        raise UdhError(f"--cache-dir {cache_dir}: no such folder; create it first")
    check_outputs_are_not_inputs(source, {"mosaic": output, "sidecar": sidecar_path(output), "preview": preview_path(output),
                                          "pair cache": pair_cache_file, "world file": world_file_path(output), "GeoTIFF": cog_path(output),
                                          "projection file": output.with_suffix(".prj"), "camera file": cameras_path(output)}, sidecar_path(output))
    remove_stale_staged(output)
    gcps = read_gcp_file(gcp) if gcp is not None else None  # a bad file fails before any work
    estimate_lens = camera is not None and str(camera) == CAMERA_ESTIMATE
    lens = read_cameras(camera) if camera is not None and not estimate_lens else None
    if gcp_image_width is not None and gcp_image_width < 1:
        raise UdhError(f"--gcp-image-width {gcp_image_width}: give the width in pixels of the images the GCP file refers to")
    started = time.perf_counter()
    truth = _load_truth(source, ground_truth)
    # Workers build the estimators from their names; estimators handed over as instances run here.
    method_options = mosaic_method_options(config.method, config.method_options)
    # The opinions every pair is asked of, in order, while the answers are doubted: the method, then the fallback.
    named = [(config.method, method_options)] + ([(config.fallback, dict(config.fallback_options))] if config.fallback else [])
    spec = None if estimator is not None or fallback is not None else EstimatorSpec(tuple(named), acceptance(config))
    estimator = estimator or create_estimator(config.method, **method_options)
    fallback = fallback or (create_estimator(config.fallback, **config.fallback_options) if config.fallback else None)
    opinions = (estimator,) if fallback is None else (estimator, fallback)

    frameset = open_frames(source, config.work_size, config.order, config.every, exclude=own_files(output), reporter=reporter, lens=lens)
    frames = frameset.frames
    if config.workers is None:  # a cluster's workers estimate the pairs; the local ones still blend the tiles
        config = replace(config, workers=automatic_workers(len(frames)) if config.scheduler is None else 1)
    if estimate_lens:
        with reporter.stage("lens", 1) as advance:
            undistort_by_fitted_lens(frameset, reporter)
            advance(1)
        lens = frameset.lens
    if gcps is not None:
        names = {f.name for f in frames}
        missing = sorted({o.image for o in gcps.observations} - names)
        if len(missing) == len({o.image for o in gcps.observations}):
            raise UdhError(f"{gcp}: none of the images it names is among the frames of {source} (e.g. {missing[0]})")
        if missing:
            reporter.warn(f"{gcp}: {len(missing)} image(s) it names are not among the frames, their observations are skipped: {', '.join(missing[:5])}")
        gcp_scale = infer_gcp_scale(gcps, frames, gcp_image_width, str(gcp))
        gcp_image_width = gcp_scale.image_width
        reporter.info(f"{Path(gcp).name}: its pixels are {gcp_scale.reason}")
        if lens is not None:  # the points were measured on the distorted frames
            gcps = undistorted_observations(gcps, lens, {f.name: f.size for f in frames}, gcp_image_width)
    cache = PairCache.open(pair_cache_file, frames, opinions, acceptance(config), resume, reporter,
                           keep=resume or cache_dir is not None)
    runner = open_runner(opinions, acceptance(config), spec, config.workers, config.scheduler, warn=reporter.warn)
    aborted = True
    try:
        pairs = _estimate_sequence(frameset, opinions, config, reporter, cache, runner)
        parts = _chain_parts(frameset, pairs)
        bridged = _bridge_by_gps(frameset, parts, pairs, opinions, config, reporter, cache, runner)
        pairs += bridged
        if any(p.ok for p in bridged):
            parts = _chain_parts(frameset, pairs)
        pairs += _close_loops(frameset, parts, pairs, opinions, config, reporter, cache, runner)
        aborted = False
    except KeyboardInterrupt:
        if cache.entries and cache.keep:
            reporter.warn(f"interrupted: the finished pair estimates are kept in {cache.path}; add --resume to the same command to go on from them")
        elif cache.entries:
            reporter.warn("interrupted: run with --resume to keep the pair estimates, so that a rerun goes on from them")
        raise
    finally:
        runner.close(abort=aborted)
    cache.save(prune=True)
    if resume:
        reporter.info(f"{cache.hits} of {cache.requests} pair estimates taken from {cache.path}")
    loops = _solve(frameset, parts, pairs, config, reporter, solve_anchors(frameset, config, reporter, gcps, gcp_image_width))
    gains: dict[int, list[float]] = {}  # per placed frame, its mean gain per channel (B, G, R)
    _plan_canvases(frameset, parts, output, config)
    staged = StagedFiles()  # the images of every part appear together, or none of them does
    try:
        for part in parts:
            gains.update(_composite_part(frameset, part, config, reporter, staged))
        _warn_about_earlier_output(output, parts, reporter)
        report = _sidecar(frameset, parts, pairs, gains, loops, truth, config, opinions, reporter, sidecar_path(output).parent)
        if gcps is not None or _gps_fixes(frameset.frames):
            with reporter.stage("georeferencing", 1) as advance:  # world files and the north-up GeoTIFFs
                _georeference(frameset, parts, report, staged, reporter, gcps, gcp_image_width, output)
                advance(1)
            if any(entry.get("georeference") for entry in report["parts"]):  # not timed where nothing was placed on the map
                report["timings_s"]["georeferencing"] = reporter.timings_s["georeferencing"]
        report["pair_cache"] = _relative_to(cache.path, sidecar_path(output).parent) if cache.keep else None
        report["summary"]["pairs_from_cache"] = cache.hits
        report["timings_s"]["total"] = time.perf_counter() - started
        # The sidecar is staged with the images and renamed last: a run that fails while writing leaves
        # the earlier run's files, all of them, and never new images beside an old sidecar.
        if frameset.lens_fit is not None and frameset.lens is not None:  # the fitted lens, for the next run and for ODM
            atomic_write_bytes(staged.path_for(cameras_path(output)), (json.dumps(frameset.lens.to_cameras_json(), indent=1) + "\n").encode())
            report["camera"]["file"] = cameras_path(output).name
        write_report_page(report, staged, output)  # NAME.report.html, from the same results as the sidecar
        atomic_write_bytes(staged.path_for(sidecar_path(output)), (json.dumps(report, indent=1) + "\n").encode())
        staged.publish()
    finally:
        staged.discard()  # after a failure; nothing is left to discard after publish()
    _remove_stale_parts(output, parts, reporter, report)
    report["sidecar"] = str(sidecar_path(output))
    return report


# ------------------------------------------------------------------------------------------ steps


def _georeference(frameset: FrameSet, parts: list[Part], report: dict[str, Any], staged: StagedFiles, reporter: Reporter,
                  gcps=None, gcp_image_width: int | None = None, output: Path | None = None) -> None:
    """World and projection files for every written part placed by ground-control points (``gcps``) or else
    by its frames' GPS (see :mod:`.gcp`, :mod:`.georef`), staged with the images; the sidecar's parts get
    their ``georeference``."""
    if gcps is not None:
        _georeference_by_gcps(frameset, parts, report, staged, reporter, gcps, gcp_image_width)
        return
    with_gps = {f.index: f.metadata for f in frameset.frames if f.metadata is not None and f.metadata.has_gps}
    if not with_gps:
        return
    if importlib.util.find_spec("pyproj") is None:
        reporter.warn("the frames carry GPS, but georeferencing needs pyproj: pip install pyproj (from the udh checkout: "
                      "pip install '.[geo]'); the mosaic is written without a world file")
        return
    if len(with_gps) < len(frameset.frames):
        reporter.warn(f"{len(frameset.frames) - len(with_gps)} of {len(frameset.frames)} frames carry no GPS; the map rests on the others")
    records = {r["index"]: r for r in report["frames"]}
    by_number = {entry["part"]: entry for entry in report["parts"]}
    placed: list[tuple[Part, Any]] = []
    for part in parts:
        if part.canvas is None or part.number not in by_number:
            continue
        entries = [(i, frameset.frames[i].size, np.asarray(records[i]["mosaic_from_frame"]), with_gps[i].latitude, with_gps[i].longitude)
                   for i in part.frames if i in with_gps and records[i]["mosaic_from_frame"] is not None]
        found = georeference_part(entries, min_frames=2)
        by_number[part.number]["georeference"] = None if found is None else found.to_json()
        if found is None:
            reporter.warn(f"{part.file.name}: fewer than 2 placed frames with GPS; written without a georeference")
            continue
        if len(found.frames_used) < MIN_GPS_FRAMES:
            reporter.warn(f"{part.file.name}: placed by 2 frames' GPS only, with nothing to check the placement")
        placed.append((part, found))
        if found.frames_rejected:
            names = ", ".join(frameset.frames[i].name for i in found.frames_rejected)
            reporter.warn(f"{part.file.name}: the GPS of {names} disagrees with the other frames' by far (a bad fix); left out of the georeference")
        _write_georeference(part, found, staged, by_number[part.number], reporter)
        reporter.info(f"{part.file.name}: georeferenced in EPSG:{found.epsg} from {len(found.frames_used)} frames' GPS, "
                      f"{found.residual_rms_m:.1f} m RMS, {found.pixel_size_m * 100:.1f} cm per pixel")
    if len(placed) > 1 and output is not None and has_rasterio():
        _write_combined_map(placed, frameset, report, staged, reporter, output)


def _write_combined_map(placed: list, frameset: FrameSet, report: dict[str, Any], staged: StagedFiles, reporter: Reporter, output: Path) -> None:
    """The parts of a split run in one north-up GeoTIFF, each placed by its own frames' GPS: GPS ties together
    what no estimated pair could. The largest part is drawn on top; the others' frames rest on GPS alone."""
    epsg = max(placed, key=lambda item: len(item[0].frames))[1].epsg  # the largest part's zone
    same_zone = sorted((item for item in placed if item[1].epsg == epsg), key=lambda item: -len(item[0].frames))
    if len(same_zone) < len(placed):
        reporter.warn(f"{len(placed) - len(same_zone)} part(s) lie in another UTM zone than EPSG:{epsg} and are left out of the one map")
    layers = []
    for part, found in same_zone:
        image = _staged_bgra(staged, part)
        if image is None:
            reporter.warn(f"{part.file.name}: its image could not be read back; left out of the one map")
            continue
        layers.append((image, found.map_from_mosaic))
    if len(layers) < 2:
        return
    try:
        written = write_combined_cog(layers, epsg, staged.path_for(cog_path(output)))
    except UdhError as exc:  # the one map is an extra: the parts and their own georeferences still stand
        staged.forget(cog_path(output))
        reporter.warn(f"no combined map: {exc}")
        return
    on_gps_alone = sum(len(part.frames) for part, _ in same_zone[1:])
    report["map"] = {**written, "file": cog_path(output).name, "crs": f"EPSG:{epsg}", "parts": len(same_zone),
                     "frames": sum(len(part.frames) for part, _ in same_zone), "frames_on_gps_alone": on_gps_alone}
    reporter.info(f"{cog_path(output).name}: {len(same_zone)} parts in one map, placed by GPS; {on_gps_alone} frames "
                  f"rest on GPS alone (outside the largest part)")


def _staged_bgra(staged: StagedFiles, part: Part) -> MosaicImage | None:
    """A part's mosaic as written this run (its staged file): a streamed TIFF read window by window, else the
    image read whole as (H, W, 4) BGRA; None if it cannot be read."""
    temporary = staged.temporary_of(part.file)
    if temporary is None:
        return None
    if streams_to_file(part.file):
        try:
            return MosaicImage(path=temporary)
        except UdhError:
            return None
    image = cv2.imread(str(temporary), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 3 or image.dtype != np.uint8:
        return None
    return MosaicImage(array=image if image.shape[2] == 4 else cv2.cvtColor(image, cv2.COLOR_BGR2BGRA))  # a JPEG mosaic has no alpha


def _write_georeference(part: Part, found, staged: StagedFiles, entry: dict[str, Any], reporter: Reporter) -> None:
    """Stage a georeferenced part's world file, .prj and north-up COG (when rasterio is installed)."""
    atomic_write_bytes(staged.path_for(world_file_path(part.file)), world_file_text(found).encode())
    atomic_write_bytes(staged.path_for(part.file.with_suffix(".prj")), projection_text(found.epsg).encode())
    georeference_mosaic_file(part.file, found.map_from_mosaic, found.epsg, staged)  # GDAL reads neither of the two above for a rotated PNG
    if not has_rasterio():
        reporter.warn("no north-up GeoTIFF: it needs rasterio (pip install rasterio; from the udh checkout: pip install '.[geo]')")
        return
    mosaic = _staged_bgra(staged, part)
    if mosaic is None:
        reporter.warn(f"{part.file.name}: its image could not be read back for the GeoTIFF; written without one")
        return
    try:
        written = write_cog(mosaic, found.map_from_mosaic, found.epsg, staged.path_for(cog_path(part.file)))
    except UdhError as exc:  # the GeoTIFF is an extra: the mosaic and its world file still stand
        staged.forget(cog_path(part.file))
        reporter.warn(f"{part.file.name}: no north-up GeoTIFF: {exc}")
        return
    entry["geotiff"] = {**written, "file": cog_path(part.file).name}


def _georeference_by_gcps(frameset: FrameSet, parts: list[Part], report: dict[str, Any], staged: StagedFiles, reporter: Reporter,
                          gcps, gcp_image_width: int | None) -> None:
    records = {r["index"]: r for r in report["frames"]}
    by_number = {entry["part"]: entry for entry in report["parts"]}
    for part in parts:
        if part.canvas is None or part.number not in by_number:
            continue
        inside = set(part.frames)
        frames = {f.name: (f.size, np.asarray(records[f.index]["mosaic_from_frame"]) if f.index in inside and records[f.index]["mosaic_from_frame"] else None)
                  for f in frameset.frames}
        try:
            found = fit_gcps(gcps, frames, gcp_image_width)
        except UdhError as exc:
            by_number[part.number]["georeference"] = None
            reporter.warn(f"{part.file.name}: not georeferenced: {exc}")
            continue
        check_gcp_fit(found, lambda width: fit_gcps(gcps, frames, width), gcp_image_width, frameset.frames)  # before any map
        by_number[part.number]["georeference"] = found.to_json()
        in_solve = report["config"].get("gcp_sigma_m", 0.0) > 0  # then a checkpoint left out of the fit was still in the solve
        by_number[part.number]["georeference"]["gcp_points_in_solve"] = in_solve
        by_number[part.number]["georeference"]["gcp_image_width"] = gcp_image_width  # None: the frames' own pixels
        for name, point in found.points.items():
            if not point["used"]:
                reporter.warn(f"{name}: contradicts the other ground-control points ({point['checkpoint_m']:.1f} m off when left out); "
                              f"reported and left out of the fit")
        for line in found.skipped[:5]:
            reporter.warn(f"GCP skipped: {line}")
        _write_georeference(part, found, staged, by_number[part.number], reporter)
        used = sum(p["used"] for p in found.points.values())
        reporter.info(f"{part.file.name}: georeferenced in EPSG:{found.epsg} by {used} ground-control points, "
                      f"{found.checkpoint_rms_m:.2f} m RMS at checkpoints (each point left out of the fit in turn"
                      + ("; optimistic, as the points also anchor the solve)" if in_solve else ")"))
        for line in residual_lines(found):
            reporter.info(line)


def _relative_to(path: Path, folder: Path) -> str:
    """``path`` as the sidecar records it: relative to the sidecar's folder (the mosaic can move with its
    files), absolute only where no relative path exists (another drive)."""
    try:
        return os.path.relpath(Path(path).absolute(), Path(folder).absolute())
    except ValueError:
        return str(Path(path).absolute())


def own_files(output: Path) -> list[Path]:
    """Outputs of this run (or an earlier one), which must never be read back as frames."""
    return ([output, sidecar_path(output), preview_path(output), cache_path(output), cog_path(output), live_picture_path(output),
             live_record_path(output), cameras_path(output), report_page_path(output), pam_path(output)]
            + [p for p in output.parent.glob(f"{output.stem}.part*")])


def _load_truth(source: Path, ground_truth: str | Path | None) -> dict | None:
    if ground_truth is not None:
        return load_ground_truth(ground_truth)
    auto = source / GROUND_TRUTH_FILE
    return load_ground_truth(auto) if source.is_dir() and auto.is_file() else None


def _estimate_sequence(frameset: FrameSet, opinions, config: MosaicConfig, reporter: Reporter, cache: PairCache, runner) -> list[PairResult]:
    """Consecutive pairs, then a bridge over each broken link (i-1 -> i+1 and i -> i+2)."""
    frames = frameset.frames
    args = (frames, opinions, acceptance(config), reporter)
    pairs = estimate_pairs([PairRequest(i, i + 1, "consecutive") for i in range(len(frames) - 1)], *args, "consecutive pairs", config.batch_size, cache, runner)
    broken = [p for p in pairs if not p.ok]
    for pair in broken:
        reporter.warn(f"pair {frames[pair.a].name} -> {frames[pair.b].name} failed ({pair.reason}); trying to bridge it")
    bridges = sorted({(a, b) for p in broken for a, b in ((p.a - 1, p.b), (p.a, p.b + 1)) if a >= 0 and b < len(frames)})
    if bridges:
        pairs += estimate_pairs([PairRequest(a, b, "bridge") for a, b in bridges], *args, "bridging gaps", config.batch_size, cache, runner)
    return pairs


def _bridge_by_gps(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], opinions, config: MosaicConfig,
                   reporter: Reporter, cache: PairCache, runner) -> list[PairResult]:
    """Pairs between parts (lone frames included) that GPS puts close together on the ground; an estimate that
    disagrees with GPS about the frames' distance is rejected (:mod:`.gps_pairs`)."""
    frames = frameset.frames
    if config.gps_pairs < 1 or len(parts) < 2:
        return []
    fixes = _gps_fixes(frames)
    if len(fixes) < 2:
        return []
    try:
        _, positions = ground_positions(fixes)
    except UdhError:  # no pyproj: the georeferencing step says how to install it
        return []
    sizes = [f.size for f in frames]
    scale = measure_ground_scale(positions, [(p.a, p.b, p.b_from_a) for p in pairs if p.ok], sizes)
    if scale is None:
        reporter.warn("the frames carry GPS, but too few pairs worked to measure the ground scale; the parts are not bridged by GPS")
        return []
    known = {(min(p.a, p.b), max(p.a, p.b)) for p in pairs}
    candidates = bridge_candidates(positions, [part.frames for part in parts], known, scale.reach_m, config.gps_pairs)
    if not candidates:
        return []
    results = estimate_pairs([PairRequest(a, b, "gps") for a, b, _ in candidates], frames, opinions, acceptance(config),
                             reporter, "GPS bridges between parts", config.batch_size, cache, runner)
    part_of = {i: part for part in parts for i in part.frames}
    placed = {id(part): part_map(positions, part.chained, sizes) for part in parts if len(part.frames) >= 3}
    for result in results:
        if not result.ok:
            continue
        # Through whichever part GPS places on the map (the larger first): where the estimate puts the other frame.
        checks = sorted([(result.a, result.b, geometry.invert(result.b_from_a)), (result.b, result.a, result.b_from_a)],
                        key=lambda c: -len(part_of[c[0]].frames))
        through = next(((f, o, h) for f, o, h in checks if placed.get(id(part_of[f])) is not None), None)
        if through is not None:
            frame, other, frame_from_other = through
            off, limit = placement_error_m(frame_from_other, frame, other, part_of[frame].chained[frame], placed[id(part_of[frame])], positions, sizes)
            what = f"places {frames[other].name} {off:.0f} m from its GPS position (limit {limit:.0f} m)"
        else:
            off, limit = gps_disagreement_m(result.b_from_a, result.a, result.b, positions, sizes, scale), gps_limit_m(scale)
            what = f"puts the frames {off:.0f} m further apart or closer than their GPS does (limit {limit:.0f} m)"
        if off > limit:
            result.status, result.b_from_a, result.reason = "rejected", None, what
    reporter.info(f"GPS: {sum(r.ok for r in results)} of {len(results)} pairs between parts joined them "
                  f"(ground scale {scale.metres_per_pixel * 100:.1f} cm per pixel from {scale.pairs_used} pairs, reach {scale.reach_m:.0f} m)")
    return results


def _chain_parts(frameset: FrameSet, pairs: list[PairResult]) -> list[Part]:
    parts = []
    for members in connected_parts(len(frameset.frames), pairs):
        reference = reference_frame(members)
        chained, tree = chain_to_reference(members, reference, pairs)
        parts.append(Part(0, members, reference, chained, dict(chained), tree))
    for number, part in enumerate((p for p in parts if len(p.frames) > 1), start=1):
        part.number = number
    return parts


# Rounds of loop closure at most (fewer when a round accepts nothing new). After each, the pairs are solved
# together, and from that solve the rejected loop pairs are estimated again and frames without a far partner get
# one. Why: over a long survey the chain drifts, so the pairs that close the longest loops (a strip's far end
# against its neighbour) get a prior 100+ px off and fail, and some overlaps do not show in the drifted
# footprints at all. On a simulated 1,988-frame survey all 415 such rejections were wrong (111 px median from
# the truth) and the last strip drifted by up to 850 px; with the rounds its frames were 2.87 px median from the
# truth after the best homography of the plane (26.3 px before).
LOOP_ROUNDS = 4


def _close_loops(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], opinions, config: MosaicConfig, reporter: Reporter, cache: PairCache,
                 runner) -> list[PairResult]:
    """Estimate non-consecutive overlapping pairs, pre-warped by the chain, and reject those that contradict it;
    then, from a solve with the accepted ones, estimate the rejected ones again and add a far partner for every
    frame without one (:data:`LOOP_ROUNDS`). Each pair appears once in the result, as last estimated."""
    frames = frameset.frames
    sizes = [f.size for f in frames]
    known = {(min(p.a, p.b), max(p.a, p.b)) for p in pairs}
    # Priors and candidates come from Part.solved: the chain at first, then each round's solve.
    wanted = {id(part): [(a, b) for a, b, _ in overlap_candidates(part.frames, part.solved, sizes, known, config.overlap_min, config.overlap_per_frame)]
              for part in parts if len(part.frames) >= 3}
    results: dict[tuple[int, int], PairResult] = {}
    for round_number in range(LOOP_ROUNDS):
        requests, requested = [], []
        for part in parts:
            for a, b in wanted.get(id(part), []):
                requested.append((a, b))
                prior = geometry.invert(part.solved[b]) @ part.solved[a]
                requests.append(PairRequest(a, b, "overlap", prior / prior[2, 2]))
        if not requests:
            break
        stage = "loop-closure pairs" if round_number == 0 else f"loop-closure pairs again, from the solve ({round_number + 1})"
        for result in estimate_pairs(requests, frames, opinions, acceptance(config), reporter, stage, config.batch_size, cache, runner):
            results[(result.a, result.b)] = result
            if not result.ok:
                continue
            w, h = frames[result.b].size
            disagreement = corner_disagreement_px(result.b_from_a, result.prior, frames[result.a].size)
            if disagreement > config.max_disagreement * float(np.hypot(w, h)):
                result.status = "rejected"
                result.reason = (f"moves the corners {disagreement:.0f} px away from the "
                                 f"{'chained' if round_number == 0 else 'solved'} prediction (limit {config.max_disagreement:.0%} of the diagonal)")
                result.b_from_a = None
        retry = {(r.a, r.b) for r in results.values() if r.status == "rejected"}
        if round_number > 0 and all(key in retry for key in requested):
            break  # nothing new accepted: a new solve would predict the same
        if round_number + 1 == LOOP_ROUNDS:
            break
        tried = known | set(results)
        solving = [part for part in parts if id(part) in wanted]
        with reporter.stage("loop-closure solves", len(solving)) as advance:
            for part in solving:
                members = set(part.frames)
                used = [p for p in [*pairs, *results.values()] if p.ok and p.a in members and p.b in members]
                # From the previous round's solve, which the pairs it had already hold: nearer this round's answer
                # than the drifted chain is.
                part.solved = solve_part(part.reference, part.solved, sizes, [pair_points(p, sizes[p.a], sizes[p.b]) for p in used], config.huber_px)
                # The solve also shows overlaps the drifted chain hid: a far partner (the next strip) for every frame
                # that has none yet, one per frame and round, so the work stays about one pair per untied frame.
                tied = {f for p in used if abs(p.b - p.a) > NEAR_IN_SEQUENCE for f in (p.a, p.b)}
                found = [(a, b) for a, b, _ in overlap_candidates(part.frames, part.solved, sizes, tried, config.overlap_min, 1)
                         if b - a > NEAR_IN_SEQUENCE and not (a in tied and b in tied)]
                wanted[id(part)] = [key for key in wanted[id(part)] if key in retry] + found
                advance(1)
    return list(results.values())


def _gps_fixes(frames) -> dict[int, tuple[float, float]]:
    """Frame index -> (latitude, longitude) of every frame whose EXIF carries GPS."""
    return {f.index: (f.metadata.latitude, f.metadata.longitude) for f in frames if f.metadata is not None and f.metadata.has_gps}


def solve_anchors(frameset: FrameSet, config: MosaicConfig, reporter: Reporter, gcps=None, gcp_image_width: int | None = None,
                  leave_out: str | None = None) -> Anchors | None:
    """The anchors of the global solve: ground-control observations (``config.gcp_sigma_m``), GPS fixes
    (``config.gps_sigma_m``), or both when they share a CRS; None for none. ``leave_out``: a ground-control
    point to leave out (checking it honestly)."""
    sizes = [f.size for f in frameset.frames]
    found = None
    if config.gcp_sigma_m > 0 and gcps is None:
        reporter.warn(f"--gcp-sigma {config.gcp_sigma_m}: no ground-control file (--gcp); the solve does without it")
    if config.gcp_sigma_m > 0 and gcps is not None:
        frames = {f.name: (f.index, f.size) for f in frameset.frames}
        found = gcp_anchors(gcps, frames, config.gcp_sigma_m, gcp_image_width, leave_out)
    if config.gps_sigma_m > 0:
        fixes = _gps_fixes(frameset.frames)
        if not fixes:
            reporter.warn(f"--gps-sigma {config.gps_sigma_m}: no frame carries GPS; the solve does without it")
        else:
            epsg, positions = ground_positions(fixes)
            gps = Anchors.frame_centres(positions, sizes, config.gps_sigma_m)
            if found is not None and epsg != gcps.epsg:
                reporter.warn(f"--gps-sigma: the GPS fixes are in EPSG:{epsg}, the ground-control points in EPSG:{gcps.epsg}; "
                              "the solve is anchored by the ground-control points alone")
            else:
                found = gps if found is None else found + gps
    return found


def _focal_px(frameset: FrameSet, part: Part) -> tuple[float, str]:
    """The focal length the camera-model solve holds for ``part``, pixels, and where it came from: a --camera
    file's, else its frames' EXIF 35 mm equivalent, else :data:`.lens_fit.DEFAULT_FOCAL` of the longer side."""
    longest = max(frameset.frames[part.reference].size)
    if frameset.lens is not None:
        return float(frameset.lens.focal_x * longest), "the --camera file"
    focal, source = frames_focal([frameset.frames[i] for i in part.frames])
    return focal * longest, source


def _solve_cameras(frameset: FrameSet, part: Part, points: list, config: MosaicConfig, reporter: Reporter,
                   anchors: Anchors | None) -> None:
    """--solve camera on one part after its homography solve: ``part.cameras`` and ``part.solved`` from the
    camera model; a part it cannot serve (frames of two sizes, no finite cameras) keeps the homography solve,
    with a warning."""
    sizes = [f.size for f in frameset.frames]
    name = frameset.frames[part.reference].name
    if len({sizes[i] for i in part.frames}) > 1:
        reporter.warn(f"--solve camera: the part of {name} mixes frame sizes, so not one camera; it keeps the homography solve")
        return
    focal, part.focal_source = _focal_px(frameset, part)
    try:
        part.cameras = solve_cameras(part.reference, part.solved, sizes, points, focal, config.huber_px, anchors=anchors)
    except UdhError as error:
        reporter.warn(f"--solve camera: the part of {name} keeps the homography solve ({error})")
        return
    part.solved = part.cameras.ref_from


def _solve(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], config: MosaicConfig, reporter: Reporter,
           anchors: Anchors | None = None) -> dict[str, Any]:
    """Global solve per part (with ``anchors``, :func:`solve_anchors`); fills every pair's consistency figures
    and returns the loop summaries."""
    sizes = [f.size for f in frameset.frames]
    loops_before, loops_after, all_after = [], [], []
    multi = [p for p in parts if len(p.frames) > 1]
    with reporter.stage("global solve", len(multi)) as advance:
        for part in multi:
            members = set(part.frames)
            inside = [p for p in pairs if p.ok and p.a in members and p.b in members]
            points = [pair_points(p, sizes[p.a], sizes[p.b]) for p in inside]
            # From the loop rounds' last solve when there was one (Part.solved starts as the chain).
            part.solved, dropped = solve_with_rejection(
                part.reference, part.solved, sizes, points, [p.kind == "overlap" or (p.kind == "gps" and id(p) not in part.tree) for p in inside],
                config.huber_px, config.outlier_px, anchors=anchors
            )
            for i, residual in dropped.items():  # loop pairs the other pairs contradict
                inside[i].consistency_px = {"before": pair_rms_px(part.chained, points[i]), "after": residual, "loop": True}
                inside[i].status, inside[i].b_from_a = "rejected", None
                inside[i].reason = (f"contradicted by the other pairs{' and the anchors' if anchors is not None else ''}: "
                                    f"{residual:.1f} px from the joint solution, which improved without it")
            inside = [p for i, p in enumerate(inside) if i not in dropped]
            points = [p for i, p in enumerate(points) if i not in dropped]
            if config.solve == "camera":
                _solve_cameras(frameset, part, points, config, reporter, anchors)
            for pair, pts in zip(inside, points):
                before, after = pair_rms_px(part.chained, pts), pair_rms_px(part.solved, pts)
                pair.consistency_px = {"before": before, "after": after, "loop": id(pair) not in part.tree}
                all_after.append(after)
                if id(pair) not in part.tree:
                    loops_before.append(before)
                    loops_after.append(after)
            # The camera model's ground, whatever --rectify says: the model knows it. Otherwise anchors already put
            # the plane on the ground (solve.solve_part), and without them --rectify puts it there here. Both after
            # the consistency figures, which stay in the reference frame's pixels.
            if part.cameras is not None:
                plane = keep_reference_view(part.cameras.ground_from_ref, part.solved, sizes, part.reference, config.max_frame_scale)
                if plane is None:
                    reporter.warn(f"--solve camera: drawing the part of {frameset.frames[part.reference].name} on the cameras' ground "
                                  "would fold a frame; it is drawn in its reference frame's view")
            elif config.rectify and anchors is None:
                plane = rectifying_homography(part.solved, sizes, part.reference, config.max_frame_scale)
            else:
                plane = None
            if plane is not None:
                part.solved = {i: plane @ h for i, h in part.solved.items()}
                part.rectified = True
            advance(1)
    return {
        "units": "pixels of each part's reference frame at full resolution",
        "loops_before": summarise(loops_before),
        "loops_after": summarise(loops_after),
        "all_pairs_after": summarise(all_after),
    }


def _plan_canvases(frameset: FrameSet, parts: list[Part], output: Path, config: MosaicConfig) -> None:
    """Every canvas is planned (and a too-big one refused) before any pixel is written."""
    sizes = [f.size for f in frameset.frames]
    for part in parts:
        # A long chain can carry a frame past the horizon of the reference's plane: report it, do not draw it.
        for i in list(part.frames):
            if not geometry.is_valid_homography(part.solved[i], *sizes[i], max_scale=config.max_frame_scale):
                part.dropped[i] = (f"its homography to the reference frame {frameset.frames[part.reference].name} is degenerate "
                                   f"(folded, past the horizon or scaled over {config.max_frame_scale:g}x; see --max-frame-scale)")
                part.frames.remove(i)
    multi = [p for p in parts if len(p.frames) > 1]
    if not multi:
        raise UdhError("no pair of frames could be matched, so nothing can be mosaicked; try --fallback sift or a larger --work-size")
    for number, (part, path) in enumerate(zip(multi, output_paths(output, len(multi))), start=1):
        part.number = number
        part.canvas = compositing.plan_canvas({i: part.solved[i] for i in part.frames}, sizes, config.blend, config.max_size,
                                              config.max_canvas_bytes, assembled=not streams_to_file(path), one_tile=frameset.is_video)
        part.file = path


def _composite_part(frameset: FrameSet, part: Part, config: MosaicConfig, reporter: Reporter, staged: StagedFiles) -> dict[int, list[float]]:
    """Composite one part and write its image and preview under the temporary names of ``staged``; returns
    each frame's mean exposure gain per channel."""
    if part.canvas is None:
        return {}
    to_mosaic = {i: part.canvas.mosaic_from_ref @ part.solved[i] for i in part.frames}
    suffix = "" if part.number == 1 else f" part {part.number}"
    gains, seams = None, None
    want_seams = config.seams != "central" and config.blend != "feather"
    if config.exposure != "none" or want_seams:
        small = draw_small(frameset, to_mosaic, part.canvas.scale, reporter, f"small copies{suffix}")
        with reporter.stage("colour and seams", 1, f"colour and seams{suffix}") as advance:
            gains = exposure_gains(config.exposure, small)
            seams = find_seams(config.seams, small) if want_seams else None
            advance(1)
    tiles = compositing.composite_tiles(frameset, to_mosaic, part.canvas.size, config.blend, reporter, f"compositing{suffix}", gains, seams,
                                        workers=config.workers)
    drawer = compositing.PreviewDrawer(part.canvas.size)
    if streams_to_file(part.file):  # blended and written tile by tile: the map's area costs no memory
        write_tiled_tiff(staged.path_for(part.file), part.canvas.size, _drawn(tiles, drawer))
    else:
        mosaic = compositing.assemble(_drawn(tiles, drawer), part.canvas.size)
        with reporter.stage("writing", 1) as advance:
            if part.file.suffix.lower() in (".jpg", ".jpeg"):
                reporter.warn(f"{part.file.name}: JPEG has no alpha channel; uncovered areas are black (use .png or .tif to keep the mask)")
                write_image(staged.path_for(part.file), mosaic[..., :3])
            else:
                write_image(staged.path_for(part.file), mosaic)
            advance(1)
        del mosaic
    if config.preview:
        part.preview = preview_path(part.file)
        write_image(staged.path_for(part.preview), drawer.image())
    return {i: mean_gain(gains[i]) if gains is not None else [1.0, 1.0, 1.0] for i in part.frames}


def streams_to_file(path: Path) -> bool:
    """Whether a mosaic written to ``path`` streams tile by tile (a TIFF, with rasterio) rather than being held
    whole to be encoded (PNG, JPEG)."""
    return path.suffix.lower() in (".tif", ".tiff") and has_rasterio()


def _drawn(tiles, drawer: "compositing.PreviewDrawer"):
    """``tiles`` passed on, each also drawn into the preview."""
    for box, tile in tiles:
        drawer.add(box, tile)
        yield box, tile


def _warn_about_earlier_output(output: Path, parts: list[Part], reporter: Reporter) -> None:
    """A split run does not write ``output`` itself: one there now is an earlier run's and is left alone."""
    written = [p for p in parts if p.canvas is not None]
    if len(written) > 1 and output.is_file():
        reporter.warn(f"{output.name} is left from an earlier run: this run is split into parts, which are written as {written[0].file.name}, ...")


def _part_number(parts: list[Part], mosaic: Path) -> int | None:
    return next((p.number for p in parts if p.file == mosaic), None)


def _remove_stale_parts(output: Path, parts: list[Part], reporter: Reporter, report: dict[str, Any] | None = None) -> None:
    """Remove part files of this output name (an earlier run with more parts) that this run did not write, and
    the georeference files (world, .prj, GeoTIFF) of an earlier run that this run did not write again: an old
    world file beside a new mosaic would put it on the map in the wrong place."""
    produced = [f for p in parts for f in (p.file, p.preview) if f is not None and p.canvas is not None]
    entries = {e["part"]: e for e in (report or {}).get("parts", [])}
    georeferenced = [p.file for p in parts if p.canvas is not None and (entries.get(p.number) or {}).get("georeference")]
    produced += [f for mosaic in georeferenced for f in (world_file_path(mosaic), mosaic.with_suffix(".prj"), pam_path(mosaic))]
    produced += [cog_path(mosaic) for mosaic in georeferenced if (entries.get(_part_number(parts, mosaic)) or {}).get("geotiff")]
    if (report or {}).get("map"):
        produced.append(cog_path(output))
    stale = stale_part_files(output, produced)
    for mosaic in [output, *(p.file for p in parts if p.file is not None)]:
        stale += [f for f in (world_file_path(mosaic), mosaic.with_suffix(".prj"), cog_path(mosaic), pam_path(mosaic))
                  if f.is_file() and f.resolve() not in {g.resolve() for g in produced} and f not in stale]
    for path in stale:
        try:
            path.unlink()
        except OSError as exc:
            reporter.warn(f"{path.name} is left from an earlier run and could not be removed ({exc.strerror})")
    if stale:
        reporter.info(f"removed {len(stale)} part files of an earlier run: {', '.join(p.name for p in stale)}")


def _sidecar(frameset: FrameSet, parts, pairs, gains, loops, truth, config, opinions, reporter: Reporter,
             folder: Path) -> dict[str, Any]:
    """The sidecar's content; its paths are relative to ``folder``, where it is written."""
    method, fallback = opinions[0], (opinions[1] if len(opinions) > 1 else None)
    frames = frameset.frames
    part_of = {i: part for part in parts for i in part.frames}
    dropped = {i: reason for part in parts for i, reason in part.dropped.items()}
    records = []
    for frame in frames:
        part = part_of.get(frame.index)
        placed = part is not None and part.canvas is not None
        mosaic_from_frame = part.canvas.mosaic_from_ref @ part.solved[frame.index] if placed else None
        reason = None if placed else dropped.get(frame.index) or _unplaced_reason(frame.index, pairs, frames)
        if not placed:
            reporter.warn(f"{frame.name} is not in any mosaic: {reason}")
        records.append(
            {
                "index": frame.index,
                "file": frame.name,
                "width": frame.size[0],
                "height": frame.size[1],
                "status": "placed" if placed else "unplaced",
                "reason": reason,
                "part": part.number if placed else None,
                "gain": float(np.mean(gains.get(frame.index, [1.0]))),
                "gain_bgr": gains.get(frame.index),
                "metadata": None if frame.metadata is None else frame.metadata.to_json(),
                "mosaic_from_frame": None if mosaic_from_frame is None else (mosaic_from_frame / mosaic_from_frame[2, 2]).tolist(),
                # --solve camera: how far the frame's camera looked from straight down (a check on oblique frames)
                "tilt_deg": part.cameras.tilt_deg.get(frame.index) if placed and part.cameras is not None else None,
            }
        )
    multi = [p for p in parts if p.canvas is not None]
    if len(multi) > 1:
        reporter.warn(f"the sequence is split into {len(multi)} parts, each written on its own: {', '.join(p.file.name for p in multi)}")
    report: dict[str, Any] = {
        "format": SIDECAR_FORMAT,
        "udh_version": __version__,
        "source": _relative_to(frameset.source, folder),
        "method": method.name,
        "method_settings": estimator_identity(method)["settings"],  # with the mosaic's defaults (search)
        "fallback": None if fallback is None else fallback.name,
        "fallback_settings": None if fallback is None else estimator_identity(fallback)["settings"],
        "config": {k: v for k, v in asdict(config).items() if k not in ("method", "fallback")},
        # 16-bit or float frames: the grey range drawn as 0-255 in the 8-bit mosaic (fractions of the type's maximum)
        "display_range": None if frameset.value_range is None else {"low": frameset.value_range[0], "high": frameset.value_range[1]},
        # the lens every frame was undistorted by, and (--camera estimate) how it was fitted
        "camera": None if frameset.lens is None and frameset.lens_fit is None else
                  {**(frameset.lens.to_json() if frameset.lens is not None else {}), "estimated": frameset.lens_fit},
        "parts": [
            {
                "part": p.number,
                "file": _relative_to(p.file, folder),
                "preview": None if p.preview is None else _relative_to(p.preview, folder),
                "width": p.canvas.size[0],
                "height": p.canvas.size[1],
                "scale": p.canvas.scale,
                "reference_frame": p.reference,
                "plane": ("ground (camera model)" if p.cameras is not None else "ground (rectified)") if p.rectified else "reference frame",
                # --solve camera: the shared focal length and how far each camera looked from straight down
                "cameras": None if p.cameras is None else {
                    "focal_px": p.cameras.focal_px,
                    "focal_source": p.focal_source,
                    "tilt_deg": {"median": float(np.median([p.cameras.tilt_deg[i] for i in p.frames])),
                                 "max": max(p.cameras.tilt_deg[i] for i in p.frames)},
                },
                "frames": p.frames,
            }
            for p in multi
        ],
        "frames": records,
        "skipped_files": frameset.skipped,
        "pairs": [p.to_json() for p in pairs],
        "loop_consistency": loops,
        "summary": {
            "frames": len(frames),
            "placed": sum(r["status"] == "placed" for r in records),
            "unplaced": sum(r["status"] != "placed" for r in records),
            "skipped_files": len(frameset.skipped),
            "parts": len(multi),
            "pairs_ok": sum(p.ok for p in pairs),
            "pairs_failed": sum(p.status == "failed" for p in pairs),
            "pairs_rejected": sum(p.status == "rejected" for p in pairs),
            "gps_pairs_joined": sum(p.ok and p.kind == "gps" for p in pairs),
        },
        "warnings": reporter.warnings,
        "timings_s": dict(reporter.timings_s),
    }
    if truth is not None:
        before, after, shape = {}, {}, {}
        for p in multi:
            before.update(corner_errors_vs_truth(frames, p.reference, {i: p.chained[i] for i in p.frames}, truth))
            after.update(corner_errors_vs_truth(frames, p.reference, {i: p.solved[i] for i in p.frames}, truth))
            shape.update(map_shape_errors(frames, {i: p.solved[i] for i in p.frames}, truth))
        report["ground_truth_error"] = {
            "measure": "corner distance of frame->reference homographies vs the truth, reference-frame pixels",
            "chained": summarise_truth(before),
            "solved": summarise_truth(after),
            "per_frame_solved": {frames[i].name: v for i, v in sorted(after.items())},
            "map_shape": {"measure": "corner distance on the mosaic plane from the true ground positions after the best similarity, "
                                     "ground pixels, per frame", **summarise(list(shape.values()))},
        }
    return report


def _unplaced_reason(index: int, pairs: list[PairResult], frames) -> str:
    tried = [p for p in pairs if index in (p.a, p.b)]
    reasons = "; ".join(f"{frames[p.a].name}->{frames[p.b].name}: {p.reason}" for p in tried[:3])
    return f"no pair with it succeeded ({reasons})" if tried else "it has no neighbouring frame"
