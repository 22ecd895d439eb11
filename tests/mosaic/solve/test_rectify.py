"""The plane of a part without anchors (udh_cli.mosaic.solve.rectify) and the map-shape measure (udh_cli.mosaic.solve.truth)."""

from __future__ import annotations

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.mosaic.inputs.frames import Frame
from udh_cli.mosaic.solve.rectify import MIN_FRAMES, rectifying_homography
from udh_cli.mosaic.solve.truth import corner_errors_vs_truth, map_shape_errors

SIZE = (320, 240)


def _survey(rows: int = 3, columns: int = 5, seed: int = 0) -> dict[int, np.ndarray]:
    """ground_from_frame of a grid survey: similarities (heading and scale jitter), 60 % overlap."""
    rng = np.random.default_rng(seed)
    out = {}
    for r in range(rows):
        for c in range(columns):
            angle, scale = rng.normal(0, 0.05), 1 + rng.normal(0, 0.02)
            similarity = np.array([[scale * np.cos(angle), -scale * np.sin(angle), 0], [scale * np.sin(angle), scale * np.cos(angle), 0], [0, 0, 1.0]])
            out[len(out)] = geometry.translation(c * 128.0, r * 96.0) @ similarity
    return out


# A plane bent by a projective warp and a shear: what a reference frame's own tilt does to a whole map.
BEND = np.array([[1.05, 0.04, 12.0], [-0.02, 0.97, -7.0], [6e-5, -4e-5, 1.0]])


def _is_similarity(h: np.ndarray, tolerance: float) -> bool:
    h = h / h[2, 2]
    return abs(h[2, 0]) < tolerance and abs(h[2, 1]) < tolerance and abs(h[0, 0] - h[1, 1]) < tolerance and abs(h[0, 1] + h[1, 0]) < tolerance


def test_a_bent_plane_is_brought_back_to_a_similarity_of_the_ground():
    ground_from = _survey()
    plane_from = {i: BEND @ g for i, g in ground_from.items()}
    sizes = [SIZE] * len(plane_from)
    plane = rectifying_homography(plane_from, sizes, reference=7)
    assert plane is not None
    assert not _is_similarity(BEND, 1e-3)
    # The frames were exact similarities of the ground, so the fix undoes the bend up to a similarity.
    assert _is_similarity(plane @ BEND, 1e-8)
    # The reference frame stays where it was: its centre fixed, no scale or turn there.
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    at = geometry.transform_points(plane_from[7], centre[None])
    np.testing.assert_allclose(geometry.transform_points(plane, at), at, atol=1e-8)
    j = geometry.homography_jacobian(plane, at[0])
    assert (j[0, 0] + j[1, 1]) / 2 == pytest.approx(1.0, abs=1e-9) and (j[1, 0] - j[0, 1]) / 2 == pytest.approx(0.0, abs=1e-9)


def test_too_few_frames_keep_the_reference_view():
    ground_from = {i: g for i, g in _survey().items() if i < MIN_FRAMES - 1}
    assert rectifying_homography({i: BEND @ g for i, g in ground_from.items()}, [SIZE] * 15, reference=0) is None


def test_a_fix_that_would_fold_a_drawable_frame_is_refused():
    plane_from = {i: BEND @ g for i, g in _survey().items()}
    # One frame drawable in the bent plane but lying across the horizon of the ground's: the unbending
    # (about the inverse of BEND) sends points where its third row vanishes to infinity.
    horizon = np.linalg.inv(BEND)[2]
    on_horizon = np.array([0.0, -horizon[2] / horizon[1]])  # a point with horizon . (x, y, 1) = 0
    plane_from[14] = geometry.translation(*(on_horizon - np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])))
    assert geometry.is_valid_homography(plane_from[14], *SIZE, max_scale=3.0)
    assert rectifying_homography(plane_from, [SIZE] * 15, reference=0) is None


def _frames(count: int) -> list[Frame]:
    return [Frame(index=i, name=f"f{i}.jpg", size=SIZE, work=np.zeros((1, 1), np.uint8)) for i in range(count)]


def test_map_shape_sees_the_bend_that_the_reference_measure_cannot_change():
    ground_from = _survey()
    frames = _frames(len(ground_from))
    truth = {"ground_from_frame": {f"f{i}.jpg": g for i, g in ground_from.items()}}
    shifted = {i: geometry.translation(40, -3) @ np.diag([2.0, 2.0, 1.0]) @ g for i, g in ground_from.items()}
    assert max(map_shape_errors(frames, shifted, truth).values()) < 1e-6  # a similarity of the ground is a perfect map
    bent = {i: BEND @ g for i, g in ground_from.items()}
    assert np.median(list(map_shape_errors(frames, bent, truth).values())) > 5.0
    # The frame-to-reference measure is blind to any homography of the whole plane.
    errors = corner_errors_vs_truth(frames, 7, bent, truth)
    assert max(v["max_corner_px"] for v in errors.values()) < 1e-6
