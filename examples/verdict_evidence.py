"""Every piece of evidence behind a method's verdict, pair by pair, on the hard real-pair benchmark's pairs.

    OMP_NUM_THREADS=1 python examples/verdict_evidence.py ../shared/data/flights ../shared/data/pairs --prefix graf \
        --n 10 --seed 0 --methods unsupervised,auto --out evidence-seed0.jsonl

One JSON line per (method, pair): the kind of motion, the pair's label, the error (mean corner distance to the
truth, px of the 800-px B), the verdict (``verified``, ``confidence``, ``verified_by``, ``stage``), the estimate's
details (the judge's evidence, or auto's policy inputs: ``score``, ``start_score``, ``ecc_correlation``...), and
candidate evidence measured here from the answer alone:

* ``align_512``: the photometric score at 512 px instead of 256;
* ``ecc_move_px``: how far one ECC level at 400 px moves a corner of A from the answer (px of the 800-px A);
* ``ecc_overlap_move_px``: the same at 200 px, measured at the points of a 9 x 9 grid over A that land in B;
* ``orb_inliers``, ``orb_disagreement_px``: ORB at 400 px, its inliers and its largest corner distance from the answer.

``--summary`` prints, for each method, the wrong answers the verdict called verified and what the file records.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.bench.hard import build_sets
from udh_cli.bench.hard_pairs import MIN_REFERENCE_INLIERS, find_pairs
from udh_cli.bench.metrics import FAIL_PX
from udh_cli.estimators import create_estimator
from udh_cli.estimators.base import is_verified, json_ready
from udh_cli.estimators.ecc import EccEstimator
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.verify import Verifier
from udh_cli.errors import EstimationFailed
from udh_cli.images import scaled_size

FINE_VERIFIER = Verifier(side=512)
CHECK_SIDE = 400  # px of the ECC step and the ORB opinion: cheap at drone frame sizes


def ecc_move_px(pair: PreparedPair, b_from_a: np.ndarray, side: int = CHECK_SIDE, overlap: bool = False) -> float:
    """Largest move (px of A) that one ECC level at ``side`` px makes from ``b_from_a``, at A's corners or (``overlap``)
    at the points of a 9 x 9 grid over A that land in B; inf if it fails."""
    scale = min(1.0, side / max(*pair.a.size, *pair.b.size))
    work_a, work_b = scaled_size(pair.a.size, scale), scaled_size(pair.b.size, scale)
    start = geometry.rescale_homography(b_from_a, pair.a.size, work_a, pair.b.size, work_b)
    try:
        moved, _, _ = EccEstimator(iterations=15, eps=1e-4, gauss_filt_size=3, min_correlation=0.0).refine(
            pair.a.contrast(work_a, 2.0), pair.b.contrast(work_b, 2.0), start)
    except EstimationFailed:
        return float("inf")
    full = geometry.rescale_homography(moved, work_a, pair.a.size, work_b, pair.b.size)
    if not overlap:
        return float(geometry.corner_errors(full, b_from_a, *pair.a.size).max())
    grid = np.stack(np.meshgrid(np.linspace(0, pair.a.size[0] - 1, 9), np.linspace(0, pair.a.size[1] - 1, 9)), -1).reshape(-1, 2)
    in_b = geometry.transform_points(b_from_a, grid)
    inside = np.isfinite(in_b).all(1) & (in_b >= 0).all(1) & (in_b <= np.array(pair.b.size) - 1).all(1)
    if inside.sum() < 3:
        return float("inf")
    moves = np.linalg.norm(geometry.transform_points(full, grid[inside]) - in_b[inside], axis=1)
    return float(moves.max()) if np.isfinite(moves).all() else float("inf")


def orb_opinion(orb, pair: PreparedPair, b_from_a: np.ndarray, side: int = CHECK_SIDE) -> tuple[int, float]:
    """ORB's inliers at ``side`` px and its largest corner distance (px of A) from ``b_from_a``."""
    scale = min(1.0, side / max(*pair.a.size, *pair.b.size))
    work_a, work_b = scaled_size(pair.a.size, scale), scaled_size(pair.b.size, scale)
    found = orb.estimate(pair.a.resized(work_a), pair.b.resized(work_b))
    if not found.ok:
        return 0, float("inf")
    full = geometry.rescale_homography(found.homography, work_a, pair.a.size, work_b, pair.b.size)
    return int(found.inliers or 0), float(geometry.corner_errors(full, b_from_a, *pair.a.size).max())


def measure(methods: list[str], sources: list[Path], prefix: str | None, n: int, seed: int, out: Path) -> None:
    pairs, _ = find_pairs(sources, prefix, MIN_REFERENCE_INLIERS)
    sets, _ = build_sets(pairs, n, seed)
    orb = create_estimator("orb")
    estimators = {m: create_estimator(m, device="cpu", threads=1) for m in methods}
    with open(out, "w") as handle:
        for pair_set in sets:
            for i in range(len(pair_set)):
                pair = PreparedPair.of(pair_set.images_a[i], pair_set.images_b[i])
                truth = pair_set.truths[i]
                for method, estimator in estimators.items():
                    found = estimator.estimate_pairs([pair])[0]
                    row = {"method": method, "kind": pair_set.name, "label": pair_set.labels[i], "ok": found.ok,
                           "verified": is_verified(found), "confidence": found.confidence, "stage": found.stage,
                           "verified_by": found.verified_by, "ms": found.elapsed_ms, "details": json_ready(found.details)}
                    if found.ok:
                        h = found.homography
                        row["homography"] = h.tolist()
                        row["error_px"] = float(geometry.mace(h, truth, *pair.a.size))
                        row["align_512"] = FINE_VERIFIER.score(pair.a, pair.b, h)
                        row["ecc_move_px"] = ecc_move_px(pair, h)
                        row["ecc_overlap_move_px"] = ecc_move_px(pair, h, side=200, overlap=True)
                        row["orb_inliers"], row["orb_disagreement_px"] = orb_opinion(orb, pair, h)
                    else:
                        row["error_px"] = float(geometry.mace(np.eye(3), truth, *pair.a.size))
                    handle.write(json.dumps(row, default=float) + "\n")
                    handle.flush()


def summary(path: Path) -> None:
    rows = [json.loads(line) for line in open(path)]
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        wrong = [r for r in mine if not r["ok"] or r["error_px"] > FAIL_PX]
        verified_wrong = [r for r in wrong if r["verified"]]
        verified = sum(r["verified"] for r in mine)
        print(f"{method}: {len(mine)} pairs, {len(wrong)} wrong, {verified} verified, {len(verified_wrong)} verified but wrong")
        for r in verified_wrong:
            print(f"  {r['error_px']:7.1f} px  {r['kind'][:12]:12s} {r['stage']:8s} conf {r['confidence']:.2f}  "
                  f"align512 {r.get('align_512', 0):.2f}  ecc {r.get('ecc_move_px', 0):6.1f}  orb {r.get('orb_inliers', 0)}/"
                  f"{r.get('orb_disagreement_px', 0):.0f}  {r['label'][:50]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sources", nargs="*", type=Path)
    parser.add_argument("--prefix")
    parser.add_argument("--n", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", default="unsupervised,auto")
    parser.add_argument("--out", type=Path, default=Path("evidence.jsonl"))
    parser.add_argument("--summary", action="store_true", help="summarise --out instead of measuring")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    if not args.summary:
        measure(args.methods.split(","), args.sources, args.prefix, args.n, args.seed, args.out)
    summary(args.out)


if __name__ == "__main__":
    main()
