"""Seams of one part with OpenCV's seam finders (``cv2.detail``), found on the part drawn small (:mod:`.small`)
and drawn at full resolution while compositing (``--seams``): ``dp`` (dynamic programming on colour) and
``graphcut`` (graph cut on colour) route the seams where overlapping frames agree; ``central`` gives every
pixel to the frame that sees it nearest its centre, with no seam search.

``dp`` runs OpenCV's ``DpSeamFinder`` one pair of frames at a time, in the finder's own order, on a window
around the pair's overlap (:data:`DP_WINDOW_MARGIN`) instead of the union of the two frames' boxes, and pairs
that share no frame in parallel threads; the seam costs it leaves are those of the finder on whole frames
(measured in docs/benchmarks.md).
"""

from __future__ import annotations

import heapq
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.mosaic.render.small import SmallPart

SEAM_FINDERS = ("dp", "graphcut", "central")  # the --seams choices
# Small-canvas pixels around two frames' overlap that the dp finder sees: more than its 2-px contour reach, so the
# overlap's own contours are found as on whole frames; the boxes' union is mostly pixels neither frame shows.
DP_WINDOW_MARGIN = 8


@dataclass
class Seams:
    """Where each frame of a part is shown: its seam mask on the small canvas (255 inside), placed at its
    corner there; ``scale`` is small-canvas pixels per canvas pixel."""

    masks: dict[int, np.ndarray]
    corners: dict[int, tuple[int, int]]
    scale: float

    def in_box(self, index: int, box: tuple[int, int, int, int]) -> np.ndarray:
        """Frame ``index``'s seam mask drawn over the canvas box ``(x0, y0, x1, y1)``: (h, w) bool, True inside."""
        x0, y0, x1, y1 = box
        cx, cy = self.corners[index]
        # canvas pixel (x, y) is small-canvas pixel (scale x, scale y), i.e. pixel (scale x - cx, scale y - cy) of the mask
        mask_from_box = np.array([[self.scale, 0.0, self.scale * x0 - cx], [0.0, self.scale, self.scale * y0 - cy]])
        drawn = cv2.warpAffine(self.masks[index], mask_from_box, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return drawn > 0


def find_seams(kind: str, small: SmallPart, workers: int = 1) -> Seams | None:
    """The seams of a part drawn small; None for ``central`` (or a single frame): compositing then gives every
    pixel to the frame that sees it nearest its centre. ``workers``: threads for ``dp``'s pairs."""
    if kind not in SEAM_FINDERS:
        raise UdhError(f"unknown seam finder '{kind}'; choose one of: {', '.join(SEAM_FINDERS)}")
    if kind == "central" or len(small.indices) < 2:
        return None
    if kind == "dp":
        found = dp_seam_masks(small.images, small.corners, small.masks, workers=workers)
    else:
        finder = cv2.detail_GraphCutSeamFinder("COST_COLOR")
        images = [cv2.UMat(image.astype(np.float32)) for image in small.images]
        found = [mask.get() for mask in finder.find(images, small.corners, [cv2.UMat(mask) for mask in small.masks])]
    return Seams(dict(zip(small.indices, found)), dict(zip(small.indices, small.corners)), small.scale)


def dp_seam_masks(images: list[np.ndarray], corners: list[tuple[int, int]], masks: list[np.ndarray],
                  margin: int = DP_WINDOW_MARGIN, workers: int = 1) -> list[np.ndarray]:
    """Seam masks by OpenCV's ``DpSeamFinder("COLOR")``, pair by pair: ``images`` (h, w, 3) uint8 placed at
    ``corners`` (x, y) with ``masks`` (h, w) uint8 (255 where the frame has pixels) on one canvas; returns new
    masks, 255 where each frame is shown.

    The pairs come in the finder's order (the farthest centres first), each on the window ``margin`` pixels
    around its two boxes' intersection (a margin that reaches past both frames gives the finder's own
    answer), skipped when the masks no longer overlap. Pairs wait only for the earlier pairs that share a
    frame with them, so ``workers`` threads give the same masks as one."""
    masks = [mask.copy() for mask in masks]
    boxes = [(x, y, x + image.shape[1], y + image.shape[0]) for (x, y), image in zip(corners, images)]
    pairs = _finder_order(boxes)

    def resolve(pair: tuple[int, int]) -> None:
        overlap = _intersect(boxes[pair[0]], boxes[pair[1]])
        if not np.any(np.logical_and(*(_crop(masks[k], boxes[k], overlap) for k in pair))):
            return  # an earlier seam already gave the overlap to one of the two
        x0, y0, x1, y1 = overlap
        window = (x0 - margin, y0 - margin, x1 + margin, y1 + margin)
        views = {k: _intersect(boxes[k], window) for k in pair}
        found = cv2.detail_DpSeamFinder("COLOR").find(  # one finder per call: it keeps the pair's labels as its state
            [_crop(images[k], boxes[k], views[k]) for k in pair], [views[k][:2] for k in pair],
            [_crop(masks[k], boxes[k], views[k]).copy() for k in pair])
        for k, mask in zip(pair, found):
            _crop(masks[k], boxes[k], views[k])[...] = mask.get()

    _run_in_pair_order(pairs, resolve, workers)
    return masks


def _finder_order(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int]]:
    """The pairs (i, j), i < j, whose canvas ``boxes`` (x0, y0, x1, y1) meet, as ``DpSeamFinder.find`` visits them:
    by the squared distance of the boxes' centres (integer, as OpenCV rounds them), the farthest first. (Pairs at
    equal distances may come in another order than OpenCV's, whose sort is not stable.)"""
    box = np.asarray(boxes, np.int64).reshape(-1, 4)
    centres = box[:, :2] + (box[:, 2:] - box[:, :2]) // 2
    first, second = np.triu_indices(len(box), 1)  # (0, 1), (0, 2), ... as OpenCV lists them before sorting
    meet = np.all(np.maximum(box[first, :2], box[second, :2]) < np.minimum(box[first, 2:], box[second, 2:]), axis=1)
    first, second = first[meet], second[meet]
    order = np.argsort(((centres[first] - centres[second]) ** 2).sum(1), kind="stable")[::-1]
    return list(zip(first[order].tolist(), second[order].tolist()))


