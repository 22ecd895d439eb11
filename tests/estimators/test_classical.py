"""Every classical estimator recovers a homography the test applied itself, and fails cleanly."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators import Estimator, create_estimator, estimator_names, require_ok
from udh_cli.estimators.ecc import EccEstimator
from udh_cli.images import to_gray_float, to_gray_u8

from conftest import textured_image, warped_pair

WIDTH, HEIGHT = 320, 240
# Corner displacement each method is tested with (px), and the corner error it must stay under (px).
# Measured on 12 seeds x (grey, colour, 16-bit): sift max 0.06, orb max 1.15, ecc max 0.04.
CASES = {"sift": (16.0, 0.2), "orb": (16.0, 2.0), "ecc": (4.0, 0.2)}
CLASSICAL = list(CASES)


def known_pair(method: str, seed: int):
    """(image_a, image_b, b_from_a) with corner offsets up to the method's displacement."""
    bound = CASES[method][0]
    b_from_a = geometry.homography_from_offsets(np.random.default_rng(1000 + seed).uniform(-bound, bound, (4, 2)), WIDTH, HEIGHT)
    image_a, image_b = warped_pair(b_from_a, WIDTH, HEIGHT, seed=seed)
    return image_a, image_b, b_from_a


def as_kind(image: np.ndarray, kind: str) -> np.ndarray:
    if kind == "colour":  # real colour: the three channels differ
        return cv2.applyColorMap(image, cv2.COLORMAP_JET)
    if kind == "16-bit":  # a sensor that fills a sixth of its range, as thermal and raw frames do
        return (1000 + image.astype(np.uint16) * 40).astype(np.uint16)
    return image


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("method", CLASSICAL)
def test_recovers_known_homography(method, seed):
    image_a, image_b, truth = known_pair(method, seed)
    result = create_estimator(method).estimate(image_a, image_b)
    assert result.ok, result.failure
    assert result.method == method and result.failure is None
    assert result.homography.shape == (3, 3) and result.homography.dtype == np.float64
    assert result.homography[2, 2] == pytest.approx(1.0)
    assert float(geometry.mace(result.homography, truth, WIDTH, HEIGHT)) < CASES[method][1]
    assert 0.5 < result.confidence <= 1.0
    assert 0.0 < result.elapsed_ms < 10_000


@pytest.mark.parametrize("kind", ["colour", "16-bit"])
@pytest.mark.parametrize("method", CLASSICAL)
def test_colour_and_16_bit_images(method, kind):
    image_a, image_b, truth = known_pair(method, seed=4)
    result = create_estimator(method).estimate(as_kind(image_a, kind), as_kind(image_b, kind))
    assert result.ok, result.failure
    assert float(geometry.mace(result.homography, truth, WIDTH, HEIGHT)) < CASES[method][1]


def test_a_and_b_may_differ_in_size():
    image_a, image_b, truth = known_pair("sift", seed=5)
    bigger_b = cv2.resize(image_b, (400, 300), interpolation=cv2.INTER_LINEAR)
    truth_big = geometry.rescale_homography(truth, (WIDTH, HEIGHT), (WIDTH, HEIGHT), (WIDTH, HEIGHT), (400, 300))
    result = create_estimator("sift").estimate(image_a, bigger_b)
    assert float(geometry.mace(result.homography, truth_big, WIDTH, HEIGHT)) < 0.3


@pytest.mark.parametrize("method", CLASSICAL)
def test_textureless_image_fails_cleanly(method):
    flat = np.full((HEIGHT, WIDTH), 128, np.uint8)
    image_a, _, _ = known_pair(method, seed=0)
    for pair in [(flat, flat), (image_a, flat), (flat, image_a)]:
        result = create_estimator(method).estimate(*pair)
        assert not result.ok
        assert result.homography is None and result.confidence == 0.0
        assert isinstance(result.failure, str) and len(result.failure) > 10 and "\n" not in result.failure
        with pytest.raises(UdhError, match=method):
            require_ok(result)


