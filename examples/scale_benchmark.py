"""Scale benchmark: simulated lawn-mower surveys of growing size, mosaicked, against their ground truth.

    python examples/scale_benchmark.py [--frames 100,500,2000] [--method auto] [--frame-size 320x240] [--keep DIR]
        [--gps-sigma 2] [--rectify] [--solve homography|camera] [--format png|tif]

For each size the simulator writes a survey with ground truth into a temporary folder (or ``--keep DIR``) in
one process, and `udh mosaic` runs on it in another, so that each size's peak memory is the mosaic's own.
Prints a Markdown table: frames placed, parts, wall time and time per frame, the pairs' share of it, peak
memory (the process's maximum resident set), the solved frames' corner error against the truth in
reference-frame pixels, and the map's shape: every frame's corners against their true ground positions after
the best similarity (``udh_cli.mosaic.solve.truth``). ``--rectify`` mosaics with ``udh mosaic --rectify``, ``--solve camera`` with ``udh mosaic --solve camera``. The
surveys carry EXIF GPS with 2 m of noise (5 cm ground pixels); ``--gps-sigma M`` mosaics them with
``udh mosaic --gps-sigma M``, the fixes anchoring the global solve.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def survey_shape(frames: int) -> tuple[int, int]:
    """(strips, frames per strip) of about ``frames`` frames, strips about 2.5 times longer than the survey is wide."""
    strips = max(1, round(math.sqrt(frames / 2.5)))
    return strips, max(2, round(frames / strips))


def simulate(frames: int, frame_size: tuple[int, int], folder: Path) -> Path:
    """Write a survey of about ``frames`` frames with its ground truth; returns its folder."""
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    strips, per_strip = survey_shape(frames)
    flight = folder / f"survey-{frames}"
    gps = GpsConfig(latitude=50.82, longitude=-0.14, noise_m=2.0)
    write_flight(flight, FlightConfig(frame_size=frame_size, strips=strips, frames_per_strip=per_strip), seed=frames, gps=gps)
    return flight


def mosaic(flight: Path, method: str, workers: int, gps_sigma: float, suffix: str = ".png", rectify: bool = False,
           solve: str = "homography") -> dict:
    """Mosaic one simulated survey in this process; the figures of one table row."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    started = time.perf_counter()
    config = MosaicConfig(method=method, workers=workers, gps_sigma_m=gps_sigma, rectify=rectify, solve=solve)
    report = run_mosaic(flight, flight.parent / f"{flight.name}-gps{gps_sigma:g}-{solve}{suffix}", config)
    elapsed = time.perf_counter() - started
    timings = report["timings_s"]
    pair_s = sum(v for k, v in timings.items() if "pairs" in k or "bridg" in k)
    solved = report.get("ground_truth_error", {}).get("solved", {})
    shape = report.get("ground_truth_error", {}).get("map_shape", {})
    return {"frames": report["summary"]["frames"], "placed": report["summary"]["placed"], "parts": report["summary"]["parts"],
            "time_s": elapsed, "pairs_s": pair_s, "solve_s": timings.get("global solve", 0.0),
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "error_mean_px": solved.get("mean_corner_px"), "error_max_px": solved.get("max_corner_px"),
            "shape_median_px": shape.get("median_px"), "shape_max_px": shape.get("max_px")}


def _child(arguments: list[str]) -> str:
    """Run this script with ``arguments`` in a fresh process; its last line of output (its stderr on failure)."""
    done = subprocess.run([sys.executable, __file__, *arguments], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(arguments)} failed:\n{done.stderr.strip()}")
    return done.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="100,500,2000", help="survey sizes, comma-separated")
    parser.add_argument("--method", default="auto")
    parser.add_argument("--frame-size", default="320x240")
    parser.add_argument("--keep", type=Path, help="write the surveys and mosaics here instead of a temporary folder")
    parser.add_argument("--workers", type=int, default=1, help="local processes estimating pairs (udh mosaic --workers)")
    parser.add_argument("--gps-sigma", type=float, default=0.0, help="udh mosaic --gps-sigma: GPS anchors in the solve (0: off)")
    parser.add_argument("--rectify", action="store_true", help="udh mosaic --rectify: draw on the plane the frames look down on")
    parser.add_argument("--solve", choices=("homography", "camera"), default="homography", help="udh mosaic --solve: the global solve's model")
    parser.add_argument("--format", choices=("png", "tif"), default="png", help="the mosaic's file: png (held whole to be encoded) or tif (streamed tile by tile)")
    parser.add_argument("--simulate", type=int, help=argparse.SUPPRESS)  # internal: write one survey, in a fresh process
    parser.add_argument("--mosaic", type=Path, help=argparse.SUPPRESS)  # internal: mosaic one survey, in a fresh process
    args = parser.parse_args()
    frame_size = tuple(int(v) for v in args.frame_size.lower().split("x"))
    if args.simulate is not None:
        print(simulate(args.simulate, frame_size, args.keep))
        return
    if args.mosaic is not None:
        print(json.dumps(mosaic(args.mosaic, args.method, args.workers, args.gps_sigma, f".{args.format}", args.rectify, args.solve)))
        return
    print("| frames | placed | parts | wall time (s) | per frame (ms) | pairs (s) | solve (s) | peak memory (MB) | corner error vs truth, mean / max (px) "
          "| map shape, median / max (px) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---|---|")
    with tempfile.TemporaryDirectory() as temporary:
        folder = args.keep or Path(temporary)
        folder.mkdir(parents=True, exist_ok=True)
        for frames in (int(v) for v in args.frames.split(",")):
            flight = _child(["--simulate", str(frames), "--frame-size", args.frame_size, "--keep", str(folder)])
            row = json.loads(_child(["--mosaic", flight, "--method", args.method, "--workers", str(args.workers),
                                     "--gps-sigma", str(args.gps_sigma), "--format", args.format, "--solve", args.solve] + (["--rectify"] if args.rectify else [])))
            error = "n/a" if row["error_mean_px"] is None else f"{row['error_mean_px']:.2f} / {row['error_max_px']:.2f}"
            shape = "n/a" if row["shape_median_px"] is None else f"{row['shape_median_px']:.2f} / {row['shape_max_px']:.2f}"
            print(f"| {row['frames']} | {row['placed']} | {row['parts']} | {row['time_s']:.1f} | {1e3 * row['time_s'] / row['frames']:.0f} | "
                  f"{row['pairs_s']:.1f} | {row['solve_s']:.2f} | {row['peak_mb']:.0f} | {error} | {shape} |", flush=True)


if __name__ == "__main__":
    main()
