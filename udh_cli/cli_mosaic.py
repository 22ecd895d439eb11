"""``udh mosaic``: the command whose options' choices and defaults live in the mosaic package, loaded by the
root group only when the command runs or shows its help (:class:`udh_cli.cli.LazyCommands`), so that ``udh --help``
and the other commands start without importing the mosaic."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from udh_cli.cli import LAZY_COMMANDS, METHOD_HELP, OPTION_HELP, Method, _choices, console, err_console
from udh_cli.estimators.registry import parse_method_options
from udh_cli.mosaic.render.composite import BLENDS as _BLENDS  # the --blend choices live there
from udh_cli.mosaic.live.follow import FollowConfig as _FollowConfig
from udh_cli.mosaic.render.gains import EXPOSURES as _EXPOSURES  # the --exposure choices live there
from udh_cli.mosaic.config import SOLVES as _SOLVES, MosaicConfig as _MosaicConfig  # the mosaic options' defaults live there
from udh_cli.mosaic.render.seams import SEAM_FINDERS as _SEAM_FINDERS  # the --seams choices live there
from udh_cli.mosaic.pairs.workers import MAX_AUTO_WORKERS as _MAX_AUTO_WORKERS, POOL_MIN_FRAMES as _POOL_MIN_FRAMES

app = typer.Typer(rich_markup_mode="rich", pretty_exceptions_enable=False, add_completion=False)
_MOSAIC = _MosaicConfig()
_FOLLOW = _FollowConfig()
Blend = _choices("Blend", _BLENDS)
Exposure = _choices("Exposure", _EXPOSURES)
SeamFinder = _choices("SeamFinder", _SEAM_FINDERS)
SolveModel = _choices("SolveModel", _SOLVES)


@app.command(help=LAZY_COMMANDS["mosaic"][1])
def mosaic(
    source: Annotated[Path, typer.Argument(metavar="SOURCE", help="Folder of JPEG/PNG/TIFF frames (consecutive frames overlap), or a video file.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Mosaic image (.png or .tif keep the alpha channel). Split runs write NAME.partK.png.")] = Path("mosaic.png"),
    method: Annotated[Method, typer.Option("--method", "-m", case_sensitive=False, metavar="NAME", help=METHOD_HELP)] = Method(_MOSAIC.method),
    fallback: Annotated[Optional[str], typer.Option("--fallback", help="Method for the pairs --method fails or doubts (e.g. sift).")] = _MOSAIC.fallback,
    method_option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    work_size: Annotated[int, typer.Option("--work-size", help="Longest side, pixels, of the copies the estimators see; homographies are rescaled exactly.")] = _MOSAIC.work_size,
    order: Annotated[str, typer.Option("--order", help="Frame order in a folder: name or time (EXIF capture time).")] = _MOSAIC.order,
    every: Annotated[int, typer.Option("--every", help="Video: keep every N-th frame.")] = _MOSAIC.every,
    min_confidence: Annotated[float, typer.Option("--min-confidence", help="Estimates below this confidence count as failed.")] = _MOSAIC.min_confidence,
    min_verified: Annotated[float, typer.Option("--min-verified", help="Estimates whose alignment check (the lower of intensity and gradient NCC at 256 px) is below this count as failed; 0: no check.")] = _MOSAIC.min_verified,
    blend: Annotated[Blend, typer.Option("--blend", case_sensitive=False, metavar="NAME", help=f"How overlapping frames are mixed: {', '.join(_BLENDS)}.")] = Blend(_MOSAIC.blend),
    max_size: Annotated[Optional[int], typer.Option("--max-size", help="Downscale the mosaic so its longest side is at most this many pixels.")] = _MOSAIC.max_size,
    max_frame_scale: Annotated[float, typer.Option("--max-frame-scale", help="Report (leave out) frames the solve draws more than this many times larger or smaller than the reference frame.")] = _MOSAIC.max_frame_scale,
    solve: Annotated[SolveModel, typer.Option("--solve", case_sensitive=False, metavar="NAME", help="The global solve's model: homography (a free one per frame) or camera (a pinhole camera per frame over flat ground, one focal length: no projective drift on long surveys, the map drawn on the ground).")] = SolveModel(_MOSAIC.solve),
    rectify: Annotated[bool, typer.Option("--rectify/--no-rectify", help="Without GPS or ground-control anchors, draw the map on the plane its frames look down on on average (nadir surveys) instead of in the reference frame's own view.")] = _MOSAIC.rectify,
    exposure: Annotated[Exposure, typer.Option("--exposure", case_sensitive=False, metavar="NAME", help="Exposure compensation (OpenCV's): per-channel gain maps over blocks, per-channel gains, one gain, or none (blocks, channels, gain, none).")] = Exposure(_MOSAIC.exposure),
    seams: Annotated[SeamFinder, typer.Option("--seams", case_sensitive=False, metavar="NAME", help="Seam finder (OpenCV's): dynamic programming (dp) or graph cut (graphcut) on colour, or central (each pixel from the frame that sees it nearest its centre).")] = SeamFinder(_MOSAIC.seams),
    overlap_per_frame: Annotated[int, typer.Option("--overlap-pairs", help="Loop-closure pairs per frame at most (0: plain chaining).")] = _MOSAIC.overlap_per_frame,
    gcp_sigma: Annotated[float, typer.Option("--gcp-sigma", min=0.0, help="With --gcp: the points' error in metres, e.g. 0.05; their observations then anchor the global solve (0: they only place the finished mosaic).")] = _MOSAIC.gcp_sigma_m,
    gps_sigma: Annotated[float, typer.Option("--gps-sigma", min=0.0, help="With GPS in the frames: the fixes' error in metres, e.g. 3; they then anchor the global solve and bound long-chain drift (0: off).")] = _MOSAIC.gps_sigma_m,
    gps_pairs: Annotated[int, typer.Option("--gps-pairs", min=0, help="With GPS in the frames: pairs tried between each two parts that GPS puts close together, e.g. 3 (0: off; short surveys split at a turn).")] = _MOSAIC.gps_pairs,
    workers: Annotated[Optional[int], typer.Option("--workers", min=1, show_default=False, help=f"Local processes estimating pairs at once (1: in this process). Default: one per core, at most {_MAX_AUTO_WORKERS}, for {_POOL_MIN_FRAMES} frames or more; 1 in live mode.")] = None,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Estimate pairs on a Dask cluster: the scheduler's address, e.g. tcp://host:8786.")] = _MOSAIC.scheduler,
    gt: Annotated[Optional[Path], typer.Option("--gt", help="Simulator ground truth (default: SOURCE/ground_truth.json when present) to report the corner error.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars; warnings and the summary only.", metavar="")] = False,
    resume: Annotated[bool, typer.Option("--resume", help="Keep every pair estimate in NAME.pairs.json as it is made, and reuse an earlier (interrupted) run's where frames, methods and settings match. Without it no cache file is written.", metavar="")] = False,
    gcp: Annotated[Optional[Path], typer.Option("--gcp", help="Ground-control points (OpenDroneMap's gcp_list.txt format) that place the mosaic on the map; each is checked by leaving it out.")] = None,
    gcp_image_width: Annotated[Optional[int], typer.Option("--gcp-image-width", help="Width in pixels of the images the --gcp file's pixels refer to, when not the frames' own (originals before downscaling).")] = None,
    camera: Annotated[Optional[Path], typer.Option("--camera", help="OpenSfM/OpenDroneMap cameras.json of the camera that took the frames: every frame is undistorted by its lens model; 'estimate' fits one radial k1 from the flight itself.")] = None,
    cache_dir: Annotated[Optional[Path], typer.Option("--cache-dir", help="Write the pair cache (NAME.pairs.json) in this folder instead of beside the mosaic; it is read only with --resume.")] = None,
    follow: Annotated[bool, typer.Option("--follow", help="Live: keep watching SOURCE (a folder) as frames arrive, draw each into NAME.live.jpg as it lands, refresh the mosaic every --refresh-every frames, finish when a DONE file appears or no frame comes for --idle-timeout.", metavar="")] = False,
    refresh_every: Annotated[int, typer.Option("--refresh-every", min=1, help="Live: rewrite the mosaic after this many new frames.")] = _FOLLOW.refresh_every,
    idle_timeout: Annotated[float, typer.Option("--idle-timeout", min=0.1, help="Live: seconds without a new frame that end the flight.")] = _FOLLOW.idle_timeout_s,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace files in the way of the outputs that no earlier run to OUTPUT wrote (a user's NAME.part1.png, another run's NAME.json); never removes them.")] = False,
) -> None:
    from udh_cli.mosaic import FollowConfig, Reporter, run_live, run_mosaic

    # -O reaches the method and the fallback alike: METHOD.KEY for one of them, a bare KEY for each that takes it.
    options = parse_method_options(method_option, [method.value, *([fallback] if fallback and fallback != method.value else [])])
    config = _MosaicConfig(
        method=method.value, fallback=fallback, method_options=options.get(method.value, {}), fallback_options=options.get(fallback, {}) if fallback else {}, work_size=work_size, order=order, every=every, min_confidence=min_confidence, min_verified=min_verified,
        blend=blend.value, max_size=max_size, max_frame_scale=max_frame_scale, rectify=rectify, solve=solve.value, exposure=exposure.value, seams=seams.value, overlap_per_frame=overlap_per_frame, gps_pairs=gps_pairs, gps_sigma_m=gps_sigma, gcp_sigma_m=gcp_sigma, workers=workers, scheduler=scheduler,
    )
    reporter = Reporter(console=err_console, progress=not quiet)
    if follow:
        live = FollowConfig(refresh_every=refresh_every, idle_timeout_s=idle_timeout)
        report = run_live(source, output, config, live, reporter, cache_dir=cache_dir, ground_truth=gt, gcp=gcp, gcp_image_width=gcp_image_width,
                          camera=camera, overwrite=overwrite)
    else:
        report = run_mosaic(source, output, config, reporter, ground_truth=gt, resume=resume, cache_dir=cache_dir, gcp=gcp,
                            gcp_image_width=gcp_image_width, camera=camera, overwrite=overwrite)
    _print_mosaic(report)


def _print_mosaic(report: dict) -> None:
    summary, loops = report["summary"], report["loop_consistency"]

    def px(stats: dict, key: str = "mean_px") -> str:
        return "-" if stats[key] is None else f"{stats[key]:.2f}"

    table = Table(title=f"udh mosaic ({report['method']}" + (f", fallback {report['fallback']})" if report["fallback"] else ")"), show_header=False)
    table.add_row("frames placed", f"{summary['placed']} of {summary['frames']}" + (f" ({summary['skipped_files']} files skipped)" if summary["skipped_files"] else ""))
    table.add_row("pairs", f"{summary['pairs_ok']} used, {summary['pairs_failed']} failed, {summary['pairs_rejected']} rejected")
    table.add_row("loop consistency (px)", f"before {px(loops['loops_before'])} mean / {px(loops['loops_before'], 'max_px')} max, after {px(loops['loops_after'])} / {px(loops['loops_after'], 'max_px')} ({loops['loops_after']['count']} loops)")
    if "ground_truth_error" in report:
        solved, chained = report["ground_truth_error"]["solved"], report["ground_truth_error"]["chained"]
        if solved["frames"]:
            table.add_row("error vs ground truth (px)", f"{solved['mean_corner_px']:.3f} mean, {solved['max_corner_px']:.3f} max corner (chained only: {chained['mean_corner_px']:.3f} / {chained['max_corner_px']:.3f})")
            shape = report["ground_truth_error"]["map_shape"]
            if shape["count"]:
                table.add_row("map shape vs ground truth (px)", f"{shape['median_px']:.3f} median, {shape['max_px']:.3f} max (corners after the best similarity)"
                              + _plane_hint(shape["median_px"], solved["mean_corner_px"], report["config"]))
        else:  # the truth names none of these frames (or not the reference): nothing to compare
            table.add_row("error vs ground truth (px)", "- (the ground truth names no placed frame with its reference)")
    for part in report["parts"]:
        shown = Path(report["sidecar"]).with_name(part["file"])  # the sidecar names it relative to its own folder
        table.add_row(f"mosaic part {part['part']}" if len(report["parts"]) > 1 else "mosaic", f"{shown} ({part['width']}x{part['height']}, {len(part['frames'])} frames)")
    cameras = [part["cameras"] for part in report["parts"] if part.get("cameras")]
    if cameras:  # --solve camera: what the solve assumed and found
        tilts = [c["tilt_deg"]["max"] for c in cameras]
        table.add_row("cameras", f"focal length {cameras[0]['focal_px']:.0f} px, held: {cameras[0]['focal_source']}; "
                                 f"tilt from straight down up to {max(tilts):.1f} degrees")
    table.add_row("sidecar", report["sidecar"])
    if report.get("report_page"):
        table.add_row("report", str(Path(report["sidecar"]).with_name(report["report_page"])))
    table.add_row("time (s)", ", ".join(f"{k} {v:.1f}" for k, v in report["timings_s"].items()))
    console.print(table)


def _plane_hint(shape_px: float, corner_px: float, config: dict) -> str:
    """A hint when the frames agree with each other but the map's plane is tilted (a run in the reference frame's view)."""
    if shape_px <= max(1.0, 5 * corner_px) or config.get("rectify") or config.get("solve") == "camera":
        return ""
    return "; the frames agree but the map is drawn in the reference frame's tilted view: try --rectify or --solve camera"
