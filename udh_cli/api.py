"""High-level library calls, one per ``udh`` command, usable without the CLI."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.estimators.registry import DEFAULT_METHOD, create_estimator

# Longest side (pixels) at which `udh estimate` works unless asked for full resolution: the precision of a
# 1600 px frame, and SIFT, ECC and the networks in bounded time and memory on a 48 MP photo.
ESTIMATE_WORK_SIZE = 1600
# Memory the full cascade can take per pixel of the two images at full resolution (its copies, pyramids and
# SIFT's scale space at once); docs/estimators.md gives the measurement.
FULL_RESOLUTION_BYTES_PER_PIXEL = 100
def _work_copy(image, work_size: int | None):
    """``image`` shrunk so that its longer side is at most ``work_size`` (None: as it is)."""
    import cv2

    longest = max(image.shape[:2])
    if work_size is None or longest <= work_size:
        return image
    scale = work_size / longest
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _check_truth_fits(truth, gt: str | Path, width: int, height: int) -> None:
    """Refuse a ground truth that sends some of A's corners through the horizon (to infinity, or to the far side):
    no corner error can be measured against it (it came out as 1.3e6 px), so it is not a truth for this image."""
    import numpy as np

    from udh_cli import geometry

    corners = np.column_stack([geometry.image_corners(width, height), np.ones(4)])
    w = corners @ np.asarray(truth, dtype=np.float64)[2]
    if not (np.all(w > 0) or np.all(w < 0)) or np.min(np.abs(w)) < 1e-9 * np.max(np.abs(w)):
        raise UdhError(f"{gt}: this ground truth sends corners of the {width}x{height} image A through the horizon (to infinity); "
                       f"it does not fit this image: check the file, and that A and B are given in its order")


def estimate_report(
    path_a: str | Path,
    path_b: str | Path,
    method: str = DEFAULT_METHOD,
    *,
    gt: str | Path | None = None,
    viz: str | Path | None = None,
    work_size: int | None = ESTIMATE_WORK_SIZE,
    overwrite: bool = False,
    **options: Any,
) -> dict[str, Any]:
    """What ``udh estimate`` does: estimate ``b_from_a`` for two image files and report on it.

    Every input is checked before the estimation starts (method, ``gt`` file, ``viz`` path), each image
    is read once, and the picture is written only after a successful estimate, so a failure leaves no file.

    Args:
        path_a, path_b: image files; any size, colour or grey, 8 or 16 bit.
        method: a registered estimator name; ``options`` go to it.
        gt: optional ground-truth homography file (``x_B ~ H x_A``), see :func:`read_homography`.
        viz: optional picture to write (.png, .jpg...): A's border warped onto B, and the truth. An existing file
            is replaced only when udh wrote it, or with ``overwrite`` (:func:`udh_cli.files.check_replaceable`).
        work_size: the images are estimated with their longer side shrunk to this many pixels (None: full
            resolution), and the answer is rescaled exactly to the full-resolution pixels.

    Returns:
        :meth:`Estimate.to_json` (keys ``method``, ``homography``, ``confidence``, ``elapsed_ms``...) plus
        ``image_a``, ``image_b``, ``size_a`` and ``size_b`` ([width, height] px), ``offsets_4pt``
        ((4, 2) px, where A's corners move in B, corner order TL, TR, BR, BL); with ``gt`` also
        ``corner_error_px`` (MACE) and ``corner_rmse_px``; with ``viz`` also ``viz``; ``verified``
        (:func:`is_verified`) and ``work_size_a`` / ``work_size_b`` (the sizes estimated at); ``notes``, when the
        model files lack metadata (:meth:`~udh_cli.estimators.base.Estimator.model_notes`).

    Raises:
        UdhError: for bad input, and when the method finds no homography.
    """
    # Imported here, not above: the command line reads this module's defaults when it starts, before NumPy is needed.
    from udh_cli import geometry
    from udh_cli.estimators.base import is_verified, require_ok
    from udh_cli.files import check_replaceable, write_output
    from udh_cli.homography_files import read_homography
    from udh_cli.images import IMAGE_SUFFIXES, check_output_path, encode_image, read_image

    estimator = create_estimator(method, **options)
    truth = read_homography(gt, "--gt") if gt is not None else None
    if viz is not None:
        check_output_path(viz, IMAGE_SUFFIXES)
        if any(Path(viz).resolve() == Path(p).resolve() for p in (path_a, path_b)):
            raise UdhError(f"{viz}: is one of the input images; write the picture to another file")
        check_replaceable(viz, overwrite)
    if work_size is not None and work_size < 32:
        raise UdhError(f"--work-size {work_size}: give at least 32 pixels")
    image_a, image_b = read_image(path_a), read_image(path_b)
    if work_size is None:
        from udh_cli.budget import check_memory

        sizes = [f"{image.shape[1]}x{image.shape[0]}" for image in (image_a, image_b)]
        check_memory(FULL_RESOLUTION_BYTES_PER_PIXEL * (image_a.shape[0] * image_a.shape[1] + image_b.shape[0] * image_b.shape[1]),
                     f"--full-resolution on {sizes[0]} and {sizes[1]} images", "leave out --full-resolution (the answer is in "
                     "full-resolution pixels all the same; --work-size sets the working size)")
    if truth is not None:
        _check_truth_fits(truth, gt, image_a.shape[1], image_a.shape[0])
    work_a, work_b = _work_copy(image_a, work_size), _work_copy(image_b, work_size)
    found = require_ok(estimator.estimate(work_a, work_b))
    size_a, size_b = (image_a.shape[1], image_a.shape[0]), (image_b.shape[1], image_b.shape[0])
    small_a, small_b = (work_a.shape[1], work_a.shape[0]), (work_b.shape[1], work_b.shape[0])
    result = dataclasses.replace(found, homography=geometry.rescale_homography(found.homography, small_a, size_a, small_b, size_b))
    # As the mosaic judges it: an answer its method does not verify (ECC, a network without its judge) must also align.
    from udh_cli.mosaic.pairs.types import Acceptance

    verified = is_verified(result) and Acceptance().judge(found, work_a, work_b, estimator.verifies_itself)[1] is None

    width, height = image_a.shape[1], image_a.shape[0]
    report = result.to_json()
    report["verified"] = verified
    if notes := estimator.model_notes():
        report["notes"] = notes
    report["work_size_a"], report["work_size_b"] = list(small_a), list(small_b)
    report["image_a"], report["image_b"] = str(path_a), str(path_b)
    report["size_a"], report["size_b"] = [width, height], [image_b.shape[1], image_b.shape[0]]
    report["offsets_4pt"] = geometry.offsets_from_homography(result.homography, width, height).tolist()
    if truth is not None:
        report["corner_error_px"] = float(geometry.mace(result.homography, truth, width, height))
        report["corner_rmse_px"] = float(geometry.corner_rmse(result.homography, truth, width, height))
    if viz is not None:
        from udh_cli.viz import draw_estimate

        label = result.method if verified else f"{result.method}: UNVERIFIED, may be wrong"
        write_output(viz, encode_image(viz, draw_estimate(image_a, image_b, result.homography, truth, label=label)), overwrite)
        report["viz"] = str(viz)
    return report
