"""The byte-budgeted cache of per-image results (udh_cli.estimators.recent)."""

from __future__ import annotations

import numpy as np

from udh_cli.estimators.recent import RecentCache, pixels_digest


def test_the_cache_keeps_the_most_recent_within_its_budget():
    cache = RecentCache(budget_bytes=3000, size_of=lambda value: value.nbytes)
    for key in range(3):
        cache.put(key, np.zeros(125))  # 1,000 bytes each
    assert cache.get(0) is not None  # used again: now the most recent
    cache.put(3, np.zeros(125))  # over budget: the least recently used (1) goes
    assert cache.get(1) is None and all(cache.get(k) is not None for k in (0, 2, 3))
    assert cache.held_bytes == 3000
    cache.put(3, np.zeros(125))  # put again: counted once
    assert cache.held_bytes == 3000
    cache.put(4, np.zeros(1000))  # larger than the budget alone: kept, everything else dropped
    assert list(cache.entries) == [4] and cache.held_bytes == 8000
    made = []
    assert cache.get_or_make(4, lambda: made.append(1)) is not None and not made  # held: not made again
    assert cache.get_or_make(5, lambda: np.ones(2)).sum() == 2.0 and cache.get(5) is not None
    cache.clear()
    assert cache.held_bytes == 0 and cache.get(5) is None


def test_the_digest_tells_apart_pixels_shapes_and_types():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert pixels_digest(image) == pixels_digest(image.copy())
    assert pixels_digest(image[:, ::-1].copy()) != pixels_digest(image)
    assert pixels_digest(image.reshape(4, 3)) != pixels_digest(image)  # same bytes, another shape
    assert pixels_digest(image.view(np.int32)) != pixels_digest(image)  # same bytes, another type
    assert len(pixels_digest(image)) == 16
