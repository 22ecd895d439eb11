"""The one judge: "verified" needs independent evidence to agree, and each check alone catches a wrong answer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import udh_cli.estimators.deep as deep
import udh_cli.estimators.matching as matching
from conftest import textured_image, warped_pair
from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.base import MIN_CONFIDENCE
from udh_cli.estimators.judge import THRESHOLDS, Evidence, disagreement, judge, judge_matched, round_trip_error
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.matching import MatchResult
from udh_cli.estimators.tiles import TileResult
from udh_cli.models_catalog import SHIPPED_MODELS, models_dir

RIGHT = Evidence(alignment=0.9, round_trip=0.005, tiles_confirm=True, match_inliers=300, match_disagreement=0.002)


def test_an_answer_all_evidence_agrees_on_is_verified():
    verdict = judge(RIGHT, 0.8)
    assert verdict.verified and verdict.failed == () and verdict.verified_by == "matches" and verdict.confidence >= 0.8
    alone = judge(Evidence(alignment=0.9, round_trip=0.005), 0.8)
    assert alone.verified and alone.verified_by == "alignment" and alone.confidence == pytest.approx(0.5 + 0.5 * 0.8)


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
    supported = judge(matched, 0.5)  # surf and trees lower right answers' alignment: supported, not verified
    assert not supported.verified and supported.verified_by == "matches" and supported.failed == ("fine alignment",)
    nothing = judge(Evidence(alignment=0.0, round_trip=0.005, match_inliers=400, is_match=True), 0.5)
    assert not nothing.verified and nothing.verified_by is None


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


@pytest.mark.parametrize("evidence, failed, by", [
    # A global match 10-20 px off at A's corners: hundreds of cells agree, the photometry does not.
    (Evidence(alignment=0.45, round_trip=0.01, match_inliers=900, is_match=True), ("fine alignment",), "matches"),
    # One that aligns where the cells are, yet no tile level up to full resolution accepts it.
    (Evidence(alignment=0.7, round_trip=0.01, match_inliers=900, is_match=True, match_tile_levels=0), ("match tiles",), "matches"),
    # A tile-confirmed cascade answer a few px off on repetitive texture.
    (Evidence(alignment=0.45, round_trip=0.01, tiles_confirm=True), ("fine alignment",), "alignment"),
])
def test_each_stricter_check_leaves_a_near_miss_supported_but_unverified(evidence, failed, by):
    verdict = judge(evidence, 0.9)
    assert not verdict.verified and verdict.failed == failed and verdict.verified_by == by
    passed = judge(Evidence(**{**evidence.__dict__, "alignment": THRESHOLDS.min_alignment, "match_tile_levels": 1}), 0.9)
    assert passed.verified and passed.verified_by == by


def test_either_tier_keeps_an_answer_on_its_side_of_the_mosaic_floor_and_supported_ranks_below_verified():
    high = Evidence(alignment=0.45, round_trip=0.01, tiles_confirm=True)
    assert judge(high, 0.9).confidence == pytest.approx(MIN_CONFIDENCE + (0.9 - MIN_CONFIDENCE) * THRESHOLDS.unverified_confidence)
    assert judge(high, 0.9).confidence < judge(Evidence(**{**high.__dict__, "alignment": 0.6}), 0.9).confidence == pytest.approx(0.95)
    assert judge(high, 0.15).confidence == pytest.approx(0.075)  # below the floor it stays below
    assert judge(Evidence(**{**high.__dict__, "alignment": 0.6}), 0.15).confidence == 0.15  # verified or not
    match = Evidence(alignment=0.45, round_trip=0.01, match_inliers=450, is_match=True)
    assert judge(match, 0.1).confidence == pytest.approx(MIN_CONFIDENCE + (0.75 - MIN_CONFIDENCE) * THRESHOLDS.unverified_confidence)


def test_a_tile_confirmed_answer_3_px_off_is_supported_not_verified_and_the_mosaic_still_checks_it(network, monkeypatch):
    """The tile stage monkeypatched to confirm an answer 3 px off (of 320): the old verdict verified it (alignment
    0.38 over the 0.3 floor); now it is returned unverified, supported by its alignment, and the mosaic, which
    cross-checks every pair in its joint solve, applies its own photometric check instead of rejecting it."""
    from udh_cli.mosaic.pairs.types import Acceptance

    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=5)
    near = geometry.translation(3.0, 0.0) @ truth
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, *args, **kwargs: [TileResult(near, 2, 1.0, 0.5, 2)] * len(pairs))
    found = network.estimate(a, b)
    assert THRESHOLDS.min_alignment_supported <= found.details["alignment"] < THRESHOLDS.min_alignment
    assert not found.verified and found.verified_by == "alignment" and found.details["verdict_failed"] == ["fine alignment"]
    score, doubt = Acceptance().judge(found, a, b)
    assert doubt is None and score == pytest.approx(found.details["alignment"], abs=1e-3)


def test_a_confident_global_match_no_tile_level_accepts_is_not_verified(monkeypatch):
    """A global match of 900 cells (monkeypatched) 1 px off where B's tiles, run on it as evidence, accept no level
    (monkeypatched tile stage): supported by its matches, so a mosaic takes it, but not verified."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    estimator = create_estimator("unsupervised", device="cpu", search=0, heading_search=0)
    if estimator.networks.matcher is None:
        pytest.skip("no shipped matcher network")
    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=5)
    answer = geometry.translation(1.0, 0.0) @ truth
    monkeypatch.setattr(matching, "global_match", lambda *args, **kwargs: MatchResult(answer, 900, 1000, 0))
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, starts, *args, **kwargs:
                        [TileResult(np.asarray(h), 0, 0.0, float("nan"), 2) for h in starts])
    found = estimator.estimate(a, b)
    assert found.stage == "match" and geometry.mace(found.homography, answer, 320, 240) < 1e-6
    assert found.details["alignment"] >= THRESHOLDS.min_alignment and found.details["match_tile_levels"] == 0
    assert not found.verified and found.verified_by == "matches" and found.details["verdict_failed"] == ["match tiles"]


