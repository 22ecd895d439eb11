"""16-bit frames in 8 bits: one flight-wide range, mapped to 0-255."""

from __future__ import annotations

import numpy as np

from udh_cli.mosaic.inputs.display import display_u8, flight_value_range, to_display


def test_one_range_for_the_flight_maps_its_sliver_of_16_bits_onto_0_255():
    rng = np.random.default_rng(0)
    works = [rng.uniform(7000, 8000, (60, 80)) / 65535 for _ in range(3)]
    works[0][0, 0] = 1.0  # a hot pixel clips, not the range
    low, high = flight_value_range(works)
    assert 7000 / 65535 < low < 7010 / 65535 and 7990 / 65535 < high < 8000 / 65535
    assert to_display(np.array([low, (low + high) / 2, high, 1.0]), (low, high)).tolist() == [0, 128, 255, 255]


def test_a_16_bit_frame_becomes_bgr_uint8_and_an_8_bit_one_stays_as_it_is():
    sixteen = np.full((4, 5), 7500, np.uint16)
    shown = display_u8(sixteen, (7000 / 65535, 8000 / 65535))
    assert shown.shape == (4, 5, 3) and shown.dtype == np.uint8 and int(shown[0, 0, 0]) in (127, 128)  # half way, in float32
    eight = np.arange(60, dtype=np.uint8).reshape(4, 5, 3)
    assert np.array_equal(display_u8(eight, None), eight)
