"""Batches of pairs: cut evenly for the workers, and an estimate that does not depend on its batch."""

import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.mosaic.pairs.estimate import even_batch_size


@pytest.mark.parametrize("count, largest, window, expected", [
    (40, 16, 4, 5),     # copr's consecutive pairs on 2 workers: 8 batches, 4 a worker
    (6, 16, 4, 1),      # a later loop round: one pair a batch, both workers busy
    (100, 16, 4, 13),
    (1000, 16, 4, 16),  # never above the largest
    (40, 16, 1, 16),    # one process: the largest batches
    (0, 16, 4, 1),
])
def test_batches_are_cut_two_per_slot_of_the_window(count, largest, window, expected):
    size = even_batch_size(count, largest, window)
    assert size == expected
    if count:
        batches = -(-count // size)
        assert batches >= min(count, 2 * window) or size == largest


def test_the_learned_estimate_of_a_pair_does_not_depend_on_its_batch():
    """Cutting batches by the number of workers must not change a mosaic: the shipped network's answers for six
    pairs in one batch, in batches of two and one by one are the same to the last bit (one onnxruntime thread, as
    the mosaic's workers run; in one process with more threads the sums may be taken in another order)."""
    estimator = create_estimator("unsupervised", threads=1)
    motions = [geometry.translation(3.0 * k - 7, 2.0 - k) for k in range(6)]
    pairs = [warped_pair(motion, seed=k) for k, motion in enumerate(motions)]
    whole = estimator.estimate_many(pairs)
    twos = [e for k in range(0, 6, 2) for e in estimator.estimate_many(pairs[k:k + 2])]
    ones = [estimator.estimate(*pair) for pair in pairs]
    for other in (twos, ones):
        assert [np.array_equal(a.homography, b.homography) for a, b in zip(whole, other)] == [True] * 6
        assert [(a.verified, a.stage) for a in whole] == [(b.verified, b.stage) for b in other]
    assert max(float(geometry.mace(e.homography, motion, 320, 240)) for e, motion in zip(whole, motions)) < 2.0
