"""Decoded full-resolution frames kept for the next stage that reads them: the small copies (:mod:`.small`) and
then the tiles (:mod:`.composite`), so that a frame is decoded once for both where the budget allows."""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Iterable, Iterator, Sequence

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.mosaic.inputs.frames import FrameSet

DECODED_CACHE_BYTES = 256 * 2**20  # decoded full-resolution frames kept for the next tiles that need them


class DecodedFrames:
    """Full-resolution frames as :meth:`FrameSet.full_images` gives them, the most recently used kept up to
    ``budget_bytes`` (0: :data:`DECODED_CACHE_BYTES`): a frame reaching several tiles is mostly decoded once.
    ``already``: frames decoded before, by index, kept first.
    Threads may share it: the frames are decoded outside its lock, so two threads may rarely decode one frame."""

    def __init__(self, frames: FrameSet, budget_bytes: int = 0, already: dict[int, np.ndarray] | None = None) -> None:
        self.frames = frames
        self.budget_bytes = budget_bytes or DECODED_CACHE_BYTES
        self.kept: OrderedDict[int, np.ndarray] = OrderedDict(sorted((already or {}).items()))  # e.g. FrameSet.take_decoded's
        self.kept_bytes = sum(image.nbytes for image in self.kept.values())
        self.lock = threading.Lock()

    @classmethod
    def taken_from(cls, frames: FrameSet, indices: Iterable[int]) -> "DecodedFrames":
        """The cache of one part's rendering: ``indices``' frames decoded while reading (:meth:`FrameSet.take_decoded`)
        kept first, in a budget less what ``frames`` still holds for the other parts: the two stay within
        :data:`DECODED_CACHE_BYTES` together."""
        already = frames.take_decoded(indices)
        return cls(frames, max(1, DECODED_CACHE_BYTES - frames.decoded_bytes()), already)

    def get(self, indices: Sequence[int]) -> Iterator[tuple[int, np.ndarray]]:
        """``(index, (H, W, 3) BGR uint8)`` for ``indices``, in sequence order; the frames not kept are decoded one
        at a time as they are reached."""
        with self.lock:  # decided once: the loop below evicts
            kept = {i: self.kept[i] for i in set(indices) if i in self.kept}
        fresh = self.frames.full_images(sorted(set(indices) - set(kept)))  # yields in sequence order too
        for i in sorted(set(indices)):
            if i in kept:
                image = kept[i]
            else:
                index, image = next(fresh)
                if index != i:
                    raise UdhError(f"frame {i} was expected from the reader, frame {index} came; this is a bug in udh, please report it")
            with self.lock:
                if i not in self.kept:
                    self.kept_bytes += image.nbytes
                    self.kept[i] = image
                self.kept.move_to_end(i)
                while len(self.kept) > 1 and self.kept_bytes > self.budget_bytes:
                    self.kept_bytes -= self.kept.popitem(last=False)[1].nbytes
            yield i, image
