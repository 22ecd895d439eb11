"""The one geometry core of udh: pure functions shared by training (torch) and inference (numpy).

Conventions (stated here once; every other module follows them)
----------------------------------------------------------------
* **Pixels.** Points are ``(x, y)`` in OpenCV's pixel convention: integer coordinates sit at pixel
  *centres*, the origin is the centre of the top-left pixel, x points right and y points down.
* **Direction.** A homography named ``b_from_a`` (3x3) maps pixel coordinates of image A to pixel
  coordinates of image B: ``x_B ~ H x_A``. A scene point seen at ``x_A`` in A is seen at ``x_B`` in B.
  This is the direction of ``cv2.findHomography(points_in_a, points_in_b)`` and of
  ``cv2.warpPerspective(image_a, b_from_a, size_b)``, which renders A in B's frame.
  Every homography that udh returns, stores or prints is ``b_from_a``, in pixels of the images given.
  The paper's ``H_AB`` samples A at ``H(x)`` for pixels ``x`` of B: it is our ``a_from_b``, the inverse.
* **Corners.** Order is top-left, top-right, bottom-right, bottom-left (clockwise on screen), at the
  centres of the corner pixels: ``(0, 0), (w-1, 0), (w-1, h-1), (0, h-1)``.
* **4-point parameterisation.** ``offsets`` of shape ``(..., 4, 2)``, in pixels: ``b_from_a`` maps
  corner ``i`` of A to ``corners[i] + offsets[i]`` in B.
* **Normalised coordinates** (torch ``grid_sample`` with ``align_corners=False``):
  ``u = (2x + 1) / w - 1``, so -1 and +1 are the outer edges of the image, not pixel centres.
* **Resizing.** An image resized from ``(w, h)`` to ``(w', h')`` maps ``x`` to ``(w'/w)(x + 0.5) - 0.5``,
  which is what ``cv2.resize`` does. Homographies are rescaled with exactly this map.

The functions accept numpy arrays or torch tensors and return the same kind, so the Tensor DLT used in
training is the very code used at inference (numpy calls of up to 8 pairs, the batch-1 case, take a closed
form of the same unique solution, tested equal to it). The exceptions build or check one 3x3 matrix in numpy
only: ``resize_matrix``, ``rescale_homography``, ``translation``, ``mirror_matrix`` and
``is_valid_homography``. torch is never imported here: a tensor argument means the caller already imported it.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

Array = Any  # numpy.ndarray or torch.Tensor; the functions return the kind they are given


def _xp(x: Array):
    """The array namespace of ``x``: numpy, or torch when ``x`` is a tensor."""
    if type(x).__module__.startswith("torch"):
        return sys.modules["torch"]
    return np


def _like(values, like: Array) -> Array:
    """``values`` as an array of the same kind, dtype and device as ``like``."""
    xp = _xp(like)
    if xp is np:
        return np.asarray(values, dtype=like.dtype if np.issubdtype(like.dtype, np.floating) else np.float64)
    return xp.as_tensor(values, dtype=like.dtype, device=like.device)


# --------------------------------------------------------------------------------------- corners


def image_corners(width: int, height: int, like: Array | None = None) -> Array:
    """The four corner-pixel centres of a ``width`` x ``height`` image, shape (4, 2), in corner order."""
    c = [[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0], [0.0, height - 1.0]]
    return np.asarray(c, dtype=np.float64) if like is None else _like(c, like)


# ------------------------------------------------------------------------------------ transforms


def to_homogeneous(points: Array) -> Array:
    """(..., N, 2) -> (..., N, 3) with a trailing 1."""
    xp = _xp(points)
    return xp.concatenate([points, xp.ones_like(points[..., :1])], -1)


def transform_points(homography: Array, points: Array) -> Array:
    """Apply ``homography`` (..., 3, 3) to ``points`` (..., N, 2); returns (..., N, 2).

    Points that map to infinity (w == 0) come back non-finite; callers that need finite output check it.
    """
    xp = _xp(points)
    projected = to_homogeneous(points) @ xp.swapaxes(homography, -1, -2)  # ..., N, 3
    return projected[..., :2] / projected[..., 2:3]


def homography_jacobian(homography: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(2, 2) derivative of ``homography`` (3, 3) at ``point`` (2,), pixels per pixel."""
    x = np.array([point[0], point[1], 1.0])
    w = float(homography[2] @ x)
    mapped = (homography[:2] @ x) / w
    return (homography[:2, :2] - np.outer(mapped, homography[2, :2])) / w


