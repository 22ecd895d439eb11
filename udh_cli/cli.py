"""The ``udh`` command line: thin commands over the library, and the one place errors become exit codes."""

from __future__ import annotations

import errno
import importlib
import inspect
import json
import signal
import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Callable, Optional

import typer
from typer.core import TyperCommand, TyperGroup
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from udh_cli import __version__
from udh_cli.errors import UdhError
from udh_cli.api import ESTIMATE_WORK_SIZE
from udh_cli.estimators.flags import OPTION_FLAGS, given_flags
from udh_cli.estimators.registry import DEFAULT_METHOD, ESTIMATORS, merge_flag_options, parse_method_options
from udh_cli.generator_settings import FlightConfig as _FlightConfig, GpsConfig as _GpsConfig, MotionConfig as _MotionConfig
from udh_cli.train.config import MOTIONS as _MOTIONS, TrainConfig as _TrainConfig
from udh_cli.models_catalog import licence_help

_TRAIN = _TrainConfig()  # the command line's defaults are the library's
_MOTION = _MotionConfig()
_FLIGHT = _FlightConfig()
_GPS = _GpsConfig(0.0, 0.0)

# Commands loaded only when invoked: the mosaic's options need the mosaic package at definition, and the bench
# group's commands would make this module too long. name -> (module defining ``app``, the one-line help the root lists).
LAZY_COMMANDS = {
    "mosaic": ("udh_cli.cli_mosaic", "Stitch a folder of UAV frames (or a video) into one mosaic, drift-free, with any estimator."),
    "bench": ("udh_cli.cli_bench", "Reproduce the paper's evaluation: every method side by side on the same pairs, with plots."),
}


class LazyCommands(TyperGroup):
    """The root group: lists each of :data:`LAZY_COMMANDS` by its help alone and imports it only when it is invoked
    (to run or to show its own help), so that ``udh --help`` and the light commands start quickly."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        groups = {name: command for name, command in self.commands.items() if isinstance(command, TyperGroup)}
        for name in groups:  # listed after the commands, as Typer lists them
            del self.commands[name]
        for name, (_, summary) in LAZY_COMMANDS.items():
            self.commands.setdefault(name, TyperCommand(name, help=summary))
        self.commands.update(groups)
        self._unloaded = set(LAZY_COMMANDS)

    def resolve_command(self, ctx: typer.Context, args: list[str]):
        if args and args[0] in self._unloaded:
            self.commands[args[0]] = typer.main.get_command(importlib.import_module(LAZY_COMMANDS[args[0]][0]).app)
            self._unloaded.discard(args[0])
        return super().resolve_command(ctx, args)


app = typer.Typer(
    name="udh",
    cls=LazyCommands,
    help="Fast, robust homography estimation and UAV image mosaicking (Unsupervised Deep Homography).",
    epilog="Exit codes: 0 done; 1 error (one line on stderr); 2 usage error; 3 udh estimate's answer did not verify; "
           "130 interrupted (Ctrl-C or SIGTERM).",
    no_args_is_help=True,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
    add_completion=False,
)
console = Console()
err_console = Console(stderr=True)


def _choices(name: str, values) -> type[Enum]:
    """A str Enum of ``values`` (taken from the library, never re-typed here): typer then checks the choice,
    matches it case-insensitively (with ``case_sensitive=False``) and completes it in the shell."""
    return Enum(name, {value: value for value in values}, type=str)


Method = _choices("Method", ESTIMATORS)
OPTION_HELP = ("An option of the method, [METHOD.]KEY=VALUE, repeatable: e.g. model=my.onnx, sift.ratio=0.8 (VALUE is read as "
               "JSON when it parses). A bare KEY goes to every method here that takes it; docs/estimators.md lists them.")
METHOD_HELP = "; ".join(f"[bold]{name}[/bold]: {description}" for name, (_, _, description) in ESTIMATORS.items())
_state = {"debug": False}
INTERRUPTED = 130  # the shell's exit code for Ctrl-C
UNVERIFIED = 3  # udh estimate: an answer was found but did not verify


def _version(value: bool) -> None:
    if value:
        console.print(f"udh {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks on errors.", metavar="")] = False,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version.", metavar="")] = False,
) -> None:
    _state["debug"] = debug


def _with_option_flags(command: Callable[..., None]) -> Callable[..., None]:
    """``command`` with a typed flag for each of :data:`OPTION_FLAGS` (after its own options, before ``-O``); the
    flags given reach it as ``flags``, keyed by option, to go where ``-O`` goes. Why generated: each option is
    described once, in the library's table."""
    own = [p for p in inspect.signature(command, eval_str=True).parameters.values() if p.name != "flags"]
    added = [inspect.Parameter(flag.key, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=None, annotation=Annotated[
        Optional[flag.kind], typer.Option(f"{flag.name}/--no-{flag.name[2:]}" if flag.switch else flag.name, min=flag.low,
                                          max=flag.high, help=flag.help)]) for flag in OPTION_FLAGS]

    def with_flags(**values) -> None:
        command(**{p.name: values[p.name] for p in own}, flags=given_flags(values))

    with_flags.__name__, with_flags.__doc__ = command.__name__, command.__doc__
    with_flags.__signature__ = inspect.Signature(own[:-1] + added + own[-1:])  # -O stays last in the help
    return with_flags


