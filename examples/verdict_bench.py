"""How often a learned answer is called verified yet wrong: the shared flights' consecutive pairs against their
SIFT references, with the verdict of the one judge and with the rule before it, recomputed from the same answers.

    python examples/verdict_bench.py [--pairs 30] [--side 800] [--min-inliers 50]

Each flight's pairs are taken evenly from its ``consecutive_pairs_sift_reference.csv``, only those whose reference
has at least ``--min-inliers`` RANSAC inliers (a reference, not ground truth), both frames shrunk to ``--side`` px.
Wrong: over 10 px mean corner error against the reference at that size, or no answer.
The rule before: unverified when the tile levels did not confirm the answer, verified by a match of
CONFIDENT_INLIERS cells, else what a mosaic accepts (alignment at 256 px >= 0.3, confidence >= 0.2).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.judge import THRESHOLDS
from udh_cli.estimators.matching import CONFIDENT_INLIERS

FLIGHTS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "flights"


def before_rule(found) -> bool:
    """The verdict a mosaic applied to these answers before the judge (see the module docstring)."""
    d = found.details
    if not found.ok or "tiles" in d.get("verdict_failed", []):
        return False
    if found.stage == "match" and (found.inliers or 0) >= CONFIDENT_INLIERS:
        return True
    confidence = found.confidence if found.verified else found.confidence / THRESHOLDS.unverified_confidence
    return d.get("alignment", 0.0) >= 0.3 and confidence >= 0.2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=30, help="pairs per flight")
    parser.add_argument("--side", type=int, default=800)
    parser.add_argument("--min-inliers", type=int, default=50)
    parser.add_argument("--list", action="store_true", help="print every wrong pair")
    parser.add_argument("--heading-search", type=int, default=None, help="unsupervised's heading_search (default: its own)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    options = {} if args.heading_search is None else {"heading_search": args.heading_search}
    estimator = create_estimator("unsupervised", device="cpu", threads=1, **options)
    print("flight          pairs  wrong   verified-but-wrong (judge / before)   unverified-but-right (judge / before)")
    totals = np.zeros(6)
    for folder in sorted(p for p in FLIGHTS.iterdir() if (p / "consecutive_pairs_sift_reference.csv").is_file()):
        with open(folder / "consecutive_pairs_sift_reference.csv") as handle:
            rows = [r for r in csv.DictReader(handle) if int(r["ransac_inliers"]) >= args.min_inliers]
        rows = [rows[i] for i in np.unique(np.linspace(0, len(rows) - 1, min(args.pairs, len(rows))).round().astype(int))]
        counts = np.zeros(6)
        for row in rows:
            # The references are in the pixels as stored (boruszyn-kite's EXIF turn is not applied to them).
            a, b = (cv2.imread(str(folder / "images" / row[key]), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) for key in ("img1", "img2"))
            scale = args.side / max(*a.shape[:2], *b.shape[:2])
            size_a = (round(a.shape[1] * scale), round(a.shape[0] * scale))
            size_b = (round(b.shape[1] * scale), round(b.shape[0] * scale))
            truth = np.array([float(v) for v in row["H_sift_ransac_1to2"].split()]).reshape(3, 3)
            truth = geometry.rescale_homography(truth, (a.shape[1], a.shape[0]), size_a, (b.shape[1], b.shape[0]), size_b)
            a, b = cv2.resize(a, size_a, interpolation=cv2.INTER_AREA), cv2.resize(b, size_b, interpolation=cv2.INTER_AREA)
            found = estimator.estimate(a, b)
            wrong = not found.ok or float(geometry.mace(found.homography, truth, *size_a)) > 10.0
            now, before = bool(found.verified), before_rule(found)
            counts += [1, wrong, wrong and now, wrong and before, not wrong and not now, not wrong and not before]
            if wrong and args.list:
                error = float(geometry.mace(found.homography, truth, *size_a)) if found.ok else float("inf")
                print(f"  wrong: {row['img1']} {row['img2']} {error:.1f} px, reference inliers {row['ransac_inliers']}, "
                      f"stage {found.stage}, verified {found.verified}, failed {found.details.get('verdict_failed')}")
        totals += counts
        print(f"{folder.name:15} {int(counts[0]):5d} {int(counts[1]):5d}   {int(counts[2]):8d} / {int(counts[3]):<8d}"
              f"                  {int(counts[4]):8d} / {int(counts[5]):<8d}")
    n = totals[0]
    print(f"all: {int(n)} pairs, wrong {totals[1] / n:.1%}; verified-but-wrong judge {totals[2] / n:.1%}, before {totals[3] / n:.1%}; "
          f"unverified-but-right judge {totals[4] / n:.1%}, before {totals[5] / n:.1%}")


if __name__ == "__main__":
    main()