def invert(homography: Array) -> Array:
    """Inverse homography, scaled so that h33 = 1 where that is possible. (..., 3, 3)."""
    xp = _xp(homography)
    inverse = xp.linalg.inv(homography)
    return inverse / inverse[..., 2:3, 2:3]


# ---------------------------------------------------------------------------------- Tensor DLT


def _similarity_normaliser(points: Array) -> Array:
    """Hartley normalisation (..., 3, 3): centre the points and scale their mean distance to sqrt(2).

    Solving the DLT in these coordinates keeps the 8x8 system well conditioned in float32.
    """
    xp = _xp(points)
    centre = points.mean(-2)  # ..., 2
    spread = xp.sqrt(((points - centre[..., None, :]) ** 2).sum(-1)).mean(-1)  # ...
    scale = (2.0**0.5) / (spread + 1e-12)
    zero = xp.zeros_like(scale)
    one = xp.ones_like(scale)
    rows = [
        xp.stack([scale, zero, -scale * centre[..., 0]], -1),
        xp.stack([zero, scale, -scale * centre[..., 1]], -1),
        xp.stack([zero, zero, one], -1),
    ]
    return xp.stack(rows, -2)


SMALL_BATCH = 8  # numpy batches up to this many pairs take the closed form (the 8x8 solve's overhead was a fifth of an estimate)


def homography_from_points(src: Array, dst: Array) -> Array:
    """Tensor DLT: the homography mapping four ``src`` points onto four ``dst`` points.

    Args:
        src: (..., 4, 2) pixel points.
        dst: (..., 4, 2) pixel points.

    Returns:
        (..., 3, 3) with h33 = 1, ``dst ~ H src``. It solves the 8x8 linear system with h33 fixed to 1
        (the paper's Tensor DLT), batched, in Hartley-normalised coordinates. Differentiable in torch.
        Degenerate input (three collinear points) gives a singular system: numpy raises
        ``LinAlgError`` and torch returns non-finite values; :func:`is_valid_homography` catches both.
    """
    xp = _xp(src)
    if xp is np and src.ndim >= 2 and src.size <= 8 * SMALL_BATCH and src.shape == dst.shape and src.shape[-2:] == (4, 2):
        return _homographies_closed_form(src, dst)
    t_src = _similarity_normaliser(src)
    t_dst = _similarity_normaliser(dst)
    s = transform_points(t_src, src)
    d = transform_points(t_dst, dst)
    x, y = s[..., 0], s[..., 1]
    u, v = d[..., 0], d[..., 1]
    one, zero = xp.ones_like(x), xp.zeros_like(x)
    rows_u = xp.stack([x, y, one, zero, zero, zero, -u * x, -u * y], -1)  # ..., 4, 8
    rows_v = xp.stack([zero, zero, zero, x, y, one, -v * x, -v * y], -1)
    system = xp.concatenate([rows_u, rows_v], -2)  # ..., 8, 8
    rhs = xp.concatenate([u, v], -1)[..., None]  # ..., 8, 1
    h = xp.linalg.solve(system, rhs)[..., 0]  # ..., 8
    h_norm = xp.concatenate([h, xp.ones_like(h[..., :1])], -1).reshape(h.shape[:-1] + (3, 3))
    homography = xp.linalg.inv(t_dst) @ h_norm @ t_src
    return homography / homography[..., 2:3, 2:3]


