"""Real pairs with a reference homography, found in the sources a user names, for ``udh bench hard``.

A source is one of:

* a **pairs CSV** (columns ``img1``, ``img2`` and an H column: ``H``, or the shared data's SIFT+RANSAC
  reference ``H_sift_ransac_1to2``; nine numbers, ``x_2 ~ H x_1``), or a folder holding one. A flight's
  ``consecutive_pairs*.csv`` gives the group "flight pairs", any other CSV "real pairs". A ``ransac_inliers``
  column, where there is one, drops references fitted to fewer than :data:`MIN_REFERENCE_INLIERS` matches.
  A ``manifest.csv`` beside it with an ``exif_orientation`` column says the references are in the stored
  (unrotated) pixels; they are turned with the images, which are read as a viewer shows them.
* an **Oxford/HPatches folder** (``graf1``... with ``H1to3p.xml``...; :mod:`udh_cli.bench.real_pairs`): "real pairs".
* a folder of such sources (e.g. ``data/flights``), searched one level down.

Every pair is scored at :data:`SCORED_SIDE`: both images shrunk (never enlarged) so that the longer side is
800 px, grey uint8, and the reference rescaled exactly with them.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.bench.real_pairs import load_folder_pairs
from udh_cli.errors import UdhError
from udh_cli.homography_files import homography_from_values, parse_numbers
from udh_cli.images import read_image, to_gray_u8

SCORED_SIDE = 800  # longest side, px, at which errors are measured: the mosaic's working size
MIN_REFERENCE_INLIERS = 50  # a SIFT reference fitted to fewer RANSAC inliers is too unsure to score against
H_COLUMNS = ("H", "H_sift_ransac_1to2")  # ground truth, then the shared data's reference
FLIGHT_GROUP, PAIRS_GROUP = "flight pairs", "real pairs"


def _stored_to_shown(orientation: int, width: int, height: int) -> np.ndarray:
    """(3, 3) from pixels of a stored ``width`` x ``height`` image to the same pixels after its EXIF
    ``orientation`` is applied (1: none, 3: half turn, 6: quarter turn clockwise, 8: anticlockwise)."""
    maps = {1: [[1, 0, 0], [0, 1, 0]], 3: [[-1, 0, width - 1], [0, -1, height - 1]],
            6: [[0, -1, height - 1], [1, 0, 0]], 8: [[0, 1, 0], [-1, 0, width - 1]]}
    if orientation not in maps:
        raise UdhError(f"EXIF orientation {orientation} (a mirrored image) is not supported; give the pairs as stored")
    return np.array(maps[orientation] + [[0, 0, 1]], np.float64)


def _shrunk(image: np.ndarray, side: int) -> np.ndarray:
    height, width = image.shape[:2]
    scale = side / max(width, height)
    if scale >= 1:
        return image
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class ReferencePair:
    """A real pair and its reference ``b_from_a``, read lazily.

    Attributes:
        group: :data:`FLIGHT_GROUP` or :data:`PAIRS_GROUP`.
        source: the folder or CSV it came from, by name.
        label: ``"a.jpg->b.jpg"``.
        image_a, image_b: paths, or images already read (Oxford folders).
        b_from_a: (3, 3) reference between the images as stored (``orientation``) or as read.
        orientation: EXIF orientation of A and B when the reference is in stored pixels; ``None`` otherwise.
    """

    group: str
    source: str
    label: str
    image_a: Path | np.ndarray
    image_b: Path | np.ndarray
    b_from_a: np.ndarray
    orientation: tuple[int, int] | None = None

    def load(self, side: int = SCORED_SIDE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(a, b, b_from_a)``: grey uint8 images with the longer side at most ``side`` px, and the reference
        between them."""
        images = [read_image(p) if isinstance(p, Path) else p for p in (self.image_a, self.image_b)]
        truth = np.asarray(self.b_from_a, np.float64)
        if self.orientation is not None:
            (ha, wa), (hb, wb) = images[0].shape[:2], images[1].shape[:2]
            stored_a = (wa, ha) if self.orientation[0] in (1, 3) else (ha, wa)
            stored_b = (wb, hb) if self.orientation[1] in (1, 3) else (hb, wb)
            truth = (_stored_to_shown(self.orientation[1], *stored_b) @ truth
                     @ np.linalg.inv(_stored_to_shown(self.orientation[0], *stored_a)))
        small = [to_gray_u8(_shrunk(image, side)) for image in images]
        sizes = [(i.shape[1], i.shape[0]) for i in images]
        truth = geometry.rescale_homography(truth, sizes[0], (small[0].shape[1], small[0].shape[0]),
                                            sizes[1], (small[1].shape[1], small[1].shape[0]))
        return small[0], small[1], truth