def matched_pair(seed: int = 5):
    """A 640 x 480 pair with room for tiles, and its true ``b_from_a``."""
    truth = geometry.homography_from_offsets(np.random.default_rng(seed).uniform(-20, 20, (4, 2)), 640, 480)
    a, b = warped_pair(truth, 640, 480, seed=seed, margin=60)
    return PreparedPair.of(a, b), truth


def test_an_answer_the_matches_verify_stays_verified_only_where_the_tiles_accept_it(network):
    """auto's SIFT answers: the right one keeps "verified" (three tile levels accept it); one 60 px off, scored as
    well as wrong SIFT answers scored on the hard benchmark's parallax pairs (0.5), is caught by the tiles, which
    accept no level, and returned supported by its matches."""
    pair, truth = matched_pair()
    measured, right = judge_matched(network, pair, truth, alignment=0.5, confidence=0.9)
    assert right.verified and right.verified_by == "matches" and right.failed == () and measured["match_tile_levels"] == 3
    wrong_answer = geometry.translation(60.0, 10.0) @ truth
    measured, wrong = judge_matched(network, pair, wrong_answer, alignment=0.5, confidence=0.9)
    assert not wrong.verified and wrong.verified_by == "matches" and wrong.failed == ("tiles",)
    assert measured["match_tile_levels"] == 0 and wrong.confidence == 0.9  # the verdict changes, not the confidence


def test_an_answer_the_matches_verify_that_aligns_nothing_is_not_verified_and_the_tiles_do_not_run(network, monkeypatch):
    pair, truth = matched_pair()
    monkeypatch.setattr("udh_cli.estimators.judge.refine_pairs_with_tiles", lambda *args, **kwargs: pytest.fail("tiles ran"))
    measured, verdict = judge_matched(network, pair, truth, alignment=THRESHOLDS.min_alignment_matched / 2, confidence=0.9)
    assert not verdict.verified and verdict.failed == ("aligns",) and measured["match_tile_levels"] is None
    measured, verdict = judge_matched(None, pair, truth, alignment=0.5, confidence=0.9)  # no network: no tile check
    assert verdict.verified and measured["match_tile_levels"] is None


def test_the_tiles_do_not_judge_a_pair_with_no_room_for_them_nor_catch_an_answer_they_can_pull_to_the_plane(network):
    """128 x 128 (the paper's patches): B has no room for tiles, so their silence says nothing and the answer stays
    verified. On a planar scene the tiles pull an answer 20 px off (of 640) back to the plane and accept their levels:
    they catch answers no plane near them explains (parallax, far off), not every error."""
    truth = geometry.translation(4.0, -3.0)
    small = PreparedPair.of(*warped_pair(truth, 128, 128, seed=5, margin=20))
    measured, verdict = judge_matched(network, small, geometry.translation(30.0, 0.0) @ truth, alignment=0.5, confidence=0.9)
    assert verdict.verified and measured["match_tile_levels"] is None
    pair, truth = matched_pair()
    measured, verdict = judge_matched(network, pair, geometry.translation(20.0, 0.0) @ truth, alignment=0.5, confidence=0.9)
    assert verdict.verified and measured["match_tile_levels"] == 3
