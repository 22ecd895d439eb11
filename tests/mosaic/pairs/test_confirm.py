"""Loop-closure pairs confirmed from the chain's prediction, and sent to the whole cascade when it is wrong."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from udh_cli import geometry
from udh_cli.estimators import Estimator
from udh_cli.mosaic.pairs.confirm import CONFIRM_MIN_SCORE, PREDICTION_CHECK
from udh_cli.mosaic.pairs.types import Acceptance
from udh_cli.mosaic.pairs.workers import judge_opinions

from conftest import warped_pair

W, H = 320, 240


class Truth(Estimator):
    """Answers the homography it is given, and counts the pairs it was asked about."""

    name: ClassVar[str] = "truth"

    def __init__(self, b_from_a: np.ndarray) -> None:
        self.b_from_a, self.asked = b_from_a, 0

    def _estimate(self, pair):
        self.asked += 1
        return self.b_from_a, 0.9, {}


def residual(dx: float, dy: float, angle_deg: float = 0.0) -> np.ndarray:
    """What the prediction left of the motion: a small rotation about the centre and a shift, pixels."""
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    rotation = geometry.translation(W / 2, H / 2) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ geometry.translation(-W / 2, -H / 2)
    return geometry.translation(dx, dy) @ rotation


def test_a_prediction_a_few_pixels_off_is_confirmed_and_refined_without_the_cascade():
    truth = residual(2.5, -1.5, 0.4)  # the chain within a few pixels: what is left after the pre-warp
    image_a, image_b = warped_pair(truth, W, H, seed=11)
    cascade = Truth(np.eye(3))
    [[(estimate, verified, doubt)]] = judge_opinions([cascade], Acceptance(), [(image_a, image_b)], [True])
    assert doubt is None and cascade.asked == 0
    assert (estimate.method, estimate.stage, estimate.verified, estimate.verified_by) == ("chain+ecc", "prediction", True, "alignment")
    assert estimate.confidence >= CONFIRM_MIN_SCORE and verified >= Acceptance().min_verified
    assert geometry.mace(np.eye(3), truth, W, H) > 2.0  # the prediction itself was off
    assert geometry.mace(estimate.homography, truth, W, H) < 0.2  # ECC from the prediction brought it within a fifth of a pixel


def test_a_wrong_prediction_falls_back_to_the_whole_cascade():
    truth = residual(30.0, 22.0, 3.0)  # the chain put B far from where it is: further than a confirmation may move it
    image_a, image_b = warped_pair(truth, W, H, seed=12)
    cascade = Truth(truth)
    [attempts] = judge_opinions([cascade], Acceptance(), [(image_a, image_b)], [True])
    assert cascade.asked == 1 and len(attempts) == 2
    (cheap, _, cheap_doubt), (answer, _, doubt) = attempts
    assert cheap.method == "chain+ecc" and not cheap.ok and cheap_doubt is not None  # never a cheap answer in the map
    assert answer.method == "truth" and doubt is None
    np.testing.assert_allclose(answer.homography, truth, atol=1e-9)


def test_unrelated_images_are_never_confirmed():
    image_a, _ = warped_pair(np.eye(3), W, H, seed=13)
    _, image_b = warped_pair(np.eye(3), W, H, seed=14)
    estimate = PREDICTION_CHECK.estimate(image_a, image_b)
    assert not estimate.ok and "chained prediction aligns too little" in estimate.failure  # no ECC spent on it


def test_only_the_marked_pairs_start_from_the_prediction():
    truth = residual(1.0, 1.0)
    pair = warped_pair(truth, W, H, seed=15)
    cascade = Truth(truth)
    out = judge_opinions([cascade], Acceptance(), [pair, pair, pair], [False, True, False])
    assert [attempts[-1][0].method for attempts in out] == ["truth", "chain+ecc", "truth"] and cascade.asked == 2
    assert [attempts[-1][0].method for attempts in judge_opinions([cascade], Acceptance(), [pair])] == ["truth"]


class Searching(Truth):
    """A :class:`Truth` whose :meth:`near_prior` twin is another instance, as the network's is without its searches."""

    def __init__(self, b_from_a: np.ndarray) -> None:
        super().__init__(b_from_a)
        self.near = Truth(b_from_a)

    def near_prior(self):
        return self.near


def test_a_prewarped_pair_the_prediction_left_doubted_asks_the_opinions_without_their_searches():
    truth = residual(30.0, 22.0, 3.0)  # too far for the confirmation: the cascade decides
    far = warped_pair(truth, W, H, seed=16)
    method = Searching(truth)
    out = judge_opinions([method], Acceptance(), [far, far, far], [True, False, True])
    assert (method.asked, method.near.asked) == (1, 2)  # the unmarked pair alone asks the searching opinion
    assert [attempts[-1][0].method for attempts in out] == ["truth"] * 3
    assert [len(attempts) for attempts in out] == [2, 1, 2]  # the marked pairs tried the prediction first
