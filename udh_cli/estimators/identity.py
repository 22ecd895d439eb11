"""The identity "estimator": the baseline every benchmark row is compared against."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from udh_cli import geometry
from udh_cli.estimators.base import Estimator


@dataclass
class IdentityEstimator(Estimator):
    """Answers "no motion": the identity, rescaled when A and B differ in size."""

    name: ClassVar[str] = "identity"

    def _estimate(self, pair):
        size_a, size_b = pair.a.size, pair.b.size
        return geometry.rescale_homography(np.eye(3), size_a, size_a, size_a, size_b), 0.0, {}
