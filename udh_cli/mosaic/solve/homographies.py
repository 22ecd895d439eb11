"""The global solve: all frame-to-reference homographies at once, from every estimated pair (loop closure).

Each pair ``b_from_a`` gives point correspondences ``p`` (in A) and ``q = b_from_a p`` (in B), sampled on a
3x3 grid over the part of A that B sees. The solve finds ``ref_from_frame`` for every frame but the
reference (held at the identity, which fixes the gauge) minimising the Huber-robust sum over pairs of
``|ref_from_a(p) - ref_from_b(q)|``, in reference-frame pixels, by Levenberg-Marquardt. Each homography is
parameterised by 8 entries (h33 = 1) in Hartley-normalised coordinates, so the normal equations are well
conditioned. They are 8 (N - 1) square but sparse (a pair ties two frames), and are assembled and solved
with scipy's sparse matrices, so memory and time grow with the pairs, not with N squared.

With anchors (GPS fixes, ground-control marks: :class:`~udh_cli.mosaic.georef.anchors.Anchors`) every frame is free, the reference too; the
anchors fix the plane instead, and the answer is expressed relative to the reference again (:func:`solve_part`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import cv2
import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

from udh_cli import geometry
from udh_cli.mosaic.georef.anchors import Anchors
from udh_cli.mosaic.georef.gps import fit_similarity
from udh_cli.mosaic.pairs.types import PairResult

GRID_POINTS = 3  # per side: 9 correspondences per pair
# Anchor residuals beyond this many of their sigmas count linearly: a GPS glitch or a mislabelled mark must not
# bend the mosaic. On copr's ground-control points, least squares instead (no Huber) pulled the mosaic 0.6 m
# closer to the points it was given but 0.4 m further from each point left out (docs/mosaic.md).
ANCHOR_HUBER_SIGMAS = 2.0
# Refits of the anchors' ground similarity: fitted to the chained centres alone, its scale and heading carry the
# chain's drift (seneca with GPS bridges: 46 m RMS from the fixes with one fit, 41 m with four; more changed nothing).
ANCHOR_ROUNDS = 4
# Anchors join a part's solve only when they lie on at least this many frames whose positions span an area (not
# a line). With every frame free, the pairs alone would let the plane shrink or shear; a few anchors cannot hold
# all of its 8 degrees of freedom: 4 tight anchors at a survey's corners let a test survey blow up to 1e5 px.
MIN_ANCHOR_FRAMES = 5
MIN_ANCHOR_SPREAD = 0.05  # the anchored positions' smaller principal extent, as a share of the larger
# An anchored solution whose pairs disagree by more than this many Huber widths on average is a collapse, not a
# compromise with the anchors (seneca's anchored pairs: 3.8 px mean): the part is solved from its pairs alone.
MAX_ANCHORED_PAIR_WIDTHS = 10.0


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


def frame_normaliser(size: tuple[int, int]) -> np.ndarray:
    """(3, 3) that centres a frame of ``size`` (width, height) and scales its longest side to 2."""
    w, h = size
    s = 2.0 / max(w, h)
    return np.array([[s, 0, -s * (w - 1) / 2], [0, s, -s * (h - 1) / 2], [0, 0, 1.0]])


def _projected(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, ...]:
    """(P, 8) homographies (h33 = 1) applied to (P, K, 2) points: x, y, the denominator w, u and v, each (P, K)."""
    g = params[:, None, :]  # P, 1, 8
    x, y = points[..., 0], points[..., 1]
    w = g[..., 6] * x + g[..., 7] * y + 1.0
    return x, y, w, (g[..., 0] * x + g[..., 1] * y + g[..., 2]) / w, (g[..., 3] * x + g[..., 4] * y + g[..., 5]) / w


def _project(params: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, 8) homographies (h33 = 1) applied to (P, K, 2) points -> (P, K, 2), without the Jacobian (the cost alone)."""
    _, _, _, u, v = _projected(params, points)
    return np.stack([u, v], -1)