@pytest.mark.parametrize("method", ["sift", "orb"])
def test_best_features_keeps_the_strongest_n(method):
    image_a, image_b, truth = known_pair(method, seed=1)
    result = create_estimator(method, best_features=50).estimate(image_a, image_b)
    assert result.ok, result.failure
    assert result.details["keypoints_a"] == 50 and result.details["keypoints_b"] == 50
    assert result.inliers <= result.details["matches"] <= 50
    # SIFT's 50 strongest keypoints spread over the image and stay accurate (measured 0.24 px).
    # ORB's 50 strongest cluster and come from coarse pyramid levels: measured 8 px here, so only sift
    # is held to a number.
    if method == "sift":
        assert float(geometry.mace(result.homography, truth, WIDTH, HEIGHT)) < 0.5
    from udh_cli.estimators.pair import PreparedImage

    estimator = create_estimator(method, best_features=50)
    kept = estimator._features(PreparedImage.of(image_a))[0]  # (50, 2) pixels
    everything, _ = estimator._detector().detectAndCompute(to_gray_u8(image_a), None)
    strongest = sorted(everything, key=lambda k: -k.response)[:50]
    weakest_kept = min(k.response for k in everything if any(np.allclose(k.pt, p) for p in kept))
    assert len(kept) == 50 and weakest_kept >= strongest[-1].response


def test_ecc_takes_iterations_and_an_initial_guess():
    truth = geometry.homography_from_offsets(np.random.default_rng(7).uniform(-20, 20, (4, 2)), WIDTH, HEIGHT)
    image_a, image_b = warped_pair(truth, WIDTH, HEIGHT, seed=7)
    guess = truth @ geometry.translation(10.0, -10.0)  # 14 px off
    refined = create_estimator("ecc", init=guess).estimate(image_a, image_b)
    assert refined.ok and float(geometry.mace(refined.homography, truth, WIDTH, HEIGHT)) < 0.2
    direct = EccEstimator().refine(to_gray_float(image_a), to_gray_float(image_b), guess)
    np.testing.assert_allclose(direct[0], refined.homography, atol=1e-9)
    # One or two iterations leave it far from the answer (measured 12.6 and 10.0 px).
    for iterations in (1, 2):
        early = create_estimator("ecc", init=guess, iterations=iterations).estimate(image_a, image_b)
        assert float(geometry.mace(early.homography, truth, WIDTH, HEIGHT)) > 5.0


@pytest.mark.parametrize("method", CLASSICAL)
def test_unrelated_images_fail_with_a_readable_reason(method):
    for seed in range(2):
        result = create_estimator(method).estimate(textured_image(seed=seed), textured_image(seed=seed + 10))
        assert not result.ok and result.confidence == 0.0
        assert "OpenCV(" not in result.failure and "/" not in result.failure and "\n" not in result.failure


def test_identity_returns_eye_and_rescales_between_sizes():
    image = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH), dtype=np.uint8)
    result = create_estimator("identity").estimate(image, image)
    assert result.ok and result.method == "identity"
    np.testing.assert_array_equal(result.homography, np.eye(3))
    half = create_estimator("identity").estimate(image, image[::2, ::2])
    np.testing.assert_allclose(half.homography, [[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]], atol=1e-15)


def test_registry():
    assert set(CLASSICAL + ["identity"]) <= set(estimator_names())
    with pytest.raises(UdhError, match="unknown method 'surf'.*sift"):
        create_estimator("surf")
    with pytest.raises(UdhError, match="does not take"):
        create_estimator("sift", no_such_option=3)


