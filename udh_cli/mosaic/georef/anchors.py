"""Anchors of the global solve: frame pixels whose position on the map is known (GPS fixes, ground-control marks)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class Anchors:
    """Points of frames whose map position is known: GPS fixes of frame centres, ground-control observations.

    Attributes:
        frames: (A,) the frame of each anchor.
        pixels: (A, 2) where it is in its frame, full-resolution pixels.
        positions: (A, 2) easting, northing in metres (one projected CRS, e.g. UTM).
        sigma_m: (A,) each position's standard error, metres: an anchor this far from the solution costs as
            much as a pair correspondence 1 px off.
    """

    frames: np.ndarray
    pixels: np.ndarray
    positions: np.ndarray
    sigma_m: np.ndarray

    @classmethod
    def frame_centres(cls, positions: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]], sigma_m: float) -> "Anchors":
        """GPS fixes: frame -> (2,) position of its centre, all with the same error."""
        frames = sorted(positions)
        pixels = np.array([[(sizes[i][0] - 1) / 2, (sizes[i][1] - 1) / 2] for i in frames]).reshape(-1, 2)
        return cls(np.array(frames, int), pixels, np.array([positions[i] for i in frames]).reshape(-1, 2), np.full(len(frames), float(sigma_m)))

    def __add__(self, other: "Anchors") -> "Anchors":
        return Anchors(*(np.concatenate([a, b]) for a, b in ((self.frames, other.frames), (self.pixels, other.pixels),
                                                             (self.positions, other.positions), (self.sigma_m, other.sigma_m))))
