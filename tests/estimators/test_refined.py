"""Photometric refinement, verification scores, and the auto method's fallback."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import pytest

from conftest import warped_pair
from udh_cli import geometry
from udh_cli.errors import EstimationFailed
from udh_cli.estimators import create_estimator
from udh_cli.estimators.base import Estimator
from udh_cli.estimators.pair import PreparedImage
from udh_cli.estimators.refined import (FALLBACK_OPTIONS, NEAR_PX, AutoOptions, Cascade, Opinion, Policy,
                                       UnsupervisedEccOptions)
from udh_cli.estimators.views import VIEWS, ViewEstimator
from udh_cli.estimators.verify import VERIFIER
from udh_cli.models_catalog import SHIPPED_MODELS, models_dir
from udh_cli.estimators.refine import PyramidEcc


def known_pair(seed: int, spread: float = 10.0):
    rng = np.random.default_rng(seed)
    truth = geometry.homography_from_offsets(rng.uniform(-spread, spread, (4, 2)), 320, 240)
    a, b = warped_pair(truth, 320, 240, seed=seed)
    return a, b, truth


@pytest.mark.parametrize("seed", range(4))
def test_refinement_improves_a_perturbed_estimate(seed):
    a, b, truth = known_pair(seed)
    rng = np.random.default_rng(100 + seed)
    start = geometry.homography_from_points(geometry.image_corners(320, 240),
                                            geometry.transform_points(truth, geometry.image_corners(320, 240)) + rng.uniform(-6, 6, (4, 2)))
    refined, correlation = PyramidEcc().refine(a, b, start)
    assert geometry.mace(start, truth, 320, 240) > 2.0
    assert geometry.mace(refined, truth, 320, 240) < 0.3
    assert correlation > 0.9


def test_an_unblurred_finest_level_keeps_the_optimum_under_strong_perspective():
    """Blurring before warping is not warping before blurring, so a blurred ECC settles off the truth when
    the perspective is strong; started at the truth, the default (no blur at the finest level) stays closer."""
    blurred, default = [], []
    for seed in range(4):
        offsets = np.array([[40, 30], [-40, 20], [-30, -30], [30, -20]], float) * np.random.default_rng(seed).uniform(0.6, 1.0)
        truth = geometry.homography_from_offsets(offsets, 320, 240)
        a, b = warped_pair(truth, 320, 240, seed=seed)
        # Without local contrast normalisation, which biases the optimum in the same way (see below).
        blurred.append(geometry.mace(PyramidEcc(blur=(3, 3, 3), contrast_sigma=0).refine(a, b, truth)[0], truth, 320, 240))
        default.append(geometry.mace(PyramidEcc(contrast_sigma=0).refine(a, b, truth)[0], truth, 320, 240))
    assert PyramidEcc().blur[-1] == 1
    assert np.mean(default) < 0.8 * np.mean(blurred)
    assert max(default) < 0.05  # px


def shaded(image: np.ndarray) -> np.ndarray:
    """``image`` under uneven light: a lit spot top right (1.35x) fading to a dark side (0.35x)."""
    ys, xs = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    light = 0.35 + np.exp(-((xs - 250) ** 2 + (ys - 60) ** 2) / (2 * 90.0**2))
    return np.clip(image.astype(np.float32) * light, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", range(3))
def test_local_contrast_keeps_refinement_precise_under_uneven_light(seed):
    """One gain and bias cannot model light that varies across the image; normalising each level's local
    contrast first can (graf1/graf3: 1.93 -> 0.66 px, models/README.md)."""
    a, b, truth = known_pair(seed)
    rng = np.random.default_rng(100 + seed)
    corners = geometry.image_corners(320, 240)
    start = geometry.homography_from_points(corners, geometry.transform_points(truth, corners) + rng.uniform(-6, 6, (4, 2)))
    plain = geometry.mace(PyramidEcc(contrast_sigma=0).refine(a, shaded(b), start)[0], truth, 320, 240)
    normalised = geometry.mace(PyramidEcc().refine(a, shaded(b), start)[0], truth, 320, 240)
    assert PyramidEcc().contrast_sigma > 0  # on by default
    assert plain > 0.4  # px: the shading pulls plain ECC off
    assert normalised < 0.15 and normalised < plain / 3


def with_blobs(image: np.ndarray, seed: int) -> np.ndarray:
    """``image`` with three textured ellipses pasted on it (occluders: content the other image does not have)."""
    out, rng = image.copy(), np.random.default_rng(seed)
    for _ in range(3):
        mask = np.zeros(image.shape, np.uint8)
        centre, axes = tuple(int(v) for v in rng.integers(40, 280, 2)), tuple(int(v) for v in rng.integers(25, 45, 2))
        cv2.ellipse(mask, centre, axes, 0, 0, 360, 1, -1)
        texture = cv2.GaussianBlur(rng.random(image.shape).astype(np.float32), (0, 0), 2)
        out = np.where(mask > 0, (np.clip(texture * 2 - 0.5, 0, 1) * 255).astype(np.uint8), out)
    return out


@pytest.mark.parametrize("seed", range(3))
def test_the_robust_pass_ignores_occluders(seed):
    """After the pyramid, ECC runs again on the pixels whose residual is small: occluders stop pulling."""
    from udh_cli.estimators.ecc import HAS_MASKED_ECC

    if not HAS_MASKED_ECC:
        pytest.skip("this OpenCV has no findTransformECCWithMask")
    a, b, truth = known_pair(seed)
    b = with_blobs(b, seed + 10)
    corners = geometry.image_corners(320, 240)
    rng = np.random.default_rng(seed)
    start = geometry.homography_from_points(corners, geometry.transform_points(truth, corners) + rng.uniform(-4, 4, (4, 2)))
    plain = geometry.mace(PyramidEcc(robust_k=0).refine(a, b, start)[0], truth, 320, 240)
    robust = geometry.mace(PyramidEcc().refine(a, b, start)[0], truth, 320, 240)
    assert PyramidEcc().robust_k > 0  # on by default
    assert plain > 0.08 and robust < 0.05 and robust < plain / 2  # px


def test_local_contrast_normalisation_and_its_strong_perspective_bias():
    """Normalising, like blurring, before warping is not the same as after: from the truth under strong
    perspective the optimum moves, but by under 0.15 px at 320 x 240."""
    offsets = np.array([[40, 30], [-40, 20], [-30, -30], [30, -20]], float)
    truth = geometry.homography_from_offsets(offsets, 320, 240)
    a, b = warped_pair(truth, 320, 240, seed=0)
    assert geometry.mace(PyramidEcc().refine(a, b, truth)[0], truth, 320, 240) < 0.15


def test_pyramid_settings_are_checked():
    with pytest.raises(ValueError, match="robust_iterations"):
        PyramidEcc(robust_iterations=0)
    with pytest.raises(ValueError, match="contrast_sigma"):
        PyramidEcc(contrast_sigma=-1)
    with pytest.raises(ValueError, match="3 levels need"):
        PyramidEcc(blur=(3, 1))
    with pytest.raises(ValueError, match="odd and positive"):
        PyramidEcc(blur=(3, 2, 1))


def test_verification_score_separates_right_from_wrong():
    right, wrong, right_structure, wrong_structure = [], [], [], []
    for seed in range(8):
        a, b, truth = known_pair(seed)
        off = geometry.homography_from_offsets(np.random.default_rng(seed).uniform(-25, 25, (4, 2)), 320, 240) @ truth
        right.append(VERIFIER.score(a, b, truth, structure=False))
        wrong.append(VERIFIER.score(a, b, off, structure=False))
        right_structure.append(VERIFIER.score(a, b, truth))
        wrong_structure.append(VERIFIER.score(a, b, off))
    assert min(right) > 0.9 and max(wrong) < 0.7
    # auto doubts answers by the structure score: the right ones stay clear above its threshold.
    min_score = Policy.min_score
    assert min(right_structure) > min_score + 0.1 and max(wrong_structure) < min_score - 0.2
    assert VERIFIER.score(a, b, None) == 0.0


@dataclass
class AlwaysFails(Estimator):
    name: ClassVar[str] = "always-fails"

    def _estimate(self, pair):
        raise EstimationFailed("made to fail")


def cascade(start, fallback="sift", escalated=None, views=None, refiner=None, name="auto") -> Cascade:
    """auto's composition around a given start: the fallback (SIFT with its role options by default), an
    escalated opinion, and views (of the identity by default, which cannot help)."""
    if fallback == "sift":
        fallback = create_estimator("sift", **FALLBACK_OPTIONS["sift"])
    opinions = [Opinion("fallback", fallback, fallback.name)] if fallback is not None else []
    if escalated is not None:
        opinions.append(Opinion("escalated", escalated, "escalated"))
    if views is None:
        views = [ViewEstimator(create_estimator("identity"), view) for view in VIEWS]
    opinions += [Opinion(view.view, view, view.view) for view in views]
    return Cascade(name, start, refiner or PyramidEcc(), tuple(opinions), Policy())


def test_auto_falls_back_when_the_first_estimate_fails():
    a, b, truth = known_pair(3)
    auto = cascade(AlwaysFails())
    estimate = auto.estimate(a, b)
    assert estimate.ok and estimate.stage == "sift"
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3


def test_auto_keeps_a_verified_answer_and_refined_alone_does_not_fall_back():
    a, b, truth = known_pair(5, spread=3.0)
    auto = cascade(create_estimator("identity"))  # identity + ECC converges for a 3 px motion
    estimate = auto.estimate(a, b)
    assert "fallback" not in estimate.details
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3
    plain = cascade(AlwaysFails(), fallback=None, views=(), name="unsupervised+ecc")
    failed = plain.estimate(a, b)
    assert not failed.ok and failed.confidence == 0.0


def test_auto_starts_from_the_network_without_its_tile_stage_and_ecc_reaches_the_same_answer():
    """ECC refines to full resolution anyway: the tile stage before it only cost time (docs/estimators.md)."""
    a, b, truth = known_pair(7, spread=20.0)
    plain, tiled = create_estimator("auto"), create_estimator("auto", tiles=True)
    assert plain.start.tiles is False and tiled.start.tiles is True
    found, found_tiled = plain.estimate(a, b), tiled.estimate(a, b)
    assert found.stage == found_tiled.stage == "network"
    assert "tile_levels" not in plain.start.estimate(a, b).details and "tile_levels" in tiled.start.estimate(a, b).details
    assert geometry.mace(found.homography, truth, 320, 240) < 0.2
    assert geometry.mace(found.homography, found_tiled.homography, 320, 240) < 0.05


def test_textureless_images_give_a_clear_failure_not_an_answer():
    flat = np.full((240, 320), 128, np.uint8)
    estimate = cascade(create_estimator("identity")).estimate(flat, flat)
    assert not estimate.ok and estimate.confidence == 0.0
    assert "no answer aligns the images" in estimate.failure


def test_gradient_ncc_is_not_fooled_by_a_smooth_scene_under_a_wrong_shift():
    """A smooth gradient with faint texture: a wrong shift keeps the intensity NCC high, not the gradient NCC."""
    from udh_cli.estimators.verify import alignment_ncc

    rng = np.random.default_rng(3)
    ys, xs = np.mgrid[0:240, 0:320].astype(np.float32)
    texture = cv2.GaussianBlur(rng.random((240, 320)).astype(np.float32), (0, 0), 1.5)
    scene = 0.6 * xs / 320 + 0.3 * ys / 240 + 0.15 * texture
    right, wrong = np.eye(3), geometry.translation(12, 9)
    assert alignment_ncc(scene, scene, right, on="gradient") > 0.99
    assert alignment_ncc(scene, scene, wrong) > 0.9  # the shading alone correlates
    assert alignment_ncc(scene, scene, wrong, on="gradient") < 0.3
    with pytest.raises(ValueError, match="intensity"):
        alignment_ncc(scene, scene, right, on="colour")


class Answers(Estimator):
    """Answers a fixed homography."""

    name: ClassVar[str] = "fixed"

    def __init__(self, homography):
        self.homography = homography

    def _estimate(self, pair):
        return self.homography, 1.0, {}


def test_a_doubtful_answer_asks_the_fallback_first_and_escalates_only_if_that_is_doubted_too():
    a, b, truth = known_pair(4)
    wrong = Answers(geometry.translation(60.0, -40.0) @ truth)  # far off: ECC cannot save it
    # SIFT settles the pair: the longer cascade is not run.
    auto = cascade(wrong, escalated=Answers(truth))
    estimate = auto.estimate(a, b)
    assert estimate.stage == "sift" and "escalated" not in estimate.details
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3
    # SIFT fails as well: the longer cascade gets its turn and wins.
    estimate = cascade(wrong, fallback=AlwaysFails(), escalated=Answers(truth)).estimate(a, b)
    assert estimate.details["fallback"]["score"] == 0.0 and estimate.stage == "escalated"
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3
    # auto's network gets the second run with its default rounds, sharing the loaded networks.
    assert AutoOptions.escalate and not UnsupervisedEccOptions.escalate  # on for auto only
    if (models_dir() / "udh-unsupervised-refine.onnx").is_file():
        learned = AutoOptions().build()
        escalated = {o.key: o.estimator for o in learned.opinions}["escalated"]
        assert [rounds for _, rounds in learned.start.stages] == [1, 1]
        assert [rounds for _, rounds in escalated.stages] == [2, 2] and escalated.network is learned.start.network
        assert [o.key for o in learned.opinions] == ["fallback", "escalated", *VIEWS]
        assert AutoOptions(network={"threads": 1}).build().start.threads == 1  # passed on to the network
        already_full = AutoOptions(network={"iterations": 2, "refine_rounds": 2}).build()
        assert "escalated" not in [o.key for o in already_full.opinions]  # rerunning it would repeat its answer


@dataclass
class DivergingRefiner(PyramidEcc):
    """An ECC pyramid that always diverges."""

    def refine(self, image_a, image_b, b_from_a):
        raise EstimationFailed("ECC moved a corner 50 px from its start: it diverged")


def test_an_answer_ecc_diverges_from_gets_a_second_opinion_even_when_it_scores_well():
    """A wrong network answer on a smooth pair can score above min_score; ECC diverging from it is the
    better warning. The fallback then runs, and its answer is kept only if it verifies better."""
    a, b, truth = known_pair(6)
    nearly = geometry.translation(0.6, -0.4) @ truth  # scores above min_score, yet 0.7 px off
    auto = cascade(Answers(nearly), refiner=DivergingRefiner())
    estimate = auto.estimate(a, b)
    assert estimate.details["score"] >= auto.policy.min_score and "refine_failure" in estimate.details
    assert estimate.details["fallback"]["method"] == "sift" and estimate.stage == "sift"
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.5
    converging = cascade(Answers(nearly))  # the same answer, refined normally: no second opinion
    assert "fallback" not in converging.estimate(a, b).details


def test_a_right_answer_with_little_overlap_still_verifies():
    """Consecutive drone frames can share under a fifth of the view (two right copr pairs: 17 %); the
    score must judge them on that overlap instead of refusing them, and still reject a wrong shift there."""
    from conftest import textured_image

    ground = textured_image(700, 240, seed=5)
    a, b = ground[:, :320], ground[:, 260:580]  # B starts 260 px right of A: 60 of 320 columns shared (19 %)
    truth = geometry.translation(-260.0, 0.0)  # x_B = x_A - 260
    assert VERIFIER.score(a, b, truth) > 0.9
    assert VERIFIER.score(a, b, geometry.translation(-245.0, 6.0)) < 0.5
    assert VERIFIER.score(a, b, geometry.translation(-300.0, 0.0)) == 0.0  # 6 % overlap: no judgement


def test_verification_is_not_fooled_by_an_occluder_but_still_rejects_a_wrong_answer():
    """A textured blob over a fifth of B (a car, a bird, a cloud) ruins the whole-overlap correlation of the
    right answer; the median over tiles ignores it, and a wrong answer stays low."""
    from udh_cli.estimators.verify import alignment_ncc

    a, b, truth = known_pair(3)
    occluded = b.copy()
    noise = cv2.GaussianBlur(np.random.default_rng(0).random(b.shape).astype(np.float32), (0, 0), 1.0)
    occluded[60:160, 40:190] = (noise[60:160, 40:190] * 255).astype(b.dtype)  # 20 % of the image
    gray_a, gray_b = (x.astype(np.float32) / 255 for x in (a, occluded))
    whole = alignment_ncc(gray_a, gray_b, truth, on="both")
    assert whole < 0.7  # the blob alone pulls the right answer under auto's threshold
    assert VERIFIER.score(a, occluded, truth) > 0.8
    wrong = geometry.translation(9.0, -7.0) @ truth
    assert VERIFIER.score(a, occluded, wrong) < 0.4


@pytest.mark.parametrize("seed", range(4))
def test_tiled_ncc_from_tile_moments_equals_the_tile_by_tile_correlation(seed):
    """The one-pass tiled NCC (six masked moments per tile) gives the per-tile loop's answer, including tiles
    that are only partly inside the overlap, tiles left out for being mostly outside, flat tiles, and the
    empty tiles of a sliver of overlap."""
    from udh_cli.estimators.verify import _ncc, _tiled_ncc

    def _tiled_ncc_loop(x, y, mask, row_edges, col_edges):  # the definition, tile by tile
        values = []
        for r0, r1 in zip(row_edges[:-1], row_edges[1:]):
            for c0, c1 in zip(col_edges[:-1], col_edges[1:]):
                inside = mask[r0:r1, c0:c1]
                if inside.size and inside.mean() >= 0.5:
                    values.append(_ncc(x[r0:r1, c0:c1][inside], y[r0:r1, c0:c1][inside]))
        return float(np.median(values)) if values else 0.0

    rng = np.random.default_rng(seed)
    x = cv2.GaussianBlur(rng.random((96, 128)).astype(np.float32), (0, 0), 2.0)
    y = 1.5 * x + 0.2 + 0.03 * rng.random(x.shape).astype(np.float32)  # gain, bias and noise
    y[:30, :40] = 0.5  # a flat corner: its tiles have no variance, so their NCC is 0
    mask = cv2.warpPerspective(np.ones_like(x), geometry.translation(rng.uniform(-40, 40), rng.uniform(-30, 30)),
                               (128, 96), flags=cv2.INTER_NEAREST) > 0.5
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    row_edges = np.linspace(rows[0], rows[-1] + 1, 5).astype(int)
    col_edges = np.linspace(cols[0], cols[-1] + 1, 5).astype(int)
    expected = _tiled_ncc_loop(x, y, mask, row_edges, col_edges)
    assert 0.3 < expected < 0.999
    assert _tiled_ncc(x, y, mask, 4) == pytest.approx(expected, abs=1e-9)
    sliver = np.zeros_like(mask)
    sliver[10:12, 5:100] = True  # two rows: most of a 4x4 grid is empty
    assert _tiled_ncc(x, y, sliver, 4) == pytest.approx(_tiled_ncc_loop(x, y, sliver, np.linspace(10, 12, 5).astype(int),
                                                                         np.linspace(5, 100, 5).astype(int)), abs=1e-12)


def test_a_network_without_refinement_stage_can_start_the_refinement():
    """supervised has no refinement network: unsupervised+ecc must not hand it the default refine_rounds."""
    if not (models_dir() / "udh-supervised.onnx").is_file():
        pytest.skip("shipped supervised model not built yet")
    refined = create_estimator("unsupervised+ecc", initial="supervised", device="cpu")
    assert refined.start.refine_rounds == 0 and len(refined.start.rounds()) == 1
    truth = geometry.translation(2.0, -1.5)
    a, b = warped_pair(truth, 320, 240, seed=4)
    assert geometry.mace(refined.estimate(a, b).homography, truth, 320, 240) < 0.3


class Matches(Estimator):
    """Answers a fixed homography with a given number of RANSAC inliers, as SIFT reports them."""

    name: ClassVar[str] = "matches"

    def __init__(self, homography, inliers):
        self.homography, self.inliers = homography, inliers

    def _estimate(self, pair):
        return self.homography, 0.9, {"inliers": self.inliers}


def occluded(image: np.ndarray, seed: int = 0) -> np.ndarray:
    """``image`` with random noise pasted over its left 60 %: right answers then score low photometrically."""
    out = image.copy()
    width = int(0.6 * image.shape[1])
    out[:, :width] = np.random.default_rng(seed).integers(0, 256, (image.shape[0], width), dtype=np.uint8)
    return out


def test_an_answer_many_matches_agree_on_outvotes_the_photometric_score():
    """Occluders (or surf) lower a right answer's score; 20 or more RANSAC inliers were never wrong on the
    held-out sets, so such an answer is kept and not escalated, and its confidence is the matcher's."""
    a, b, truth = known_pair(2)
    b = occluded(b)
    wrong = Answers(geometry.translation(30.0, 20.0) @ truth)
    assert VERIFIER.score(a, b, truth) < Policy.min_score  # doubted on its score
    auto = cascade(wrong, fallback=Matches(truth, inliers=40), escalated=wrong)
    estimate = auto.estimate(a, b)
    assert estimate.stage == "matches" and estimate.verified_by == "matches"
    assert "escalated" not in estimate.details and estimate.confidence >= 0.9 and estimate.verified
    # ECC may polish the matched answer but not leave it: no corner moves by over NEAR_PX (2 px).
    assert geometry.corner_errors(estimate.homography, truth, 320, 240).max() <= NEAR_PX


