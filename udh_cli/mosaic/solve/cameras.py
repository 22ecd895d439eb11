"""The camera-model solve: every frame a pinhole camera over one flat ground, instead of a free homography.

Why: the homography solve (:mod:`.homographies`) gives every frame 8 free parameters. Its pairs fix each frame
relative to its neighbours, but a long survey can still bend by small perspective errors that compound from
pair to pair (projective drift), which their loops do not show (the scale benchmark in docs/benchmarks.md).
A camera looking at a flat ground has 6 degrees of freedom (a rotation and a position), and all the frames of a
flight share one focal length; that bend is no motion of any camera, so this model cannot make it. It is what a
structure-from-motion bundle adjustment (OpenSfM in ODM) does over a planar scene, with the pairs' grid
correspondences in place of tracked points. Where the ground is not flat (relief, buildings, a forest's
canopy) the model fits the pairs less tightly than free homographies do.

Conventions: those of :mod:`udh_cli.simulate` (its module docstring), which renders the simulated flights
with the same cameras: ``frame_from_ground = K R [[1, 0, -X], [0, 1, -Y], [0, 0, Z]]``, Z into the ground, a
Rodrigues vector for ``R``, the principal point at the frame's centre and one focal length ``f`` in pixels for
all frames. The ground's units are the reference frame's pixels where it looks straight down: the reference
camera starts at ``R = I``, ``(X, Y)`` at its centre and ``Z = f``, so the homography solve's plane is the
starting ground. The reference keeps its ``X``, ``Y``, ``Z`` and the Rodrigues vector's third entry (the gauge:
a similarity of the ground); its roll and pitch, which the homography solve could not tell, are solved with
the others.

The Jacobian is taken by central differences, each of the 6 camera parameters moved in every frame at once (a
residual sees at most two frames; 12 batched evaluations of every pair's points), and the Levenberg-Marquardt of
the homography solve (:func:`.homographies.levenberg_marquardt`) runs on the sparse normal equations, with the same
Huber loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
from scipy import sparse

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.georef.gps import fit_similarity
from udh_cli.mosaic.inputs.lens_fit import DEFAULT_FOCAL
from udh_cli.mosaic.solve.homographies import ANCHOR_HUBER_SIGMAS, Anchors, PairPoints, anchor_targets, anchors_hold, huber, levenberg_marquardt

PARAMETERS = 6  # per frame: Rodrigues vector (3), X, Y, Z
GAUGE = (2, 3, 4, 5)  # the reference's parameters held fixed: its yaw, X, Y and Z
# Central-difference steps: radians for the rotation; a share of the altitude for the position and of f for f.
ROTATION_STEP = 1e-6
POSITION_STEP = 1e-6
# Levenberg-Marquardt iterations at most. A solved focal length trades with the cameras' tilts along a shallow
# valley, which needs about 200 (tests/mosaic/solve/test_cameras.py); with it held the solve stops far sooner, once
# a step gains less than 1e-10 of the cost.
ITERATIONS = 200


@dataclass(frozen=True)
class CameraSolution:
    """What the camera solve found.

    Attributes:
        ref_from: frame -> (3, 3) ``ref_from_frame``, h33 = 1, the reference the identity.
        ground_from_ref: (3, 3) from the reference frame's pixels to the ground plane (units: about one reference
            pixel at nadir), the homography that draws the map on the ground instead of in the reference's view.
        focal_px: the focal length used, pixels (held, or solved with ``solve_focal``).
        tilt_deg: frame -> how far its optical axis is from straight down, degrees.
    """

    ref_from: dict[int, np.ndarray]
    ground_from_ref: np.ndarray
    focal_px: float
    tilt_deg: dict[int, float]


def rotations(rvecs: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 3) Rodrigues vectors, exact near zero too. Why not OpenCV's Rodrigues:
    it takes one vector a call, and the Jacobian needs every frame's rotation 12 times an iteration."""
    theta = np.linalg.norm(rvecs, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    x, y, z = rvecs[:, 0], rvecs[:, 1], rvecs[:, 2]
    zero = np.zeros_like(x)
    skew = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)
    return np.eye(3) + a[:, None, None] * skew + b[:, None, None] * (skew @ skew)


