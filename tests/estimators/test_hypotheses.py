"""Starts beyond the networks' reach: the heading search (any in-plane turn) and the shift hypotheses' geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import textured_image
from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.hypotheses import heading_angles, heading_hypotheses, turn_matrix
from udh_cli.models_catalog import SHIPPED_MODELS, models_dir

WIDTH, HEIGHT = 400, 300


def turned_pair(degrees: float, seed: int = 21, scene: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A: the central 400 x 300 window of an 800 x 600 scene (test-made unless given); B: that window turned by
    ``degrees`` counter-clockwise about its centre and shifted, so that B sees only the scene at any angle. And b_from_a."""
    scene = textured_image(800, 600, seed=seed) if scene is None else cv2.resize(scene, (800, 600), interpolation=cv2.INTER_AREA)
    x0, y0 = 200, 150
    turn = np.vstack([cv2.getRotationMatrix2D(((WIDTH - 1) / 2, (HEIGHT - 1) / 2), degrees, 1.0), [0, 0, 1]])
    b_from_a = geometry.translation(9.0, -6.0) @ turn
    b = cv2.warpPerspective(scene, b_from_a @ geometry.translation(-x0, -y0), (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR)
    return scene[y0 : y0 + HEIGHT, x0 : x0 + WIDTH].copy(), b, b_from_a


def test_heading_angles_cover_the_circle_without_the_turns_already_tried():
    assert heading_angles(12, (0.0, 180.0)) == [30.0 * k for k in range(1, 12) if k != 6]
    assert heading_angles(8) == [45.0 * k for k in range(8)]


def test_a_turned_view_maps_its_answer_back_to_the_unturned_images():
    """The view's exact answer (B turned by 70 degrees against A) maps back to the pair's own b_from_a."""
    side = 64
    small_b = np.random.default_rng(0).random((1, side, side)).astype(np.float32)
    views = heading_hypotheses(small_b.copy(), small_b, [70.0])
    truth_in_view = turn_matrix(70.0, side)  # A is B here: the view's B is A turned by 70 degrees
    np.testing.assert_allclose(views.whole(0, truth_in_view), np.eye(3), atol=1e-9)
    # The turn is counter-clockwise on screen: the right-hand edge's midpoint goes up.
    moved = geometry.transform_points(turn_matrix(90.0, side), np.array([[side - 1.0, (side - 1) / 2]]))
    np.testing.assert_allclose(moved, [[(side - 1) / 2, 0.0]], atol=1e-9)


@pytest.fixture(scope="module")
def shipped():
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    # Neither the matcher (its quarter turns would rescue some angles) nor the shift search: the heading search alone.
    return (create_estimator("unsupervised", device="cpu", matcher_model="", search=0),
            create_estimator("unsupervised", device="cpu", matcher_model="", search=0, heading_search=0))


@pytest.mark.parametrize("degrees, beyond_reach", [(37.0, False), (90.0, True), (143.0, False), (260.0, True)])
def test_a_pair_turned_by_any_angle_is_answered_within_a_few_pixels(shipped, degrees, beyond_reach):
    """37 degrees from B as given and 143 from its half turn are within the cascade's and the tiles' reach; a
    quarter turn or 260 degrees is not: there the heading search answers, where without it the network is lost."""
    with_search, without = shipped
    a, b, truth = turned_pair(degrees)
    found = with_search.estimate(a, b)
    error = float(geometry.mace(found.homography, truth, WIDTH, HEIGHT))
    assert found.ok and error < 3.0 and found.verified, (error, found.details)
    if beyond_reach:
        # The turn given to B's copy undoes B's turn: the nearest of the 12 to -degrees (as the match's heading).
        assert abs((found.details["heading"] + degrees + 180) % 360 - 180) <= 15
        before = without.estimate(a, b)
        assert not before.ok or float(geometry.mace(before.homography, truth, WIDTH, HEIGHT)) > 10.0
        assert not before.verified


@pytest.mark.parametrize("degrees", [115.0, 290.0])
def test_a_turned_frame_of_the_example_flight_is_answered_within_a_few_pixels(shipped, degrees):
    from pathlib import Path

    from udh_cli.images import read_image

    frame = read_image(Path(__file__).resolve().parents[2] / "examples" / "sim_flight" / "frame_003.jpg")
    a, b, truth = turned_pair(degrees, scene=frame)
    found = shipped[0].estimate(a, b)
    error = float(geometry.mace(found.homography, truth, WIDTH, HEIGHT))
    assert found.ok and error < 3.0 and found.verified, (error, found.details)


def test_an_unturned_confident_pair_skips_the_heading_search(shipped):
    with_search, _ = shipped
    a, b, truth = turned_pair(0.0)
    found = with_search.estimate(a, b)
    assert float(geometry.mace(found.homography, truth, WIDTH, HEIGHT)) < 2.0 and found.verified
    assert "headings" not in found.details["stage_ms"] and "heading" not in found.details


def test_heading_search_takes_a_sensible_count(shipped):
    from udh_cli.errors import UdhError

    with pytest.raises(UdhError, match="heading_search"):
        create_estimator("unsupervised", device="cpu", heading_search=2)


def test_the_coarse_networks_share_the_refinement_rounds_and_answer_as_their_own_cascades_do(shipped, monkeypatch):
    """Every coarse network's answers go through the refinement rounds together: one call a round, and each
    candidate is the answer of that network's own whole cascade."""
    from udh_cli.estimators.hypotheses import cascade_headings
    from udh_cli.onnx_model import OnnxHomographyModel

    estimator = shipped[1]
    assert len(estimator.networks.first) == 2 and estimator.headings == 2 and estimator.refine_rounds >= 1
    a, b, _ = turned_pair(12.0, seed=4)
    small_a, small_b = (cv2.resize(image, (128, 128), interpolation=cv2.INTER_AREA)[None] / np.float32(255) for image in (a, b))
    calls = []
    predict = OnnxHomographyModel.predict_offsets
    monkeypatch.setattr(OnnxHomographyModel, "predict_offsets", lambda self, *args: calls.append(self) or predict(self, *args))
    found, scores = cascade_headings(estimator, small_a, small_b)
    assert len(calls) == len(estimator.networks.first) * estimator.iterations + estimator.refine_rounds
    monkeypatch.undo()
    later = estimator.rounds()[estimator.iterations:]
    own = [estimator.predict_small(small_a, small_b, [coarse] * estimator.iterations + later) for coarse in estimator.networks.first]
    own_scores = [estimator.score(small_a[0], small_b[0], h[0]) for h in own]
    assert scores[0] >= max(own_scores) - 1e-6  # the half turn may do better still, never worse
    if scores[0] == max(own_scores):
        np.testing.assert_allclose(found[0], own[int(np.argmax(own_scores))][0], atol=1e-6)
