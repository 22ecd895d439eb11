"""Known motions laid on real pairs, one draw per kind of motion, for ``udh bench hard``.

A real pair (A, B) with a reference ``b_from_a`` becomes a harder one by warping B with a known homography
``moved_from_b`` drawn for one kind of motion: the new truth is ``moved_from_b @ b_from_a``
(:func:`move_pair`). Every motion turns, scales and tilts about B's centre ``c``, in that order from B:

    moved_from_b = T(c) · S(scale) · R(turn) · P(tilt) · T(-c)

where ``P`` is the view of a camera of focal length ``f`` (B's longer side, a 53-degree field of view) turned by
``tilt`` degrees about an axis in the image plane at ``axis`` degrees from x (90: a vertical axis, the yaw
of a camera looking sideways). Angles in degrees, scale as a factor (> 1 magnifies).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from udh_cli import geometry

# The kinds of motion a UAV pair shows, each drawn as below.
MOTION_KINDS = ("extreme viewpoint and scale", "in-plane rotation", "vertical-axis rotation", "mixed", "scale")
MIN_OVERLAP = 0.25  # share of A that must stay inside the moved B: less leaves too little to match on
OVERLAP_GRID = 24  # A is sampled on a 24 x 24 grid of points to measure the overlap
# A's corners may land at most this many of B's longer sides from B's centre: beyond, near the horizon, the corner
# error magnifies the reference's own error of a pixel or two into hundreds, and measures nothing of the method.
MAX_CORNER_REACH = 1.5


@dataclass(frozen=True)
class Motion:
    """One drawn motion about B's centre (see the module docstring)."""

    kind: str
    turn: float = 0.0  # degrees, x towards y: clockwise on screen, since image y points down
    scale: float = 1.0
    tilt: float = 0.0  # degrees of the camera's turn out of the image plane
    axis: float = 90.0  # degrees from x of the in-plane axis the camera turns about

    def homography(self, size_b: tuple[int, int]) -> np.ndarray:
        """(3, 3) ``moved_from_b`` for an image B of ``size_b`` = (width, height) pixels."""
        width, height = size_b
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        centred = scaling(self.scale) @ rotation(self.turn) @ tilting(self.tilt, self.axis, float(max(width, height)))
        moved = geometry.translation(cx, cy) @ centred @ geometry.translation(-cx, -cy)
        return moved / moved[2, 2]

    def describe(self) -> str:
        return f"turn {self.turn:.0f} deg, scale {self.scale:.2f}, tilt {self.tilt:.0f} deg about {self.axis:.0f} deg"


def rotation(degrees: float) -> np.ndarray:
    """(3, 3) in-plane rotation about the origin by ``degrees`` (x towards y)."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def scaling(factor: float) -> np.ndarray:
    """(3, 3) isotropic scaling about the origin."""
    return np.diag([factor, factor, 1.0])


def tilting(degrees: float, axis_degrees: float, focal: float) -> np.ndarray:
    """(3, 3) ``K R K^-1`` about the origin: a camera of focal length ``focal`` pixels turned by ``degrees``
    about the in-plane axis at ``axis_degrees`` from x (Rodrigues' formula)."""
    u = np.array([math.cos(math.radians(axis_degrees)), math.sin(math.radians(axis_degrees)), 0.0])
    angle = math.radians(degrees)
    cross = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
    turn = np.eye(3) * math.cos(angle) + math.sin(angle) * cross + (1 - math.cos(angle)) * np.outer(u, u)
    k = np.diag([focal, focal, 1.0])
    return k @ turn @ np.linalg.inv(k)


def _octaves(rng: np.random.Generator, low: float, high: float) -> float:
    """A scale of 2^±U(low, high): magnified or shrunk alike."""
    return float(2.0 ** (rng.choice([-1.0, 1.0]) * rng.uniform(low, high)))


def draw_motion(kind: str, rng: np.random.Generator) -> Motion:
    """One motion of ``kind`` (one of :data:`MOTION_KINDS`):

    * extreme viewpoint and scale: a 35-55 degree tilt about any axis and 1.5x-2.2x scale either way;
    * in-plane rotation: any angle, uniform over the circle;
    * vertical-axis rotation: a 25-50 degree yaw (the strong perspective of a sideways turn);
    * mixed: any angle, 0.6x-1.6x scale, a tilt of up to 35 degrees about any axis;
    * scale: 1.3x-2x, magnified or shrunk, nothing else.
    """
    if kind == "extreme viewpoint and scale":
        return Motion(kind, scale=_octaves(rng, 0.6, 1.15), tilt=float(rng.uniform(35, 55)), axis=float(rng.uniform(0, 180)))
    if kind == "in-plane rotation":
        return Motion(kind, turn=float(rng.uniform(0, 360)))
    if kind == "vertical-axis rotation":
        return Motion(kind, tilt=float(rng.choice([-1.0, 1.0]) * rng.uniform(25, 50)), axis=90.0)
    if kind == "mixed":
        return Motion(kind, turn=float(rng.uniform(0, 360)), scale=float(2.0 ** rng.uniform(-0.7, 0.7)),
                      tilt=float(rng.uniform(0, 35)), axis=float(rng.uniform(0, 180)))
    if kind == "scale":
        return Motion(kind, scale=_octaves(rng, 0.4, 1.0))
    raise ValueError(f"unknown kind of motion {kind!r}; choose one of {', '.join(MOTION_KINDS)}")


def overlap(b_from_a: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]) -> float:
    """Share of A's area (sampled on a grid) that ``b_from_a`` puts inside B, 0..1; points beyond the horizon
    count as outside."""
    (wa, ha), (wb, hb) = size_a, size_b
    xs, ys = np.meshgrid(np.linspace(0, wa - 1, OVERLAP_GRID), np.linspace(0, ha - 1, OVERLAP_GRID))
    points = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 1) @ np.asarray(b_from_a, np.float64).T
    ahead = points[:, 2] > 1e-12 * np.abs(points[:, 2]).max()
    x = np.where(ahead, points[:, 0] / np.where(ahead, points[:, 2], 1.0), -1.0)
    y = np.where(ahead, points[:, 1] / np.where(ahead, points[:, 2], 1.0), -1.0)
    return float(np.mean(ahead & (x >= 0) & (x <= wb - 1) & (y >= 0) & (y <= hb - 1)))


def move_pair(image_b: np.ndarray, b_from_a: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B warped by ``motion`` (``moved_from_b``) onto a canvas of B's size, black outside B, and the new truth
    ``moved_from_a = motion @ b_from_a``. Returns ``(moved_b, moved_from_a)``."""
    height, width = image_b.shape[:2]
    moved = cv2.warpPerspective(image_b, motion, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    truth = np.asarray(motion, np.float64) @ np.asarray(b_from_a, np.float64)
    return moved, truth / truth[2, 2]


def fits(b_from_a: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int], min_overlap: float = MIN_OVERLAP) -> bool:
    """Whether a truth can be scored: valid on all of A (no corner beyond the horizon), A's corners within
    :data:`MAX_CORNER_REACH` of B, and A at least ``min_overlap`` inside B."""
    if not geometry.is_valid_homography(b_from_a, *size_a):
        return False
    centre = (np.asarray(size_b, np.float64) - 1) / 2
    reach = np.linalg.norm(geometry.transform_points(b_from_a, geometry.image_corners(*size_a)) - centre, axis=1).max()
    return reach <= MAX_CORNER_REACH * max(size_b) and overlap(b_from_a, size_a, size_b) >= min_overlap
