"""GPS makes a mosaic whole: candidate pairs between parts from the frames' GPS positions, and a check of
each estimate against them.

When consecutive pairs fail (a turn, a low-texture field), a run splits into parts. Frames whose GPS
positions lie close together overlap on the ground whatever their order in the sequence: the return leg of
a strip, or the frame after a gap. Those pairs are worth estimating, and an estimate that joins two parts
must agree with GPS: the distance its homography puts between the two frames' centres, in metres (at the
flight's ground scale measured on the pairs that did work), is compared with the GPS distance.

All positions are WGS 84 / UTM metres (pyproj), so distances are in metres on the ground.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from udh_cli import geometry

MIN_SCALE_PAIRS = 3  # ground scale from fewer working pairs than this is not trusted
REACH_STEPS = 2.0  # candidate frames lie within this many median GPS steps of each other
GPS_TOLERANCE = 0.5  # an estimate may disagree with GPS by this share of the reach, plus the GPS noise floor
GPS_NOISE_M = 5.0  # consumer GPS fixes scatter by a few metres


@dataclass(frozen=True)
class GroundScale:
    """The flight's ground scale and the GPS reach of a candidate pair.

    Attributes:
        metres_per_pixel: median ground size of a full-resolution pixel, from pairs that worked.
        reach_m: frames closer than this on the ground are candidates (``REACH_STEPS`` median GPS steps).
        pairs_used: how many working pairs measured the scale.
    """

    metres_per_pixel: float
    reach_m: float
    pairs_used: int


def ground_positions(latitudes_longitudes: dict[int, tuple[float, float]]) -> dict[int, np.ndarray]:
    """Frame index -> (easting, northing) metres in the UTM zone of the median position (pyproj)."""
    from udh_cli.mosaic.georef import utm_epsg, utm_transformer

    if not latitudes_longitudes:
        return {}
    indices = sorted(latitudes_longitudes)
    latitudes = np.array([latitudes_longitudes[i][0] for i in indices])
    longitudes = np.array([latitudes_longitudes[i][1] for i in indices])
    epsg = utm_epsg(float(np.median(latitudes)), float(np.median(longitudes)))
    eastings, northings = utm_transformer(epsg).transform(longitudes, latitudes)
    return {i: np.array([e, n]) for i, e, n in zip(indices, eastings, northings)}


def centre_distance_px(b_from_a: np.ndarray, size_a: tuple[int, int], size_b: tuple[int, int]) -> float:
    """How far A's centre lands from B's centre in B's pixels under ``b_from_a``: the frames' offset."""
    centre_a = np.array([[(size_a[0] - 1) / 2, (size_a[1] - 1) / 2]])
    landed = geometry.transform_points(b_from_a, centre_a)[0]
    return float(np.hypot(landed[0] - (size_b[0] - 1) / 2, landed[1] - (size_b[1] - 1) / 2))


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
    return GroundScale(float(np.median(ratios)), REACH_STEPS * max(float(np.median(steps)), GPS_NOISE_M), len(ratios))


def bridge_candidates(positions: dict[int, np.ndarray], parts: Sequence[Sequence[int]], known: set[tuple[int, int]],
                      reach_m: float, per_gap: int) -> list[tuple[int, int, float]]:
    """Frame pairs of different parts (a lone frame is a part) within ``reach_m`` of each other on the ground:
    ``(a, b, metres)`` with ``a < b``, nearest first, at most ``per_gap`` for each pair of parts, none of them
    in ``known``."""
    part_of = {frame: k for k, part in enumerate(parts) for frame in part}
    indices = np.array(sorted(i for i in positions if i in part_of))
    if len(indices) < 2 or per_gap < 1:
        return []
    points = np.stack([positions[i] for i in indices])
    labels = np.array([part_of[i] for i in indices])
    distances = np.linalg.norm(points[:, None] - points[None], axis=2)
    rows, cols = np.nonzero((distances <= reach_m) & (labels[:, None] < labels[None]))  # each pair of parts once
    found: dict[tuple[int, int], list[tuple[int, int, float]]] = {}
    for r, c in sorted(zip(rows, cols), key=lambda rc: distances[rc]):
        a, b = sorted((int(indices[r]), int(indices[c])))
        gap = (int(labels[r]), int(labels[c]))
        if (a, b) in known or len(found.setdefault(gap, [])) >= per_gap:
            continue
        found[gap].append((a, b, float(distances[r, c])))
    return sorted((c for chosen in found.values() for c in chosen), key=lambda c: c[2])


def gps_disagreement_m(b_from_a: np.ndarray, a: int, b: int, positions: dict[int, np.ndarray], sizes: Sequence[tuple[int, int]],
                       scale: GroundScale) -> float:
    """How far, in metres, the distance an estimate puts between two frames' centres is from their GPS distance."""
    metres = float(np.linalg.norm(positions[a] - positions[b]))
    return abs(centre_distance_px(b_from_a, sizes[a], sizes[b]) * scale.metres_per_pixel - metres)


def gps_limit_m(scale: GroundScale) -> float:
    """The largest :func:`gps_disagreement_m` an estimate joining two parts may have."""
    return GPS_TOLERANCE * scale.reach_m + GPS_NOISE_M
