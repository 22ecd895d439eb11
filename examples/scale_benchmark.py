"""Scale benchmark: simulated lawn-mower surveys of growing size, mosaicked, against their ground truth.

    python examples/scale_benchmark.py [--frames 100,500,2000] [--method auto] [--frame-size 320x240] [--keep DIR]

For each size the simulator (`udh simulate`) writes a survey with ground truth into a temporary folder (or
``--keep DIR``), and `udh mosaic` runs on it in a fresh process, so that each size's peak memory is its own.
Prints a Markdown table: frames placed, parts, wall time and time per frame, the pairs' share of it, peak
memory (the process's maximum resident set), and the solved frames' corner error against the truth, in
reference-frame pixels.
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


def run_one(frames: int, method: str, frame_size: tuple[int, int], folder: Path) -> dict:
    """Simulate and mosaic one survey in this process; the figures of one table row."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, write_flight

    strips, per_strip = survey_shape(frames)
    flight = folder / f"survey-{frames}"
    write_flight(flight, FlightConfig(frame_size=frame_size, strips=strips, frames_per_strip=per_strip), seed=frames)
    started = time.perf_counter()
    report = run_mosaic(flight, folder / f"survey-{frames}.png", MosaicConfig(method=method))
    elapsed = time.perf_counter() - started
    timings = report["timings_s"]
    pair_s = sum(v for k, v in timings.items() if "pairs" in k or "bridg" in k)
    solved = report.get("ground_truth_error", {}).get("solved", {})
    return {"frames": report["summary"]["frames"], "placed": report["summary"]["placed"], "parts": report["summary"]["parts"],
            "time_s": elapsed, "pairs_s": pair_s, "solve_s": timings.get("global solve", 0.0),
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "error_mean_px": solved.get("mean_corner_px"), "error_max_px": solved.get("max_corner_px")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="100,500,2000", help="survey sizes, comma-separated")
    parser.add_argument("--method", default="auto")
    parser.add_argument("--frame-size", default="320x240")
    parser.add_argument("--keep", type=Path, help="write the surveys and mosaics here instead of a temporary folder")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: one size, in a fresh process
    args = parser.parse_args()
    frame_size = tuple(int(v) for v in args.frame_size.lower().split("x"))
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.method, frame_size, args.keep)))
        return
    print(f"| frames | placed | parts | wall time (s) | per frame (ms) | pairs (s) | solve (s) | peak memory (MB) | corner error vs truth, mean / max (px) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    with tempfile.TemporaryDirectory() as temporary:
        folder = args.keep or Path(temporary)
        folder.mkdir(parents=True, exist_ok=True)
        for frames in (int(v) for v in args.frames.split(",")):
            command = [sys.executable, __file__, "--one", str(frames), "--method", args.method, "--frame-size", args.frame_size, "--keep", str(folder)]
            row = json.loads(subprocess.run(command, check=True, capture_output=True, text=True).stdout.splitlines()[-1])
            error = "n/a" if row["error_mean_px"] is None else f"{row['error_mean_px']:.2f} / {row['error_max_px']:.2f}"
            print(f"| {row['frames']} | {row['placed']} | {row['parts']} | {row['time_s']:.1f} | {1e3 * row['time_s'] / row['frames']:.0f} | "
                  f"{row['pairs_s']:.1f} | {row['solve_s']:.2f} | {row['peak_mb']:.0f} | {error} |", flush=True)


if __name__ == "__main__":
    main()
