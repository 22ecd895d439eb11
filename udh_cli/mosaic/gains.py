"""Gain (exposure) compensation: one multiplier per frame so that overlapping frames agree in brightness.

The model is OpenCV's GainCompensator (Brown & Lowe): minimise over gains ``g``
``sum_pairs N_ab [ (g_a I_ab - g_b I_ba)^2 / sigma_n^2 + ((1 - g_a)^2 + (1 - g_b)^2) / sigma_g^2 ]``
where ``I_ab`` is the mean grey level of A where it overlaps B and ``N_ab`` the overlap in pixels; the
prior term keeps the gains near 1. It is linear in ``g``; means are measured on the working copies.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.frames import Frame
from udh_cli.mosaic.pairs import PairResult

SIGMA_N = 10.0  # grey levels: how closely overlapping means should agree
SIGMA_G = 0.1  # how far a gain may stray from 1 at the same cost


def overlap_means(pair: PairResult, frames: Sequence[Frame]) -> tuple[float, float, float]:
    """``(N_ab, I_ab, I_ba)``: overlap size as a share of A's working pixels, and both mean grey levels."""
    fa, fb = frames[pair.a], frames[pair.b]
    work_b_from_a = geometry.rescale_homography(pair.b_from_a, fa.size, fa.work_size, fb.size, fb.work_size)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    b_in_a = cv2.warpPerspective(fb.work, work_b_from_a, fa.work_size, flags=flags)
    inside = cv2.warpPerspective(np.full(fb.work.shape, 255, np.uint8), work_b_from_a, fa.work_size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP) > 0
    count = int(inside.sum())
    if count == 0:
        return 0.0, 0.0, 0.0
    return count / inside.size, float(fa.work[inside].mean()), float(b_in_a[inside].mean())


def solve_gains(n_frames: int, pairs: Sequence[PairResult], frames: Sequence[Frame]) -> np.ndarray:
    """(n_frames,) gains from every accepted pair; frames without pairs keep gain 1."""
    system = np.zeros((n_frames, n_frames))
    rhs = np.zeros(n_frames)
    for pair in pairs:
        if not pair.ok:
            continue
        n, i_ab, i_ba = overlap_means(pair, frames)
        a, b = pair.a, pair.b
        system[a, a] += n * (i_ab**2 / SIGMA_N**2 + 1 / SIGMA_G**2)
        system[b, b] += n * (i_ba**2 / SIGMA_N**2 + 1 / SIGMA_G**2)
        system[a, b] -= n * i_ab * i_ba / SIGMA_N**2
        system[b, a] -= n * i_ab * i_ba / SIGMA_N**2
        rhs[a] += n / SIGMA_G**2
        rhs[b] += n / SIGMA_G**2
    lonely = np.diag(system) == 0
    system[lonely, lonely] = 1.0
    rhs[lonely] = 1.0
    return np.linalg.solve(system, rhs)
