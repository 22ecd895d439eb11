"""The pair graph: which frames connect (parts), chaining to a reference frame, and overlap candidates."""

from __future__ import annotations

from collections import deque
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.pairs.types import PairResult

_KIND_PRIORITY = {"consecutive": 0, "bridge": 1, "gps": 2, "overlap": 3}  # chain along the sequence first


def connected_parts(n_frames: int, pairs: Sequence[PairResult]) -> list[list[int]]:
    """Frames grouped by the ``ok`` pairs that connect them, each part sorted, parts in sequence order."""
    parent = list(range(n_frames))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for pair in pairs:
        if pair.ok:
            parent[root(pair.a)] = root(pair.b)
    groups: dict[int, list[int]] = {}
    for i in range(n_frames):
        groups.setdefault(root(i), []).append(i)
    return sorted(groups.values(), key=lambda g: g[0])


def reference_frame(part: Sequence[int]) -> int:
    """The middle frame of a part: chaining from the middle halves the longest chain and its distortion."""
    return part[len(part) // 2]


def chain_to_reference(part: Sequence[int], reference: int, pairs: Sequence[PairResult]) -> tuple[dict[int, np.ndarray], set[int]]:
    """``ref_from_frame`` (3, 3) for every frame of ``part``, by breadth-first chaining from ``reference``.

    Only consecutive, bridge and GPS pairs are followed (consecutive first), so this is plain sequential chaining,
    the drift of which the loop-closure pairs then measure. Returns the homographies and the ids
    (``id(pair)``) of the pairs used as tree edges; every other ``ok`` pair in the part closes a loop.
    """
    members = set(part)
    adjacency: dict[int, list[PairResult]] = {i: [] for i in part}
    sequential = (p for p in pairs if p.ok and p.kind != "overlap" and p.a in members and p.b in members)
    for pair in sorted(sequential, key=lambda p: _KIND_PRIORITY[p.kind]):
        adjacency[pair.a].append(pair)
        adjacency[pair.b].append(pair)
    ref_from: dict[int, np.ndarray] = {reference: np.eye(3)}
    tree: set[int] = set()
    queue = deque([reference])
    while queue:
        current = queue.popleft()
        for pair in adjacency[current]:
            other = pair.b if pair.a == current else pair.a
            if other in ref_from:
                continue
            # current_from_other: the pair maps a -> b.
            current_from_other = pair.b_from_a if (pair.a == other) else geometry.invert(pair.b_from_a)
            h = ref_from[current] @ current_from_other
            ref_from[other] = h / h[2, 2]
            tree.add(id(pair))
            queue.append(other)
    return ref_from, tree


def footprint(ref_from_frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A frame's four corners in reference pixels, (4, 2) float32."""
    return geometry.transform_points(ref_from_frame, geometry.image_corners(*size)).astype(np.float32)


# Loop pairs at most this far apart in the sequence close loops the chain nearly closes already: a frame with
# none but these is not tied to another strip (loops.close_loops gives it a far partner).
NEAR_IN_SEQUENCE = 3
BOX_BLOCK_ROWS = 256  # frames per block of overlap_candidates' bounding-box test


def overlap_share(quad_a: np.ndarray, quad_b: np.ndarray) -> float:
    """Intersection area of two convex quadrilaterals over the smaller one's area, in [0, 1]."""
    area, _ = cv2.intersectConvexConvex(quad_a, quad_b)
    smaller = min(cv2.contourArea(quad_a), cv2.contourArea(quad_b))
    return float(area) / smaller if smaller > 0 else 0.0


def overlap_candidates(
    part: Sequence[int],
    ref_from: dict[int, np.ndarray],
    sizes: Sequence[tuple[int, int]],
    known: set[tuple[int, int]],
    min_overlap: float,
    per_frame: int,
) -> list[tuple[int, int, float]]:
    """Non-consecutive frame pairs of a part whose chained footprints overlap by ``min_overlap`` or more.

    Each frame gets at most ``per_frame`` new partners, the best-overlapping first, which bounds the work
    at ``per_frame * N`` pairs. Returns ``(a, b, share)`` with ``a < b``, best overlap first.
    """
    quads = {i: footprint(ref_from[i], sizes[i]) for i in part}
    ordered = sorted(i for i in part if np.isfinite(quads[i]).all() and cv2.isContourConvex(quads[i].reshape(-1, 1, 2)))
    if len(ordered) < 2:
        return []
    lows = np.stack([quads[i].min(0) for i in ordered])  # F, 2 bounding boxes
    highs = np.stack([quads[i].max(0) for i in ordered])
    found = []
    # Bounding boxes reject most pairs before the exact polygon intersection, compared with numpy a block of rows
    # at a time against every frame: a Python loop over all F x F pairs costs seconds at 2,000 frames, and a
    # whole F x F comparison would hold F squared bytes.
    for start in range(0, len(ordered), BOX_BLOCK_ROWS):
        rows = slice(start, start + BOX_BLOCK_ROWS)
        apart = (lows[rows, None, :] > highs[None, :, :]).any(-1) | (lows[None, :, :] > highs[rows, None, :]).any(-1)
        row, column = np.nonzero(~apart)  # row-major: a ascending, then b
        row += start
        for ia, ib in zip(row.tolist(), column.tolist()):
            a, b = ordered[ia], ordered[ib]
            if b - a < 2 or (a, b) in known:  # b - a >= 2 also keeps a < b: ``ordered`` is sorted
                continue
            share = overlap_share(quads[a], quads[b])
            if share >= min_overlap:
                found.append((a, b, share))
    found.sort(key=lambda t: -t[2])
    taken: dict[int, int] = {}
    chosen = []
    for a, b, share in found:
        if taken.get(a, 0) < per_frame and taken.get(b, 0) < per_frame:
            chosen.append((a, b, share))
            taken[a] = taken.get(a, 0) + 1
            taken[b] = taken.get(b, 0) + 1
    return chosen