def test_fewer_matches_ask_for_more_opinions_and_win_only_when_nothing_verifies():
    a, b, truth = known_pair(2)
    wrong = Answers(geometry.translation(30.0, 20.0) @ truth)
    # Occluded: nothing verifies photometrically, so the 8 matches' answer is kept after the other opinions.
    auto = cascade(wrong, fallback=Matches(truth, inliers=8), escalated=wrong)
    estimate = auto.estimate(a, occluded(b))
    assert "escalated" in estimate.details and "mirrored" in estimate.details
    assert estimate.stage == "matches" and estimate.verified_by == "matches"
    assert geometry.corner_errors(estimate.homography, truth, 320, 240).max() <= NEAR_PX
    # Clear images: the longer cascade's answer verifies and beats 8 matches agreeing on a wrong one.
    auto = cascade(wrong, fallback=Matches(wrong.homography, inliers=8), escalated=Answers(truth))
    estimate = auto.estimate(a, b)
    assert estimate.stage == "escalated" and estimate.verified_by != "matches"
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3 and estimate.confidence >= auto.policy.min_score


def test_views_are_the_last_opinions_and_the_best_verified_one_is_kept():
    """When the network, SIFT and the longer cascade all stay doubted, the cascade looks at mirrored,
    flipped and swapped copies; the answer that verifies best is kept."""
    a, b, truth = known_pair(8)
    wrong = Answers(geometry.translation(60.0, -40.0) @ truth)
    mirror = geometry.mirror_matrix(320, 240, horizontal=True)

    class RightWhenMirrored(Estimator):
        """The truth when shown the mirrored pair (as seen there), far off otherwise."""

        def _estimate(self, pair):
            image_a = pair.a
            if np.array_equal(image_a.grey, PreparedImage.of(cv2.flip(a, 1)).grey):
                return mirror @ truth @ mirror, 1.0, {}
            return wrong.homography, 1.0, {}

    right_when_mirrored = RightWhenMirrored()
    views = [ViewEstimator(right_when_mirrored, view) for view in ("flipped", "mirrored", "swapped")]
    auto = cascade(wrong, fallback=AlwaysFails(), escalated=wrong, views=views)
    estimate = auto.estimate(a, b)
    assert estimate.stage == "mirrored" and "swapped" not in estimate.details  # settled: no more looks
    assert estimate.details["flipped"]["score"] < 0.3 and estimate.verified
    assert geometry.mace(estimate.homography, truth, 320, 240) < 0.3
    assert AutoOptions.views == ("mirrored", "flipped", "swapped") and UnsupervisedEccOptions.views == ()


