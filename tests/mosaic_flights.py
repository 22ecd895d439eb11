"""Helpers for the mosaic tests: small simulated flights and an estimator that fails on chosen pairs."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np

from conftest import cached_copy
from udh_cli.errors import EstimationFailed
from udh_cli.estimators import Estimator, create_estimator
from udh_cli.estimators.pair import PreparedImage
from udh_cli.images import read_image
from udh_cli.mosaic.inputs.frames import work_copy
from udh_cli.simulate import FlightConfig, write_flight

SMALL = FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=4, focal_px=300.0)  # 8 frames, fast
ACCURATE = FlightConfig(frame_size=(480, 360), strips=2, frames_per_strip=5, focal_px=450.0)  # 10 frames, SIFT-friendly


def make_flight(folder: Path, config: FlightConfig = SMALL, seed: int = 3) -> list[Path]:
    """Write a simulated flight into ``folder``; returns its frame paths in order.

    Each ``(config, seed)`` is simulated once per run and copied; like the simulator, it refuses a used folder.
    """
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        write_flight(folder, config, seed)  # raises the simulator's own error
    cached_copy(folder, ("flight", config, seed), lambda built: write_flight(built, config, seed))
    return sorted(folder.glob("frame_*.jpg"))


def distort(image: np.ndarray, lens) -> np.ndarray:
    """What ``lens`` (a :class:`~udh_cli.mosaic.inputs.lens.Lens`) makes of a pinhole image: distorted pixel d shows the
    pinhole pixel its undistortion gives."""
    import cv2

    height, width = image.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(width), np.arange(height)), -1).reshape(-1, 2).astype(np.float64)
    source = lens.undistort_points(grid, (width, height)).reshape(height, width, 2).astype(np.float32)
    return cv2.remap(image, source[..., 0], source[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def fingerprint(image) -> str:
    """The same text for an image array and for that image prepared (its grey pixels)."""
    return hashlib.sha1(np.ascontiguousarray(PreparedImage.of(image).grey).tobytes()).hexdigest()


def work_fingerprints(paths: list[Path], work_size: int = 800) -> list[str]:
    """Fingerprints of the working copies the pipeline hands to estimators, frame by frame."""
    return [fingerprint(work_copy(read_image(p), work_size)) for p in paths]


class FailOn(Estimator):
    """Wraps a real estimator and fails every pair for which ``should_fail(index_a, index_b)`` is true.

    Frames are recognised by the fingerprints of their working copies; a pre-warped image (loop closure)
    matches no frame and gets index ``None``.
    """

    name: ClassVar[str] = "failing"

    def __init__(self, fingerprints: list[str], should_fail: Callable[[int | None, int | None], bool], inner: str = "sift") -> None:
        self.index = {f: i for i, f in enumerate(fingerprints)}
        self.should_fail = should_fail
        self.inner = create_estimator(inner)
        self.calls: list[tuple[int | None, int | None]] = []

    def _estimate(self, pair):
        image_a, image_b = pair.a, pair.b
        a, b = self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))
        self.calls.append((a, b))
        if self.should_fail(a, b):
            raise EstimationFailed("made to fail by the test")
        return self.inner._estimate(pair)

    def estimate_pairs(self, pairs):
        self.batches = getattr(self, "batches", []) + [len(pairs)]
        return super().estimate_pairs(pairs)
