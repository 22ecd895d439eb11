"""The one judge: "verified" needs independent evidence to agree, and each check alone catches a wrong answer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import udh_cli.estimators.deep as deep
from conftest import textured_image, warped_pair
from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.judge import THRESHOLDS, Evidence, disagreement, judge, round_trip_error
from udh_cli.estimators.tiles import TileResult
from udh_cli.models_catalog import SHIPPED_MODELS, models_dir

RIGHT = Evidence(alignment=0.9, round_trip=0.005, tiles_confirm=True, match_inliers=300, match_disagreement=0.002)


def test_an_answer_all_evidence_agrees_on_is_verified():
    verdict = judge(RIGHT, 0.8)
    assert verdict.verified and verdict.failed == () and verdict.verified_by == "matches" and verdict.confidence >= 0.8
    alone = judge(Evidence(alignment=0.9, round_trip=0.005), 0.8)
    assert alone.verified and alone.verified_by == "alignment" and alone.confidence == 0.8


@pytest.mark.parametrize("change, check", [
    ({"alignment": 0.0}, "alignment"),
    ({"round_trip": 0.2}, "round trip"),
    ({"tiles_confirm": False, "match_inliers": None, "match_disagreement": None}, "tiles"),
    ({"match_inliers": 60, "match_disagreement": 0.1}, "match agrees"),
])
def test_each_check_alone_fails_the_verdict(change, check):
    fields = {**RIGHT.__dict__, **change}
    verdict = judge(Evidence(**fields), 0.8)
    assert not verdict.verified and verdict.verified_by is None and verdict.failed == (check,)
    assert verdict.confidence == pytest.approx(0.8 * THRESHOLDS.unverified_confidence)


def test_one_piece_of_evidence_is_not_enough():
    """The photometric score alone (no round trip could be measured, no tiles, no match) does not verify."""
    assert not judge(Evidence(alignment=0.99), 0.9).verified


def test_a_weak_match_is_no_opinion_and_a_confident_one_lowers_the_alignment_floor():
    weak = Evidence(alignment=0.9, round_trip=0.005, match_inliers=THRESHOLDS.match_evidence_inliers - 1, match_disagreement=0.5)
    assert judge(weak, 0.8).verified  # as many cells as frames of different flights reach: says nothing
    matched = Evidence(alignment=0.2, round_trip=0.005, match_inliers=400, match_disagreement=0.0, is_match=True)
    assert judge(matched, 0.5).verified_by == "matches"  # surf and trees lower right answers' alignment
    assert not judge(Evidence(alignment=0.0, round_trip=0.005, match_inliers=400, is_match=True), 0.5).verified


def test_round_trip_and_disagreement_are_shares_of_the_side():
    shift = geometry.translation(4.0, 0.0)
    assert round_trip_error(shift, np.eye(3), 128) == pytest.approx(4.0 / 128)
    assert round_trip_error(shift, np.linalg.inv(shift), 128) == pytest.approx(0.0, abs=1e-12)
    assert disagreement(shift, np.eye(3), (400, 300)) == pytest.approx(4.0 / 400)
    assert round_trip_error(np.full((3, 3), np.nan), np.eye(3), 128) == float("inf")


@pytest.fixture(scope="module")
def network():
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    return create_estimator("unsupervised", device="cpu", search=0, heading_search=0, matcher_model="")


def test_a_right_answer_passes_and_a_wrong_one_the_tiles_confirmed_is_caught(network, monkeypatch):
    """Tile levels that wrongly confirm an answer 60 px off (a monkeypatched tile stage) no longer verify it: the
    photometric check, measured on the images, catches it (the round trip, 24 px of 128, is left to gross errors)."""
    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=5)
    right = network.estimate(a, b)
    assert right.verified and geometry.mace(right.homography, truth, 320, 240) < 2.0
    assert right.details["round_trip"] <= THRESHOLDS.max_round_trip and right.details["alignment"] >= THRESHOLDS.min_alignment
    moved = geometry.translation(60.0, 0.0) @ truth
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, *args, **kwargs: [TileResult(moved, 2, 1.0, 0.5, 2)] * len(pairs))
    wrong = network.estimate(a, b)
    assert geometry.mace(wrong.homography, moved, 320, 240) < 1e-6 and wrong.details["tile_levels"] == 2
    assert not wrong.verified and wrong.details["verdict_failed"] == ["alignment"] and wrong.details["alignment"] < 0.1
    assert wrong.confidence < right.confidence


def test_a_network_that_always_answers_the_same_shift_fails_the_round_trip(network, monkeypatch):
    """A network output monkeypatched to 'B is A moved 20 px right' (the right answer, as it happens) is caught
    by the round trip: run from B to A, from the answer's inverse, it still moves 20 px, where a right answer
    leaves the network nothing to move."""
    truth = geometry.translation(20.0 * 320 / 128, 0.0)  # 20 px of the 128-px input
    a, b = warped_pair(truth, seed=6, margin=60)
    untiled = create_estimator("unsupervised", device="cpu", search=0, heading_search=0, matcher_model="", tiles=False,
                               iterations=1, refine_rounds=0, flight_model="")
    offsets = np.tile([[20.0, 0.0]], (4, 1))
    monkeypatch.setattr(untiled.network, "predict_offsets", lambda patches, batch_size=64: np.repeat(offsets[None], len(patches), 0))
    found = untiled.estimate(a, b)
    assert geometry.mace(found.homography, truth, 320, 240) < 1e-6  # forward, it happens to be right
    assert not found.verified and found.details["verdict_failed"] == ["round trip"]
    assert found.details["round_trip"] == pytest.approx(20.0 / 128, abs=1e-4)


@pytest.mark.parametrize("kind", ["no overlap", "textureless", "upside down"])
def test_pairs_without_a_right_answer_get_no_verified_answer(kind):
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    a = textured_image(480, 360, seed=31)
    if kind == "no overlap":
        b = textured_image(480, 360, seed=32)
    elif kind == "textureless":
        rng = np.random.default_rng(0)
        a = np.full((360, 480), 120, np.uint8) + rng.integers(0, 2, (360, 480), dtype=np.uint8)
        b = np.full((360, 480), 121, np.uint8) + rng.integers(0, 2, (360, 480), dtype=np.uint8)
    else:
        b = cv2.flip(a, 0)  # a mirror image: no homography that keeps the picture's handedness maps A onto it
    found = create_estimator("unsupervised", device="cpu").estimate(a, b)
    assert not found.verified, found.details
    assert found.confidence < 0.5


def test_an_unjudged_network_leaves_the_verdict_to_its_caller(network):
    """auto's start runs unjudged: its Cascade judges the answer after ECC, and the verdict's work is not done twice."""
    a, b = warped_pair(geometry.translation(6.0, -4.0), seed=5)
    unjudged = create_estimator("unsupervised", device="cpu", search=0, matcher_model="", judged=False).estimate(a, b)
    assert unjudged.ok and unjudged.verified is None and "verdict" not in unjudged.details["stage_ms"]
    assert "verdict_failed" not in unjudged.details and unjudged.confidence > 0.5
    from udh_cli.estimators.refined import AutoOptions

    assert AutoOptions().build().start.judged is False
