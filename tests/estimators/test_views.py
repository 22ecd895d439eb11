"""Another look at a pair: an estimator on a mirrored, flipped or swapped copy, its answer mapped back."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators import create_estimator
from udh_cli.estimators.base import Estimator
from udh_cli.estimators.views import VIEWS, ViewEstimator


@pytest.mark.parametrize("view", VIEWS)
def test_a_view_maps_its_answer_back_to_the_pair_as_given(view):
    """A and B of different widths and heights, so that a mirror of the wrong image or axis would show."""
    truth = geometry.homography_from_offsets(np.array([[8, -5], [-6, 4], [5, 7], [-4, -6]], float), 320, 240)
    a, b = warped_pair(truth, 320, 240, seed=7)
    b = b[:220, :300]  # B narrower and shorter than A (cropped at the right and bottom: the same pixel frame)
    estimate = ViewEstimator(create_estimator("sift"), view).estimate(a, b)
    assert estimate.ok and estimate.details["view"] == view and estimate.inliers >= 15
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.5


class Fails(Estimator):
    def _estimate(self, pair):
        raise EstimationFailed("made to fail")


def test_a_view_reports_the_inner_failure_and_checks_its_name():
    a, b = warped_pair(np.eye(3), 64, 48)
    failed = ViewEstimator(Fails(), "swapped").estimate(a, b)
    assert not failed.ok and failed.failure == "made to fail"
    with pytest.raises(UdhError, match="choose one of mirrored, flipped, swapped"):
        ViewEstimator(Fails(), "rotated")