def _run_in_pair_order(pairs: list[tuple[int, int]], run: Callable[[tuple[int, int]], None], workers: int) -> None:
    """``run(pair)`` for every pair, each after every earlier pair that shares a frame with it; in ``workers``
    threads (OpenCV releases the GIL), the lowest-numbered ready pair first."""
    if workers <= 1:
        for pair in pairs:
            run(pair)
        return
    waiting_for = [0] * len(pairs)
    then = [[] for _ in pairs]  # the later pairs that wait for each one
    last = {}
    for n, (i, j) in enumerate(pairs):
        for before in {last.get(i), last.get(j)} - {None}:
            then[before].append(n)
            waiting_for[n] += 1
        last[i] = last[j] = n
    ready = [n for n, count in enumerate(waiting_for) if count == 0]
    running = {}
    with ThreadPoolExecutor(workers, thread_name_prefix="udh-seams") as pool:
        while ready or running:
            while ready and len(running) < workers:
                n = heapq.heappop(ready)
                running[pool.submit(run, pairs[n])] = n
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                future.result()
                for n in then[running.pop(future)]:
                    waiting_for[n] -= 1
                    if waiting_for[n] == 0:
                        heapq.heappush(ready, n)


def _intersect(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
    x0, y0, x1, y1 = max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def _crop(image: np.ndarray, box: tuple[int, int, int, int], part: tuple[int, int, int, int]) -> np.ndarray:
    """The view of ``image`` (placed over canvas ``box``) that covers the canvas box ``part`` inside it."""
    return image[part[1] - box[1] : part[3] - box[1], part[0] - box[0] : part[2] - box[0]]
