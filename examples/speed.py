"""Inference speed on this machine: the network alone, and the whole `estimate` against SIFT and ORB.

    python examples/speed.py [--images DIR] [--pairs 50]

Runs every method on the same 320x240 pairs in one process (after a warm-up) and prints median times.
"Whole estimate" = decode the two JPEGs from memory, convert, resize, run the method, and for the learned
methods the DLT and the exact rescale to the original pixels. Times are medians over the pairs, and so is the
corner error of each method on the whole frames, at the corners of the patch the pair was drawn from (A's border
is reflected texture where the warp left the source).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.onnx_model import OnnxHomographyModel
from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs, split_holdout

DEFAULT_IMAGES = Path("../shared/data/pools/rsscn7-aerial/images")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=Path, default=DEFAULT_IMAGES)
    parser.add_argument("--pairs", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime intra-op threads")
    parser.add_argument("--network", type=Path, action="append", default=[],
                        help="another udh ONNX network to time alone (e.g. a corr-lite export); repeatable")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    _, held_out = split_holdout(list_images(args.images))
    sources = load_sources(held_out[:40])
    # Whole 320x240 frames: A is the source warped by a rho-32 perturbation, B is the source.
    batch = make_pairs(sources, args.pairs, PairConfig(rho=32), np.random.default_rng(0))
    frames = [(cv2.imencode(".jpg", (batch.context_a[i, 0] * 255).astype(np.uint8))[1],
               cv2.imencode(".jpg", sources[batch.source_index[i]])[1]) for i in range(args.pairs)]
    patch_truths, patch_size = batch.homographies(), batch.patch_a.shape[1]

    networks = []
    for precision in ("int8", "fp32"):  # the shipped default (int8) and the float32 networks it was made from
        cascade = create_estimator("unsupervised", device="cpu", threads=args.threads, precision=precision)
        networks += [(f"{stage}, {precision}", network, f"{rounds} round(s) by default")
                     for stage, (network, rounds) in zip(("coarse network", "refinement network"), cascade.stages)]
    for path in args.network:
        network = OnnxHomographyModel.load(path, "cpu", args.threads)
        networks.append((f"{path.name} ({network.metadata.get('arch')})", network, "not shipped"))
    for stage, network, note in networks:
        patch = np.random.default_rng(0).random((1, 2, network.input_size, network.input_size), dtype=np.float32)
        for _ in range(20):
            network.predict_offsets(patch)
        times = []
        for _ in range(200):
            start = time.perf_counter()
            network.predict_offsets(patch)
            times.append((time.perf_counter() - start) * 1e3)
        print(f"{stage} alone (onnxruntime CPU, batch 1, {args.threads} thread): median {np.median(times):.2f} ms per round, {note}")

    single = {"device": "cpu", "threads": args.threads, "iterations": 1, "refine_rounds": 0}
    methods = {"unsupervised, 1 coarse round": ("unsupervised", single),
               "the same, fp32": ("unsupervised", {**single, "precision": "fp32"}),
               "unsupervised, default cascade": ("unsupervised", {"device": "cpu", "threads": args.threads}),
               "auto (the default method)": ("auto", {"device": "cpu", "threads": args.threads}),
               "orb": ("orb", {}), "sift": ("sift", {})}
    results, errors = {}, {}
    for name, (method, options) in methods.items():
        estimator = create_estimator(method, **options)
        whole = []
        for i, (jpeg_a, jpeg_b) in enumerate(frames):
            start = time.perf_counter()
            a = cv2.imdecode(jpeg_a, cv2.IMREAD_GRAYSCALE)
            b = cv2.imdecode(jpeg_b, cv2.IMREAD_GRAYSCALE)
            estimate = estimator.estimate(a, b)
            if i >= 3:  # warm-up
                whole.append((time.perf_counter() - start) * 1e3)
            found = estimate.homography if estimate.ok else np.eye(3)  # no answer: scored as no motion
            # Scored where the pair was drawn, at the patch's corners (as `udh bench --mode full` does): the frame's
            # own corners lie far outside the perturbed patch, where any error is magnified.
            x0, y0 = (float(v) for v in batch.origin[i])
            in_patch = geometry.translation(-x0, -y0) @ found @ geometry.translation(x0, y0)
            errors.setdefault(name, []).append(float(geometry.mace(in_patch, patch_truths[i], patch_size, patch_size)))
        results[name] = float(np.median(whole))
    for name, ms in results.items():
        error = np.array(errors[name])
        print(f"whole estimate, {name:>30}: median {ms:7.2f} ms per 320x240 pair  ({ms / results['sift']:.3f} x SIFT); "
              f"corner error median {np.median(error):.2f} px, {100 * np.mean(error > 10):.0f} % over 10 px")


if __name__ == "__main__":
    main()
