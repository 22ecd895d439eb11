"""The pair prepared once (udh_cli.estimators.pair): the same pixels as converting again, and few conversions."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from conftest import textured_image, warped_pair
from udh_cli import geometry, images
from udh_cli.estimators import create_estimator, estimator_names
from udh_cli.estimators.pair import PreparedImage, PreparedPair


@pytest.fixture
def conversions(monkeypatch):
    """Counts every call of images.to_gray_float, under whatever name a udh module imported it."""
    calls = []
    original = images.to_gray_float

    def counted(image):
        calls.append(image.shape)
        return original(image)

    for name, module in list(sys.modules.items()):
        if name.startswith("udh_cli") and getattr(module, "to_gray_float", None) is original:
            monkeypatch.setattr(module, "to_gray_float", counted)
    return calls


def test_prepared_copies_equal_converting_the_original_again():
    grey = textured_image(320, 240, seed=3)
    colour = cv2.merge([grey, np.roll(grey, 7, 1), 255 - grey])
    prepared = PreparedImage.of(colour)
    assert prepared.size == (320, 240) and prepared.shape == (240, 320)
    np.testing.assert_array_equal(prepared.grey, images.to_gray_float(colour))
    np.testing.assert_array_equal(prepared.resized((160, 100)), cv2.resize(images.to_gray_float(colour), (160, 100), interpolation=cv2.INTER_AREA))
    assert prepared.resized((160, 100)) is prepared.resized((160, 100))  # made once
    np.testing.assert_array_equal(prepared.grey_u8(), images.to_gray_u8(colour))
    np.testing.assert_array_equal(prepared.flipped(1).grey, images.to_gray_float(cv2.flip(colour, 1)))
    np.testing.assert_array_equal(prepared.contrast((160, 100), 2.0), images.local_contrast(prepared.resized((160, 100)), 2.0))
    deep = (colour.astype(np.uint16) * 4 + 7000)  # a narrow 16-bit range: stretched for the detectors
    np.testing.assert_array_equal(PreparedImage.of(deep).grey_u8(), images.to_gray_u8(deep, stretch=True))
    with pytest.raises(ValueError):
        prepared.grey[0, 0] = 1.0  # shared copies are read-only
    assert PreparedImage.of(prepared) is prepared


def test_a_prepared_pair_gives_the_same_estimate_as_the_arrays():
    truth = np.array([[1.0, 0.02, 5.0], [-0.01, 1.0, -3.0], [0.0, 0.0, 1.0]])
    a, b = warped_pair(truth, 320, 240, seed=5)
    sift = create_estimator("sift")
    from_arrays = sift.estimate(a, b)
    prepared = PreparedPair.of(a, b)
    from_prepared = sift.estimate_many([prepared])[0]
    np.testing.assert_array_equal(from_arrays.homography, from_prepared.homography)
    swapped = sift.estimate_pairs([prepared.swapped()])[0]
    assert geometry.mace(np.linalg.inv(swapped.homography), truth, 320, 240) < 0.5


def test_auto_converts_each_image_to_grey_once(conversions):
    """2 conversions for a pair that verifies at once, and still 2 for one that asks every second opinion
    (SIFT, the longer cascade, the mirrored, flipped and swapped views): every stage reads the prepared pair."""
    auto = create_estimator("auto", threads=1)
    truth = np.array([[1.0, 0.01, 6.0], [-0.01, 1.0, -4.0], [0.0, 0.0, 1.0]])
    a, b = warped_pair(truth, 320, 240, seed=11)
    conversions.clear()
    easy = auto.estimate(a, b)
    assert easy.ok and easy.stage == "network" and len(conversions) == 2
    unrelated_a, unrelated_b = textured_image(320, 240, seed=1), textured_image(320, 240, seed=2)
    conversions.clear()
    hard = auto.estimate(unrelated_a, unrelated_b)
    assert {"fallback", "escalated", "mirrored", "flipped", "swapped"} <= set(hard.details)
    assert len(conversions) == 2


def test_a_prepared_image_sent_to_another_process_keeps_its_pixels_and_stays_read_only():
    import pickle

    prepared = PreparedImage.of(textured_image(320, 240, seed=4))
    prepared.resized((160, 120))
    copy = pickle.loads(pickle.dumps(prepared, protocol=4))  # the multiprocessing default
    np.testing.assert_array_equal(copy.grey, prepared.grey)
    assert copy.source_dtype == np.uint8 and copy._cache == {}  # the copies are remade, not sent
    with pytest.raises(ValueError):
        copy.grey[0, 0] = 1.0


@pytest.mark.parametrize("name", estimator_names())
def test_every_method_converts_each_image_once(name, conversions):
    estimator = create_estimator(name)
    truth = np.array([[1.0, 0.01, 6.0], [-0.01, 1.0, -4.0], [0.0, 0.0, 1.0]])
    a, b = warped_pair(truth, 320, 240, seed=11)
    conversions.clear()
    estimator.estimate(a, b)
    assert len(conversions) == 2
