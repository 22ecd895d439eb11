"""High-level library calls, one per ``udh`` command, usable without the CLI."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from udh_cli.estimators import Estimate, create_estimator, require_ok
from udh_cli.images import read_image


def estimate_files(path_a: str | Path, path_b: str | Path, method: str = "sift", **options: Any) -> Estimate:
    """Read two image files and estimate ``b_from_a`` in their full-resolution pixels.

    ``options`` go to the estimator (e.g. ``best_features=50`` for sift). Raises :class:`UdhError` for
    bad files or an unknown method, and when the method finds no homography.
    """
    image_a, image_b = read_image(path_a), read_image(path_b)
    estimator = create_estimator(method, **options)
    return require_ok(estimator.estimate(image_a, image_b))