def test_the_fallback_takes_its_role_options_unless_given_its_own():
    """As auto's fallback SIFT keeps low-contrast keypoints and matches with FLANN; explicit options replace those."""
    def fallback(**options):
        return create_estimator("auto", device="cpu", **options).opinions[0]

    role = fallback()
    assert role.key == "fallback" and role.stage == "sift"
    assert role.estimator.contrast_threshold == FALLBACK_OPTIONS["sift"]["contrast_threshold"] == 0.002
    assert role.estimator.matcher == "flann" and role.estimator.best_features == 10000
    recorded = create_estimator("auto", device="cpu").settings()["opinions"][0]  # mosaic settings and caches say what ran
    assert recorded["method"] == "sift" and recorded["contrast_threshold"] == 0.002 and recorded["matcher"] == "flann"
    plain = fallback(fallback_options={}).estimator
    assert plain.contrast_threshold == 0.02 and plain.matcher == "auto"  # SIFT's own defaults
    assert fallback(fallback="orb").estimator.name == "orb"  # no role options for orb


@pytest.mark.parametrize(("options", "message"), [
    ({"views": "mirrored"}, "views takes a list of names"),
    ({"views": ["rotated"]}, "choose one of mirrored, flipped, swapped"),
    ({"trusted_inliers": 3}, "must be at least 4"),
    ({"fallback_options": {"colour": True}}, "does not take colour"),
    ({"min_score": 0.0}, r"must be in \(0, 1\]"),
    ({"initial": "identity"}, "must be a network: unsupervised, supervised"),
    ({"refiner": 3}, "refiner takes a PyramidEcc"),
    ({"fallback_options": "abc"}, "fallback_options takes the fallback's options as a JSON object"),
])
def test_bad_auto_options_fail_when_it_is_made(options, message):
    from udh_cli.errors import UdhError

    with pytest.raises(UdhError, match=message):
        create_estimator("auto", device="cpu", **options)


