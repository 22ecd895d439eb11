"""The global solve: all frame-to-reference homographies at once, from every estimated pair (loop closure).

Each pair ``b_from_a`` gives point correspondences ``p`` (in A) and ``q = b_from_a p`` (in B), sampled on a
3x3 grid over the part of A that B sees. The solve finds ``ref_from_frame`` for every frame but the
reference (held at the identity, which fixes the gauge) minimising the Huber-robust sum over pairs of
``|ref_from_a(p) - ref_from_b(q)|``, in reference-frame pixels, by Levenberg-Marquardt. Each homography is
parameterised by 8 entries (h33 = 1) in Hartley-normalised coordinates, so the normal equations are well
conditioned. They are 8 (N - 1) square but sparse (a pair ties two frames), and are assembled and solved
with scipy's sparse matrices, so memory and time grow with the pairs, not with N squared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import warnings

import cv2
import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from udh_cli import geometry
from udh_cli.mosaic.georef import fit_similarity
from udh_cli.mosaic.pairs import PairResult

GRID_POINTS = 3  # per side: 9 correspondences per pair
MIN_ANCHORS = 4  # GPS fixes a part needs before they join its solve: the map homography needs four


@dataclass(frozen=True)
class Anchors:
    """Map positions that pull frame centres in the solve (GPS fixes), with their uncertainty.

    Attributes:
        positions: frame -> (2,) easting, northing in metres (a projected CRS, e.g. UTM).
        sigma_m: the fixes' standard error, metres: a fix this far from the solution costs as much as a pair
            correspondence 1 px off.
    """

    positions: dict[int, np.ndarray]
    sigma_m: float


@dataclass(frozen=True)
class PairPoints:
    """Correspondences of one pair: ``points_a`` (K, 2) in A's pixels, ``points_b`` (K, 2) in B's pixels."""

    a: int
    b: int
    points_a: np.ndarray
    points_b: np.ndarray


def pair_points(pair: PairResult, size_a: tuple[int, int], size_b: tuple[int, int]) -> PairPoints:
    """A 3x3 grid over the bounding box of the overlap (A's rectangle and B's footprint seen in A)."""
    rect_a = geometry.image_corners(*size_a).astype(np.float32)
    b_in_a = geometry.transform_points(geometry.invert(pair.b_from_a), geometry.image_corners(*size_b)).astype(np.float32)
    area, polygon = cv2.intersectConvexConvex(rect_a, b_in_a)
    if polygon is not None and area > 0.01 * cv2.contourArea(rect_a):
        low, high = polygon.reshape(-1, 2).min(0), polygon.reshape(-1, 2).max(0)
    else:  # no overlap left by the estimate: use A's corners (the residual then shows the disagreement)
        low, high = rect_a.min(0), rect_a.max(0)
    ticks = np.linspace(0.0, 1.0, GRID_POINTS)
    grid = np.stack(np.meshgrid(ticks, ticks), -1).reshape(-1, 2)
    points_a = low + grid * (high - low)
    return PairPoints(pair.a, pair.b, points_a, geometry.transform_points(pair.b_from_a, points_a))


def pair_rms_px(ref_from: dict[int, np.ndarray], points: PairPoints) -> float:
    """RMS distance in reference pixels between where A's and B's homographies put the same scene points."""
    diff = geometry.transform_points(ref_from[points.a], points.points_a) - geometry.transform_points(ref_from[points.b], points.points_b)
    return float(np.sqrt((diff**2).sum(-1).mean()))


def _normaliser(size: tuple[int, int]) -> np.ndarray:
    """Centre the frame and scale its longest side to 2."""
    w, h = size
    s = 2.0 / max(w, h)
    return np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]])


def _project_with_jacobian(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points by 8-parameter homographies, batched.

    Args:
        params: (P, 8) one homography per pair (h33 = 1).
        points: (P, K, 2).

    Returns:
        projected (P, K, 2) and the Jacobian with respect to the parameters (P, K, 2, 8).
    """
    g = params[:, None, :]  # P, 1, 8
    x, y = points[..., 0], points[..., 1]
    w = g[..., 6] * x + g[..., 7] * y + 1.0
    u = (g[..., 0] * x + g[..., 1] * y + g[..., 2]) / w
    v = (g[..., 3] * x + g[..., 4] * y + g[..., 5]) / w
    zero = np.zeros_like(x)
    du = np.stack([x / w, y / w, 1 / w, zero, zero, zero, -u * x / w, -u * y / w], -1)
    dv = np.stack([zero, zero, zero, x / w, y / w, 1 / w, -v * x / w, -v * y / w], -1)
    return np.stack([u, v], -1), np.stack([du, dv], -2)


