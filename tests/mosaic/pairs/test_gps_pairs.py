"""GPS bridges between parts: candidates from ground positions, the ground scale, and the check of an estimate."""

from __future__ import annotations

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.mosaic.pairs.gps import GroundScale, bridge_candidates, gps_disagreement_m, gps_limit_m, measure_ground_scale

pytest.importorskip("pyproj")


def test_candidates_join_different_parts_nearest_first_and_at_most_per_gap():
    # Two strips 30 m apart, 10 m steps; part 0 is the first strip, part 1 the return leg, frame 8 is alone.
    positions = {i: np.array([10.0 * i, 0.0]) for i in range(4)}
    positions.update({4 + i: np.array([30.0 - 10.0 * i, 30.0]) for i in range(4)})
    positions[8] = np.array([5.0, 12.0])
    parts = [[0, 1, 2, 3], [4, 5, 6, 7], [8]]
    found = bridge_candidates(positions, parts, known={(0, 8)}, reach_m=31.0, per_gap=2)
    between_strips = [(a, b) for a, b, _ in found if a < 4 <= b < 8]
    assert between_strips == [(0, 7), (1, 6)]  # the two nearest pairs straight across, 30 m apart, and no more
    # The lone frame: its two nearest in each strip, except (0, 8), which is known already (13 m, tried before).
    lone = sorted((a, b, round(m, 2)) for a, b, m in found if b == 8)
    assert lone == [(1, 8, 13.0), (2, 8, 19.21), (6, 8, 18.68), (7, 8, 18.68)]
    assert [m for _, _, m in found] == sorted(m for _, _, m in found)  # nearest first
    assert bridge_candidates(positions, parts, set(), reach_m=5.0, per_gap=2) == []


def test_the_ground_scale_comes_from_the_pairs_that_worked_and_checks_a_bridge():
    # 0.05 m per pixel; consecutive frames 20 m (400 px) apart along x.
    sizes = [(640, 480)] * 5
    positions = {i: np.array([20.0 * i, 0.0]) for i in range(5)}
    working = [(i, i + 1, geometry.translation(-400.0, 0.0)) for i in range(4)]
    scale = measure_ground_scale(positions, working, sizes)
    assert scale.metres_per_pixel == pytest.approx(0.05) and scale.reach_m == pytest.approx(40.0) and scale.pairs_used == 4
    assert measure_ground_scale(positions, working[:2], sizes) is None  # two pairs do not fix a scale
    # A bridge 0 -> 2 that says 800 px agrees with GPS; one that says 100 px is 35 m off, beyond the limit.
    assert gps_disagreement_m(geometry.translation(-800.0, 0.0), 0, 2, positions, sizes, scale) == pytest.approx(0.0)
    wrong = gps_disagreement_m(geometry.translation(-100.0, 0.0), 0, 2, positions, sizes, scale)
    assert wrong == pytest.approx(35.0) and wrong > gps_limit_m(GroundScale(0.05, 40.0, 4))


def test_a_flight_split_at_its_turn_is_made_whole_by_gps_pairs(tmp_path):
    """The turn between the two strips fails (its consecutive pair and both bridges); pairs across the strips,
    which GPS finds, join the parts into one mosaic, and the sidecar says how many did."""
    from mosaic_flights import FailOn, work_fingerprints
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=5, focal_px=300.0), seed=5,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.1, noise_m=0.3))
    prints = work_fingerprints(sorted(folder.glob("frame_*.jpg")))
    turn = FailOn(prints, lambda a, b: a is not None and b is not None and (a < 5) != (b < 5) and abs(a - b) <= 2)
    report = run_mosaic(folder, tmp_path / "whole.png", MosaicConfig(overlap_per_frame=1, gps_pairs=3), estimator=turn, fallback=turn)
    assert report["summary"]["parts"] == 1 and report["summary"]["placed"] == 10
    assert report["summary"]["gps_pairs_joined"] >= 1
    joined = [p for p in report["pairs"] if p["kind"] == "gps" and p["status"] == "ok"]
    assert joined and all((p["a"] < 5) != (p["b"] < 5) for p in joined)  # GPS pairs cross between the strips
    solved = report["ground_truth_error"]["solved"]
    assert solved["frames"] == 10 and solved["max_corner_px"] < 3.0  # and join them where they belong
    off = run_mosaic(folder, tmp_path / "split.png", MosaicConfig(overlap_per_frame=1, gps_pairs=0), estimator=turn, fallback=turn)
    assert off["summary"]["parts"] == 2 and off["summary"]["gps_pairs_joined"] == 0