@app.command()
@_with_option_flags
def estimate(
    image_a: Annotated[Path, typer.Argument(metavar="IMAGE_A", help="Image A (any size; colour or grey; 8 or 16 bit).")],
    image_b: Annotated[Path, typer.Argument(metavar="IMAGE_B", help="Image B.")],
    method: Annotated[Method, typer.Option("--method", "-m", case_sensitive=False, help=METHOD_HELP)] = Method(DEFAULT_METHOD),
    json_output: Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout instead of tables.", metavar="")] = False,
    viz: Annotated[Optional[Path], typer.Option("--viz", help="Write a picture: A's border warped onto B.")] = None,
    gt: Annotated[Optional[Path], typer.Option("--gt", help="Ground-truth homography file (A to B) to report the corner error.")] = None,
    work_size: Annotated[int, typer.Option(help="Estimate with the images' longer side shrunk to this many pixels; the answer is in full-resolution pixels.")] = ESTIMATE_WORK_SIZE,
    full_resolution: Annotated[bool, typer.Option("--full-resolution", help="Estimate at the images' full resolution (slow and memory-hungry on large photos).", metavar="")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --viz file that udh did not write.", metavar="")] = False,
    option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    flags: Optional[dict] = None,
) -> None:
    """Estimate the homography that maps pixels of IMAGE_A to IMAGE_B ([bold]x_B ~ H x_A[/bold]).

    Exit codes: 0 a verified answer; 3 an answer that did not verify (printed, may be wrong); 1 no answer or bad input.
    """
    from udh_cli.api import estimate_report

    try:
        options = merge_flag_options(method.value, flags or {}, parse_method_options(option, [method.value]).get(method.value, {}))
        report = estimate_report(image_a, image_b, method.value, gt=gt, viz=viz, work_size=None if full_resolution else work_size,
                                 overwrite=overwrite, **options)
    except UdhError as exc:
        if json_output:  # scripts read stdout: one object, whatever happened
            sys.stdout.write(json.dumps({"method": method.value, "ok": False, "verified": False, "failure": str(exc), "exit_code": 1}) + "\n")
        raise
    code = 0 if report["verified"] else UNVERIFIED
    if json_output:
        sys.stdout.write(json.dumps({**report, "exit_code": code}) + "\n")
    else:
        _print_estimate(report)
    for note in report.get("notes", []):
        err_console.print(f"note: {note}", highlight=False, soft_wrap=True)
    if code:
        err_console.print("[yellow]warning:[/yellow] this answer did not verify (a low confidence, or no alignment and no matches "
                          "that agree on it): it is the best found, and may be wrong", highlight=False)
        raise typer.Exit(code)


if estimate.__doc__:  # None under python -OO
    estimate.__doc__ += f"\n    Licence of the shipped weights (models/README.md, \"Data and licenses\"): {licence_help()}\n"


def _print_estimate(payload: dict) -> None:
    from udh_cli import geometry

    width, height = payload["size_a"]
    matrix = Table(title=f"H ({payload['method']}): pixels of A -> pixels of B", show_header=False)
    for row in payload["homography"]:
        matrix.add_row(*(f"{v: .6g}" for v in row))
    console.print(matrix)
    corners = Table(title="4-point parameterisation: where A's corners land in B")
    for column in ("corner", "in A (x, y)", "in B (x, y)", "offset (px)"):
        corners.add_column(column, justify="right")
    names = ("top-left", "top-right", "bottom-right", "bottom-left")
    for name, c, off in zip(names, geometry.image_corners(width, height), payload["offsets_4pt"]):
        corners.add_row(name, f"{c[0]:.0f}, {c[1]:.0f}", f"{c[0] + off[0]:.2f}, {c[1] + off[1]:.2f}", f"{off[0]:+.2f}, {off[1]:+.2f}")
    console.print(corners)
    summary = f"confidence {payload['confidence']:.3f}   time {payload['elapsed_ms']:.1f} ms"
    if "corner_error_px" in payload:
        summary += f"   corner error {payload['corner_error_px']:.3f} px (RMSE {payload['corner_rmse_px']:.3f})"
    if "viz" in payload:
        summary += f"   picture: {payload['viz']}"
    console.print(summary)


@app.command()
def train(
    data: Annotated[Optional[list[Path]], typer.Option("--data", "-d", help="Folder of images (synthetic pairs) or of a flight (consecutive frames). Repeat for more.")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Run folder: checkpoint.pt, best.pt, metrics.jsonl, config.json.")] = Path("runs/udh"),
    mode: Annotated[str, typer.Option(help="unsupervised (photometric L1, no labels), supervised (L2 on synthetic labels) or match (the matcher's descriptors, from synthetic flight motion; with --motion flight).")] = _TRAIN.mode,
    arch: Annotated[Optional[str], typer.Option(help="Network: corr (CPU-friendly; the default, or --init's own), corr-global (corr with global matches, for flight motion), corr-lite (faster, slimmer), corr-fine (full-resolution refinement), vgg-paper (the paper's 34 M network) or matcher (dense descriptors for global matching; --mode match).")] = None,
    rho: Annotated[float, typer.Option(help="Largest corner perturbation of synthetic pairs, px (paper: 16/32/45 for 85/75/65 % overlap).")] = _TRAIN.rho,
    steps: Annotated[Optional[int], typer.Option(help="Total optimiser steps (default 20000; with --resume, the run's own).")] = None,
    batch: Annotated[int, typer.Option(help="Pairs per step (per process under torchrun).")] = _TRAIN.batch,
    lr: Annotated[Optional[float], typer.Option(help="Adam learning rate (default: the paper's, 1e-4 unsupervised, 5e-4 supervised; 3e-4 match).")] = None,
    init: Annotated[Optional[str], typer.Option(help="Fine-tune from a checkpoint file or a shipped model (unsupervised, supervised).")] = None,
    teacher: Annotated[Optional[str], typer.Option(help="Distil from this checkpoint or shipped model (unsupervised mode): its answers join the loss, no labels.")] = None,
    teacher_weight: Annotated[float, typer.Option(help="Weight of the mean |offset - teacher's offset| (px) beside the photometric loss.")] = _TRAIN.teacher_weight,
    resume: Annotated[bool, typer.Option("--resume", help="Continue the run in --out from its last checkpoint.", metavar="")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the run in --out (without it, a folder holding a run is refused).", metavar="")] = False,
    data_kind: Annotated[str, typer.Option(help="auto (pools and flights given together are mixed), pool or flight.")] = _TRAIN.data_kind,
    real_fraction: Annotated[float, typer.Option(help="With pools and flights together: the share of each batch from the flights' real pairs.")] = _TRAIN.real_fraction,
    source_side: Annotated[int, typer.Option(help="Pool images at this longer side, pairs from 320x240 windows of them (the tile stage's scale); 0: the paper's 320x240.")] = _TRAIN.source_side,
    small_motion: Annotated[float, typer.Option(help="Share of synthetic pairs with a random smaller rho.")] = _TRAIN.small_motion_fraction,
    illumination: Annotated[bool, typer.Option(help="Random brightness/contrast/gamma on the network's inputs.", metavar="")] = _TRAIN.illumination,
    occluders: Annotated[float, typer.Option(min=0.0, max=1.0, help="Share of pairs (0-1) with random occluding blobs on the network's inputs.")] = _TRAIN.occluders,
    photometric: Annotated[str, typer.Option(help="What the unsupervised L1 compares: intensity (the paper's) or contrast (local contrast, blind to vignetting, hot spots and exposure).")] = _TRAIN.photometric,
    motion: Annotated[str, typer.Option(help="paper (corner perturbation by --rho) or flight (whole frames with real flight motion; --rho is then the perspective jitter).")] = _MOTIONS[0],
    max_heading: Annotated[float, typer.Option(help="Flight motion: largest turn, degrees either way.")] = _MOTION.max_heading,
    max_scale: Annotated[float, typer.Option(help="Flight motion: largest scale change, a factor either way.")] = _MOTION.scale_range[1],
    max_shift: Annotated[float, typer.Option(help="Flight motion: largest shift, as a fraction of the frame.")] = _MOTION.max_shift,
    min_overlap: Annotated[float, typer.Option(help="Flight motion: least share of B that A's view covers.")] = _MOTION.min_overlap,
    residual: Annotated[float, typer.Option(help="Flight motion, a later round of the cascade: A pre-warped by an answer off by up to this many px (0: a first round).")] = _MOTION.residual,
    patch_size: Annotated[int, typer.Option(help="Network input side, px, a multiple of 32 (--mode match: the views' height; they are 4:3).")] = _TRAIN.patch_size,
    eval_every: Annotated[int, typer.Option(help="Validate every N steps.")] = _TRAIN.eval_every,
    seed: Annotated[int, typer.Option(help="Seed for data and initialisation.")] = _TRAIN.seed,
    threads: Annotated[Optional[int], typer.Option(help="torch CPU threads (default: torch's choice).")] = None,
) -> None:
    """Train the unsupervised or supervised network (needs the [bold]train[/bold] extra: torch)."""
    _require_torch()
    from udh_cli.train.config import flight_motion
    from udh_cli.train.loop import TrainConfig, train as run_training
    from udh_cli.train.warm_start import init_arch

    config = TrainConfig(
        mode=mode, data=[str(d) for d in data or []], data_kind=data_kind, real_fraction=real_fraction, source_side=source_side, arch=arch or init_arch(init, mode), patch_size=patch_size, rho=rho, small_motion_fraction=small_motion,
        illumination=illumination, occluders=occluders, photometric=photometric,
        motion=flight_motion(motion, rho, max_heading, max_scale, max_shift, min_overlap, residual), steps=steps, batch=batch, lr=lr, seed=seed, eval_every=eval_every,
        checkpoint_every=eval_every, init=init, teacher=teacher, teacher_weight=teacher_weight, out=str(out),
    )
    last = run_training(config, resume=resume, threads=threads, overwrite=overwrite, on_note=lambda note: err_console.print(f"note: {note}"))
    summary = ", ".join(f"{k} {v:.4g}" for k, v in last.items() if isinstance(v, float))
    console.print(f"done at step {last.get('step')}: {summary}; checkpoints in {out}")


def _require_torch() -> None:
    try:
        import torch  # noqa: F401
    except ImportError:
        raise UdhError("training and export need torch: from the udh checkout, pip install '.[train]'") from None


@app.command("export-onnx")
def export_onnx(
    checkpoint: Annotated[Path, typer.Argument(metavar="CHECKPOINT", help="A checkpoint written by `udh train` (checkpoint.pt or best.pt).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="The .onnx file to write.")] = Path("model.onnx"),
    check_images: Annotated[Optional[Path], typer.Option(help="Folder of images whose synthetic pairs join the parity check.")] = None,
    licence: Annotated[Optional[str], typer.Option(help="The weights' licence, recorded in the model (e.g. 'CC BY 4.0; trained on CC0 and CC BY images'): the terms of the images it was trained on decide it.")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing output file that udh did not write.", metavar="")] = False,
) -> None:
    """Export a checkpoint's network to ONNX with its metadata, and check parity against torch."""
    _require_torch()
    import numpy as np

    from udh_cli.train.export import export_onnx as run_export

    real = None
    if check_images is not None:
        from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs

        sources = load_sources(list_images(check_images)[:20], min_count=1)
        pairs = make_pairs(sources, 16, PairConfig(), np.random.default_rng(0), with_context=False)
        real = np.stack([pairs.patch_a, pairs.patch_b], 1)
    result = run_export(checkpoint, output, real, overwrite, licence)
    meta = result["metadata"]
    if meta["mode"] == "match":  # descriptors of images of any size, not offsets of a fixed input
        console.print(f"wrote {result['path']}: {meta['arch']} ({meta['mode']}), {meta['steps']} steps, images of any size "
                      f"(sides multiples of 4); max |onnx - torch| = {result['max_abs_diff']:.2e} in a descriptor")
    else:
        console.print(f"wrote {result['path']}: {meta['arch']} ({meta['mode']}), {meta['steps']} steps, "
                      f"input {meta['input_size']}px; max |onnx - torch| = {result['max_abs_diff']:.2e} px")


@app.command()
def quantize(
    model: Annotated[Path, typer.Argument(metavar="MODEL", help="A float32 udh ONNX model (from `udh export-onnx`).")],
    data: Annotated[list[Path], typer.Option("--data", "-d", help="Folders of training images to calibrate on (repeatable); every 10th image, the benchmarks' held-out split, is left out.")],
    output: Annotated[Optional[Path], typer.Option("--output", "-o", help="The int8 .onnx file to write (default: MODEL's name with -int8, beside it).")] = None,
    pairs: Annotated[int, typer.Option(help="Calibration pairs per motion level (4 levels up to the model's training rho).")] = 64,
    images: Annotated[int, typer.Option(help="At most this many images are drawn from --data.")] = 200,
    seed: Annotated[int, typer.Option(help="Seed of the image draw and the synthetic pairs.")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing output file that udh did not write (the shipped int8 model among them).", metavar="")] = False,
) -> None:
    """Quantize a network to int8 for faster CPU inference, calibrated on synthetic pairs of your images."""
    from udh_cli.train.quantize import quantize_from_folders

    with console.status("calibrating..."):
        result = quantize_from_folders(model, output, data, images, pairs, seed, overwrite)
    console.print(f"wrote {result['path']}: int8 of {model.name}; offsets differ from float32 by "
                  f"{result['median_drift_px']:.3f} px median, {result['max_drift_px']:.2f} px at most ({result['check_pairs']} check pairs)")


@app.command()
def simulate(
    folder: Annotated[Path, typer.Argument(metavar="FOLDER", help="Folder to write the frames and ground_truth.json into (created; must be empty or new).")],
    seed: Annotated[int, typer.Option(help="Seed: the same seed gives the same flight.")] = 0,
    strips: Annotated[int, typer.Option(min=1, max=100, help="Parallel flight lines, flown back and forth.")] = _FLIGHT.strips,
    frames_per_strip: Annotated[int, typer.Option(min=2, max=1000, help="Frames along each line.")] = _FLIGHT.frames_per_strip,
    width: Annotated[int, typer.Option(min=64, max=8000, help="Frame width, pixels.")] = _FLIGHT.frame_size[0],
    height: Annotated[int, typer.Option(min=64, max=8000, help="Frame height, pixels.")] = _FLIGHT.frame_size[1],
    forward_overlap: Annotated[float, typer.Option(min=0.1, max=0.95, help="Share of a frame the next one on its line sees again.")] = _FLIGHT.forward_overlap,
    side_overlap: Annotated[float, typer.Option(min=0.0, max=0.95, help="Share of a frame that neighbouring lines share.")] = _FLIGHT.side_overlap,
    tilt_deg: Annotated[float, typer.Option(min=0.0, max=30.0, help="Largest camera roll and pitch, degrees.")] = _FLIGHT.tilt_deg,
    noise_sigma: Annotated[float, typer.Option(min=0.0, max=50.0, help="Sensor noise, grey levels.")] = _FLIGHT.noise_sigma,
    ground_preview: Annotated[bool, typer.Option("--ground-preview", help="Also write FOLDER_ground.jpg, the whole ground, beside the folder.", metavar="")] = False,
    gps: Annotated[Optional[str], typer.Option("--gps", metavar="LAT,LON", help="Write EXIF GPS into the frames, the ground's top-left corner at LAT,LON (WGS84 degrees).")] = None,
    gps_noise: Annotated[float, typer.Option(min=0.0, max=100.0, help="With --gps: each fix's error, metres (standard deviation).")] = _GPS.noise_m,
    metres_per_pixel: Annotated[float, typer.Option(min=0.001, max=10.0, help="With --gps: ground size of one ground-image pixel, metres.")] = _GPS.metres_per_pixel,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="With --ground-preview: replace an existing FOLDER_ground.jpg that udh did not write.", metavar="")] = False,
) -> None:
    """Write a simulated drone flight with exact ground truth (frames + ground_truth.json), for trying udh anywhere."""
    from udh_cli.simulate import write_flight

    config = _FlightConfig(frame_size=(width, height), strips=strips, frames_per_strip=frames_per_strip, forward_overlap=forward_overlap,
                           side_overlap=side_overlap, tilt_deg=tilt_deg, noise_sigma=noise_sigma,
                           focal_px=_FLIGHT.focal_px * width / _FLIGHT.frame_size[0])
    gps_config = None
    if gps is not None:
        try:
            latitude, longitude = (float(v) for v in gps.split(","))
        except ValueError:
            raise UdhError(f"--gps {gps}: give LAT,LON in degrees, e.g. --gps 46.85,-92.0") from None
        if not (-80.0 <= latitude <= 84.0 and -180.0 <= longitude <= 180.0):
            raise UdhError(f"--gps {gps}: latitude must be within -80..84 (UTM) and longitude within -180..180")
        gps_config = _GpsConfig(latitude, longitude, metres_per_pixel=metres_per_pixel, noise_m=gps_noise)
    path = write_flight(folder, config, seed, ground_preview=ground_preview, gps=gps_config, overwrite=overwrite)
    err_console.print(f"wrote {strips * frames_per_strip} frames and {path}", highlight=False, soft_wrap=True)


def main() -> None:
    """Console-script entry point: runs the app and turns errors into one line and an exit code.

    Exit codes: 0 done; 1 an error (one line on stderr, ``error: ...``); 2 a usage error (Click's convention:
    a missing argument, a malformed option); 3 ``udh estimate`` printed an answer that did not verify;
    130 interrupted, by Ctrl-C or by SIGTERM (handled alike: temporary files are removed, a mosaic keeps its
    pair cache for --resume).
    """
    previous = _terminate_as_interrupt()
    try:
        _run()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _terminate_as_interrupt():
    """Make SIGTERM (``kill``, a job scheduler's stop) raise KeyboardInterrupt, as Ctrl-C does, so that the
    command unwinds the same way; returns the handler to restore (None when none could be installed)."""

    def interrupt(signum, frame):  # noqa: ARG001 - signal handler signature
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except (ValueError, OSError, AttributeError):  # not the main thread, or no SIGTERM here
        return None
    return signal.SIG_DFL if previous is None else previous


def _run() -> None:
    try:
        # standalone_mode=False hands usage errors to us, so that they too come out as one line.
        code = app(standalone_mode=False)
    except UdhError as exc:
        if _state["debug"]:
            raise
        _fail(str(exc), 1)
    except (KeyboardInterrupt, typer.Abort):
        _fail("interrupted", INTERRUPTED)
    except OSError as exc:
        if _state["debug"] or exc.errno != errno.ENAMETOOLONG:
            raise
        from udh_cli.images import shown_path

        # Any path argument can be too long; the library checks the ones it opens, this catches the rest.
        _fail(f"{shown_path(exc.filename)}: the path is too long for this file system; give a shorter one", 1)
    except Exception as exc:  # noqa: BLE001 - the last line of defence: no traceback without --debug
        if _is_usage_error(exc):
            if type(exc).__name__ != "NoArgsIsHelpError":  # that one has printed the help already
                context = getattr(exc, "ctx", None)
                hint = f"; see '{context.command_path} --help'" if context is not None else ""
                # Typer's choice types validate through pydantic, which starts its message with "Value error, ".
                message = exc.format_message().replace("Value error, ", "").rstrip(".")
                _fail(f"{message}{hint}", exc.exit_code)
            sys.exit(exc.exit_code)
        if _state["debug"]:
            raise
        _fail(f"internal error: {type(exc).__name__}: {exc} (rerun as 'udh --debug ...' for details)", 1)
    if code == INTERRUPTED:  # Typer turns Ctrl-C into a quiet exit code 130; say what happened
        _fail("interrupted", INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)


def _is_usage_error(exc: Exception) -> bool:
    """Typer's (Click's) bad-usage exceptions: a missing argument, an option given a wrong value..."""
    return hasattr(exc, "format_message") and isinstance(getattr(exc, "exit_code", None), int)


def _fail(message: str, code: int) -> None:
    # Messages hold paths and hints like 'udh[train]': print them as text, not as rich markup.
    err_console.print(f"[bold red]error:[/bold red] {escape(message)}", highlight=False, soft_wrap=True)
    sys.exit(code)


if __name__ == "__main__":
    main()
