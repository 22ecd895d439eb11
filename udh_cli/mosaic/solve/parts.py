"""A part: a connected run of frames mosaicked on its own, from chaining to the global solve."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.pairs.types import PairResult
from udh_cli.mosaic.solve.cameras import CameraSolution
from udh_cli.mosaic.solve.graph import chain_to_reference, connected_parts, reference_frame


@dataclass
class Part:
    """A connected run of frames mosaicked on its own: its frames, its reference and their homographies to it."""

    number: int
    frames: list[int]
    reference: int
    chained: dict[int, np.ndarray]
    solved: dict[int, np.ndarray]  # the chain at first, then each loop round's solve, then the global solve's
    tree: set[int]
    rectified: bool = False  # solved on the ground's plane (rectify.py, cameras.py) rather than in the reference frame's view
    cameras: CameraSolution | None = None  # the camera-model solve's answer (--solve camera)
    focal_source: str | None = None  # where the camera-model solve's focal length came from


def chain_parts(frameset: FrameSet, pairs: list[PairResult]) -> list[Part]:
    """The connected parts of the pairs that worked, each chained to its reference frame; numbered from 1,
    lone frames left at 0."""
    parts = []
    for members in connected_parts(len(frameset.frames), pairs):
        reference = reference_frame(members)
        chained, tree = chain_to_reference(members, reference, pairs)
        parts.append(Part(0, members, reference, chained, dict(chained), tree))
    for number, part in enumerate((p for p in parts if len(p.frames) > 1), start=1):
        part.number = number
    return parts