def _huber(errors: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """Huber cost and IRLS weight of point residual norms (any shape)."""
    cost = np.where(errors <= k, 0.5 * errors**2, k * (errors - 0.5 * k))
    weight = np.where(errors <= k, 1.0, k / np.maximum(errors, 1e-12))
    return cost, weight


def solve_part(
    reference: int,
    initial: dict[int, np.ndarray],
    sizes: Sequence[tuple[int, int]],
    points: Sequence[PairPoints],
    huber_px: float = 2.0,
    iterations: int = 60,
    anchors: Anchors | None = None,
) -> dict[int, np.ndarray]:
    """Jointly refine ``ref_from_frame`` for the frames of one part.

    Args:
        reference: the frame held at the identity.
        initial: frame -> (3, 3) ``ref_from_frame`` (the chained estimate); its keys are the part.
        sizes: (width, height) of every frame, full resolution.
        points: correspondences of every accepted pair inside the part.
        huber_px: residuals beyond this many reference pixels count linearly (robust to bad pairs).
        anchors: GPS fixes of the part's frames (used when at least :data:`MIN_ANCHORS` are in the part):
            each frame's centre is pulled towards its fix through a map homography from the reference frame
            to the ground plane (a homography, not a similarity: the reference frame itself may look at the
            ground at a slant), solved with the frames. Chained homographies drift projectively over long
            sequences while their loops stay consistent; the fixes bound that drift.

    Returns:
        frame -> refined ``ref_from_frame`` (3, 3), h33 = 1; the reference stays the identity.
    """
    frames = [i for i in sorted(initial) if i != reference]
    anchored = [] if anchors is None else [i for i in sorted(initial) if i in anchors.positions]
    if len(anchored) < MIN_ANCHORS:
        anchored = []
    if not frames or not (points or anchored):
        return dict(initial)
    n = len(frames)
    slot = {frame: k for k, frame in enumerate(frames)}
    slot[reference] = n  # a dummy slot whose rows and columns are dropped: the reference is fixed
    t_ref = _normaliser(sizes[reference])
    normalisers = {i: _normaliser(sizes[i]) for i in initial}
    params = np.zeros((n + 1, 8))
    for i in initial:
        g = t_ref @ initial[i] @ np.linalg.inv(normalisers[i])
        params[slot[i]] = (g / g[2, 2]).ravel()[:8]
    slot_a = np.array([slot[p.a] for p in points], dtype=int)
    slot_b = np.array([slot[p.b] for p in points], dtype=int)
    points_a = np.stack([geometry.transform_points(normalisers[p.a], p.points_a) for p in points]) if points else np.zeros((0, 1, 2))  # P, K, 2
    points_b = np.stack([geometry.transform_points(normalisers[p.b], p.points_b) for p in points]) if points else np.zeros((0, 1, 2))
    k = huber_px * t_ref[0, 0]  # in normalised reference units
    size = 8 * n + (8 if anchored else 0)  # the map homography's 8 parameters follow the frames' parameters
    if anchored:
        # Map metres, centred and scaled like the frames; an anchor residual of sigma_m weighs as 1 px would.
        fixes = np.stack([anchors.positions[i] for i in anchored])
        map_mean, map_scale = fixes.mean(0), max(float(np.abs(fixes - fixes.mean(0)).max()), 1e-6)
        targets = (fixes - map_mean) / map_scale
        anchor_weight = t_ref[0, 0] / (anchors.sigma_m / map_scale)
        anchor_slots = np.array([slot[i] for i in anchored])
        centres = np.stack([geometry.transform_points(normalisers[i], np.array([[(sizes[i][0] - 1) / 2, (sizes[i][1] - 1) / 2]]))
                            for i in anchored])  # A, 1, 2 in each frame's normalised coordinates
        start_centres = _project_with_jacobian(params[anchor_slots], centres)[0][:, 0]
        # Started from the best similarity (closed form, and defined even for fixes along one line).
        map_params = (fit_similarity(start_centres, targets).ravel()[:8]).copy()
    else:
        map_params = np.zeros(0)

    def anchor_terms(current: np.ndarray, map_params: np.ndarray):
        """Anchor residuals (A, 2), their Jacobians for the frame (A, 2, 8) and the map homography (A, 2, 8)."""
        projected, jacobian = _project_with_jacobian(current[anchor_slots], centres)
        q, jacobian = projected[:, 0], jacobian[:, 0]  # A, 2 and A, 2, 8
        mapped, d_params = _project_with_jacobian(np.repeat(map_params[None], len(q), 0), q[:, None])
        mapped, d_params = mapped[:, 0], d_params[:, 0]
        g = map_params
        w = g[6] * q[:, 0] + g[7] * q[:, 1] + 1.0
        d_point = np.stack([np.stack([(g[0] - mapped[:, 0] * g[6]) / w, (g[1] - mapped[:, 0] * g[7]) / w], -1),
                            np.stack([(g[3] - mapped[:, 1] * g[6]) / w, (g[4] - mapped[:, 1] * g[7]) / w], -1)], -2)  # A, 2, 2
        residual = anchor_weight * (mapped - targets)
        return residual, anchor_weight * np.einsum("aij,ajk->aik", d_point, jacobian), anchor_weight * d_params

    def cost_of(current: np.ndarray, map_params: np.ndarray) -> float:
        total = 0.0
        if points:
            residual = _project_with_jacobian(current[slot_a], points_a)[0] - _project_with_jacobian(current[slot_b], points_b)[0]
            total += float(_huber(np.sqrt((residual**2).sum(-1)), k)[0].sum())
        if anchored:
            total += float(_huber(np.sqrt((anchor_terms(current, map_params)[0] ** 2).sum(-1)), k)[0].sum())
        return total

    # 8x8 block (row, column) indices inside the 8n x 8n system, shared by every pair's four blocks.
    block_rows, block_cols = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")

    def normal_equations(current: np.ndarray, map_params: np.ndarray):
        """The Gauss-Newton system (scipy CSR, ``size`` square: each pair touches two frames and each anchor one
        frame and the map homography, so it is sparse and its memory and time grow with the pairs, not with n
        squared) and the gradient (``size``,)."""
        # The gradient's layout: the frames, the reference's dummy slot (dropped), the map homography.
        gradient = np.zeros(8 * n + 8 + 8)
        rows, cols, values = [], [], []

        def add(slot_rows: np.ndarray, slot_cols: np.ndarray, blocks: np.ndarray) -> None:
            """Add (B, r, c) blocks at the given offsets of the system."""
            _, r, c = blocks.shape
            rows.append((slot_rows[:, None, None] + np.arange(r)[None, :, None] + np.zeros((1, 1, c), int)).ravel())
            cols.append((slot_cols[:, None, None] + np.zeros((1, r, 1), int) + np.arange(c)[None, None, :]).ravel())
            values.append(blocks.ravel())

        if points:
            proj_a, jac_a = _project_with_jacobian(current[slot_a], points_a)
            proj_b, jac_b = _project_with_jacobian(current[slot_b], points_b)
            residual = proj_a - proj_b  # P, K, 2
            _, weight = _huber(np.sqrt((residual**2).sum(-1)), k)  # P, K
            for s1, j1, sign1 in ((slot_a, jac_a, 1.0), (slot_b, jac_b, -1.0)):
                np.add.at(gradient, (s1[:, None] * 8 + np.arange(8)).ravel(),
                          (sign1 * np.einsum("pk,pkij,pki->pj", weight, j1, residual)).ravel())
                for s2, j2, sign2 in ((slot_a, jac_a, 1.0), (slot_b, jac_b, -1.0)):
                    keep = (s1 < n) & (s2 < n)  # the reference's dummy slot is fixed: its rows and columns are dropped
                    add(s1[keep] * 8, s2[keep] * 8, sign1 * sign2 * np.einsum("pk,pkij,pkil->pjl", weight[keep], j1[keep], j2[keep]))
        if anchored:
            residual, jac_frame, jac_map = anchor_terms(current, map_params)
            _, weight = _huber(np.sqrt((residual**2).sum(-1)), k)  # A
            free = anchor_slots < n
            at_map = np.full(int(free.sum()), 8 * n)
            np.add.at(gradient, (anchor_slots[free, None] * 8 + np.arange(8)).ravel(),
                      np.einsum("a,aij,ai->aj", weight[free], jac_frame[free], residual[free]).ravel())
            gradient[8 * n + 8:] += np.einsum("a,aij,ai->j", weight, jac_map, residual)
            add(anchor_slots[free] * 8, anchor_slots[free] * 8, np.einsum("a,aij,ail->ajl", weight[free], jac_frame[free], jac_frame[free]))
            cross = np.einsum("a,aij,ail->ajl", weight[free], jac_frame[free], jac_map[free])
            add(anchor_slots[free] * 8, at_map, cross)
            add(at_map, anchor_slots[free] * 8, cross.transpose(0, 2, 1))
            add(np.array([8 * n]), np.array([8 * n]), np.einsum("a,aij,ail->jl", weight, jac_map, jac_map)[None])
        if rows:
            system = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))
        else:
            system = sparse.csr_matrix((size, size))
        return system, np.r_[gradient[:8 * n], gradient[8 * n + 8:]] if anchored else gradient[:8 * n]

    damping = 1e-3
    cost = cost_of(params, map_params)
    system, gradient = normal_equations(params, map_params)
    for _ in range(iterations):
        diagonal = system.diagonal() + 1e-12
        with warnings.catch_warnings():
            warnings.simplefilter("error", sparse_linalg.MatrixRankWarning)
            try:
                step = sparse_linalg.spsolve((system + sparse.diags(damping * diagonal)).tocsc(), -gradient)
            except (sparse_linalg.MatrixRankWarning, RuntimeError):
                step = None
        if step is None or not np.isfinite(step).all():
            damping *= 10
            continue
        trial = params.copy()
        trial[:n] += step[:8 * n].reshape(n, 8)
        trial_map = map_params + step[8 * n:]
        trial_cost = cost_of(trial, trial_map)
        if trial_cost < cost:
            improvement = (cost - trial_cost) / max(cost, 1e-30)
            params, map_params, cost = trial, trial_map, trial_cost
            system, gradient = normal_equations(params, map_params)
            damping = max(damping / 3, 1e-9)
            if improvement < 1e-10:
                break
        else:
            damping *= 5
            if damping > 1e8:
                break
    out = {}
    for i in initial:
        g = np.append(params[slot[i]], 1.0).reshape(3, 3)
        h = np.linalg.inv(t_ref) @ g @ normalisers[i]
        out[i] = h / h[2, 2]
    out[reference] = np.eye(3)
    return out


