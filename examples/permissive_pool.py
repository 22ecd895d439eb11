"""Build a training pool from permissively licensed images only, for weights anyone may use.

    python examples/permissive_pool.py --data ../shared/data --out pools/permissive [--side 512]

Takes every frame of the brighton-beach (BSD-2-Clause), seneca (CC0 1.0) and boruszyn-kite (CC BY 3.0) flights,
the package-samples images (CC0 / public domain / CC BY 2.0) and 60 grounds painted by udh's own simulator, and
writes them as JPEGs with the longer side at most ``--side`` pixels. copr (CC BY-SA 4.0) is left out: its
share-alike terms would reach weights trained on it, and it stays a flight no network has seen. Train with
``udh train --data OUT ...`` (docs/training.md); models/README.md records which runs used it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from udh_cli.images import read_image
from udh_cli.simulate import make_ground

FLIGHTS = ("brighton-beach", "seneca", "boruszyn-kite")
GROUNDS = 60
GROUND_SEED = 1000  # away from the seeds udh simulate uses by default
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}


def _write(image, path: Path, side: int) -> None:
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    height, width = image.shape[:2]
    scale = side / max(height, width)
    if scale < 1:
        image = cv2.resize(image, (round(width * scale), round(height * scale)), interpolation=cv2.INTER_AREA)
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 85]):
        raise SystemExit(f"{path}: could not be written")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="the shared data folder (flights/ and pools/ in it)")
    parser.add_argument("--out", type=Path, required=True, help="a new or empty folder for the pool")
    parser.add_argument("--side", type=int, default=512, help="longest side of the written images, px")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if any(args.out.iterdir()):
        raise SystemExit(f"{args.out}: not empty; give a new folder")
    sources = [(f"{flight}_", sorted((args.data / "flights" / flight / "images").iterdir())) for flight in FLIGHTS]
    sources.append(("samples_", sorted((args.data / "pools" / "package-samples").rglob("*"))))
    count = 0
    for prefix, paths in sources:
        for path in paths:
            if path.suffix.lower() not in IMAGE_SUFFIXES:
                continue
            image = read_image(path)
            if min(image.shape[:2]) < 64 or image.dtype != "uint8":
                continue
            _write(image, args.out / f"{prefix}{path.stem}.jpg", args.side)
            count += 1
    for index in range(GROUNDS):
        _write(make_ground((640, 480), seed=GROUND_SEED + index), args.out / f"ground_{index:03d}.jpg", args.side)
        count += 1
    print(f"{count} images in {args.out}")


if __name__ == "__main__":
    main()