def test_a_polish_that_leaves_the_matches_is_dropped_and_the_details_say_so():
    """ECC moving a matched answer by more than NEAR_PX is not kept, and what is returned is the matched answer."""
    a, b, truth = known_pair(2)
    off = geometry.translation(5.0, 0.0) @ truth  # ECC pulls this 5 px back towards the truth
    wrong = Answers(geometry.translation(30.0, 20.0) @ truth)
    auto = cascade(wrong, fallback=Matches(off, inliers=8), escalated=wrong, views=())
    estimate = auto.estimate(a, b)
    assert estimate.details["fallback"]["refinement_kept"] is False
    np.testing.assert_allclose(estimate.homography, off / off[2, 2], atol=1e-9)


class _Twinned(Estimator):
    """Names the twin :meth:`near_prior` gives."""

    name: ClassVar[str] = "twinned"

    def __init__(self, label: str) -> None:
        self.label = label

    def near_prior(self):
        return _Twinned(self.label + " near")


def test_a_cascade_near_its_prior_takes_every_opinion_near_its_prior():
    cascade = Cascade("auto", _Twinned("start"), opinions=(Opinion("fallback", _Twinned("sift"), "sift"),
                                                          Opinion("mirrored", ViewEstimator(_Twinned("view"), "mirrored"), "mirrored")))
    near = cascade.near_prior()
    assert near.start.label == "start near" and near.opinions[0].estimator.label == "sift near"
    assert near.opinions[1].estimator.inner.label == "view near" and near.opinions[1].key == "mirrored"
    assert cascade.start.label == "start" and near.policy == cascade.policy


