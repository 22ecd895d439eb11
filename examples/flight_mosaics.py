"""Mosaic real flights with several methods and print what a mapper looks at: frames placed, parts, loop
consistency after the solve, and wall time.

    python examples/flight_mosaics.py FLIGHT_FOLDER [FLIGHT_FOLDER ...] [--methods unsupervised,auto,sift]
        [--out mosaics/] [-O unsupervised.model=file.onnx]

Each FLIGHT_FOLDER is a folder of frames (or one holding ``images/``, as the shared flights do). Mosaics and
sidecars go to ``--out``; the table goes to stdout as Markdown. This is how the README's real-flight table
for ``--method unsupervised`` next to ``auto`` and ``sift`` is measured.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from udh_cli.estimators.registry import parse_method_options
from udh_cli.mosaic import MosaicConfig, run_mosaic


def frames_folder(folder: Path) -> Path:
    return folder / "images" if (folder / "images").is_dir() else folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("flights", type=Path, nargs="+")
    parser.add_argument("--methods", default="unsupervised,auto,sift")
    parser.add_argument("--out", type=Path, default=Path("flight-mosaics"))
    parser.add_argument("-O", "--option", action="append", default=[], help="[METHOD.]KEY=VALUE, as in udh mosaic")
    args = parser.parse_args()
    options = parse_method_options(args.option, args.methods.split(","))
    args.out.mkdir(parents=True, exist_ok=True)
    print("| flight | method | placed | parts | loop consistency after solve (mean / max px) | loops | time (s) |")
    print("|---|---|---:|---:|---|---:|---:|")
    for flight in args.flights:
        for method in args.methods.split(","):
            config = MosaicConfig(method=method, method_options=options.get(method, {}))
            started = time.perf_counter()
            report = run_mosaic(frames_folder(flight), args.out / f"{flight.name}-{method.replace('+', '_')}.png", config)
            elapsed = time.perf_counter() - started
            summary, after = report["summary"], report["loop_consistency"].get("loops_after") or {}
            consistency = f"{after['mean_px']:.2f} / {after['max_px']:.2f}" if after.get("count") else "no loops"
            print(f"| {flight.name} | {method} | {summary['placed']}/{summary['frames']} | {summary['parts']} | {consistency} | "
                  f"{after.get('count', 0)} | {elapsed:.1f} |", flush=True)


if __name__ == "__main__":
    main()