def _orientations(folder: Path) -> dict[str, int] | None:
    """File name -> EXIF orientation from ``manifest.csv`` beside a pairs CSV; None where it says nothing."""
    manifest = folder / "manifest.csv"
    if not manifest.is_file():
        return None
    with open(manifest, newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or "exif_orientation" not in rows[0] or "file" not in rows[0]:
        return None
    return {row["file"]: int(float(row["exif_orientation"] or 1)) for row in rows}


def _resolve(folder: Path, name: str) -> Path:
    nested = folder / "images" / name
    return nested if not (folder / name).exists() and nested.exists() else folder / name


def csv_pairs(path: Path, min_inliers: int = MIN_REFERENCE_INLIERS) -> list[ReferencePair]:
    """The pairs of a pairs CSV (see the module docstring); images are read only when loaded."""
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UdhError(f"{path}: not a readable CSV ({exc})") from None
    columns = list(rows[0]) if rows else []
    h_column = next((c for c in H_COLUMNS if c in columns), None)
    if h_column is None or "img1" not in columns or "img2" not in columns:
        raise UdhError(f"{path}: needs columns img1, img2 and one of {', '.join(H_COLUMNS)}")
    group = FLIGHT_GROUP if path.name.startswith("consecutive_pairs") else PAIRS_GROUP
    orientations = _orientations(path.parent)
    pairs = []
    for line, row in enumerate(rows, start=2):
        if "ransac_inliers" in row and float(row["ransac_inliers"] or 0) < min_inliers:
            continue
        try:
            values = parse_numbers(row[h_column] or "")
        except ValueError:
            values = []
        truth = homography_from_values(values, f"{path}, line {line}, column {h_column}")
        name_a, name_b = (row[c].strip() for c in ("img1", "img2"))
        orientation = None if orientations is None else (orientations.get(name_a, 1), orientations.get(name_b, 1))
        pairs.append(ReferencePair(group, path.parent.name if path.parent.name else path.name, f"{name_a}->{name_b}",
                                   _resolve(path.parent, name_a), _resolve(path.parent, name_b), truth, orientation))
    return pairs


def _pairs_csv_in(folder: Path) -> Path | None:
    for candidate in sorted(folder.glob("*.csv")):
        with open(candidate, newline="") as handle:
            header = next(csv.reader(handle), [])
        if "img1" in header and "img2" in header and any(c in header for c in H_COLUMNS):
            return candidate
    return None


def source_pairs(path: Path, prefix: str | None = None, min_inliers: int = MIN_REFERENCE_INLIERS) -> list[ReferencePair]:
    """The pairs of one source (see the module docstring); [] for a folder that is not a source."""
    if path.is_file():
        return csv_pairs(path, min_inliers)
    found = _pairs_csv_in(path)
    if found is not None:
        return csv_pairs(found, min_inliers)
    if any(path.glob("H1to*")) or any(path.glob("H_1_*")):
        pair_set = load_folder_pairs(path, prefix)
        return [ReferencePair(PAIRS_GROUP, path.name, label, a, b, truth) for label, a, b, truth
                in zip(pair_set.labels, pair_set.images_a, pair_set.images_b, pair_set.truths)]
    return []


def find_pairs(sources: list[Path], prefix: str | None = None,
               min_inliers: int = MIN_REFERENCE_INLIERS) -> tuple[list[ReferencePair], list[str]]:
    """Every reference pair in ``sources`` (each a source or a folder of sources), and notes on what was
    skipped. Raises :class:`UdhError` for a missing path or when no pair is found."""
    pairs: list[ReferencePair] = []
    notes: list[str] = []
    for source in sources:
        source = Path(source)
        if not source.exists():
            raise UdhError(f"{source}: no such file or folder; give pair sources (a pairs CSV, a flight folder, an Oxford folder)")
        own = source_pairs(source, prefix, min_inliers)
        if own or source.is_file():
            pairs.extend(own)
            continue
        for folder in sorted(p for p in source.iterdir() if p.is_dir()):
            found = source_pairs(folder, prefix, min_inliers)
            pairs.extend(found)
            if not found:
                notes.append(f"{folder}: no pairs with a reference homography; skipped")
    if not pairs:
        raise UdhError(f"{', '.join(map(str, sources))}: no pairs with a reference homography found; give a pairs CSV "
                       f"(img1,img2,H), a flight folder with consecutive_pairs_sift_reference.csv, or an Oxford folder")
    return pairs, notes
