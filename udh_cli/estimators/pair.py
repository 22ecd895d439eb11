"""A pair prepared once: both images made grey float32 one time, and every smaller copy made one time.

Every stage of an estimate (the network's S x S input, the tile pyramid, ECC's pyramid, the verification
score at 256 px, SIFT's 8-bit input, the mirrored and swapped second opinions) reads the same
:class:`PreparedImage` instead of converting the raw image again. The cached copies are read-only, so a stage
that would change one in place fails loudly instead of corrupting the next stage's input.
(OpenStitching's ``ImageHandler`` and LightGlue's ``Extractor.extract`` follow the same idea.)

Conventions: sizes are ``(width, height)`` in pixels, as in :mod:`udh_cli.geometry`; resizing is
``cv2.INTER_AREA`` and its exact homography is :func:`udh_cli.geometry.resize_matrix`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Union

import cv2
import numpy as np

from udh_cli import images


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


@dataclass(eq=False)
class PreparedImage:
    """One image as every estimator stage reads it.

    Attributes:
        grey: (H, W) float32 grey in [0, 1] (:func:`udh_cli.images.to_gray_float`), read-only.
        source_dtype: the dtype of the image it was made from: 8-bit images go to feature detectors as they
            are, deeper ones are stretched to their own range first (:meth:`grey_u8`).
    """

    grey: np.ndarray
    source_dtype: np.dtype
    _cache: dict[Any, np.ndarray] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, image: "ImageLike", name: str = "image") -> "PreparedImage":
        """``image`` itself if it is prepared already, else a new one: the only grey conversion it gets.
        Raises :class:`~udh_cli.errors.UdhError` naming ``name`` for an image no estimator can take."""
        if isinstance(image, PreparedImage):
            return image
        images.check_image(image, name)
        return cls(_read_only(images.to_gray_float(image)), np.dtype(image.dtype))

    @property
    def size(self) -> tuple[int, int]:
        """(width, height), pixels."""
        return self.grey.shape[1], self.grey.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), as numpy's ``shape`` of the grey image."""
        return self.grey.shape[0], self.grey.shape[1]

    def resized(self, size: tuple[int, int]) -> np.ndarray:
        """(h, w) float32 grey at ``size`` = (w, h), area-averaged, made once; ``grey`` itself at its own size."""
        size = (int(size[0]), int(size[1]))
        if size == self.size:
            return self.grey
        key = ("resized", size)
        if key not in self._cache:
            self._cache[key] = _read_only(cv2.resize(self.grey, size, interpolation=cv2.INTER_AREA))
        return self._cache[key]

    def derived(self, key: Any, make: "Callable[[], np.ndarray]") -> np.ndarray:
        """A copy made once by ``make`` and kept read-only under ``key`` (e.g. a network's descriptors of it)."""
        if key not in self._cache:
            self._cache[key] = _read_only(make())
        return self._cache[key]

    def contrast(self, size: tuple[int, int], sigma: float) -> np.ndarray:
        """:func:`udh_cli.images.local_contrast` of :meth:`resized` at ``size``, made once."""
        key = ("contrast", (int(size[0]), int(size[1])), float(sigma))
        if key not in self._cache:
            self._cache[key] = _read_only(images.local_contrast(self.resized(size), sigma))
        return self._cache[key]

    def grey_u8(self) -> np.ndarray:
        """(H, W) uint8 grey for feature detectors, made once: 8-bit sources as they are (the same values as
        :func:`udh_cli.images.to_gray_u8`), 16-bit and float sources stretched to their 0.1-99.9 percentiles,
        or a frame that fills a sixth of 16 bits would keep about 40 grey levels."""
        if "u8" not in self._cache:
            grey = self.grey if self.source_dtype == np.uint8 else images.stretch_contrast(self.grey)
            self._cache["u8"] = _read_only(np.clip(grey * 255.0 + 0.5, 0, 255).astype(np.uint8))
        return self._cache["u8"]

    def __getstate__(self) -> dict:
        # Sent to another process: the grey image only (the copies are cheaper to remake than to send).
        return {"grey": np.array(self.grey), "source_dtype": self.source_dtype}

    def __setstate__(self, state: dict) -> None:
        self.grey, self.source_dtype, self._cache = _read_only(state["grey"]), state["source_dtype"], {}

    def flipped(self, code: int) -> "PreparedImage":
        """A new prepared image of the mirrored (``code`` 1) or upside-down (0) picture (``cv2.flip`` codes).
        Converting to grey is per pixel, so this equals preparing the flipped original."""
        return PreparedImage(_read_only(cv2.flip(self.grey, code)), self.source_dtype)


ImageLike = Union[np.ndarray, PreparedImage]


@dataclass(eq=False)
class PreparedPair:
    """Images A and B of one estimate, prepared (:class:`PreparedImage`)."""

    a: PreparedImage
    b: PreparedImage

    @classmethod
    def of(cls, image_a: ImageLike, image_b: ImageLike) -> "PreparedPair":
        return cls(PreparedImage.of(image_a, "image A"), PreparedImage.of(image_b, "image B"))

    def swapped(self) -> "PreparedPair":
        """B and A exchanged, sharing their caches."""
        return PreparedPair(self.b, self.a)

    def flipped(self, code: int) -> "PreparedPair":
        """Both images flipped alike (``cv2.flip`` codes: 1 left-right, 0 upside down)."""
        return PreparedPair(self.a.flipped(code), self.b.flipped(code))

    def square(self, side: int) -> tuple[np.ndarray, np.ndarray]:
        """Both images squashed whole to ``side`` x ``side``: the networks' input."""
        return self.a.resized((side, side)), self.b.resized((side, side))
