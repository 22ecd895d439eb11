"""Live-mode benchmark: frames written into a folder at a steady rate, followed by `udh mosaic --follow`.

    python examples/live_latency.py [--frames 20] [--fps 2] [--frame-size 1600x1200] [--method auto]

The simulator writes a survey with ground truth; a writer thread then copies its frames one by one into an
empty folder at ``--fps`` frames a second (each file written in one go, as a camera or a copy would), and
``run_live`` follows that folder with its defaults. Prints, per frame, the time from the file's last write to
its appearance in the quick look (``NAME.live.jpg``, read from ``NAME.live.json``), their median, 95th
percentile and maximum; the refreshes; and the final mosaic's loop consistency against a batch run of the
finished folder (the target: equal within 0.1 px).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--fps", type=float, default=2.0)
    parser.add_argument("--frame-size", default="1600x1200")
    parser.add_argument("--method", default="auto")
    args = parser.parse_args()
    width, height = (int(v) for v in args.frame_size.split("x"))

    from udh_cli.mosaic import FollowConfig, MosaicConfig, run_live, run_mosaic
    from udh_cli.simulate import FlightConfig, write_flight

    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        source, live, out = scratch / "source", scratch / "live", scratch / "out"
        live.mkdir()
        out.mkdir()
        strips = 2
        write_flight(source, FlightConfig(frame_size=(width, height), strips=strips, frames_per_strip=max(2, args.frames // strips),
                                          focal_px=0.94 * width), seed=7)
        frames = sorted(source.glob("frame_*.jpg"))

        def fly() -> None:
            period = 1.0 / args.fps
            start = time.monotonic()
            for k, path in enumerate(frames):
                time.sleep(max(0.0, start + k * period - time.monotonic()))
                (live / path.name).write_bytes(path.read_bytes())
            (live / "DONE").write_text("")

        config = MosaicConfig(method=args.method)
        writer = threading.Thread(target=fly)
        started = time.perf_counter()
        writer.start()
        report = run_live(live, out / "live.png", config, FollowConfig(idle_timeout_s=30.0))
        writer.join()
        wall = time.perf_counter() - started
        look = json.loads((out / "live.live.json").read_text())
        latencies = np.array([f["latency_s"] for f in look["frames"] if f["placed"]])
        batch = run_mosaic(source, out / "batch.png", config)

    print("| frames | placed in the quick look | latency median | p95 | max | refreshes | live loops (px) | batch loops (px) | wall time |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    live_loops = report["loop_consistency"]["loops_after"] or {}
    batch_loops = batch["loop_consistency"]["loops_after"] or {}
    print(f"| {len(frames)} ({width}x{height}, {args.fps:g} fps) | {look['frames_placed']} | {np.median(latencies):.2f} s | "
          f"{np.percentile(latencies, 95):.2f} s | {latencies.max():.2f} s | {report['live']['refreshes']} | "
          f"{live_loops.get('mean_px', float('nan')):.3f} | {batch_loops.get('mean_px', float('nan')):.3f} | {wall:.1f} s |")
    for frame in look["frames"]:
        print(f"  {frame['name']}: {'placed' if frame['placed'] else 'not placed'}, {frame['latency_s']} s, {frame.get('stage') or frame.get('failure')}")


if __name__ == "__main__":
    main()
