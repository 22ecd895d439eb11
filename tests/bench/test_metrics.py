"""Benchmark figures against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.bench import metrics

P = 128  # patch side
CORNERS = geometry.image_corners(P, P)


def test_bucket_means_split_the_sorted_pairs_30_30_40():
    errors = np.array([10, 9, 8, 7, 6, 5, 4, 3, 2, 1], dtype=float)  # unsorted on purpose
    assert metrics.bucket_means(errors) == pytest.approx([2.0, 5.0, 8.5])  # (1,2,3), (4,5,6), (7,8,9,10)


def test_bucket_means_of_too_few_pairs_are_nan_not_an_error():
    lo, mid, hi = metrics.bucket_means(np.array([4.0]))
    assert math.isnan(lo) and mid == 4.0 and math.isnan(hi)


def test_pair_errors_translation_one_corner_and_no_answer():
    truth = np.eye(3)
    one_corner = geometry.homography_from_points(CORNERS, CORNERS + [[0, 0], [0, 0], [0, 0], [3, 4]])
    estimates = [geometry.translation(3, 4), one_corner, None]
    truths = np.stack([truth, truth, geometry.translation(6, 8)])
    mace, rmse, answered = metrics.pair_errors(estimates, truths, [(P, P)] * 3, [np.eye(3)] * 3)
    # A 3-4-5 shift moves every corner by 5; one corner off by 5 gives mean 5/4 and RMSE sqrt(25/4);
    # no answer is scored as the identity, 10 px from a (6, 8) shift.
    assert mace == pytest.approx([5.0, 1.25, 10.0])
    assert rmse == pytest.approx([5.0, 2.5, 10.0])
    assert answered.tolist() == [True, True, False]


def test_failures_are_no_answer_or_over_10_px():
    mace = np.array([1.0, 10.0, 10.5, 3.0, np.inf])
    answered = np.array([True, True, True, False, True])
    assert metrics.failures(mace, answered).tolist() == [False, False, True, True, True]


def test_summarize_by_hand():
    mace = np.array([1.0, 2.0, 3.0, 4.0, 100.0])
    rmse = mace * 1.5
    answered = np.array([True, True, True, True, False])
    summary = metrics.summarize(mace, rmse, answered, np.array([5.0, 1.0, 2.0, 4.0, 3.0]))
    assert summary.pairs == 5
    assert summary.mace_mean == pytest.approx(22.0)
    assert summary.mace_median == pytest.approx(3.0)
    assert summary.rmse_mean == pytest.approx(33.0)
    # 5 pairs: buckets hold sorted indices [0, 2), [2, 3), [3, 5).
    assert (summary.bucket_0_30, summary.bucket_30_60, summary.bucket_60_100) == pytest.approx((1.5, 3.0, 52.0))
    assert summary.mace_p95 == pytest.approx(4.0 + 0.8 * 96.0)  # linear interpolation at rank 3.8
    assert summary.failure_rate == pytest.approx(0.2)
    assert summary.no_answer_rate == pytest.approx(0.2)
    assert summary.time_median_ms == 3.0 and summary.time_mean_ms == 3.0


def test_percentile_profile_is_sorted_with_centred_percentiles():
    percent, ordered = metrics.percentile_profile(np.array([3.0, 1.0, 2.0, 4.0]))
    assert percent.tolist() == [12.5, 37.5, 62.5, 87.5]
    assert ordered.tolist() == [1.0, 2.0, 3.0, 4.0]
