"""Another look at a pair: an estimator run on a mirrored, flipped or swapped copy, its answer mapped back.

A network's large mistakes depend on how the pair is shown to it, so the same network on a mirrored pair is
a second opinion with errors of its own. On the 12 held-out rho-45 pairs that no other candidate of ``auto``
solved, the cascade on a mirrored or swapped copy, refined by ECC, solved 2 with scores of 0.86-0.91.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.base import Estimate, Estimator
from udh_cli.estimators.pair import PreparedPair

VIEWS = ("mirrored", "flipped", "swapped")  # left-right, upside down, A and B exchanged


@dataclass
class ViewEstimator(Estimator):
    """``inner`` on a transformed copy of the pair; ``b_from_a`` of the images as given.

    Attributes:
        inner: any estimator.
        view: one of :data:`VIEWS`. "mirrored" and "flipped" transform both images alike (``cv2.flip``);
            "swapped" estimates B -> A and inverts it.
    """

    name: ClassVar[str] = "view"
    inner: Estimator
    view: str

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise UdhError(f"view '{self.view}': choose one of {', '.join(VIEWS)}")

    def near_prior(self) -> "ViewEstimator":
        return ViewEstimator(self.inner.near_prior(), self.view)

    def _estimate(self, pair: PreparedPair) -> tuple[np.ndarray, float, dict]:
        if self.view == "swapped":
            found = _answer(self.inner.estimate_pairs([pair.swapped()])[0])
            b_from_a = geometry.invert(found.homography)
        else:
            horizontal = self.view == "mirrored"
            found = _answer(self.inner.estimate_pairs([pair.flipped(1 if horizontal else 0)])[0])  # cv2.flip codes
            mirror_a = geometry.mirror_matrix(*pair.a.size, horizontal)
            mirror_b = geometry.mirror_matrix(*pair.b.size, horizontal)
            b_from_a = mirror_b @ found.homography @ mirror_a  # each mirror is its own inverse
        return b_from_a, found.confidence, {"view": self.view, **found.details, "inliers": found.inliers}


def _answer(found: Estimate) -> Estimate:
    """``found`` if it has a homography, else :class:`EstimationFailed` with its reason."""
    if not found.ok:
        raise EstimationFailed(found.failure or "no estimate")
    return found