def _square_to_quad(quad: list[list[float]]) -> list[list[float]]:
    """The homography taking the unit square's corners (0,0), (1,0), (1,1), (0,1) to ``quad``'s four points.

    Heckbert's closed form (1989): the unique answer of the same 8x8 system, in plain floats. Raises
    ``LinAlgError`` when three of the points are collinear, as ``numpy.linalg.solve`` does."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = quad
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    den = dx1 * dy2 - dx2 * dy1
    if den == 0.0:  # NaN input gives NaN output, as the 8x8 solve does
        raise np.linalg.LinAlgError("Singular matrix: collinear points")
    g = (dx3 * dy2 - dx2 * dy3) / den
    h = (dx1 * dy3 - dx3 * dy1) / den
    return [[x1 - x0 + g * x1, x3 - x0 + h * x3, x0], [y1 - y0 + g * y1, y3 - y0 + h * y3, y0], [g, h, 1.0]]


def _homographies_closed_form(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """:func:`homography_from_points` for a few numpy pairs: ``dst_from_square . square_from_src``."""
    out = np.empty(src.shape[:-2] + (3, 3), dtype=np.float64)
    flat_src, flat_dst, flat_out = src.reshape(-1, 4, 2).tolist(), dst.reshape(-1, 4, 2).tolist(), out.reshape(-1, 3, 3)
    for k, (s, d) in enumerate(zip(flat_src, flat_dst)):
        square_from_src = np.linalg.inv(np.array(_square_to_quad(s)))
        h = np.array(_square_to_quad(d)) @ square_from_src
        flat_out[k] = h / h[2, 2]
    dtype = np.result_type(src.dtype, dst.dtype)
    return out.astype(dtype, copy=False) if np.issubdtype(dtype, np.floating) else out


def homography_from_offsets(offsets: Array, width: int, height: int) -> Array:
    """4-point parameterisation -> 3x3. ``offsets`` (..., 4, 2) in pixels; returns ``b_from_a`` (..., 3, 3)."""
    corners = image_corners(width, height, like=offsets)
    return homography_from_points(_xp(offsets).broadcast_to(corners, offsets.shape), corners + offsets)


def offsets_from_homography(homography: Array, width: int, height: int) -> Array:
    """3x3 -> 4-point parameterisation: (..., 3, 3) -> (..., 4, 2) pixel offsets of A's corners in B."""
    corners = image_corners(width, height, like=homography)
    return transform_points(homography, corners) - corners


# ------------------------------------------------------------------------- normalised coordinates


def pixel_to_normalized(width: int, height: int, like: Array | None = None) -> Array:
    """(3, 3) matrix taking pixel coordinates to ``grid_sample`` coordinates (align_corners=False)."""
    m = [[2.0 / width, 0.0, 1.0 / width - 1.0], [0.0, 2.0 / height, 1.0 / height - 1.0], [0.0, 0.0, 1.0]]
    return np.asarray(m, dtype=np.float64) if like is None else _like(m, like)


def normalized_homography(dst_from_src: Array, src_size: tuple[int, int], dst_size: tuple[int, int]) -> Array:
    """A pixel homography expressed between normalised coordinates: ``N_dst H N_src^-1``.

    Sizes are ``(width, height)``. With ``dst_from_src = a_from_b`` (the inverse of the estimate), this is
    the paper's normalised inverse ``M^-1 H^-1 M``, ready for :func:`sampling_grid`.
    """
    n_src = pixel_to_normalized(*src_size, like=dst_from_src)
    n_dst = pixel_to_normalized(*dst_size, like=dst_from_src)
    xp = _xp(dst_from_src)
    return n_dst @ dst_from_src @ xp.linalg.inv(n_src)


