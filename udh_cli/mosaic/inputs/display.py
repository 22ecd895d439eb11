"""16-bit and float frames shown in 8 bits: one grey range for the whole flight, applied to every frame."""

from __future__ import annotations

import numpy as np

from udh_cli.images import to_bgr_u8

DISPLAY_PERCENTILES = (0.1, 99.9)  # the grey range of 16-bit frames kept in 8 bits; outliers (hot pixels) clip


def flight_value_range(works: list[np.ndarray]) -> tuple[float, float]:
    """One (low, high) grey range for every frame of a 16-bit or float flight, from all their work copies.

    Why one range: thermal and raw frames fill a sliver of their 16 bits (7000-8000 of 65535), so 8 bits of
    the whole range hold a few grey levels; stretching each frame on its own would give neighbours different
    greys for the same ground, and seams in the mosaic.
    """
    sample = np.concatenate([w[:: max(1, w.shape[0] // 200), :: max(1, w.shape[1] // 200)].ravel() for w in works])
    low, high = (float(v) for v in np.percentile(sample, DISPLAY_PERCENTILES))
    return (low, high) if high > low else (low, low + 1e-6)


def to_display(grey_or_colour: np.ndarray, value_range: tuple[float, float]) -> np.ndarray:
    """Float data in [0, 1] of its type's range -> uint8 with ``value_range`` mapped to 0-255."""
    low, high = value_range
    return np.clip((grey_or_colour - low) / (high - low) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def display_u8(image: np.ndarray, value_range: tuple[float, float] | None) -> np.ndarray:
    """A full-resolution frame as (H, W, 3) uint8 BGR for compositing, with the flight's range for 16-bit data."""
    if image.dtype == np.uint8 or value_range is None:
        return to_bgr_u8(image)
    from udh_cli.images import _unit_float

    return to_bgr_u8(to_display(_unit_float(image), value_range))