def _project_with_jacobian(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points by 8-parameter homographies, batched.

    Args:
        params: (P, 8) one homography per pair (h33 = 1).
        points: (P, K, 2).

    Returns:
        projected (P, K, 2) and the Jacobian with respect to the parameters (P, K, 2, 8).
    """
    x, y, w, u, v = _projected(params, points)
    zero = np.zeros_like(x)
    du = np.stack([x / w, y / w, 1 / w, zero, zero, zero, -u * x / w, -u * y / w], -1)
    dv = np.stack([zero, zero, zero, x / w, y / w, 1 / w, -v * x / w, -v * y / w], -1)
    return np.stack([u, v], -1), np.stack([du, dv], -2)


def huber(errors: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
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
        anchors: map positions of points of the part's frames, GPS fixes or ground-control observations (used
            when they are on at least :data:`MIN_ANCHOR_FRAMES` frames of the part spread over an area).
            Why: the pairs fix every frame relative to its neighbours, but leave the part free to bend by an
            almost global homography that only the reference frame's own pairs resist: the projective drift
            of long chains, invisible in their loop consistency. The fixes lie on the flat ground, where the
            map is a similarity. So with anchors the frames are solved in a plane that a similarity (fitted
            to the chained centres, then refitted to the solved ones, :data:`ANCHOR_ROUNDS`) maps onto the
            fixes, each anchored point pulled towards its position, the reference frame free like the others;
            the solution is then expressed in the reference frame's pixels again. A solution whose pairs
            disagree by :data:`MAX_ANCHORED_PAIR_WIDTHS` Huber widths on average is a collapse, and the part is
            solved from its pairs alone.

    Returns:
        frame -> refined ``ref_from_frame`` (3, 3), h33 = 1; the reference stays the identity.
    """
    frames = [i for i in sorted(initial) if i != reference]
    anchored = [] if anchors is None else [row for row, frame in enumerate(anchors.frames) if int(frame) in initial]
    if anchored and not anchors_hold(anchors, anchored):
        anchored = []
    if not frames or not (points or anchored):
        return dict(initial)
    n = len(frames)
    slot = {frame: k for k, frame in enumerate(frames)}
    slot[reference] = n  # the reference's slot: fixed (dropped from the system) unless anchors hold the part
    free = n + 1 if anchored else n
    t_ref = frame_normaliser(sizes[reference])
    normalisers = {i: frame_normaliser(sizes[i]) for i in initial}
    params = np.zeros((n + 1, 8))
    for i in initial:
        g = t_ref @ initial[i] @ np.linalg.inv(normalisers[i])
        params[slot[i]] = (g / g[2, 2]).ravel()[:8]
    slot_a = np.array([slot[p.a] for p in points], dtype=int)
    slot_b = np.array([slot[p.b] for p in points], dtype=int)
    points_a = np.stack([geometry.transform_points(normalisers[p.a], p.points_a) for p in points]) if points else np.zeros((0, 1, 2))  # P, K, 2
    points_b = np.stack([geometry.transform_points(normalisers[p.b], p.points_b) for p in points]) if points else np.zeros((0, 1, 2))
    k = huber_px * t_ref[0, 0]  # in normalised reference units
    k_anchor = ANCHOR_HUBER_SIGMAS * t_ref[0, 0]  # an anchor's residual is in units of its sigma times t_ref[0, 0]
    if anchored:
        # Map metres centred and scaled like the frames; a fix sigma_m away weighs as a pair 1 px off would.
        targets, map_scale = anchor_targets(anchors, anchored)
        anchor_weight = (t_ref[0, 0] * map_scale / anchors.sigma_m[anchored])[:, None]  # A, 1
        anchor_frames = [int(anchors.frames[row]) for row in anchored]
        anchor_slots = np.array([slot[i] for i in anchor_frames])
        centres = np.stack([geometry.transform_points(normalisers[i], anchors.pixels[row][None])
                            for i, row in zip(anchor_frames, anchored)])  # A, 1, 2 in each frame's normalised coordinates
        ground = fit_similarity(_project(params[anchor_slots], centres)[:, 0], targets)[:2]  # 2 x 3

    def anchor_terms(current: np.ndarray):
        """Anchor residuals (A, 2) and their Jacobians for the frames (A, 2, 8)."""
        projected, jacobian = _project_with_jacobian(current[anchor_slots], centres)
        mapped = projected[:, 0] @ ground[:, :2].T + ground[:, 2]
        return anchor_weight * (mapped - targets), anchor_weight[:, :, None] * np.einsum("ij,ajk->aik", ground[:, :2], jacobian[:, 0])

    def cost_of(current: np.ndarray) -> float:
        total = 0.0
        if points:
            residual = _project(current[slot_a], points_a) - _project(current[slot_b], points_b)
            total += float(huber(np.sqrt((residual**2).sum(-1)), k)[0].sum())
        if anchored:
            total += float(huber(np.sqrt((anchor_terms(current)[0] ** 2).sum(-1)), k_anchor)[0].sum())
        return total

    # 8x8 block (row, column) indices inside the system, shared by every block.
    block_rows, block_cols = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")

    def normal_equations(current: np.ndarray):
        """The Gauss-Newton system (8 free x 8 free, scipy CSR: each pair touches two frames and each anchor one,
        so it is sparse and its memory and time grow with the pairs, not with n squared) and the gradient."""
        gradient = np.zeros((n + 1, 8))
        rows, cols, values = [], [], []

        def add(s1: np.ndarray, s2: np.ndarray, blocks: np.ndarray) -> None:
            keep = (s1 < free) & (s2 < free)  # a fixed reference's rows and columns are dropped
            rows.append((s1[keep, None, None] * 8 + block_rows).ravel())
            cols.append((s2[keep, None, None] * 8 + block_cols).ravel())
            values.append(blocks[keep].ravel())

        if points:
            proj_a, jac_a = _project_with_jacobian(current[slot_a], points_a)
            proj_b, jac_b = _project_with_jacobian(current[slot_b], points_b)
            residual = proj_a - proj_b  # P, K, 2
            _, weight = huber(np.sqrt((residual**2).sum(-1)), k)  # P, K
            # Sums over a pair's points and axes as batched products of (P, 2K, 8) rows: BLAS, where einsum loops.
            rows_of = {id(j): j.reshape(len(j), -1, 8) for j in (jac_a, jac_b)}
            for s1, j1, sign1 in ((slot_a, jac_a, 1.0), (slot_b, jac_b, -1.0)):
                weighted = (weight[..., None, None] * j1).reshape(len(j1), -1, 8)  # P, 2K, 8
                np.add.at(gradient, s1, sign1 * np.matmul(residual.reshape(len(j1), 1, -1), weighted)[:, 0])
                for s2, j2, sign2 in ((slot_a, jac_a, 1.0), (slot_b, jac_b, -1.0)):
                    add(s1, s2, sign1 * sign2 * np.matmul(weighted.transpose(0, 2, 1), rows_of[id(j2)]))
        if anchored:
            residual, jacobian = anchor_terms(current)
            _, weight = huber(np.sqrt((residual**2).sum(-1)), k_anchor)  # A
            np.add.at(gradient, anchor_slots, np.einsum("a,aij,ai->aj", weight, jacobian, residual))
            add(anchor_slots, anchor_slots, np.einsum("a,aij,ail->ajl", weight, jacobian, jacobian))
        system = sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(8 * free, 8 * free))
        return system, gradient[:free].ravel()

    def optimise(params: np.ndarray) -> np.ndarray:
        """Levenberg-Marquardt from ``params``, with the current ``ground`` similarity."""

        def moved(current: np.ndarray, step: np.ndarray) -> np.ndarray:
            trial = current.copy()
            trial[:free] += step.reshape(free, 8)
            return trial

        return levenberg_marquardt(params, cost_of, normal_equations, moved, iterations)

    params = optimise(params)
    for _ in range(ANCHOR_ROUNDS - 1 if anchored else 0):
        # The similarity was fitted to the chained centres, which drift; refitted to the solved ones, it lets
        # the frames settle at the scale and heading their pairs allow (block coordinate descent).
        ground = fit_similarity(_project(params[anchor_slots], centres)[:, 0], targets)[:2]
        params = optimise(params)
    out = {}
    for i in initial:
        g = np.append(params[slot[i]], 1.0).reshape(3, 3)
        out[i] = np.linalg.inv(t_ref) @ g @ normalisers[i]
    if anchored:  # the reference moved with the others: express every frame relative to it again
        back = np.linalg.inv(out[reference])
        for i in out:
            h = back @ out[i]
            out[i] = h / h[2, 2]
        if points and np.mean([pair_rms_px(out, p) for p in points]) > MAX_ANCHORED_PAIR_WIDTHS * huber_px:
            return solve_part(reference, initial, sizes, points, huber_px, iterations)
    out[reference] = np.eye(3)
    return out