def pixel_grid(width: int, height: int, like: Array | None = None) -> Array:
    """Pixel-centre coordinates of every pixel, shape (height, width, 2), (x, y) order."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    grid = np.stack([xs, ys], -1)
    return grid if like is None else _like(grid, like)


def sampling_grid(a_from_b: Array, size_a: tuple[int, int], size_b: tuple[int, int]) -> Array:
    """Where to sample image A for every pixel of B, as ``grid_sample`` coordinates.

    Args:
        a_from_b: (..., 3, 3) pixel homography from B to A (the inverse of an estimate ``b_from_a``).
        size_a: (width, height) of A, the image that is sampled.
        size_b: (width, height) of B, whose pixel grid is filled.

    Returns:
        (..., h_b, w_b, 2) normalised coordinates in A (align_corners=False). Sampling A there renders
        A in B's frame, like ``cv2.warpPerspective(a, b_from_a, size_b)``.
    """
    a_norm_from_b_norm = normalized_homography(a_from_b, size_b, size_a)  # ..., 3, 3
    w_b, h_b = size_b
    # Normalised B coordinates of B's pixel centres.
    grid_b = transform_points(pixel_to_normalized(w_b, h_b, like=a_from_b), pixel_grid(w_b, h_b, like=a_from_b))
    sampled = transform_points(a_norm_from_b_norm, grid_b.reshape(h_b * w_b, 2))  # ..., N, 2
    return sampled.reshape(tuple(a_from_b.shape[:-2]) + (h_b, w_b, 2))


# ------------------------------------------------------------------------------------ resizing


def resize_matrix(size_from: tuple[int, int], size_to: tuple[int, int]) -> np.ndarray:
    """(3, 3) map from pixel coordinates of an image of ``size_from`` to the same image resized to ``size_to``.

    Sizes are ``(width, height)``. Pixel centres move by half a pixel when scaling:
    ``x' = s (x + 0.5) - 0.5``, as ``cv2.resize`` samples. ``s`` is the ratio of the sizes, which is what
    ``cv2.resize(image, size_to)`` uses; ``cv2.resize(image, None, fx=f)`` rounds the size but samples with
    ``f`` itself, so resize to an explicit size whenever the result is paired with this matrix.
    """
    sx = size_to[0] / size_from[0]
    sy = size_to[1] / size_from[1]
    return np.array([[sx, 0.0, 0.5 * (sx - 1.0)], [0.0, sy, 0.5 * (sy - 1.0)], [0.0, 0.0, 1.0]])


def rescale_homography(
    b_from_a: np.ndarray,
    size_a_from: tuple[int, int],
    size_a_to: tuple[int, int],
    size_b_from: tuple[int, int] | None = None,
    size_b_to: tuple[int, int] | None = None,
) -> np.ndarray:
    """A homography found between images of one resolution, expressed for another.

    ``b_from_a`` maps pixels of A at ``size_a_from`` to pixels of B at ``size_b_from``; the result maps A at
    ``size_a_to`` to B at ``size_b_to`` (B's sizes default to A's). Exact for any scale, and the two
    axes may scale differently: ``H' = S_b H S_a^-1``.
    """
    size_b_from = size_a_from if size_b_from is None else size_b_from
    size_b_to = size_a_to if size_b_to is None else size_b_to
    s_a = resize_matrix(size_a_from, size_a_to)
    s_b = resize_matrix(size_b_from, size_b_to)
    out = s_b @ np.asarray(b_from_a, dtype=np.float64) @ np.linalg.inv(s_a)
    return out / out[2, 2]


def translation(dx: float, dy: float) -> np.ndarray:
    """(3, 3) homography shifting points by (dx, dy) pixels."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def mirror_matrix(width: int, height: int, horizontal: bool = True) -> np.ndarray:
    """(3, 3) map from pixels of a ``width`` x ``height`` image to the same image mirrored left-right
    (``horizontal``, ``cv2.flip(image, 1)``: ``x' = w - 1 - x``) or upside down (``cv2.flip(image, 0)``:
    ``y' = h - 1 - y``). Its own inverse."""
    if horizontal:
        return np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return np.array([[1.0, 0.0, 0.0], [0.0, -1.0, height - 1.0], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------- metrics


def corner_errors(b_from_a_est: Array, b_from_a_true: Array, width: int, height: int) -> Array:
    """Distance in B's pixels between where each estimate and the truth put A's four corners. (..., 4)."""
    xp = _xp(b_from_a_true)
    corners = image_corners(width, height, like=b_from_a_true)
    diff = transform_points(b_from_a_est, corners) - transform_points(b_from_a_true, corners)
    return xp.sqrt((diff**2).sum(-1))


def mace(b_from_a_est: Array, b_from_a_true: Array, width: int, height: int) -> Array:
    """Mean average corner error in pixels (DeTone et al.): the mean of the four corner distances. (...)."""
    return corner_errors(b_from_a_est, b_from_a_true, width, height).mean(-1)


def corner_rmse(b_from_a_est: Array, b_from_a_true: Array, width: int, height: int) -> Array:
    """The paper's 4-point RMSE in pixels: ``sqrt(mean_i |c_i_est - c_i_true|^2)`` over the corners. (...)."""
    xp = _xp(b_from_a_true)
    return xp.sqrt((corner_errors(b_from_a_est, b_from_a_true, width, height) ** 2).mean(-1))


# ---------------------------------------------------------------------------------- validation


def is_valid_homography(b_from_a: np.ndarray | None, width: int, height: int, max_scale: float = 20.0) -> bool:
    """Whether ``b_from_a`` is a usable estimate for an A of ``width`` x ``height`` pixels.

    Rejects: non-finite entries; a singular matrix; A's corners mapping through infinity (the horizon
    crosses the image); a folded or twisted quadrilateral; and a scale change beyond ``max_scale``.
    Plain Python floats: it runs several times per estimate on one 3x3, where numpy's per-call cost
    was a tenth of a batch-1 network pass.
    """
    if b_from_a is None:
        return False
    h = np.asarray(b_from_a, dtype=np.float64)
    if h.shape != (3, 3) or not np.all(np.isfinite(h)):
        return False
    (a, b, c), (d, e, f), (g, i, j) = h.tolist()
    det = a * (e * j - f * i) - b * (d * j - f * g) + c * (d * i - e * g)
    # Singular relative to Hadamard's bound (|det| <= the product of the row norms), which a translation alone
    # cannot shrink: the cube of the largest entry called a frame 23,000 px from the reference singular.
    bound = math.hypot(a, b, c) * math.hypot(d, e, f) * math.hypot(g, i, j)
    if abs(det) < 1e-12 * bound:
        return False
    corners = ((0.0, 0.0), (width - 1.0, 0.0), (width - 1.0, height - 1.0), (0.0, height - 1.0))
    w = [g * x + i * y + j for x, y in corners]
    # H is defined up to scale, sign included (-H is the same map): what matters is that all of A's
    # corners have w of one sign, i.e. none of them lies beyond the horizon.
    sign = -1.0 if all(v < 0 for v in w) else 1.0
    floor = 1e-9 * max(abs(v) for v in w)
    if any(sign * v <= floor for v in w):
        return False
    quad = [((a * x + b * y + c) / v, (d * x + e * y + f) / v) for (x, y), v in zip(corners, w)]
    if not all(math.isfinite(q) for point in quad for q in point):
        return False
    # A convex, same-orientation quadrilateral: every turn has the sign of the original square's.
    edges = [(quad[(k + 1) % 4][0] - quad[k][0], quad[(k + 1) % 4][1] - quad[k][1]) for k in range(4)]
    if not all(edges[k][0] * edges[(k + 1) % 4][1] - edges[k][1] * edges[(k + 1) % 4][0] > 0 for k in range(4)):
        return False
    area_a = float(max(width - 1, 1) * max(height - 1, 1))
    area_b = 0.5 * abs(sum(quad[k][0] * quad[(k + 1) % 4][1] - quad[(k + 1) % 4][0] * quad[k][1] for k in range(4)))
    ratio = area_b / area_a
    return 1.0 / max_scale**2 < ratio < max_scale**2
