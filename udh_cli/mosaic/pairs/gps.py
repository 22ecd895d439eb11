"""GPS makes a mosaic whole: candidate pairs between parts from the frames' GPS positions, and a check of
each estimate against them.

When consecutive pairs fail (a turn, a low-texture field), a run splits into parts. Frames whose GPS
positions lie close together overlap on the ground whatever their order in the sequence: the return leg of
a strip, or the frame after a gap. Those pairs are worth estimating, and an estimate that joins two parts
must agree with GPS. Where one of the parts is placed on the map by its frames' GPS (a similarity fitted to
its chained frame centres), the estimate places the other frame's centre through that part, and the place
must be near that frame's GPS position. Between two lone frames only the distance can be checked: the
distance the homography puts between the centres, in metres at the flight's ground scale measured on the
pairs that did work, against the GPS distance.

All positions are WGS 84 / UTM metres (pyproj), so distances are in metres on the ground.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.georef.gps import fit_similarity, to_utm

MIN_SCALE_PAIRS = 3  # ground scale from fewer working pairs than this is not trusted
REACH_STEPS = 2.0  # candidate frames lie within this many median GPS steps of each other,
FOOTPRINT_SHARE = 0.75  # or within this share of a frame's shorter side on the ground
GPS_TOLERANCE = 0.5  # an estimate may disagree with GPS by this share of the reach, plus the GPS noise floor
GPS_NOISE_M = 5.0  # consumer GPS fixes scatter by a few metres
PLACEMENT_TOLERANCE = 3.0  # an estimate may place a frame this many times the part's GPS residual away (and 2x the noise)


@dataclass(frozen=True)
class GroundScale:
    """The flight's ground scale and the GPS reach of a candidate pair.

    Attributes:
        metres_per_pixel: median ground size of a full-resolution pixel, from pairs that worked.
        reach_m: frames closer than this on the ground are candidates (``REACH_STEPS`` median GPS steps, or
            ``FOOTPRINT_SHARE`` of a frame's shorter side on the ground, whichever is more).
        pairs_used: how many working pairs measured the scale.
    """

    metres_per_pixel: float
    reach_m: float
    pairs_used: int


def ground_positions(latitudes_longitudes: dict[int, tuple[float, float]]) -> tuple[int, dict[int, np.ndarray]]:
    """``(EPSG code, frame index -> (easting, northing) metres)`` in the UTM zone of the median position (pyproj)."""
    if not latitudes_longitudes:
        return 0, {}
    indices = sorted(latitudes_longitudes)
    epsg, points = to_utm(np.array([latitudes_longitudes[i][0] for i in indices]), np.array([latitudes_longitudes[i][1] for i in indices]))
    return epsg, dict(zip(indices, points))


def centre_distance_px(b_from_a: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]) -> float:
    """How far A's centre lands from B's centre in B's pixels under ``b_from_a``: the frames' offset."""
    return float(np.linalg.norm(_centre_in(b_from_a, size_a) - _centre_in(np.eye(3), size_b)))


def measure_ground_scale(positions: dict[int, np.ndarray], working: Sequence[tuple[int, int, np.ndarray]],
                         sizes: Sequence[tuple[int, int]]) -> GroundScale | None:
    """The ground scale from pairs that worked, ``(a, b, b_from_a)`` at full resolution, whose frames both have
    GPS; None when fewer than :data:`MIN_SCALE_PAIRS` moved far enough to measure it (a hover)."""
    ratios, steps = [], []
    for a, b, b_from_a in working:
        if a not in positions or b not in positions:
            continue
        metres = float(np.linalg.norm(positions[a] - positions[b]))
        pixels = centre_distance_px(b_from_a, sizes[a], sizes[b])
        if abs(b - a) == 1:
            steps.append(metres)
        # Moves of a tenth of the frame or more: shorter ones would be measured mostly in GPS noise.
        if pixels > 0.1 * float(np.hypot(*sizes[b])):
            ratios.append(metres / pixels)
    if len(ratios) < MIN_SCALE_PAIRS or not steps:
        return None
    metres_per_pixel = float(np.median(ratios))
    # Frames overlap on the ground out to about their own footprint, whatever the forward step (a hover's steps
    # are metres, and the next strip lies two or more steps away): the reach is the larger of the two.
    footprint_m = FOOTPRINT_SHARE * metres_per_pixel * float(np.median([min(sizes[i]) for i in positions if i < len(sizes)]))
    return GroundScale(metres_per_pixel, max(REACH_STEPS * float(np.median(steps)), footprint_m, GPS_NOISE_M), len(ratios))


def bridge_candidates(positions: dict[int, np.ndarray], parts: Sequence[Sequence[int]], known: set[tuple[int, int]],
                      reach_m: float, per_gap: int) -> list[tuple[int, int, float]]:
    """Frame pairs of different parts (a lone frame is a part) within ``reach_m`` of each other on the ground:
    ``(a, b, metres)`` with ``a < b``, nearest first, at most ``per_gap`` for each pair of parts, none of them
    in ``known``."""
    from scipy.spatial import cKDTree

    part_of = {frame: k for k, part in enumerate(parts) for frame in part}
    indices = np.array(sorted(i for i in positions if i in part_of))
    if len(indices) < 2 or per_gap < 1:
        return []
    points = np.stack([positions[i] for i in indices])
    labels = np.array([part_of[i] for i in indices])
    # A k-d tree finds the close pairs without an N x N distance matrix (thousands of frames).
    close = cKDTree(points).query_pairs(reach_m, output_type="ndarray")
    close = close[labels[close[:, 0]] != labels[close[:, 1]]]
    distances = np.linalg.norm(points[close[:, 0]] - points[close[:, 1]], axis=1)
    found: dict[tuple[int, int], list[tuple[int, int, float]]] = {}
    for (r, c), metres in sorted(zip(close.tolist(), distances.tolist()), key=lambda item: (item[1], item[0])):
        a, b = sorted((int(indices[r]), int(indices[c])))
        gap = tuple(sorted((int(labels[r]), int(labels[c]))))
        if (a, b) in known or len(found.setdefault(gap, [])) >= per_gap:
            continue
        found[gap].append((a, b, float(metres)))
    return sorted((c for chosen in found.values() for c in chosen), key=lambda c: c[2])


def gps_disagreement_m(b_from_a: np.ndarray, a: int, b: int, positions: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]],
                       scale: GroundScale) -> float:
    """How far, in metres, the distance an estimate puts between two frames' centres is from their GPS distance."""
    metres = float(np.linalg.norm(positions[a] - positions[b]))
    return abs(centre_distance_px(b_from_a, sizes[a], sizes[b]) * scale.metres_per_pixel - metres)


def gps_limit_m(scale: GroundScale) -> float:
    """The largest :func:`gps_disagreement_m` an estimate joining two parts may have."""
    return GPS_TOLERANCE * scale.reach_m + GPS_NOISE_M


def part_map(positions: dict[int, np.ndarray], ref_from_frame: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]]) -> tuple[np.ndarray, float] | None:
    """A part placed on the map by its frames' GPS: ``(map_from_ref, residual RMS m)``, a similarity fitted to
    the chained frame centres (reference pixels) and their positions; None with fewer than 3 frames with GPS."""
    frames = [i for i in ref_from_frame if i in positions and np.isfinite(ref_from_frame[i]).all()]
    if len(frames) < 3:
        return None
    centres = np.array([_centre_in(ref_from_frame[i], sizes[i]) for i in frames])
    points = np.stack([positions[i] for i in frames])
    fit = fit_similarity(centres, points)
    residual = np.linalg.norm(geometry.transform_points(fit, centres) - points, axis=1)
    return fit, float(np.sqrt(np.mean(residual**2)))


def placement_error_m(frame_from_other: np.ndarray, frame: int, other: int, ref_from_frame: np.ndarray, placed: tuple[np.ndarray, float],
                      positions: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]]) -> tuple[float, float]:
    """Where an estimate puts ``other``'s centre on the map, through ``frame``'s part (``ref_from_frame`` of
    ``frame``, the part's ``placed`` = :func:`part_map`): ``(metres from other's GPS position, the limit)``."""
    map_from_ref, residual_m = placed
    centre = _centre_in(map_from_ref @ ref_from_frame @ frame_from_other, sizes[other])
    limit = max(2 * GPS_NOISE_M, PLACEMENT_TOLERANCE * residual_m)
    return float(np.linalg.norm(centre - positions[other])), limit


def _centre_in(h: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Where ``h`` puts the centre of a frame of ``size`` (width, height)."""
    return geometry.transform_points(h, np.array([[(size[0] - 1) / 2, (size[1] - 1) / 2]]))[0]