def levenberg_marquardt(state, cost_of: Callable[[Any], float], normal_equations: Callable[[Any], tuple[sparse.spmatrix, np.ndarray]],
                        moved: Callable[[Any, np.ndarray], Any], iterations: int):
    """Levenberg-Marquardt with Marquardt's diagonal scaling, from ``state`` (any value ``moved`` understands).

    ``cost_of(state)``: the robust cost; ``normal_equations(state)``: the Gauss-Newton system (F, F) sparse
    and gradient (F,) over the free unknowns; ``moved(state, step)``: the state after a step (F,), or None when
    that state is not allowed. At most ``iterations`` steps; stops once a step improves the cost by less than
    1e-10 of it, or the damping passes 1e8. Returns the best state found.
    """
    damping = 1e-3
    cost = cost_of(state)
    system, gradient = normal_equations(state)
    for _ in range(iterations):
        diagonal = system.diagonal() + 1e-12
        try:
            step = solve_symmetric(system + sparse.diags(damping * diagonal), -gradient)
        except RuntimeError:  # SuperLU: an exactly singular factor
            step = None
        if step is None or not np.isfinite(step).all():
            damping *= 10
            continue
        trial = moved(state, step)
        trial_cost = np.inf if trial is None else cost_of(trial)
        if trial_cost < cost:
            improvement = (cost - trial_cost) / max(cost, 1e-30)
            state, cost = trial, trial_cost
            system, gradient = normal_equations(state)
            damping = max(damping / 3, 1e-9)
            if improvement < 1e-10:
                break
        else:
            damping *= 5
            if damping > 1e8:
                break
    return state


