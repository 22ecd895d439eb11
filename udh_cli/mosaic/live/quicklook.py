"""The live quick look: each new frame chained onto its predecessor and drawn into a small picture at once.

Why beside the refreshes of live mode (:mod:`.follow`): a refresh is a whole run (every pair so far, the global
solve, full-resolution compositing), seconds to minutes for a long flight, while a field user wants to see each
frame land as it arrives. The quick look estimates only the new frame against the last placed one, with the
mosaic's own opinions and acceptance test, composes that onto its placement, pastes the frame's small copy
over the picture (the newest frame on top) and rewrites ``NAME.live.jpg`` and ``NAME.live.json``. It is a chain,
so it drifts and a failed pair leaves the frame out of it; the refreshes and the final run make the mosaic
itself, drift-free. Conventions: :mod:`udh_cli.geometry` (``b_from_a`` maps A's pixels to B's).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator
from udh_cli.images import atomic_write_bytes, read_image, to_bgr_u8, to_gray_u8
from udh_cli.mosaic.inputs.frames import work_copy
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.mosaic.pairs.workers import judge_opinions

FRAME_SIDE = 240  # longer side, pixels, of a frame in the picture: a whole survey stays a few MB to encode
MAX_SIDE = 3000  # the picture is halved when it would grow past this many pixels on a side
GROWTH = 512  # pixels added on each side that must grow, so that the picture is not reallocated per frame
BACKGROUND = 40  # grey of the picture where no frame is
MAX_PAIR_SCALE = 3.0  # consecutive frames of one flight differ in scale far less (the mosaic's --max-frame-scale)


@dataclass
class _Placed:
    """A frame in the chain: its work copy (grey) and its picture-from-work-copy homography (3, 3)."""

    grey: np.ndarray
    picture_from_work: np.ndarray


class QuickLook:
    """Frames in, ``NAME.live.jpg`` and ``NAME.live.json`` out, one frame at a time (see the module's docstring).

    Args:
        output: the mosaic's path; the quick look's files are named after it.
        opinions: the mosaic's estimators, asked in order while the answer is doubted.
        acceptance: the mosaic's :class:`~udh_cli.mosaic.pairs.types.Acceptance`.
        work_size: longest side, pixels, of the copies the estimators see (the mosaic's ``--work-size``).
    """

    def __init__(self, output: Path, opinions: Sequence[Estimator], acceptance, work_size: int) -> None:
        self.output = output
        self.opinions = list(opinions)
        self.acceptance = acceptance
        self.work_size = work_size
        self.picture = np.zeros((1, 1, 4), np.uint8)  # BGRA; alpha marks what frames cover
        self.picture_from_ref = np.eye(3)  # picture pixels from the first frame's full-resolution pixels (the reference)
        self.last: _Placed | None = None
        self.records: list[dict] = []

    def add(self, path: Path, seen_at: float | None = None) -> dict:
        """Place and draw the frame at ``path`` (complete on disk); returns its record: ``name``, ``placed``,
        ``stage`` (or ``failure``), ``ref_from_frame`` (3x3, its full-resolution pixels to the first frame's),
        ``seen_at`` and ``drawn_at`` (Unix seconds) and ``latency_s`` (from the file's last write to drawn)."""
        seen_at = time.time() if seen_at is None else seen_at
        record = {"name": path.name, "placed": False, "stage": None, "seen_at": seen_at}
        try:
            image = read_image(path)
        except UdhError as exc:
            record["failure"] = str(exc)
            return self._finish(record, path)
        # 16-bit and thermal frames are stretched one by one (the mosaic stretches over the whole flight).
        colour = to_bgr_u8(image) if image.dtype == np.uint8 else cv2.cvtColor(to_gray_u8(image, stretch=True), cv2.COLOR_GRAY2BGR)
        grey = work_copy(to_gray_u8(colour), self.work_size)
        height, width = colour.shape[:2]
        small_scale = FRAME_SIDE / max(width, height)
        small = cv2.resize(colour, (max(1, round(width * small_scale)), max(1, round(height * small_scale))), interpolation=cv2.INTER_AREA)
        small_from_full = geometry.resize_matrix((width, height), (small.shape[1], small.shape[0]))
        work_from_full = geometry.resize_matrix((width, height), (grey.shape[1], grey.shape[0]))
        if self.last is None:  # the first frame sets the picture's scale and place: its small copy's pixels
            self.picture_from_ref = small_from_full
            picture_from_full = small_from_full
            record.update(placed=True, stage="first frame")
        else:
            attempts = judge_opinions(self.opinions, self.acceptance, [(grey, self.last.grey)])[0]
            estimate, _, doubt = attempts[-1]
            if doubt is not None or estimate.homography is None:
                record["failure"] = doubt or estimate.failure
                return self._finish(record, path)
            # The estimate is last_from_new in work-copy pixels; checked there, since the picture's own scale
            # shrinks as it is halved to hold a long flight.
            if not geometry.is_valid_homography(estimate.homography, grey.shape[1], grey.shape[0], max_scale=MAX_PAIR_SCALE):
                record["failure"] = f"its pair homography degenerates (folded, past the horizon or scaled over {MAX_PAIR_SCALE:g}x)"
                return self._finish(record, path)
            picture_from_full = self.last.picture_from_work @ estimate.homography @ work_from_full
            record.update(placed=True, stage=estimate.stage or estimate.method)
        picture_from_small = picture_from_full @ np.linalg.inv(small_from_full)
        picture_from_small = self._make_room(picture_from_small, small.shape[1], small.shape[0])
        picture_from_full = picture_from_small @ small_from_full
        self._paste(small, picture_from_small)
        self.last = _Placed(grey, picture_from_full @ np.linalg.inv(work_from_full))
        ref_from_frame = np.linalg.inv(self.picture_from_ref) @ picture_from_full
        record["ref_from_frame"] = (ref_from_frame / ref_from_frame[2, 2]).tolist()
        return self._finish(record, path, write_picture=True)

    def _make_room(self, picture_from_small: np.ndarray, width: int, height: int) -> np.ndarray:
        """Grow (and if need be halve) the picture so that a frame placed by ``picture_from_small`` fits; returns
        the placement in the picture's new pixels. Every placement kept is moved with it."""
        corners = geometry.transform_points(picture_from_small, geometry.image_corners(width, height))
        low, high = np.floor(corners.min(0)).astype(int), np.ceil(corners.max(0)).astype(int)
        rows, columns = self.picture.shape[:2]
        left, top = max(0, -low[0]), max(0, -low[1])
        right, bottom = max(0, high[0] + 1 - columns), max(0, high[1] + 1 - rows)
        if left or top or right or bottom:
            pad = [GROWTH if amount else 0 for amount in (left, top, right, bottom)]
            pad = [max(p, a) for p, a in zip(pad, (left, top, right, bottom))]
            self.picture = cv2.copyMakeBorder(self.picture, pad[1], pad[3], pad[0], pad[2], cv2.BORDER_CONSTANT, value=(0, 0, 0, 0))
            self._move(geometry.translation(pad[0], pad[1]))
            picture_from_small = geometry.translation(pad[0], pad[1]) @ picture_from_small
        while max(self.picture.shape[:2]) > MAX_SIDE:
            rows, columns = self.picture.shape[:2]
            self.picture = cv2.resize(self.picture, (max(1, columns // 2), max(1, rows // 2)), interpolation=cv2.INTER_AREA)
            self._move(np.diag([0.5, 0.5, 1.0]))
            picture_from_small = np.diag([0.5, 0.5, 1.0]) @ picture_from_small
        return picture_from_small

    def _move(self, new_from_old: np.ndarray) -> None:
        self.picture_from_ref = new_from_old @ self.picture_from_ref
        if self.last is not None:
            self.last.picture_from_work = new_from_old @ self.last.picture_from_work

    def _paste(self, small: np.ndarray, picture_from_small: np.ndarray) -> None:
        """The frame's small copy over the picture, inside its footprint only."""
        rows, columns = self.picture.shape[:2]
        corners = geometry.transform_points(picture_from_small, geometry.image_corners(small.shape[1], small.shape[0]))
        x0, y0 = np.maximum(np.floor(corners.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(corners.max(0)).astype(int) + 1, (columns, rows))
        box_from_small = geometry.translation(-x0, -y0) @ picture_from_small
        drawn = cv2.warpPerspective(small, box_from_small, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.full(small.shape[:2], 255, np.uint8), box_from_small, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST) > 0
        box = self.picture[y0:y1, x0:x1]
        box[..., :3][inside] = drawn[inside]
        box[..., 3][inside] = 255

    def shown(self) -> np.ndarray:
        """The picture as written: (h, w, 3) BGR, cropped to what the frames cover, on a dark background."""
        x, y, w, h = cv2.boundingRect((self.picture[..., 3] > 0).astype(np.uint8))
        box = self.picture[y : y + max(h, 1), x : x + max(w, 1)]
        alpha = box[..., 3:4].astype(np.float32) / 255.0
        return (box[..., :3] * alpha + BACKGROUND * (1 - alpha) + 0.5).astype(np.uint8)

    def _finish(self, record: dict, path: Path, write_picture: bool = False) -> dict:
        """Write the picture (when it changed) and the record file, both atomically; returns ``record``."""
        if write_picture:
            ok, encoded = cv2.imencode(".jpg", self.shown(), [cv2.IMWRITE_JPEG_QUALITY, 85])
            if ok:
                atomic_write_bytes(RunFiles(self.output).live_picture, encoded.tobytes())
        record["drawn_at"] = time.time()
        try:
            record["latency_s"] = round(record["drawn_at"] - path.stat().st_mtime, 3)
        except OSError:
            record["latency_s"] = None
        self.records.append(record)
        placed = sum(r["placed"] for r in self.records)
        document = {"format": "udh-mosaic-live/1", "picture": RunFiles(self.output).live_picture.name, "frames_seen": len(self.records),
                    "frames_placed": placed, "frames": self.records}
        atomic_write_bytes(RunFiles(self.output).live_record, (json.dumps(document, indent=1) + "\n").encode())
        return record