def test_a_gps_pair_that_places_a_frame_far_from_its_gps_is_rejected(tmp_path):
    """The same split flight, but every pair across the strips answers 150 px (15 m) off the truth, and the
    mosaic's alignment check (--min-verified) is off so that it would let them through: GPS places the other strip's
    frame that far from its fix (0.3 m noise, sub-metre residual) and rejects every such pair."""
    from mosaic_flights import FailOn, fingerprint, work_fingerprints
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    class ShiftedAcross(FailOn):
        def _estimate(self, pair):
            image_a, image_b = pair.a, pair.b
            homography, confidence, details = super()._estimate(pair)
            a, b = self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))
            if a is not None and b is not None and (a < 5) != (b < 5):
                homography = geometry.translation(150.0, 0.0) @ homography
            return homography, confidence, details

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=5, focal_px=300.0), seed=5,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.1, noise_m=0.3))
    prints = work_fingerprints(sorted(folder.glob("frame_*.jpg")))
    liar = ShiftedAcross(prints, lambda a, b: a is not None and b is not None and (a < 5) != (b < 5) and abs(a - b) <= 2)
    report = run_mosaic(folder, tmp_path / "m.png", MosaicConfig(overlap_per_frame=1, min_verified=0.0, gps_pairs=3), estimator=liar, fallback=liar)
    across = [p for p in report["pairs"] if p["kind"] == "gps"]
    assert across and all(p["status"] == "rejected" and "from its GPS position" in p["reason"] for p in across)
    assert report["summary"]["parts"] == 2 and report["summary"]["gps_pairs_joined"] == 0


def test_gps_fixes_anchor_the_solve_of_a_flight_when_asked(tmp_path):
    """--gps-sigma: the fixes join the global solve. On a short flight with precise fixes (5 cm, half a pixel)
    the solution stays within 1.5 px of where the pairs alone put it, with every frame placed; fixes of 3 px
    noise on so short a flight pull the frames by about that much (the anchors bound long-chain drift, they
    do not add precision to a well-tied flight). A flight without GPS is told so."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.errors import UdhError
    from udh_cli.mosaic.report import Reporter
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=5, focal_px=300.0), seed=5,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.1, noise_m=0.05))
    plain = run_mosaic(folder, tmp_path / "plain.png", MosaicConfig(method="sift"))
    anchored = run_mosaic(folder, tmp_path / "anchored.png", MosaicConfig(method="sift", gps_sigma_m=0.05))
    assert anchored["summary"]["placed"] == plain["summary"]["placed"] == 10
    errors = [r["ground_truth_error"]["solved"]["max_corner_px"] for r in (plain, anchored)]
    assert errors[1] < errors[0] + 1.5 and errors[1] < 3.0
    with pytest.raises(UdhError, match="--gps-sigma -1"):
        run_mosaic(folder, tmp_path / "bad.png", MosaicConfig(method="sift", gps_sigma_m=-1.0))
    nogps = tmp_path / "nogps"
    write_flight(nogps, FlightConfig(frame_size=(320, 240), strips=1, frames_per_strip=4), seed=2)
    reporter = Reporter(quiet=True)
    run_mosaic(nogps, tmp_path / "n.png", MosaicConfig(method="sift", gps_sigma_m=2.0), reporter=reporter)
    assert any("no frame carries GPS" in w for w in reporter.warnings)