def solve_symmetric(matrix: sparse.spmatrix, rhs: np.ndarray) -> np.ndarray:
    """Solve the damped normal equations ``matrix @ x = rhs`` (symmetric positive definite, (8F, 8F) sparse).

    SuperLU in its symmetric mode: a minimum-degree ordering of the matrix's own graph and pivots kept on the
    diagonal. Why not ``spsolve``'s default (COLAMD, partial pivoting), which ignores the symmetry: on simulated
    lawn-mower surveys the solve took 40.1 s at 1,988 frames and 5.8 s at 504 with it, 12.6 s and 2.2 s like
    this, to the same solution within 1e-6 px. Why not a dense Cholesky for small systems: LAPACK's threads
    made a 41-frame flight's solves 20x slower on a busy machine (docs/benchmarks.md, "Speed"). SuperLU is scipy's own; a
    Cholesky (CHOLMOD) would need one more package. A zero pivot raises RuntimeError or leaves non-finite
    values, which the caller treats as a failed step.
    """
    factor = sparse_linalg.splu(sparse.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options={"SymmetricMode": True})
    return factor.solve(rhs)


def anchor_targets(anchors: Anchors, rows: list[int]) -> tuple[np.ndarray, float]:
    """The positions of anchors ``rows`` centred and divided by their largest offset, (A, 2), and that scale
    (metres): map coordinates of about 1, as the solves' normalised frames are."""
    fixes = anchors.positions[rows]
    map_scale = max(float(np.abs(fixes - fixes.mean(0)).max()), 1e-6)
    return (fixes - fixes.mean(0)) / map_scale, map_scale


def anchors_hold(anchors: Anchors, rows: list[int]) -> bool:
    """Whether anchors ``rows`` lie on :data:`MIN_ANCHOR_FRAMES` frames or more, spread over an area."""
    if len({int(anchors.frames[r]) for r in rows}) < MIN_ANCHOR_FRAMES:
        return False
    positions = anchors.positions[rows]
    extent = np.linalg.svd(positions - positions.mean(0), compute_uv=False)
    return bool(extent[0] > 0 and extent[-1] >= MIN_ANCHOR_SPREAD * extent[0])


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