def solve_with_rejection(
    reference: int,
    initial: dict[int, np.ndarray],
    sizes: Sequence[tuple[int, int]],
    points: Sequence[PairPoints],
    removable: Sequence[bool],
    huber_px: float = 2.0,
    outlier_px: float = 5.0,
    max_rounds: int = 4,
    max_candidates: int = 12,
    anchors: Anchors | None = None,
) -> tuple[dict[int, np.ndarray], dict[int, float]]:
    """:func:`solve_part`, then find and drop the loop-closure pairs that the other pairs contradict.

    A pair is strained when its residual after the solve exceeds ``outlier_px`` and 3x the median. Strained
    ``removable`` (loop-closure) pairs are dropped. But the Huber loss cannot always tell a wrong loop pair
    from the chain it bends, and then the chain carries the error instead. So, while sequential pairs are
    strained, each loop pair that spans a strained one in the sequence is left out in turn, the solve is
    re-run from the current solution, and the pair whose absence lowers the others' squared residuals the
    most is dropped, if that at least halves them.

    ``anchors``: GPS fixes that join every solve (:func:`solve_part`).

    Returns the solution and ``{index into points: residual px}`` of the dropped pairs.
    """
    active = list(range(len(points)))
    dropped: dict[int, float] = {}
    solved = solve_part(reference, initial, sizes, points, huber_px, anchors=anchors)
    for _ in range(max_rounds):
        residuals = {i: pair_rms_px(solved, points[i]) for i in active}
        if not residuals:
            break
        limit = max(outlier_px, 3.0 * float(np.median(list(residuals.values()))))
        strained = [i for i in active if residuals[i] > limit]
        if not strained:
            break
        strained_loops = [i for i in strained if removable[i]]
        if strained_loops:  # loop pairs far off the joint solution: wrong or parallax-ridden matches
            for i in strained_loops:
                dropped[i] = residuals[i]
                active.remove(i)
            solved = solve_part(reference, solved, sizes, [points[i] for i in active], huber_px, anchors=anchors)
            continue
        spans = [(min(points[i].a, points[i].b), max(points[i].a, points[i].b)) for i in strained]
        candidates = [i for i in active if removable[i] and any(max(lo, min(points[i].a, points[i].b)) <= min(hi, max(points[i].a, points[i].b)) for lo, hi in spans)]
        candidates = sorted(candidates, key=lambda i: -residuals[i])[:max_candidates]
        best, best_ratio, best_solution = None, 0.5, None
        for candidate in candidates:
            rest = [i for i in active if i != candidate]
            before = sum(residuals[i] ** 2 for i in rest)
            trial = solve_part(reference, solved, sizes, [points[i] for i in rest], huber_px, iterations=20, anchors=anchors)
            ratio = sum(pair_rms_px(trial, points[i]) ** 2 for i in rest) / max(before, 1e-12)
            if ratio < best_ratio:
                best, best_ratio, best_solution = candidate, ratio, trial
        if best is None:
            break
        dropped[best] = residuals[best]
        active.remove(best)
        solved = solve_part(reference, best_solution, sizes, [points[i] for i in active], huber_px, anchors=anchors)
    return solved, dropped


def summarise(values: Sequence[float]) -> dict[str, float | int | None]:
    """count, mean, median and max of a list of pixel figures (``None`` when empty)."""
    if not values:
        return {"count": 0, "mean_px": None, "median_px": None, "max_px": None}
    array = np.asarray(values, dtype=np.float64)
    return {"count": int(array.size), "mean_px": float(array.mean()), "median_px": float(np.median(array)), "max_px": float(array.max())}
