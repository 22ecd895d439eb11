"""Seams of one part with OpenCV's seam finders (``cv2.detail``), found on the part drawn small (:mod:`.small`)
and drawn at full resolution while compositing (``--seams``): ``dp`` (dynamic programming on colour) and
``graphcut`` (graph cut on colour) route the seams where overlapping frames agree; ``central`` gives every
pixel to the frame that sees it nearest its centre, with no seam search.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.small import SmallPart

SEAM_FINDERS = ("dp", "graphcut", "central")  # the --seams choices


@dataclass
class Seams:
    """Where each frame of a part is shown: its seam mask on the small canvas (255 inside), placed at its
    corner there; ``scale`` is small-canvas pixels per canvas pixel."""

    masks: dict[int, np.ndarray]
    corners: dict[int, tuple[int, int]]
    scale: float

    def in_box(self, index: int, box: tuple[int, int, int, int]) -> np.ndarray:
        """Frame ``index``'s seam mask drawn over the canvas box ``(x0, y0, x1, y1)``: (h, w) bool, True inside."""
        x0, y0, x1, y1 = box
        cx, cy = self.corners[index]
        # canvas pixel (x, y) is small-canvas pixel (scale x, scale y), i.e. pixel (scale x - cx, scale y - cy) of the mask
        mask_from_box = np.array([[self.scale, 0.0, self.scale * x0 - cx], [0.0, self.scale, self.scale * y0 - cy]])
        drawn = cv2.warpAffine(self.masks[index], mask_from_box, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return drawn > 0


def find_seams(kind: str, small: SmallPart) -> Seams | None:
    """The seams of a part drawn small; None for ``central`` (or a single frame): compositing then gives every
    pixel to the frame that sees it nearest its centre."""
    if kind not in SEAM_FINDERS:
        raise UdhError(f"unknown seam finder '{kind}'; choose one of: {', '.join(SEAM_FINDERS)}")
    if kind == "central" or len(small.indices) < 2:
        return None
    finder = cv2.detail_DpSeamFinder("COLOR") if kind == "dp" else cv2.detail_GraphCutSeamFinder("COST_COLOR")
    images = [cv2.UMat(image.astype(np.float32)) for image in small.images]
    found = finder.find(images, small.corners, [cv2.UMat(mask) for mask in small.masks])
    masks = {i: (mask.get() if isinstance(mask, cv2.UMat) else np.asarray(mask)) for i, mask in zip(small.indices, found)}
    return Seams(masks, dict(zip(small.indices, small.corners)), small.scale)
