"""One test over every registered estimator: the Estimate contract (timm's one test per registered model)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.estimators import Estimate, create_estimator, estimator_names

TRUE = np.array([[1.0, 0.01, 6.0], [-0.01, 1.0, -4.0], [0.0, 0.0, 1.0]])
# How close each method must land on a small, textured, well-overlapping pair (px of mean corner error).
ACCURACY = {"identity": 20.0, "supervised": 6.0, "unsupervised": 3.0, "orb": 2.0}


@pytest.fixture(scope="module")
def pair():
    return warped_pair(TRUE, width=320, height=240, seed=11)


@pytest.mark.parametrize("name", estimator_names())
def test_the_estimate_contract(name, pair):
    a, b = pair
    found = create_estimator(name).estimate(a, b)
    assert isinstance(found, Estimate) and found.method == name and found.ok and found.failure is None
    assert found.homography.shape == (3, 3) and found.homography.dtype == np.float64 and found.homography[2, 2] == 1.0
    assert 0.0 <= found.confidence <= 1.0 and 0.0 < found.elapsed_ms < 60_000
    # Direction: b_from_a, pixels of the images given.
    assert float(geometry.mace(found.homography, TRUE, 320, 240)) < ACCURACY.get(name, 1.0)
    assert found.verified in (None, True, False) and (found.verified_by is None or found.verified)
    found.to_json()  # JSON-ready


@pytest.mark.parametrize("name", estimator_names())
def test_a_failure_is_reported_not_raised(name):
    flat = np.full((240, 320), 128, np.uint8)
    found = create_estimator(name).estimate(flat, flat)
    if found.ok:  # a method may answer a flat pair (the identity is as good as any), but never confidently
        assert found.confidence < 0.5 or name == "identity" and found.confidence == 0.0
    else:
        assert found.homography is None and found.confidence == 0.0 and found.failure
        assert found.verified in (None, False)
