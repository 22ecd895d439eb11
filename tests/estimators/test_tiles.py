"""The tile stage: the refinement network on full-resolution tiles, fitted robustly, and the heading search."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.estimators import create_estimator
from udh_cli.estimators.tiles import TileRefinement, refine_with_tiles
from udh_cli.images import to_gray_float
from udh_cli.models_catalog import shipped_onnx
from udh_cli.onnx_model import OnnxHomographyModel

TRUE = np.array([[1.02, 0.03, 21.0], [-0.025, 0.99, -13.0], [1.5e-5, -1e-5, 1.0]])


@pytest.fixture(scope="module")
def refiner() -> OnnxHomographyModel:
    return OnnxHomographyModel.load(shipped_onnx("unsupervised-refine", None))


@pytest.fixture(scope="module")
def big_pair():
    return warped_pair(TRUE, width=1600, height=1200, seed=3, margin=80)


def _perturbed(h: np.ndarray, size: tuple[int, int], pixels: float, seed: int) -> np.ndarray:
    corners = geometry.image_corners(*size)
    moved = geometry.transform_points(h, corners) + np.random.default_rng(seed).uniform(-pixels, pixels, (4, 2))
    return geometry.homography_from_points(corners, moved)


@pytest.mark.parametrize("seed", [0, 1])
def test_tiles_recover_a_known_homography_at_full_resolution(refiner, big_pair, seed):
    a, b = big_pair
    start = _perturbed(TRUE, (1600, 1200), 12.0, seed)  # what a 128x128 network leaves at 1600 px
    before = float(geometry.mace(start, TRUE, 1600, 1200))
    result = refine_with_tiles(refiner, to_gray_float(a), to_gray_float(b), start)
    after = float(geometry.mace(result.b_from_a, TRUE, 1600, 1200))
    assert before > 5.0
    assert after < 1.0, (before, after)
    assert result.levels_used == result.levels_run == 2 and result.agreeing >= 0.75 and result.residual_px < 1.0
    assert result.confirms()


@pytest.mark.parametrize("seed", [7, 8, 9, 10, 11])
def test_a_start_beyond_the_tiles_reach_is_left_as_it_was(refiner, big_pair, seed):
    a, b = big_pair
    start = _perturbed(TRUE, (1600, 1200), 300.0, seed)
    result = refine_with_tiles(refiner, to_gray_float(a), to_gray_float(b), start, TileRefinement(max_move=16.0))
    assert result.levels_used == 0 and result.levels_run == 2 and np.isnan(result.residual_px) and not result.confirms()
    np.testing.assert_allclose(result.b_from_a, start / start[2, 2])


def test_an_answer_is_confirmed_by_two_levels_or_by_all_that_ran():
    from udh_cli.estimators.tiles import CONFIRMING_LEVELS, TileResult

    def result(used, run):
        return TileResult(np.eye(3), used, 0.5, 1.0, run)

    assert CONFIRMING_LEVELS == 2
    assert [result(used, 3).confirms() for used in range(4)] == [False, False, True, True]
    assert result(1, 1).confirms() and not result(0, 1).confirms()  # a pair with room for one level only


def test_flat_images_give_no_tiles(refiner):
    flat = np.full((600, 800), 0.5, np.float32)
    result = refine_with_tiles(refiner, flat, flat, np.eye(3))
    assert result.levels_used == 0


def test_the_heading_search_finds_a_half_turn_the_test_made(big_pair):
    a, b = big_pair
    turned = np.ascontiguousarray(b[::-1, ::-1])
    h, w = b.shape[:2]
    half_turn = np.array([[-1.0, 0, w - 1.0], [0, -1.0, h - 1.0], [0, 0, 1.0]])
    truth = half_turn @ TRUE
    searched = create_estimator("unsupervised").estimate(a, turned)
    # The matcher and the heading search try half turns too.
    plain = create_estimator("unsupervised", headings=1, matcher_model="", heading_search=0).estimate(a, turned)
    assert searched.ok and float(geometry.mace(searched.homography, truth, 1600, 1200)) < 2.0
    assert not plain.ok or float(geometry.mace(plain.homography, truth, 1600, 1200)) > 100.0
    assert searched.details["tile_levels"] >= 1
    # The heading search alone finds it when the cascade tries only B as given...
    turned_only = create_estimator("unsupervised", headings=1, matcher_model="").estimate(a, turned)
    assert turned_only.details["heading"] == 180.0 and float(geometry.mace(turned_only.homography, truth, 1600, 1200)) < 2.0
    # ...and so does the matcher.
    matched = create_estimator("unsupervised", headings=1, heading_search=0).estimate(a, turned)
    assert matched.ok and matched.details.get("matched") and float(geometry.mace(matched.homography, truth, 1600, 1200)) < 2.0


def test_the_paper_setting_runs_a_single_pass_without_tiles(big_pair):
    a, b = big_pair
    single = create_estimator("unsupervised", iterations=1, refine_rounds=0, headings=1, tiles=False).estimate(a, b)
    assert "tile_levels" not in single.details and single.details["iterations"] == 1
