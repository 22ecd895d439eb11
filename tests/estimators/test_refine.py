"""The ECC pyramid's clean-texture rule: the finest level at ``clean_side`` where the coarser level already
correlates well, at ``work_side`` elsewhere."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.estimators.ecc import HAS_MASKED_ECC, EccEstimator
from udh_cli.estimators.refine import PyramidEcc

WIDTH, HEIGHT = 800, 600  # larger than work_side, as the mosaic's frames are


@pytest.fixture
def ecc_widths(monkeypatch) -> list[int]:
    """The width (pixels) of every image ECC aligns, in order: the pyramid's levels, then the robust pass."""
    widths: list[int] = []
    refine = EccEstimator.refine

    def spy(self, gray_a, gray_b, b_from_a, mask_b=None):
        widths.append(gray_a.shape[1])
        return refine(self, gray_a, gray_b, b_from_a, mask_b)

    monkeypatch.setattr(EccEstimator, "refine", spy)
    return widths


def pair_and_start(seed: int, noise: float = 0.0):
    """A test-made 800 x 600 pair, its true ``b_from_a`` and a start 10 px off at most; ``noise``: the standard
    deviation (grey levels) of the noise added to B, which lowers every level's correlation as surf does."""
    rng = np.random.default_rng(seed)
    truth = geometry.homography_from_offsets(rng.uniform(-20, 20, (4, 2)), WIDTH, HEIGHT)
    image_a, image_b = warped_pair(truth, WIDTH, HEIGHT, seed=seed, margin=60)
    if noise:
        image_b = np.clip(image_b + rng.normal(0.0, noise, image_b.shape), 0, 255).astype(np.uint8)
    corners = geometry.image_corners(WIDTH, HEIGHT)
    start = geometry.homography_from_points(corners, geometry.transform_points(truth, corners) + rng.uniform(-10, 10, (4, 2)))
    return image_a, image_b, truth, start


@pytest.mark.parametrize("seed", range(2))
def test_a_clean_pair_aligns_its_finest_level_at_the_clean_side(seed, ecc_widths):
    image_a, image_b, truth, start = pair_and_start(seed)
    clean, _ = PyramidEcc().refine(image_a, image_b, start)
    assert ecc_widths == [120, 240, 400] + [400] * HAS_MASKED_ECC  # the coarse levels of work_side 480, then 400 px and the robust pass
    full, _ = PyramidEcc(clean_side=None).refine(image_a, image_b, start)
    assert ecc_widths[3 + HAS_MASKED_ECC:] == [120, 240, 480] + [480] * HAS_MASKED_ECC
    assert geometry.mace(start, truth, WIDTH, HEIGHT) > 3.0
    assert geometry.mace(clean, truth, WIDTH, HEIGHT) < 0.05  # px of the 800-px images
    assert float(geometry.corner_errors(clean, full, WIDTH, HEIGHT).max()) < 0.05


@pytest.mark.parametrize("seed", range(2))
def test_a_pair_that_correlates_poorly_keeps_the_work_side(seed, ecc_widths):
    image_a, image_b, _, start = pair_and_start(seed, noise=60.0)
    kept, _ = PyramidEcc().refine(image_a, image_b, start)
    assert ecc_widths == [120, 240, 480] + [480] * HAS_MASKED_ECC
    np.testing.assert_array_equal(kept, PyramidEcc(clean_side=None).refine(image_a, image_b, start)[0])


def test_images_no_larger_than_the_clean_side_align_as_before(ecc_widths):
    image_a, image_b, _, start = pair_and_start(0)
    small_a, small_b = image_a[:240, :320], image_b[:240, :320]  # the same motion: both crops start at (0, 0)
    np.testing.assert_array_equal(PyramidEcc().refine(small_a, small_b, start)[0],
                                  PyramidEcc(clean_side=None).refine(small_a, small_b, start)[0])
    assert ecc_widths[:3 + HAS_MASKED_ECC] == [80, 160, 320] + [320] * HAS_MASKED_ECC


def test_the_clean_side_is_checked():
    with pytest.raises(ValueError, match="clean_side"):
        PyramidEcc(clean_side=0)
