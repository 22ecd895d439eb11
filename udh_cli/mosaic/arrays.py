"""``mosaic_images``: the mosaic of a list of image arrays, returned as arrays (for notebooks and scripts).

The frames go through :func:`~udh_cli.mosaic.run.run_mosaic` unchanged: they are written losslessly (PNG)
into a private temporary folder with the mosaic, read back, and the folder is removed, so the caller gets
arrays and no files. Every option of the command line is a field of :class:`~udh_cli.mosaic.config.MosaicConfig`.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from udh_cli.errors import UdhError


@dataclass(frozen=True)
class MosaicResult:
    """What :func:`mosaic_images` returns.

    Attributes:
        images: one (H, W, 4) uint8 mosaic per part (BGRA, or RGBA for ``rgb=True``; alpha 0 where no frame
            is), the largest part first; a flight that no estimate could join in one piece has several.
        homographies: per input image, in order: the (3, 3) ``mosaic_from_frame`` that maps its pixels (x, y,
            centres at integers) into its part's mosaic pixels, or None when it was not placed.
        parts: per input image, the index into ``images`` of its part, or None when it was not placed.
        summary: the run's summary (frames placed, pairs used, failed and rejected, ...).
        report: everything the sidecar JSON of ``udh mosaic`` holds (pairs, loop consistency, timings, warnings).
    """

    images: list[np.ndarray]
    homographies: list[np.ndarray | None]
    parts: list[int | None]
    summary: dict[str, Any]
    report: dict[str, Any]

    @property
    def image(self) -> np.ndarray:
        """The (largest) mosaic."""
        return self.images[0]


def mosaic_images(images: Sequence[np.ndarray], config=None, rgb: bool = False, **options: Any) -> MosaicResult:
    """Mosaic ``images`` (consecutive ones overlap, as the frames of a flight) and return the result as arrays.

    Args:
        images: two or more (H, W) grey or (H, W, 3) colour arrays, uint8 or uint16, BGR as OpenCV and
            :func:`udh_cli.images.read_image` give them (``rgb=True``: RGB, as PIL, imageio and matplotlib).
        config: a :class:`~udh_cli.mosaic.config.MosaicConfig`; None: the defaults.
        rgb: the arrays are RGB, and the mosaic comes back RGBA.
        **options: fields of ``MosaicConfig`` to change, e.g. ``method="sift"``, ``blend="feather"``.

    Raises :class:`UdhError` for unusable input (fewer than two images, an unknown option, an array that is not
    an image) and when no pair of images could be matched. Nothing is written outside a temporary folder,
    which is removed.
    """
    from udh_cli.mosaic.config import MosaicConfig
    from udh_cli.mosaic.run import run_mosaic

    config = config or MosaicConfig()
    unknown = sorted(set(options) - set(MosaicConfig.__dataclass_fields__))
    if unknown:
        raise UdhError(f"mosaic_images: unknown option(s) {', '.join(unknown)}; use fields of MosaicConfig")
    config = replace(config, **{"preview": False, **options})
    frames = [_checked(image, k, rgb) for k, image in enumerate(images)]
    if len(frames) < 2:
        raise UdhError(f"mosaic_images: give at least two images (got {len(frames)})")
    folder = Path(tempfile.mkdtemp(prefix="udh-mosaic-"))
    try:
        names = [f"frame_{k:06d}.png" for k in range(len(frames))]  # name order is the sequence order
        (folder / "frames").mkdir()
        for name, frame in zip(names, frames):
            if not cv2.imwrite(str(folder / "frames" / name), frame, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                raise UdhError(f"mosaic_images: the temporary folder {folder} could not be written (is the disk full?)")
        report = run_mosaic(folder / "frames", folder / "mosaic.png", replace(config, order="name"))
        return _result(report, folder, names, rgb)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _checked(image: Any, index: int, rgb: bool) -> np.ndarray:
    """An input array as the frame file to write (BGR), or a clear error naming its position."""
    array = np.asarray(image)
    if array.dtype not in (np.uint8, np.uint16) or not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] in (1, 3))):
        raise UdhError(f"mosaic_images: image {index} is {array.dtype} with shape {array.shape}; give (H, W) or (H, W, 3) uint8 or uint16")
    if min(array.shape[:2]) < 16:
        raise UdhError(f"mosaic_images: image {index} is {array.shape[1]}x{array.shape[0]} pixels; give at least 16x16")
    if array.ndim == 3 and array.shape[2] == 3 and rgb:
        return cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    return array


def _result(report: dict[str, Any], folder: Path, names: list[str], rgb: bool) -> MosaicResult:
    parts = sorted(report["parts"], key=lambda p: -len(p["frames"]))
    images, position = [], {}
    for k, part in enumerate(parts):
        image = cv2.imread(str(folder / part["file"]), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise UdhError(f"mosaic_images: the mosaic of part {part['part']} could not be read back")
        if image.ndim == 3 and image.shape[2] == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
        images.append(cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA) if rgb else image)
        position[part["part"]] = k
    by_name = {record["file"]: record for record in report["frames"]}
    homographies, part_of = [], []
    for name in names:
        record = by_name.get(name)
        placed = record is not None and record["mosaic_from_frame"] is not None
        homographies.append(np.array(record["mosaic_from_frame"]) if placed else None)
        part_of.append(position.get(record["part"]) if placed else None)
    for key in ("sidecar", "pair_cache", "source", "report_page"):
        report.pop(key, None)  # paths of the temporary folder, gone now
    return MosaicResult(images, homographies, part_of, report["summary"], report)