def ground_from_frame(params: np.ndarray, focal: float, centres: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``ground_from_frame`` of cameras ``params`` (N, 6) with focal length ``focal`` px and principal
    points ``centres`` (N, 2) px: the inverse of ``K R [[1, 0, -X], [0, 1, -Y], [0, 0, Z]]``."""
    n = len(params)
    k_inv = np.zeros((n, 3, 3))
    k_inv[:, 0, 0] = k_inv[:, 1, 1] = 1.0 / focal
    k_inv[:, :2, 2] = -centres / focal
    k_inv[:, 2, 2] = 1.0
    x, y, z = params[:, 3], params[:, 4], params[:, 5]
    m_inv = np.zeros((n, 3, 3))
    m_inv[:, 0, 0] = m_inv[:, 1, 1] = 1.0
    m_inv[:, 0, 2], m_inv[:, 1, 2], m_inv[:, 2, 2] = x / z, y / z, 1.0 / z
    return m_inv @ np.transpose(rotations(params[:, :3]), (0, 2, 1)) @ k_inv


def camera_from_homography(frame_from_ground: np.ndarray, focal: float, centre: np.ndarray) -> np.ndarray:
    """(6,) the camera nearest a (3, 3) ``frame_from_ground``: its rotation's first two columns are the nearest
    orthonormal pair to ``K^-1 H``'s (a polar decomposition), its position from the third column."""
    k_inv = np.array([[1 / focal, 0, -centre[0] / focal], [0, 1 / focal, -centre[1] / focal], [0, 0, 1.0]])
    m = k_inv @ frame_from_ground
    u, s, vt = np.linalg.svd(m[:, :2], full_matrices=False)
    scale = float(s.mean())
    r12 = u @ vt
    rotation = np.column_stack([r12, np.cross(r12[:, 0], r12[:, 1])])
    position = rotation.T @ m[:, 2] / scale  # (-X, -Y, Z)
    if position[2] < 0:  # the homography's sign is free: the camera is above the ground
        rotation[:, :2] *= -1
        position = rotation.T @ (-m[:, 2]) / scale
    rvec = cv2.Rodrigues(rotation)[0].ravel()  # OpenCV's: exact at a half turn too, where the trace formula is not
    return np.array([*rvec, -position[0], -position[1], position[2]])


def _project(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, K, 2) of (P, K, 2) points through (P, 3, 3) homographies."""
    mapped = np.einsum("pij,pkj->pki", h[:, :, :2], points) + h[:, None, :, 2]
    return mapped[..., :2] / mapped[..., 2:]


def solve_cameras(
    reference: int,
    initial: dict[int, np.ndarray],
    sizes: Sequence[tuple[int, int]],
    points: Sequence[PairPoints],
    focal_px: float | None = None,
    huber_px: float = 2.0,
    iterations: int = ITERATIONS,
    solve_focal: bool = False,
    anchors: Anchors | None = None,
) -> CameraSolution:
    """Refine a part's ``ref_from_frame`` (``initial``, from the homography solve) as cameras over a flat ground.

    Args:
        reference: the part's reference frame.
        initial: frame -> (3, 3) ``ref_from_frame``; its keys are the part.
        sizes: (width, height) of every frame, full resolution; the part's frames must share one.
        points: correspondences of every accepted pair inside the part (:func:`.homographies.pair_points`).
        focal_px: the focal length, pixels (None: :data:`DEFAULT_FOCAL` of the longer side).
        huber_px: residuals beyond this many ground units (about reference pixels) count linearly.
        solve_focal: solve the focal length too, from ``focal_px``. Off by default: a nadir survey shows it only
            through its few degrees of tilt, so the map hardly depends on it, and on real flights a solved focal
            length ran off to absorb what the model lacks, lens distortion and relief (docs/mosaic.md).
        anchors: map positions of points of the part's frames (GPS fixes, ground-control observations), used as
            :func:`.homographies.solve_part` uses them: when they lie on enough frames spread over an area, each pulls
            its point, through a similarity from the ground to the map solved with the cameras, towards its
            position; an anchor ``sigma_m`` off costs as much as a pair 1 px off. Why, when the cameras cannot
            bend: a long chain can still drift in scale and heading.

    Raises :class:`UdhError` when the frames differ in size (one camera is assumed) or the solve does not give
    finite cameras.
    """
    frames = sorted(initial)
    if len({sizes[i] for i in frames}) > 1:
        raise UdhError("the camera-model solve assumes one camera, and this part's frames differ in size; use --solve homography")
    width, height = sizes[reference]
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    focal = float(focal_px or DEFAULT_FOCAL * max(width, height))
    n = len(frames)
    slot = {frame: k for k, frame in enumerate(frames)}
    ref_slot = slot[reference]
    ref_inverse = geometry.invert(initial[reference])
    params = np.stack([camera_from_homography(geometry.invert(ref_inverse @ initial[i]), focal, centre) for i in frames])
    centres = np.tile(centre, (n, 1))
    if not points:
        return _solution(frames, reference, params, focal, centres)

    slot_a = np.array([slot[p.a] for p in points])
    slot_b = np.array([slot[p.b] for p in points])
    points_a = np.stack([p.points_a for p in points])  # P, K, 2
    points_b = np.stack([p.points_b for p in points])
    pairs, per_pair = points_a.shape[:2]
    anchored = [] if anchors is None else [row for row, frame in enumerate(anchors.frames) if int(frame) in initial]
    if anchored and not anchors_hold(anchors, anchored):
        anchored = []
    anchor_slots = np.array([slot[int(anchors.frames[row])] for row in anchored], int)
    anchor_pixels = anchors.pixels[anchored][:, None, :] if anchored else np.zeros((0, 1, 2))  # A, 1, 2
    targets, anchor_weight, to_map = np.zeros((0, 2)), np.zeros((0, 1)), np.zeros(4)
    if anchored:
        targets, map_scale = anchor_targets(anchors, anchored)
        anchor_weight = (map_scale / anchors.sigma_m[anchored])[:, None]  # A, 1: an anchor sigma_m off weighs as 1 px
        on_ground = _project(ground_from_frame(params, focal, centres)[anchor_slots], anchor_pixels)[:, 0]
        similarity = fit_similarity(on_ground, targets)
        to_map = np.array([similarity[0, 0], similarity[0, 1], similarity[0, 2], similarity[1, 2]])
    # The unknowns, one vector: every frame's 6, the focal length, then the similarity from the ground to the map
    # (p, q, tx, ty: map = [[p, q], [q, -p]] ground + t, a reflection as the map's y points up), with anchors only.
    focal_column = n * PARAMETERS
    map_columns = focal_column + 1 + np.arange(4)
    fixed = np.zeros(focal_column + 5, bool)
    fixed[[ref_slot * PARAMETERS + j for j in GAUGE]] = True
    fixed[focal_column] = not solve_focal
    fixed[map_columns] = not anchored
    free_index = np.cumsum(~fixed) - 1
    free = int((~fixed).sum())
    pair_rows = np.arange(pairs * per_pair * 2).reshape(pairs, per_pair, 2)
    anchor_rows = pair_rows.size + np.arange(len(anchored) * 2).reshape(len(anchored), 2)

    def split(state: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        return state[:focal_column].reshape(n, PARAMETERS), float(state[focal_column]), state[map_columns]

    def residuals(state: np.ndarray, ground_from: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Pair residuals (P, K, 2), ground units, and anchor residuals (A, 2), 1 per sigma; ``ground_from``:
        the frames' (N, 3, 3) when already computed."""
        cameras, f, (p, q, tx, ty) = split(state)
        g = ground_from_frame(cameras, f, centres) if ground_from is None else ground_from
        pair = _project(g[slot_a], points_a) - _project(g[slot_b], points_b)
        x, y = _project(g[anchor_slots], anchor_pixels)[:, 0].T
        on_map = np.stack([p * x + q * y + tx, q * x - p * y + ty], -1)
        return pair, anchor_weight * (on_map - targets)

    def cost_of(state: np.ndarray) -> float:
        pair, anchor = residuals(state)
        return float(huber(np.linalg.norm(pair, axis=-1), huber_px)[0].sum() + huber(np.linalg.norm(anchor, axis=-1), ANCHOR_HUBER_SIGMAS)[0].sum())

    def normal_equations(state: np.ndarray):
        """The Gauss-Newton system over the free unknowns (sparse: a pair ties two frames, an anchor one frame and
        the similarity, the focal length all) and its gradient; the Jacobian by central differences, each
        frame's parameter moved in all frames at once (a residual sees at most two frames)."""
        cameras, f, (p, q, _, _) = split(state)
        ground_from = ground_from_frame(cameras, f, centres)
        pair, anchor = residuals(state, ground_from)
        pair_weight = huber(np.linalg.norm(pair, axis=-1), huber_px)[1]  # P, K
        anchor_weight_now = huber(np.linalg.norm(anchor, axis=-1), ANCHOR_HUBER_SIGMAS)[1]  # A
        derivative_a = np.empty((pairs, per_pair, 2, PARAMETERS))
        derivative_b = np.empty((pairs, per_pair, 2, PARAMETERS))
        derivative_anchor = np.empty((len(anchored), 2, PARAMETERS))
        linear = np.array([[p, q], [q, -p]])
        for j in range(PARAMETERS):
            step = np.full(n, ROTATION_STEP) if j < 3 else POSITION_STEP * cameras[:, 5]
            shifted = []
            for sign in (1.0, -1.0):
                moved = cameras.copy()
                moved[:, j] += sign * step
                shifted.append(ground_from_frame(moved, f, centres))
            derivative_a[..., j] = (_project(shifted[0][slot_a], points_a) - _project(shifted[1][slot_a], points_a)) / (2 * step[slot_a, None, None])
            derivative_b[..., j] = -(_project(shifted[0][slot_b], points_b) - _project(shifted[1][slot_b], points_b)) / (2 * step[slot_b, None, None])
            moved_on_ground = _project(shifted[0][anchor_slots], anchor_pixels)[:, 0] - _project(shifted[1][anchor_slots], anchor_pixels)[:, 0]
            derivative_anchor[..., j] = anchor_weight * (moved_on_ground @ linear.T) / (2 * step[anchor_slots, None])
        derivative_f = [np.zeros_like(pair), np.zeros_like(anchor)]  # (P, K, 2), (A, 2): nothing when it is held
        if solve_focal:
            f_step = POSITION_STEP * f
            plus, minus = state.copy(), state.copy()
            plus[focal_column] += f_step
            minus[focal_column] -= f_step
            derivative_f = [(a - b) / (2 * f_step) for a, b in zip(residuals(plus), residuals(minus))]
        x, y = _project(ground_from[anchor_slots], anchor_pixels)[:, 0].T
        one, zero = np.ones_like(x), np.zeros_like(x)
        derivative_map = anchor_weight[..., None] * np.stack([np.stack([x, y, one, zero], -1), np.stack([-y, x, zero, one], -1)], 1)  # A, 2, 4
        columns_a = slot_a[:, None] * PARAMETERS + np.arange(PARAMETERS)  # P, 6
        columns_b = slot_b[:, None] * PARAMETERS + np.arange(PARAMETERS)
        columns_anchor = anchor_slots[:, None] * PARAMETERS + np.arange(PARAMETERS)  # A, 6
        blocks = [  # (rows, columns, values), each broadcast to its values' shape
            (pair_rows[..., None], columns_a[:, None, None, :], derivative_a),
            (pair_rows[..., None], columns_b[:, None, None, :], derivative_b),
            (pair_rows, focal_column, derivative_f[0]),
            (anchor_rows[..., None], columns_anchor[:, None, :], derivative_anchor),
            (anchor_rows, focal_column, derivative_f[1]),
            (anchor_rows[..., None], map_columns, derivative_map),
        ]
        all_rows = np.concatenate([np.broadcast_to(r, v.shape).ravel() for r, _, v in blocks])
        all_columns = np.concatenate([np.broadcast_to(c, v.shape).ravel() for _, c, v in blocks])
        all_values = np.concatenate([v.ravel() for _, _, v in blocks])
        keep = ~fixed[all_columns]
        jacobian = sparse.csr_matrix((all_values[keep], (all_rows[keep], free_index[all_columns[keep]])),
                                     shape=(pair_rows.size + anchor_rows.size, free))
        row_weight = np.concatenate([np.repeat(pair_weight.ravel(), 2), np.repeat(anchor_weight_now, 2)])
        residual = np.concatenate([pair.ravel(), anchor.ravel()])
        return (jacobian.T @ (sparse.diags(row_weight) @ jacobian)).tocsc(), jacobian.T @ (row_weight * residual)

    def moved(state: np.ndarray, step: np.ndarray) -> np.ndarray | None:
        trial = state.copy()
        trial[~fixed] += step
        cameras, f, _ = split(trial)
        return trial if f > 0 and (cameras[:, 5] > 0).all() else None  # above the ground, a positive focal length

    state = levenberg_marquardt(np.concatenate([params.ravel(), [focal], to_map]), cost_of, normal_equations, moved, iterations)
    params, focal, _ = split(state)
    return _solution(frames, reference, params, focal, centres)


def _solution(frames: list[int], reference: int, params: np.ndarray, focal: float, centres: np.ndarray) -> CameraSolution:
    ground_from = ground_from_frame(params, focal, centres)
    if not np.isfinite(ground_from).all():
        raise UdhError("the camera-model solve did not converge to finite cameras; use --solve homography")
    slot = {frame: k for k, frame in enumerate(frames)}
    ref_from_ground = np.linalg.inv(ground_from[slot[reference]])
    ref_from = {}
    for i in frames:
        h = ref_from_ground @ ground_from[slot[i]]
        ref_from[i] = h / h[2, 2]
    ref_from[reference] = np.eye(3)
    ground_from_ref = ground_from[slot[reference]] / ground_from[slot[reference]][2, 2]
    axes = rotations(params[:, :3])[:, 2, :]  # each camera's optical axis in ground coordinates (row 3 of R)
    tilt = np.degrees(np.arccos(np.clip(np.abs(axes[:, 2]), 0.0, 1.0)))
    return CameraSolution(ref_from, ground_from_ref, float(focal), {i: float(tilt[slot[i]]) for i in frames})