@dataclass
class _Matches(Estimator):
    """A stand-in for SIFT: ``answer`` with ``inliers`` RANSAC inliers."""

    name: ClassVar[str] = "sift"
    answer: np.ndarray | None = None
    inliers: int = 100

    def _estimate(self, pair):
        return self.answer, 0.9, {"inliers": self.inliers}


@pytest.mark.parametrize("off_px, verified, failed", [(0.0, True, []), (60.0, False, ["aligns"])])
def test_auto_keeps_an_answer_its_matches_verify_and_verifies_it_only_when_the_judge_agrees(off_px, verified, failed):
    """A network that fails, then a fallback whose 100 matches agree on an answer: the right one is verified (three
    tile levels accept it), one 60 px off (of 640) that aligns nothing is kept as the same answer, supported by its
    matches but not verified, and the mosaic still takes it."""
    from udh_cli.mosaic.pairs.types import Acceptance

    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    network = create_estimator("unsupervised", device="cpu", search=0, heading_search=0, matcher_model="")
    truth = geometry.homography_from_offsets(np.random.default_rng(5).uniform(-20, 20, (4, 2)), 640, 480)
    a, b = warped_pair(truth, 640, 480, seed=5, margin=60)
    answer = geometry.translation(off_px, off_px / 6) @ truth
    auto = Cascade("auto", AlwaysFails(), PyramidEcc(), (Opinion("fallback", _Matches(answer), "sift"),), Policy(), tiles_from=network)
    found = auto.estimate(a, b)
    assert found.stage == "sift" and geometry.mace(found.homography, answer, 640, 480) < NEAR_PX
    assert found.verified is verified and found.verified_by == "matches" and found.details["verdict_failed"] == failed
    assert found.details["match_tile_levels"] == (3 if verified else None)
    assert Acceptance().judge(found, a, b, auto.verifies_itself) == (None, None)
