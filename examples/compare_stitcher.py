"""Compare `udh mosaic` with OpenCV's Stitcher (SCANS mode) on one flight, in one run.

    OMP_NUM_THREADS=1 python examples/compare_stitcher.py ../shared/data/flights/brighton-beach/images \
        --out /tmp/brighton --methods sift orb

For every udh method it reports frames placed, parts, time per stage and loop consistency before and after
the global solve; for the Stitcher, frames placed (its final component) and wall time. The mosaics are
written into --out (keep them out of the repository when the frames are not yours). The figures go to
stdout as one JSON object, and to --out/compare.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2

from udh_cli.images import IMAGE_SUFFIXES, read_image, to_bgr_u8, write_image
from udh_cli.mosaic import MosaicConfig, Reporter, run_mosaic


def run_udh(frames: Path, out: Path, method: str, work_size: int, max_size: int | None) -> dict:
    report = run_mosaic(frames, out / f"udh_{method}.png", MosaicConfig(method=method, work_size=work_size, max_size=max_size), Reporter())
    loops = report["loop_consistency"]
    return {
        "tool": f"udh mosaic --method {method}",
        "frames": report["summary"]["frames"],
        "placed": report["summary"]["placed"],
        "parts": report["summary"]["parts"],
        "pairs_ok": report["summary"]["pairs_ok"],
        "pairs_failed": report["summary"]["pairs_failed"],
        "pairs_rejected": report["summary"]["pairs_rejected"],
        "loops_before_px": {k: loops["loops_before"][k] for k in ("count", "mean_px", "median_px", "max_px")},
        "loops_after_px": {k: loops["loops_after"][k] for k in ("count", "mean_px", "median_px", "max_px")},
        "time_s": {k: round(v, 2) for k, v in report["timings_s"].items()},
    }


def run_stitcher(frames: Path, out: Path) -> dict:
    paths = sorted(p for p in frames.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    start = time.perf_counter()
    images = [to_bgr_u8(read_image(p)) for p in paths]
    stitcher = cv2.Stitcher_create(cv2.Stitcher_SCANS)
    status, pano = stitcher.stitch(images)
    elapsed = time.perf_counter() - start
    placed = len(stitcher.component()) if status == cv2.Stitcher_OK else 0
    if status == cv2.Stitcher_OK:
        write_image(out / "opencv_stitcher_scans.png", pano)
    return {"tool": "cv2.Stitcher SCANS", "frames": len(paths), "placed": placed, "status": int(status), "time_s": {"total": round(elapsed, 2)}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("frames", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--methods", nargs="+", default=["sift", "orb"])
    parser.add_argument("--work-size", type=int, default=MosaicConfig.work_size)
    parser.add_argument("--max-size", type=int, default=None)
    parser.add_argument("--no-stitcher", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = [run_udh(args.frames, args.out, m, args.work_size, args.max_size) for m in args.methods]
    if not args.no_stitcher:
        results.append(run_stitcher(args.frames, args.out))
    text = json.dumps({"flight": str(args.frames), "results": results}, indent=1)
    (args.out / "compare.json").write_text(text + "\n")
    sys.stdout.write(text + "\n")


if __name__ == "__main__":
    main()