@pytest.mark.parametrize(
    ("method", "options", "message"),
    [
        ("sift", {"ratio": "abc"}, "option ratio takes float, not 'abc'"),
        ("orb", {"best_features": 2.5}, "option best_features takes int or none"),
        ("ecc", {"iterations": "200"}, "option iterations takes int"),
        ("sift", {"lmeds_refit": "yes"}, "option lmeds_refit takes bool"),
        ("sift", {"best_features": -3}, "best_features -3 must be at least 1"),
        ("orb", {"ratio": 0.0}, r"ratio 0.0 must be in \(0, 1\]"),
        ("ecc", {"iterations": 0}, "iterations 0 must be at least 1"),
        ("sift", {"matcher": "brute"}, "matcher 'brute' must be bf, flann or auto"),
        ("orb", {"matcher": "flann"}, "flann needs float descriptors"),
    ],
)
def test_bad_option_values_fail_when_the_estimator_is_made(method, options, message):
    # Options come from the command line (-O, --option): a bad one must stop the run at once, not fail
    # every pair later or (best_features=-3) silently drop the three strongest keypoints.
    with pytest.raises(UdhError, match=message):
        create_estimator(method, **options)


def test_flann_matching_agrees_with_brute_force_and_repeats_exactly():
    truth = geometry.homography_from_offsets(np.array([[9, -6], [-7, 5], [6, 8], [-5, -7]], float), 320, 240)
    a, b = warped_pair(truth, 320, 240, seed=4)
    exact = create_estimator("sift", contrast_threshold=0.002).estimate(a, b)
    flann = [create_estimator("sift", matcher="flann", contrast_threshold=0.002).estimate(a, b) for _ in range(2)]
    assert flann[0].inliers >= 0.95 * exact.inliers > 0
    assert geometry.mace(flann[0].homography, truth, 320, 240) < 0.3
    np.testing.assert_array_equal(flann[0].homography, flann[1].homography)  # seeded: the same answer twice


def test_option_values_of_a_kin_type_are_accepted():
    assert create_estimator("sift", ratio=1, best_features=np.int64(50)).best_features == 50
    assert create_estimator("ecc", iterations=np.int32(20), eps=0).eps == 0


@pytest.mark.parametrize("method", ["sift", "identity"])
def test_estimate_many_and_json(method):
    image_a, image_b, _ = known_pair("sift", seed=2)
    results = create_estimator(method).estimate_many([(image_a, image_b), (image_b, image_a)])
    assert len(results) == 2 and all(r.ok for r in results)
    payload = json.loads(json.dumps(results[0].to_json()))
    assert {"method", "homography", "elapsed_ms", "confidence", "ok", "failure", "details"} <= set(payload)
    assert np.asarray(payload["homography"]).shape == (3, 3)


class _Broken(Estimator):
    """Returns whatever it is told to, to check the base class's guard."""

    name = "broken"

    def __init__(self, answer):
        self.answer = answer

    def _estimate(self, pair):
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer, 0.9, {}


def test_base_class_never_returns_garbage():
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    corners = geometry.image_corners(WIDTH, HEIGHT)
    folded = cv2.getPerspectiveTransform(corners.astype(np.float32), corners[[0, 2, 1, 3]].astype(np.float32) + np.float32([[0, 0], [5, 3], [-4, 2], [0, 0]]))
    for answer in [np.full((3, 3), np.nan), np.zeros((3, 3)), folded]:
        result = _Broken(answer).estimate(image, image)
        assert not result.ok and result.confidence == 0.0 and "degenerate" in result.failure
    failed = _Broken(EstimationFailed("only 3 matches")).estimate(image, image)
    assert not failed.ok and failed.failure == "only 3 matches" and failed.confidence == 0.0
    # A valid answer scaled by -2 comes back normalised to h33 = 1.
    result = _Broken(-2.0 * geometry.translation(3, 4)).estimate(image, image)
    assert result.ok
    np.testing.assert_allclose(result.homography, geometry.translation(3, 4))
    assert result.confidence == pytest.approx(0.9)


def test_bad_image_arrays_raise_udh_error():
    good = np.zeros((HEIGHT, WIDTH), np.uint8)
    for bad in [np.zeros((1, 1), np.uint8), np.zeros((HEIGHT, WIDTH, 2), np.uint8), np.full((20, 20), np.nan, np.float32)]:
        with pytest.raises(UdhError):
            create_estimator("sift").estimate(good, bad)


