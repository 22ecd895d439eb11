"""A byte-budgeted cache of what was computed from recent images, shared by a process's estimators.

In a mosaic each frame is in several pairs (consecutive, bridge, loop closure), and what an estimator computes
from one image alone (SIFT's keypoints, the matcher's descriptors) is most of its time. Entries are keyed by
the pixels' digest (:func:`pixels_digest`), so a changed image is never served stale results. The budget is in
bytes rather than images, since frames differ tenfold in keypoints and descriptor grids differ with their size.
Why not ``functools.lru_cache``: it counts entries, not bytes, and cannot key on an array.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from typing import Any, Callable, Hashable

import numpy as np


def pixels_digest(image: np.ndarray) -> bytes:
    """16-byte digest of an array's shape, dtype and values: the key of what is computed from it."""
    digest = hashlib.blake2b(np.ascontiguousarray(image).data, digest_size=16)
    digest.update(repr((image.shape, image.dtype.str)).encode())
    return digest.digest()


class RecentCache:
    """Values by key, least recently used first, dropped from the front beyond ``budget_bytes`` (the newest
    entry is always kept); ``size_of(value)`` gives a value's bytes. Safe to share between threads (a Dask
    worker runs several)."""

    def __init__(self, budget_bytes: int, size_of: Callable[[Any], int]) -> None:
        self.budget_bytes = budget_bytes
        self.size_of = size_of
        self.entries: OrderedDict = OrderedDict()
        self.held_bytes = 0
        self.lock = threading.Lock()

    def get(self, key: Hashable) -> Any | None:
        with self.lock:
            value = self.entries.get(key)
            if value is not None:
                self.entries.move_to_end(key)
            return value

    def put(self, key: Hashable, value: Any) -> Any:
        """Keep ``value`` under ``key``, dropping the least recently used beyond the budget; returns ``value``."""
        with self.lock:
            if key in self.entries:
                self.held_bytes -= self.size_of(self.entries.pop(key))
            self.entries[key] = value
            self.held_bytes += self.size_of(value)
            while len(self.entries) > 1 and self.held_bytes > self.budget_bytes:
                self.held_bytes -= self.size_of(self.entries.popitem(last=False)[1])
        return value

    def get_or_make(self, key: Hashable, make: Callable[[], Any]) -> Any:
        """The value under ``key``, made by ``make`` and kept when there is none (two threads may both make it)."""
        found = self.get(key)
        return found if found is not None else self.put(key, make())

    def clear(self) -> None:
        with self.lock:
            self.entries.clear()
            self.held_bytes = 0
