"""Reading and writing 3x3 homography files (ground truth, results)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.files import read_side_file


MAX_HOMOGRAPHY_FILE_BYTES = 2**20  # nine numbers, or an OpenCV FileStorage file or estimate's JSON around them


def read_homography(path: str | Path, option: str = "") -> np.ndarray:
    """Read a 3x3 homography, ``b_from_a`` in pixels, normalised to h33 = 1.

    Accepted forms: nine numbers separated by spaces, commas or newlines (row-major; Oxford/HPatches
    ``H1to3p`` text files are of this kind); a JSON list of 3 rows or of 9 numbers, or an object with a
    ``homography`` key (``udh estimate --json`` output); an OpenCV FileStorage ``.xml``/``.yml`` file,
    whose first matrix is taken. Only a regular file of at most 1 MiB is read (``option``, e.g. ``--gt``, is
    named in the messages). Raises :class:`UdhError` for anything else.
    """
    path = Path(path)
    if path.is_dir():
        raise UdhError(f"{path}: is a folder, not a homography file")
    if not (path.exists() or path.is_symlink()):
        raise UdhError(f"{path}: no such homography file; check the path")
    text = read_side_file(path, option, MAX_HOMOGRAPHY_FILE_BYTES).decode("utf-8-sig", errors="replace")  # binary: 'not a 3x3'
    suffix = path.suffix.lower()
    try:
        if suffix in (".xml", ".yml", ".yaml"):
            values = _read_filestorage(text)
        elif suffix == ".json":
            data = json.loads(text)
            values = data.get("homography") if isinstance(data, dict) else data
        else:
            values = parse_numbers(text)
    except (ValueError, TypeError, AttributeError, RecursionError, json.JSONDecodeError, cv2.error):  # RecursionError: absurdly nested JSON
        values = None
    return homography_from_values(values, str(path))


def parse_numbers(text: str) -> list[float]:
    """Numbers separated by spaces, commas, semicolons or newlines; ValueError for anything else."""
    return [float(v) for v in re.split(r"[\s,;]+", text.strip()) if v]


def homography_from_values(values, where: str) -> np.ndarray:
    """Nine numbers (row-major, any nesting) -> (3, 3) ``b_from_a`` with h33 = 1.

    Raises :class:`UdhError`, naming ``where`` (a file, a CSV line...), unless they are nine finite numbers
    with h33 != 0 that do not flatten the image.
    """
    try:
        matrix = np.asarray(values, dtype=np.float64).reshape(3, 3)
    except (ValueError, TypeError):
        raise UdhError(f"{where}: not a 3x3 homography; write nine numbers, row-major, x_B ~ H x_A") from None
    if not np.isfinite(matrix).all() or abs(matrix[2, 2]) < 1e-12 * max(1.0, float(np.abs(matrix).max())):
        raise UdhError(f"{where}: the homography is not finite or has h33 = 0; give a usable x_B ~ H x_A")
    matrix = matrix / matrix[2, 2]
    # Singularity is judged on the normalised matrix, so a scaled identity (1e-6 * I) is not "singular".
    if abs(np.linalg.det(matrix)) < 1e-12 * max(1.0, float(np.abs(matrix).max()) ** 3):
        raise UdhError(f"{where}: the homography is singular (it flattens the image to a line)")
    return matrix


def _read_filestorage(text: str) -> np.ndarray:
    """The first matrix node in the text of an OpenCV FileStorage file; ValueError if there is none."""
    try:
        storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError):  # the parser raises (wrapped as SystemError) on malformed XML/YAML
        raise ValueError("unparsable") from None
    if not storage.isOpened():
        raise ValueError("unreadable")
    root = storage.root()
    for key in root.keys():
        matrix = root.getNode(key).mat()
        if matrix is not None:
            return matrix
    raise ValueError("no matrix")


def format_homography(matrix: np.ndarray) -> str:
    """Nine numbers, three to a line, with full precision: the format :func:`read_homography` reads."""
    return "\n".join(" ".join(f"{v:.10g}" for v in row) for row in np.asarray(matrix, dtype=np.float64)) + "\n"