def test_features_are_detected_once_per_image_and_never_served_stale(monkeypatch):
    import udh_cli.estimators.features as features

    features._FEATURE_CACHE.clear()
    a, b = warped_pair(np.array([[1.0, 0.0, 5.0], [0.0, 1.0, -3.0], [0.0, 0.0, 1.0]]), seed=21)
    calls = []
    real = features.FeatureRansacEstimator._detect_uncached
    monkeypatch.setattr(features.FeatureRansacEstimator, "_detect_uncached", lambda self, gray: calls.append(1) or real(self, gray))
    sift = create_estimator("sift")
    first, second = sift.estimate(a, b), sift.estimate(b, a)
    assert len(calls) == 2  # A and B once each, though each took part in two pairs
    np.testing.assert_allclose(second.homography @ first.homography, np.eye(3), atol=0.02)
    changed = a.copy()
    changed[:20] = 0
    sift.estimate(changed, b)
    assert len(calls) == 3  # new pixels, new detection
    create_estimator("sift", contrast_threshold=0.01).estimate(a, b)
    assert len(calls) == 5  # other settings, other features


def test_one_option_syntax_for_every_command():
    from udh_cli.estimators.registry import parse_method_options

    # A bare KEY reaches every method here that takes it; METHOD.KEY only that one; values are JSON or text.
    got = parse_method_options(["ratio=0.8", "ecc.iterations=200", "model=my.v2.onnx"], ["sift", "ecc", "unsupervised"])
    assert got == {"sift": {"ratio": 0.8}, "ecc": {"iterations": 200}, "unsupervised": {"model": "my.v2.onnx"}}
    assert parse_method_options(["threads=1"], ["auto", "unsupervised", "sift"]) == {"auto": {"network": {"threads": 1}},
                                                                                      "unsupervised": {"threads": 1}}
    assert parse_method_options(None, ["sift"]) == {}
    with pytest.raises(UdhError, match="KEY=VALUE"):
        parse_method_options(["junk"], ["sift"])
    with pytest.raises(UdhError, match="'orb' is not a method of this command"):
        parse_method_options(["orb.ratio=0.8"], ["sift"])
    with pytest.raises(UdhError, match="no method here takes 'iterations'.*sift takes: ratio"):
        parse_method_options(["iterations=3"], ["sift"])


def test_the_feature_cache_keeps_what_its_byte_budget_holds():
    from udh_cli.estimators.features import _FeatureCache

    rng = np.random.default_rng(0)

    def features(count):  # SIFT-like: float descriptors of whole numbers 0-255
        return rng.random((count, 2)) * 300, np.round(rng.random((count, 128)) * 255).astype(np.float32), rng.random(count).astype(np.float32)

    per_frame = 100 * (16 + 128 + 4)  # float64 points, descriptors held as bytes, float32 responses
    cache = _FeatureCache(budget_bytes=3 * per_frame)
    kept = {frame: features(100) for frame in range(3)}
    for frame, found in kept.items():
        cache.put(frame, *found)
    points, descriptors, _ = cache.get(0)  # used again: now the most recent
    assert descriptors.dtype == np.float32 and np.array_equal(descriptors, kept[0][1]) and np.array_equal(points, kept[0][0])
    assert not points.flags.writeable and not descriptors.flags.writeable  # shared: nobody may change them
    cache.put(3, *features(100))  # over budget: the least recently used (1) goes
    assert cache.get(1) is None and all(cache.get(k) is not None for k in (0, 2, 3))
    assert cache.held_bytes == 3 * per_frame
    cache.put(3, *features(100))  # put again: counted once
    assert cache.held_bytes == 3 * per_frame
    fractional = (rng.random((10, 2)), rng.random((10, 128)).astype(np.float32), rng.random(10).astype(np.float32))
    cache.put(4, *fractional)  # not whole numbers: held as they are
    assert np.array_equal(cache.get(4)[1], fractional[1])
    cache.put(5, *features(1000))  # larger than the budget alone: kept, everything else dropped
    assert list(cache.recent.entries) == [5] and cache.held_bytes == 10 * per_frame
    cache.clear()
    assert cache.held_bytes == 0 and not cache.recent.entries
