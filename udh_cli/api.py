"""High-level library calls, one per ``udh`` command, usable without the CLI."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import DEFAULT_METHOD, Estimate, create_estimator, require_ok
from udh_cli.homography_files import read_homography
from udh_cli.images import IMAGE_SUFFIXES, check_output_path, read_image, write_image


def estimate_files(path_a: str | Path, path_b: str | Path, method: str = DEFAULT_METHOD, **options: Any) -> Estimate:
    """Read two image files and estimate ``b_from_a`` in their full-resolution pixels.

    ``options`` go to the estimator (e.g. ``best_features=50`` for sift). Raises :class:`UdhError` for
    bad files or an unknown method, and when the method finds no homography.
    """
    estimator = create_estimator(method, **options)  # an unknown method fails before any file is read
    return require_ok(estimator.estimate(read_image(path_a), read_image(path_b)))


def estimate_report(
    path_a: str | Path,
    path_b: str | Path,
    method: str = DEFAULT_METHOD,
    *,
    gt: str | Path | None = None,
    viz: str | Path | None = None,
    **options: Any,
) -> dict[str, Any]:
    """What ``udh estimate`` does: estimate ``b_from_a`` for two image files and report on it.

    Every input is checked before the estimation starts (method, ``gt`` file, ``viz`` path), each image
    is read once, and the picture is written only after a successful estimate, so a failure leaves no file.

    Args:
        path_a, path_b: image files; any size, colour or grey, 8 or 16 bit.
        method: a registered estimator name; ``options`` go to it.
        gt: optional ground-truth homography file (``x_B ~ H x_A``), see :func:`read_homography`.
        viz: optional picture to write (.png, .jpg...): A's border warped onto B, and the truth.

    Returns:
        :meth:`Estimate.to_json` (keys ``method``, ``homography``, ``confidence``, ``elapsed_ms``...) plus
        ``image_a``, ``image_b``, ``size_a`` and ``size_b`` ([width, height] px), ``offsets_4pt``
        ((4, 2) px, where A's corners move in B, corner order TL, TR, BR, BL); with ``gt`` also
        ``corner_error_px`` (MACE) and ``corner_rmse_px``; with ``viz`` also ``viz``.

    Raises:
        UdhError: for bad input, and when the method finds no homography.
    """
    estimator = create_estimator(method, **options)
    truth = read_homography(gt) if gt is not None else None
    if viz is not None:
        check_output_path(viz, IMAGE_SUFFIXES)
        if any(Path(viz).resolve() == Path(p).resolve() for p in (path_a, path_b)):
            raise UdhError(f"{viz}: is one of the input images; write the picture to another file")
    image_a, image_b = read_image(path_a), read_image(path_b)
    result = require_ok(estimator.estimate(image_a, image_b))

    width, height = image_a.shape[1], image_a.shape[0]
    report = result.to_json()
    report["image_a"], report["image_b"] = str(path_a), str(path_b)
    report["size_a"], report["size_b"] = [width, height], [image_b.shape[1], image_b.shape[0]]
    report["offsets_4pt"] = geometry.offsets_from_homography(result.homography, width, height).tolist()
    if truth is not None:
        report["corner_error_px"] = float(geometry.mace(result.homography, truth, width, height))
        report["corner_rmse_px"] = float(geometry.corner_rmse(result.homography, truth, width, height))
    if viz is not None:
        from udh_cli.viz import draw_estimate

        write_image(viz, draw_estimate(image_a, image_b, result.homography, truth, label=result.method))
        report["viz"] = str(viz)
    return report
