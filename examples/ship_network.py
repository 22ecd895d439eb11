"""Ship a trained coarse network: the float32 and int8 ONNX files, the fine-tuning weights, the resumable
run and its learning curves, all in ``models/``. Needs the ``train`` extra (torch, onnx).

    python examples/ship_network.py RUN_FOLDER --name udh-unsupervised-flight --training-name permissive-flight --licence permissive --data IMAGES [--data IMAGES ...]

``RUN_FOLDER`` is a ``udh train --out`` folder. Its last checkpoint (the weights that resume and fine-tune
are the weights that ship) becomes ``models/NAME.onnx`` (checked for
parity against torch on synthetic pairs of the first ``--data`` folder) and ``models/NAME-int8.onnx``
(``udh quantize``, calibrated on ``--data``; none for a matcher, which ships in float32). Both record the terms
of ``--licence``'s set (``models_catalog.WEIGHTS_LICENCES``: those of the images the run trained on). The run's ``checkpoint.pt``, ``metrics.jsonl`` and
``config.json`` go to ``models/training/TRAINING_NAME/``: ``udh train --out ... --resume`` continues it
exactly, and ``udh train --init`` fine-tunes from it (``models_catalog.SHIPPED_RUNS``). With ``--weights-only``
the run's weights alone go there as ``weights.pt`` (a third of the checkpoint: no optimiser state, so it
fine-tunes but does not resume), which keeps ``models/`` under its 50 MB. The learning curves,
``models/learning_curves.png``, are redrawn from every shipped run's log.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np

from udh_cli.images import write_image
from udh_cli.models_catalog import WEIGHTS_LICENCES
from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs
from udh_cli.train.curves import learning_curve_plot, read_metrics
from udh_cli.train.export import export_onnx
from udh_cli.train.quantize import quantize_from_folders

MODELS = Path(__file__).resolve().parents[1] / "models"
# Logs drawn in models/learning_curves.png: the runs behind the shipped networks.
CURVES = {"coarse, flight motion": "permissive-flight", "coarse, paper motion": "permissive-coarse",
          "refinement": "permissive-refine", "matcher (global match)": "permissive-matcher"}
WEIGHT_KEYS = ("format", "model", "config", "step", "normalization")  # what --weights-only keeps of a checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--name", default="udh-unsupervised-flight", help="file stem in models/")
    parser.add_argument("--training-name", required=True, help="folder in models/training/ (models_catalog.SHIPPED_RUNS names the shipped ones)")
    parser.add_argument("--data", type=Path, action="append", required=True, help="training image folders (calibration)")
    parser.add_argument("--licence", choices=sorted(WEIGHTS_LICENCES), required=True, help="the set whose terms the weights carry")
    parser.add_argument("--weights-only", action="store_true", help="keep the weights, not the resumable checkpoint")
    args = parser.parse_args()

    sources = load_sources(list_images(args.data[0])[:20], min_count=1)
    check = make_pairs(sources, 16, PairConfig(), np.random.default_rng(0), with_context=False)
    exported = export_onnx(args.run / "checkpoint.pt", MODELS / f"{args.name}.onnx", np.stack([check.patch_a, check.patch_b], 1),
                           overwrite=True, licence=WEIGHTS_LICENCES[args.licence])
    print(f"{exported['path']}: parity {exported['max_abs_diff']:.2e}")
    if exported["metadata"]["mode"] != "match":
        quantized = quantize_from_folders(MODELS / f"{args.name}.onnx", MODELS / f"{args.name}-int8.onnx", args.data, overwrite=True)
        print(f"{quantized['path']}: {quantized['median_drift_px']:.3f} px median from float32")

    kept = MODELS / "training" / args.training_name
    kept.mkdir(parents=True, exist_ok=True)
    for name in ("metrics.jsonl", "config.json") if args.weights_only else ("checkpoint.pt", "metrics.jsonl", "config.json"):
        shutil.copy2(args.run / name, kept / name)
    if args.weights_only:
        import torch

        state = torch.load(args.run / "checkpoint.pt", map_location="cpu", weights_only=True)
        torch.save({key: state[key] for key in WEIGHT_KEYS}, kept / "weights.pt")
    runs = {label: read_metrics(MODELS / "training" / folder / "metrics.jsonl") for label, folder in CURVES.items()
            if (MODELS / "training" / folder / "metrics.jsonl").is_file()}
    write_image(MODELS / "learning_curves.png", learning_curve_plot(runs, title="held-out median corner error, single pass"))
    print(f"{kept}: {'weights' if args.weights_only else 'resumable run'}; {MODELS / 'learning_curves.png'} redrawn ({', '.join(runs)})")


if __name__ == "__main__":
    cv2.setNumThreads(1)
    main()
