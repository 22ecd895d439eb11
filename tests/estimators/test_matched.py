"""``--method matcher``: the learned matcher alone (udh_cli.estimators.matched)."""

from __future__ import annotations

import pytest

from conftest import BlockDescriptors, export_tiny_network, textured_image
from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator
from udh_cli.estimators.matching import MAX_MATCH_SIDE


@pytest.fixture(scope="module")
def matcher(tmp_path_factory):
    """The method with an untrained matcher file loaded, then its network swapped for the block descriptors."""
    path = export_tiny_network(tmp_path_factory.mktemp("matcher"), "matcher", seed=0)
    estimator = create_estimator("matcher", model=str(path), device="cpu")
    assert estimator.model_files() == [str(path)]
    estimator.network = BlockDescriptors()
    return estimator


def test_the_matcher_alone_finds_a_large_shift_and_verifies_it_by_its_matches(matcher):
    scene = textured_image(700, 500, seed=12)
    a, b = scene[100:356, 50:434], scene[164:420, 178:562]  # 384 x 256, A's content moved by (-128, -64)
    estimate = matcher.estimate(a, b)
    assert estimate.ok and estimate.verified and estimate.verified_by == "matches"
    assert estimate.inliers >= 150 and estimate.confidence > 0.5
    assert geometry.mace(estimate.homography, geometry.translation(-128, -64), 384, 256) < 1.0


def test_frames_that_share_nothing_are_a_failure_that_says_why(matcher):
    estimate = matcher.estimate(textured_image(384, 256, seed=1), textured_image(384, 256, seed=2))
    assert not estimate.ok and "cells agree" in estimate.failure


def test_bad_options_are_refused(tmp_path):
    path = export_tiny_network(tmp_path, "matcher", seed=0)
    for options, message in (({"headings": 3}, "headings"), ({"side": 10}, "side"), ({"escalate_side": 4096}, "escalate_side"), ({"min_inliers": 2}, "min_inliers")):
        with pytest.raises(UdhError, match=message):
            create_estimator("matcher", model=str(path), **options)
    with pytest.raises(UdhError, match="not a matcher"):
        create_estimator("matcher", model=str(export_tiny_network(tmp_path, "corr", seed=0)))


def test_a_model_file_rewritten_in_place_is_never_served_the_old_descriptors(tmp_path):
    """The descriptor cache outlives a network (a Dask worker, a notebook): it keys by the model's bytes."""
    import shutil

    from udh_cli.estimators import matching
    from udh_cli.estimators.pair import PreparedImage
    from udh_cli.onnx_model import OnnxMatcher

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first, second = export_tiny_network(tmp_path / "a", "matcher", seed=0), export_tiny_network(tmp_path / "b", "matcher", seed=1)
    image = textured_image(128, 96, seed=3).astype("float32") / 255
    path = tmp_path / "model.onnx"
    shutil.copy(first, path)
    old = OnnxMatcher.load(path, "cpu", 1)
    described_old = matching._described(old, PreparedImage.of(image), (128, 96), 0)
    shutil.copy(second, path)
    new = OnnxMatcher.load(path, "cpu", 1)
    assert new.identity != old.identity and OnnxMatcher.load(path, "cpu", 1).identity == new.identity
    described_new = matching._described(new, PreparedImage.of(image), (128, 96), 0)
    assert not (described_new == described_old).all()
    assert (described_new == new.describe(image)).all()


def test_near_its_prior_the_matcher_keeps_its_network_and_tries_b_as_it_lies(matcher):
    near = matcher.near_prior()
    assert (near.headings, near.escalate_side) == (1, None) and near.network is matcher.network
    assert (matcher.headings, matcher.escalate_side) == (4, MAX_MATCH_SIDE)  # the matcher itself is unchanged
