"""``udh bench``: the benchmark commands, loaded by the root group (:data:`udh_cli.cli.LAZY_COMMANDS`) only when
invoked; each command is one call into :mod:`udh_cli.bench`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Optional

import typer

from udh_cli.cli import LAZY_COMMANDS, OPTION_HELP, Method, err_console
from udh_cli.estimators.registry import DEFAULT_METHOD, parse_method_options

app = typer.Typer(
    help=LAZY_COMMANDS["bench"][1],
    no_args_is_help=True,
    rich_markup_mode="rich",
)

_METHODS_HELP = "Comma-separated registry names (default: every registered method)."
OVERWRITE_HELP = "Replace existing output files that udh did not write (without it, only files an earlier udh run wrote, unchanged, are replaced)."


@app.command("synthetic")
def bench_synthetic(
    images: Annotated[Optional[Path], typer.Option("--images", help="Folder of held-out images, all used. Default: the held-out tenth of ../shared/data/pools/rsscn7-aerial/images.")] = None,
    rho: Annotated[str, typer.Option("--rho", help="Corner perturbations in px, comma-separated (16,32,45 = the paper's 85/75/65 % overlap).")] = "16,32,45",
    n: Annotated[int, typer.Option("--n", help="Pairs per rho.")] = 500,
    seed: Annotated[int, typer.Option("--seed", help="Seed: the same seed gives the same pairs.")] = 0,
    illumination: Annotated[bool, typer.Option("--illumination/--no-illumination", help="Random brightness, contrast and gamma per image, as in the paper.", metavar="")] = True,
    occluders: Annotated[bool, typer.Option("--occluders/--no-occluders", help="Random textured blobs on the patches (the paper's future work).", metavar="")] = False,
    methods: Annotated[Optional[str], typer.Option("--methods", "-m", help=_METHODS_HELP)] = None,
    mode: Annotated[str, typer.Option("--mode", help="What sift/orb/ecc see: patch (128x128), full (320x240 frames, as the paper) or both. Other methods always get patches.")] = "both",
    out: Annotated[Path, typer.Option("--out", help="Folder for results.md/.csv/.json, per_pair.csv and the two PNG plots.")] = Path("bench-results"),
    save_pairs: Annotated[Optional[Path], typer.Option("--save-pairs", help="Also save the generated pairs to this .npz.")] = None,
    load_pairs: Annotated[Optional[Path], typer.Option("--load-pairs", help="Run on pairs saved with --save-pairs (replaces --images, --rho, --n and --seed).")] = None,
    option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Draw percentiles.png and speed_accuracy.png.", metavar="")] = True,
    motion: Annotated[str, typer.Option("--motion", help="paper (128x128 patches, corners moved by --rho) or flight (whole 320x240 frames with real flight motion: turns, scale, low overlap).")] = "paper",
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP, metavar="")] = False,
) -> None:
    """Benchmark on synthetic pairs from held-out images, drawn with the training generator."""
    from udh_cli.bench import check_output_folder, run_synthetic_bench
    from udh_cli.bench.runner import parse_methods
    from udh_cli.bench.suite import bench_options, parse_rhos

    check_output_folder(out, overwrite)
    result = run_synthetic_bench(
        images=images, rhos=parse_rhos(rho), count=n, seed=seed, illumination=illumination, occluders=occluders,
        methods=parse_methods(methods) if methods else None, mode=mode, options=bench_options(option, methods),
        save_pairs=save_pairs, load_pairs=load_pairs, motion=motion, overwrite=overwrite,
    )
    _finish_bench(result, out, plots, overwrite)


@app.command("pairs")
def bench_pairs(
    source: Annotated[Path, typer.Argument(metavar="SOURCE", help="A CSV (img1,img2,H: nine numbers, x2 ~ H x1) or an Oxford/HPatches folder (imgN + H1toNp).")],
    methods: Annotated[Optional[str], typer.Option("--methods", "-m", help=_METHODS_HELP)] = None,
    h_column: Annotated[str, typer.Option("--h-column", help="CSV column holding H.")] = "H",
    prefix: Annotated[Optional[str], typer.Option("--prefix", help="Folder: the image series, e.g. graf for graf1/graf3, when several match.")] = None,
    out: Annotated[Path, typer.Option("--out", help="Folder for the result files and plots.")] = Path("bench-results"),
    option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Draw percentiles.png and speed_accuracy.png.", metavar="")] = True,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP, metavar="")] = False,
) -> None:
    """Benchmark on real image pairs with known homographies."""
    from udh_cli.bench import check_output_folder, run_pairs_bench
    from udh_cli.bench.runner import parse_methods
    from udh_cli.bench.suite import bench_options

    check_output_folder(out, overwrite)
    result = run_pairs_bench(source, methods=parse_methods(methods) if methods else None, h_column=h_column,
                             prefix=prefix, options=bench_options(option, methods))
    _finish_bench(result, out, plots, overwrite)


@app.command("speed")
def bench_speed(
    folder: Annotated[Path, typer.Argument(metavar="FOLDER", help="A folder of a flight's frames, mosaicked as `udh mosaic FOLDER` would.")],
    method: Annotated[Method, typer.Option("--method", "-m", case_sensitive=False, help="The mosaic's method.")] = Method(DEFAULT_METHOD),
    workers: Annotated[Optional[int], typer.Option("--workers", min=1, show_default=False, help="Local processes estimating pairs (default: the mosaic's own choice).")] = None,
    pairs: Annotated[int, typer.Option("--pairs", min=0, help="Also time single pairs: the first N consecutive pairs of FOLDER at full resolution (0: none).")] = 0,
    methods: Annotated[Optional[str], typer.Option("--methods", help="With --pairs: comma-separated methods, interleaved on the same pairs (default: unsupervised,auto,sift).")] = None,
    out: Annotated[Path, typer.Option("--out", help="Folder for results.json, results.md and stages.png.")] = Path("bench-speed"),
    keep_mosaic: Annotated[bool, typer.Option("--keep-mosaic", help="Write the mosaic into --out as well (default: a temporary folder, removed after).", metavar="")] = False,
    option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP, metavar="")] = False,
) -> None:
    """Time a mosaic stage by stage against a fixed workload timed in the same run (every frame decoded and run
    through SIFT at 800 px on one thread), so that figures from different machines compare."""
    from udh_cli.bench import check_output_folder
    from udh_cli.bench.runner import parse_methods
    from udh_cli.bench.speed import PAIR_METHODS, run_speed_bench
    from udh_cli.bench.speed_report import markdown, write_speed_outputs

    check_output_folder(out, overwrite)
    pair_methods = parse_methods(methods) if methods else list(PAIR_METHODS)
    options = parse_method_options(option, list(dict.fromkeys([method.value, *(pair_methods if pairs else [])])))
    result = run_speed_bench(folder, method.value, workers, options, pairs, pair_methods, mosaic_dir=out if keep_mosaic else None, progress=True)
    written = write_speed_outputs(result, out, overwrite)
    sys.stdout.write(markdown(result))
    err_console.print(f"wrote {', '.join(str(p) for p in written)}", highlight=False, soft_wrap=True)


@app.command("hard")
def bench_hard(
    sources: Annotated[list[Path], typer.Argument(metavar="SOURCE...", help="Pairs with a reference H: a pairs CSV (img1,img2,H or H_sift_ransac_1to2), a flight folder with consecutive_pairs_sift_reference.csv, an Oxford folder (graf1 + H1to3p.xml), or folders of them.")],
    methods: Annotated[str, typer.Option("--methods", "-m", help="Comma-separated registry names.")] = "unsupervised,auto,sift",
    n: Annotated[int, typer.Option("--n", help="Pairs per kind of motion.")] = 20,
    seed: Annotated[int, typer.Option("--seed", help="Seed: the same seed gives the same pairs and motions.")] = 0,
    prefix: Annotated[Optional[str], typer.Option("--prefix", help="Oxford folders: the image series, e.g. graf, when several match.")] = None,
    min_inliers: Annotated[int, typer.Option("--min-inliers", help="Leave out reference pairs whose CSV gives fewer RANSAC inliers.")] = 50,
    out: Annotated[Path, typer.Option("--out", help="Folder for results.md, results.json and reliability.png.")] = Path("bench-hard"),
    option: Annotated[Optional[list[str]], typer.Option("--option", "-O", help=OPTION_HELP)] = None,
    plots: Annotated[bool, typer.Option("--plots/--no-plots", help="Draw reliability.png.", metavar="")] = True,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP, metavar="")] = False,
) -> None:
    """Real pairs with known motion (as captured, turned, scaled, tilted): failures, verified-but-wrong and a reliability diagram."""
    from udh_cli.bench import check_output_folder
    from udh_cli.bench.hard import run_hard_bench
    from udh_cli.bench.hard_report import markdown_table, write_hard_outputs
    from udh_cli.bench.runner import parse_methods
    from udh_cli.bench.suite import bench_options

    check_output_folder(out, overwrite)
    result = run_hard_bench(sources, methods=parse_methods(methods), count=n, seed=seed, prefix=prefix,
                            min_inliers=min_inliers, options=bench_options(option, methods))
    written = write_hard_outputs(result, out, plots=plots, overwrite=overwrite)
    sys.stdout.write(markdown_table(result))
    err_console.print(f"wrote {', '.join(str(p) for p in written)}", highlight=False, soft_wrap=True)


def _finish_bench(result, out: Path, plots: bool, overwrite: bool) -> None:
    from udh_cli.bench import markdown_table, write_outputs

    written = write_outputs(result, out, plots=plots, overwrite=overwrite)
    sys.stdout.write(markdown_table(result))
    err_console.print(f"wrote {', '.join(str(p) for p in written)}", highlight=False, soft_wrap=True)
