"""Real image pairs with known homographies, for ``udh bench pairs``.

Two ways to list them:

* a **CSV** file with columns ``img1``, ``img2`` and ``H``: nine numbers, row-major, separated by spaces
  (or commas/semicolons inside a quoted field), ``x_2 ~ H x_1`` in pixels. Relative image paths are
  resolved against the CSV's folder (or its ``images/`` subfolder, the shared-data layout). Another column can hold H (``h_column``); the shared-data CSVs, for
  instance, hold SIFT+RANSAC *references* in ``H_sift_ransac_1to2``, which are not ground truth.
* an **Oxford/HPatches-style folder**: images ``<prefix>1.<ext>`` ... ``<prefix>N.<ext>`` and homography
  files ``H1toNp`` (Oxford; any extension :func:`udh_cli.homography_files.read_homography` reads, e.g.
  OpenCV's ``H1to3p.xml``) or ``H_1_N`` (HPatches), each mapping image 1 to image N.
"""

from __future__ import annotations

import csv
import io
import re
from pathlib import Path

import numpy as np

from udh_cli.bench.pairsets import PairSet
from udh_cli.errors import UdhError
from udh_cli.files import read_side_text
from udh_cli.homography_files import homography_from_values, parse_numbers, read_homography
from udh_cli.images import IMAGE_SUFFIXES, read_image

PAIR_IMAGE_SUFFIXES = tuple(IMAGE_SUFFIXES) + (".ppm", ".pgm")  # Oxford's sequences ship as PPM
_OXFORD_H = re.compile(r"^H(\d+)to(\d+)p?(\.\w+)?$")
_HPATCHES_H = re.compile(r"^H_(\d+)_(\d+)(\.\w+)?$")
_NUMBERED = re.compile(r"^(.*?)(\d+)$")


def load_real_pairs(path: str | Path, h_column: str = "H", prefix: str | None = None) -> PairSet:
    """A CSV file or an Oxford/HPatches folder (see the module docstring) as a :class:`PairSet`."""
    path = Path(path)
    if path.is_dir():
        return load_folder_pairs(path, prefix)
    if path.is_file():
        return load_csv_pairs(path, h_column)
    raise UdhError(f"{path}: no such file or folder; give a pairs CSV or an Oxford/HPatches-style folder")


def load_csv_pairs(path: Path, h_column: str = "H") -> PairSet:
    """Read a pairs CSV (columns ``img1``, ``img2`` and ``h_column``)."""
    try:
        rows = list(csv.DictReader(io.StringIO(read_side_text(path), newline="")))
        columns = list(rows[0].keys()) if rows else []
    except csv.Error as exc:
        raise UdhError(f"{path}: not a readable CSV ({exc})") from None
    if not rows:
        raise UdhError(f"{path}: no pairs; write a header img1,img2,H and one line per pair")
    missing = [c for c in ("img1", "img2", h_column) if c not in columns]
    if missing:
        raise UdhError(f"{path}: missing column(s) {', '.join(missing)}; it has {', '.join(map(str, columns))}")
    images_a, images_b, truths, labels = [], [], [], []
    for line, row in enumerate(rows, start=2):
        try:
            values = parse_numbers(row[h_column] or "")
        except ValueError:
            values = []
        matrix = homography_from_values(values, f"{path}, line {line}, column {h_column}")
        path_a, path_b = (_resolve(path.parent, (row[c] or "").strip()) for c in ("img1", "img2"))
        images_a.append(read_image(path_a))
        images_b.append(read_image(path_b))
        truths.append(matrix)
        labels.append(f"{path_a.name}->{path_b.name}")
    return PairSet(name=path.name, images_a=images_a, images_b=images_b, truths=np.stack(truths), labels=labels)


def _resolve(folder: Path, name: str) -> Path:
    """``name`` relative to the CSV's folder, or to its ``images/`` subfolder when only that holds it."""
    direct = folder / name
    nested = folder / "images" / name
    return nested if not direct.exists() and nested.exists() else direct


def load_folder_pairs(folder: Path, prefix: str | None = None) -> PairSet:
    """Read an Oxford/HPatches-style folder; ``prefix`` picks the image series when several share numbers."""
    numbered: dict[str, dict[int, Path]] = {}
    for image in sorted(folder.iterdir()):
        match = _NUMBERED.match(image.stem)
        if image.is_file() and image.suffix.lower() in PAIR_IMAGE_SUFFIXES and match:
            numbered.setdefault(match.group(1), {})[int(match.group(2))] = image
    h_files = []
    for candidate in sorted(folder.iterdir()):
        match = _OXFORD_H.match(candidate.name) or _HPATCHES_H.match(candidate.name)
        if candidate.is_file() and match:
            h_files.append((candidate, int(match.group(1)), int(match.group(2))))
    if not h_files:
        raise UdhError(f"{folder}: no homography files named H1to<N>p or H_1_<N>; give an Oxford/HPatches folder or a CSV")
    images_a, images_b, truths, labels = [], [], [], []
    for h_file, i, j in h_files:
        series = [p for p, by_number in numbered.items() if i in by_number and j in by_number]
        if prefix is not None:
            series = [p for p in series if p == prefix]
        if not series:
            wanted = f"'{prefix}{i}' and '{prefix}{j}'" if prefix is not None else f"'<name>{i}' and '<name>{j}'"
            raise UdhError(f"{folder}: {h_file.name} needs images {wanted} next to it; none found")
        if len(series) > 1:
            names = ", ".join(repr(p) for p in series)
            raise UdhError(f"{folder}: {h_file.name} could belong to the image series {names}; choose one with --prefix")
        path_a, path_b = numbered[series[0]][i], numbered[series[0]][j]
        images_a.append(read_image(path_a))
        images_b.append(read_image(path_b))
        truths.append(read_homography(h_file))
        labels.append(f"{path_a.name}->{path_b.name}")
    return PairSet(name=folder.name, images_a=images_a, images_b=images_b, truths=np.stack(truths), labels=labels)
