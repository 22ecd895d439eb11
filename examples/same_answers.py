"""Record every registered method's answers on fixed pairs, or compare two such records: a refactor's check
that no answer changed.

    python examples/same_answers.py record /tmp/before.json [--data ../shared/data]
    python examples/same_answers.py compare /tmp/before.json /tmp/after.json

The pairs: the contract pair of tests/estimators/test_contract.py and a flat one (made here), and, where the
shared data is present, 12 real pairs (6 consecutive copr pairs at 800 px, 3 brighton-beach pairs, 3 of
pairs/), estimated in one batch per method. Recorded per answer: the homography, confidence, verified,
verified_by, stage and details without timings. The comparison reports the largest corner difference, px,
and every other field that differs.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import create_estimator, estimator_names
from udh_cli.images import read_image

ROOT = Path(__file__).resolve().parents[1]

CONTRACT_H = np.array([[1.0, 0.01, 6.0], [-0.01, 1.0, -4.0], [0.0, 0.0, 1.0]])  # test_contract.TRUE
TIMINGS = ("stage_ms", "elapsed_ms")
# Variants of the learned method that take branches its defaults do not: (label, name, options, near_prior).
VARIANTS = (("unsupervised near_prior", "unsupervised", {}, True),
            ("unsupervised no tiles, search 1", "unsupervised", {"tiles": False, "search": 1}, False),
            ("unsupervised one heading, no heading search", "unsupervised", {"headings": 1, "heading_search": 0}, False))


def _at_800(image: np.ndarray) -> np.ndarray:
    scale = 800 / max(image.shape[:2])
    return cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)


def real_pairs(data: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The 12 real pairs, named; none when ``data`` is absent."""
    if not data.is_dir():
        return []
    copr = sorted((data / "flights/copr/images").glob("*"))[:7]
    brighton = sorted((data / "flights/brighton-beach/images").glob("*"))
    pairs = [(f"copr {a.name}", _at_800(read_image(a)), _at_800(read_image(b))) for a, b in zip(copr, copr[1:])]
    pairs += [(f"brighton {brighton[i].name}", _at_800(read_image(brighton[i])), _at_800(read_image(brighton[i + 1])))
              for i in (0, 5, 10)]
    named = (("uav-mountain/images/A1.JPG", "uav-mountain/images/A2.JPG"), ("vlfeat/river1.jpg", "vlfeat/river2.jpg"),
             ("opencv-samples/aero1.jpg", "opencv-samples/aero3.jpg"))
    pairs += [(a, _at_800(read_image(data / "pairs" / a)), _at_800(read_image(data / "pairs" / b))) for a, b in named]
    return pairs


def _plain(value):
    """JSON-ready copy of a details value without timings."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if k not in TIMINGS}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _answer(found, size) -> dict:
    return {"homography": None if found.homography is None else found.homography.tolist(), "size": list(size),
            "confidence": found.confidence, "verified": found.verified, "verified_by": found.verified_by,
            "stage": found.stage, "failure": found.failure, "inliers": found.inliers,
            "verification_score": found.verification_score, "details": _plain(found.details)}


def contract_pair() -> tuple[np.ndarray, np.ndarray]:
    """The pair of tests/estimators/test_contract.py, made by the tests' own ``warped_pair``."""
    spec = importlib.util.spec_from_file_location("udh_tests_conftest", ROOT / "tests" / "conftest.py")
    conftest = sys.modules[spec.name] = importlib.util.module_from_spec(spec)  # its dataclasses look themselves up there
    spec.loader.exec_module(conftest)
    return conftest.warped_pair(CONTRACT_H, width=320, height=240, seed=11)


def record(out: Path, data: Path) -> None:
    contract = contract_pair()
    flat = (np.full((240, 320), 128, np.uint8),) * 2
    real = real_pairs(data)
    runs = [(name, name, {}, False) for name in estimator_names()] + list(VARIANTS)
    answers = {}
    for label, name, options, near in runs:
        estimator = create_estimator(name, **options)
        estimator = estimator.near_prior() if near else estimator
        answers[f"{label} | contract"] = _answer(estimator.estimate(*contract), (320, 240))
        answers[f"{label} | flat"] = _answer(estimator.estimate(*flat), (320, 240))
        if real:
            found = estimator.estimate_many([(a, b) for _, a, b in real])
            for (pair, a, _), one in zip(real, found):
                answers[f"{label} | {pair}"] = _answer(one, (a.shape[1], a.shape[0]))
        print(label, "done", flush=True)
    out.write_text(json.dumps(answers, indent=1, sort_keys=True))
    print(f"{len(answers)} answers -> {out}")


def _differences(before, after, path="") -> list[str]:
    if isinstance(before, dict) and isinstance(after, dict):
        if before.keys() != after.keys():
            return [f"{path}: keys {sorted(before.keys() ^ after.keys())}"]
        return [d for k in before for d in _differences(before[k], after[k], f"{path}.{k}")]
    if isinstance(before, float) and isinstance(after, float):
        return [] if abs(before - after) <= 1e-9 else [f"{path}: {before} -> {after}"]
    return [] if before == after else [f"{path}: {before} -> {after}"]


def compare(before_path: Path, after_path: Path) -> int:
    before, after = json.loads(before_path.read_text()), json.loads(after_path.read_text())
    problems, largest = [], 0.0
    if before.keys() != after.keys():
        problems.append(f"answers: {sorted(before.keys() ^ after.keys())}")
    for key in sorted(before.keys() & after.keys()):
        was, now = before[key], after[key]
        if (was["homography"] is None) != (now["homography"] is None):
            problems.append(f"{key}: homography {was['homography']} -> {now['homography']}")
        elif was["homography"] is not None:
            width, height = was["size"]
            error = float(geometry.corner_errors(np.array(was["homography"]), np.array(now["homography"]), width, height).max())
            largest = max(largest, error)
            if not error <= 1e-6:
                problems.append(f"{key}: corners moved {error:.3g} px")
        rest = {k: v for k, v in was.items() if k != "homography"}
        problems += [f"{key}{d}" for d in _differences(rest, {k: v for k, v in now.items() if k != "homography"})]
    print(f"{len(before)} answers compared; largest corner difference {largest:.3g} px; {len(problems)} differences")
    for line in problems:
        print("  " + line)
    return 1 if problems else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("record")
    rec.add_argument("out", type=Path)
    rec.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    cmp = commands.add_parser("compare")
    cmp.add_argument("before", type=Path)
    cmp.add_argument("after", type=Path)
    args = parser.parse_args()
    if args.command == "record":
        record(args.out, args.data)
        return 0
    return compare(args.before, args.after)


if __name__ == "__main__":
    raise SystemExit(main())
