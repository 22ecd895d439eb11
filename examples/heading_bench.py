"""Pairs turned by known in-plane angles, made from real frames: failures per angle bucket, and time per pair.

    python examples/heading_bench.py [--frames 3] [--step 22.5] [--method unsupervised] [-O KEY=VALUE ...]

For each frame (the shared flights' images, ../shared/data/flights/*/images, every few files, and the example
flight), the frame is shrunk to 800 px, A is its central 400 x 300 window and B the same window turned by the angle
about its centre, with a random perspective of up to 16 px at each corner and a shift of up to 20 px: B sees only
real texture at any angle. A failure is no answer or a mean corner error over 10 px at 400 x 300. The frames are
never written anywhere.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter, defaultdict
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.registry import parse_key_value
from udh_cli.images import read_image

FLIGHTS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "flights"
SIM_FLIGHT = Path(__file__).resolve().parent / "sim_flight"
WIDTH, HEIGHT = 400, 300


def turned_pair(frame: np.ndarray, degrees: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, b_from_a): A the central 400 x 300 window of ``frame`` shrunk to 800 px, B that window turned by
    ``degrees`` counter-clockwise on screen, perturbed and shifted."""
    scale = 800 / max(frame.shape[:2])
    source = cv2.resize(frame, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    height, width = source.shape[:2]
    x0, y0 = (width - WIDTH) // 2, (height - HEIGHT) // 2
    centre = ((WIDTH - 1) / 2, (HEIGHT - 1) / 2)
    turn = np.vstack([cv2.getRotationMatrix2D(centre, degrees, 1.0), [0, 0, 1]])
    corners = geometry.image_corners(WIDTH, HEIGHT)
    moved = corners + rng.uniform(-16, 16, (4, 2)) + rng.uniform(-20, 20, 2)
    perturb = cv2.getPerspectiveTransform(corners.astype(np.float32), moved.astype(np.float32))
    b_from_a = perturb @ turn
    image_a = source[y0 : y0 + HEIGHT, x0 : x0 + WIDTH]
    image_b = cv2.warpPerspective(source, b_from_a @ geometry.translation(-x0, -y0), (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
    return image_a, image_b, b_from_a / b_from_a[2, 2]


def frames(per_flight: int) -> list[Path]:
    """Every few frames of each shared flight and of the example flight."""
    folders = sorted(p / "images" for p in FLIGHTS.glob("*") if (p / "images").is_dir()) + [SIM_FLIGHT]
    chosen = []
    for folder in folders:
        files = sorted(f for f in folder.iterdir() if f.suffix.lower() in (".jpg", ".jpeg", ".png"))
        chosen += [files[i] for i in np.linspace(0, len(files) - 1, per_flight).round().astype(int)]
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3, help="frames per flight")
    parser.add_argument("--step", type=float, default=22.5, help="degrees between the angles tried")
    parser.add_argument("--method", default="unsupervised")
    parser.add_argument("-O", dest="options", action="append", default=[])
    parser.add_argument("--json", type=Path, help="write every pair's result here")
    args = parser.parse_args()
    from verdict_bench import before_rule  # the rule before the judge, recomputed from the same answers

    cv2.setNumThreads(1)
    options = dict(parse_key_value(item) for item in args.options)
    estimator = create_estimator(args.method, device="cpu", threads=1, **options)
    rng = np.random.default_rng(0)
    angles = np.arange(0.0, 360.0, args.step)
    rows = []
    for path in frames(args.frames):
        frame = read_image(path)
        for degrees in angles:
            jittered = float(degrees + (rng.uniform(-5, 5) if degrees else 0.0))
            a, b, truth = turned_pair(frame, jittered, rng)
            started = time.perf_counter()
            found = estimator.estimate(a, b)
            elapsed_ms = (time.perf_counter() - started) * 1e3
            error = float(geometry.mace(found.homography, truth, WIDTH, HEIGHT)) if found.ok else float("inf")
            rows.append({"frame": path.name, "degrees": jittered, "error_px": error, "verified": found.verified,
                         "verified_before": before_rule(found),
                         "ms": elapsed_ms, "stage": found.stage})
    buckets = defaultdict(list)
    for row in rows:
        bucket = 0 if row["degrees"] == 0 else int(((row["degrees"] + 22.5) % 360) // 45) * 45
        buckets[bucket if row["degrees"] else "0 exactly"].append(row)
    print(f"{args.method} {options}: {len(rows)} pairs from {len(rows) // len(angles)} frames")
    print("bucket   pairs  failures  verified-but-wrong (judge / before)  unverified-but-right  median px  median ms  stages")
    for bucket, group in sorted(buckets.items(), key=lambda kv: (isinstance(kv[0], int), kv[0] if isinstance(kv[0], int) else 0)):
        errors = np.array([r["error_px"] for r in group])
        wrong = errors > 10
        verified = np.array([bool(r["verified"]) for r in group])
        before = np.array([r["verified_before"] for r in group])
        print(f"{str(bucket):>9} {len(group):6d} {wrong.mean():8.1%} {(wrong & verified).mean():12.1%} / {(wrong & before).mean():6.1%} "
              f"{(~wrong & ~verified).mean():18.1%} {np.median(errors):10.2f} {np.median([r['ms'] for r in group]):10.1f}  "
              f"{dict(Counter(r['stage'] for r in group))}")
    unturned = [r["ms"] for r in rows if r["degrees"] == 0]
    everything = np.array([r["error_px"] for r in rows])
    wrong_verified = np.mean([r["error_px"] > 10 and bool(r["verified"]) for r in rows])
    wrong_before = np.mean([r["error_px"] > 10 and r["verified_before"] for r in rows])
    print(f"all: failures {np.mean(everything > 10):.1%}, verified-but-wrong {wrong_verified:.1%} (before {wrong_before:.1%}); "
          f"unturned pairs: median {np.median(unturned):.1f} ms a pair")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
