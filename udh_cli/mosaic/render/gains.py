"""Exposure compensation of one part with OpenCV's compensators (``cv2.detail``), found on the part drawn small
(:mod:`.small`) and applied at full resolution while compositing (``--exposure``):

- ``gain``: one multiplier per frame (Brown & Lowe), ``channels``: one per colour channel (white balance too);
- ``blocks``: a smooth per-channel gain map over 32 px blocks of each frame (vignetting, uneven light);
- ``none``: the frames as they are.
"""

from __future__ import annotations

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.small import SmallPart

EXPOSURES = ("blocks", "channels", "gain", "none")  # the --exposure choices


def _compensator(kind: str):
    if kind == "gain":
        return cv2.detail.GainCompensator()
    if kind == "channels":
        return cv2.detail.ChannelsCompensator()
    if kind == "blocks":
        return cv2.detail.BlocksChannelsCompensator()
    raise UdhError(f"unknown exposure compensation '{kind}'; choose one of: {', '.join(EXPOSURES)}")


def exposure_gains(kind: str, small: SmallPart) -> dict[int, np.ndarray]:
    """Per frame: (3,) gains for ``gain`` and ``channels`` (B, G, R), or a (rows, cols, 3) gain map over the
    frame's warped box for ``blocks``; all ones for ``none``."""
    if kind == "none" or len(small.indices) < 2:
        return {i: np.ones(3) for i in small.indices}
    compensator = _compensator(kind)
    compensator.feed(corners=small.corners, images=[cv2.UMat(image) for image in small.images],
                     masks=[cv2.UMat(mask) for mask in small.masks])
    gains = {}
    for i, found in zip(small.indices, compensator.getMatGains()):
        found = np.asarray(found, np.float64)
        if kind == "blocks":
            gains[i] = found if found.ndim == 3 else np.repeat(found[..., None], 3, axis=2)
        else:
            gains[i] = np.resize(found.ravel()[:3] if found.size >= 3 else found.ravel(), 3)
        if not np.isfinite(gains[i]).all():  # a frame with no usable overlap: leave it as it is
            gains[i] = np.ones(3)
    return gains


def apply_gain(warped: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """(h, w, 3) float32 warped frame times its gains; a gain map is stretched over the warped box."""
    if gain.ndim == 1:
        return warped * gain.astype(np.float32)
    height, width = warped.shape[:2]
    return warped * cv2.resize(gain.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)


def mean_gain(gain: np.ndarray) -> list[float]:
    """(3,) mean gain per channel (B, G, R), for the sidecar."""
    return [float(v) for v in gain.reshape(-1, 3).mean(0)]
