"""Ground-control points: the file format, its bad input, and a simulated flight placed by its points."""

from __future__ import annotations

import json

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.georef.gcp import fit_gcps, read_gcp_file

pyproj = pytest.importorskip("pyproj")

HEADER = "+proj=utm +zone=11 +ellps=WGS84 +datum=WGS84 +units=m +no_defs\n"


def _write(path, lines: list[str], header: str = HEADER):
    path.write_text(header + "\n".join(lines) + "\n")
    return path


def test_the_odm_format_is_read_and_bad_files_are_named_by_line(tmp_path):
    good = read_gcp_file(_write(tmp_path / "g.txt", ["235269.88 3811198.11 0.0 3609.37 2293.79 IMG_0037.jpg gcp02",
                                                    "235262.54\t3811203.5\t0.0\t3472.1\t1000.5\tIMG_0052.jpg\tgcp04"]))
    assert good.epsg == 32611 and [o.name for o in good.observations] == ["gcp02", "gcp04"]
    assert good.observations[1].px == pytest.approx(3472.1)
    for lines, header, message in [
        (["1 2 3 4 5 a.jpg"], "+proj=nonsense\n", "unknown CRS"),
        (["1 2 3 4 a.jpg"], HEADER, "line 2: expected"),
        (["1 2 x 4 5 a.jpg"], HEADER, "line 2: x, y, z, px and py must be numbers"),
        (["1 2 3 nan 5 a.jpg"], HEADER, "not finite"),
    ]:
        with pytest.raises(UdhError, match=message):
            read_gcp_file(_write(tmp_path / "bad.txt", lines, header))
    with pytest.raises(UdhError, match="empty GCP file"):
        read_gcp_file(_write(tmp_path / "empty.txt", [], ""))
    lonlat = read_gcp_file(_write(tmp_path / "ll.txt", ["-119.87 34.41 0 10 10 a.jpg p"], "WGS84\n"))
    assert lonlat.epsg == 32611 and 200000 < lonlat.observations[0].x < 300000  # to UTM 11N


def _simulated_gcps(truth: dict, names: list[str], m_per_px: float = 0.05, origin=(235000.0, 3811000.0)):
    """GCP lines for ground points seen by the frames, from the simulator's exact ground_from_frame."""
    width, height = truth["frame_size"]
    rng = np.random.default_rng(1)
    lines, k = [], 0
    for record in truth["frames"]:
        px, py = rng.uniform(40, width - 40), rng.uniform(40, height - 40)
        gx, gy = geometry.transform_points(np.array(record["ground_from_frame"]), np.array([[px, py]]))[0]
        for other in truth["frames"]:  # every frame that sees this ground point observes it
            fx, fy = geometry.transform_points(geometry.invert(np.array(other["ground_from_frame"])), np.array([[gx, gy]]))[0]
            if 5 < fx < width - 5 and 5 < fy < height - 5:
                lines.append(f"{origin[0] + gx * m_per_px:.3f} {origin[1] - gy * m_per_px:.3f} 0 {fx:.3f} {fy:.3f} {other['file']} {names[k]}")
        k += 1
        if k == len(names):
            break
    return lines


def test_a_simulated_flight_is_placed_by_its_points_and_a_wrong_point_is_left_out(tmp_path):
    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    folder = tmp_path / "flight"
    folder.mkdir()
    make_flight(folder, SMALL, seed=8)
    truth = json.loads((folder / "ground_truth.json").read_text())
    names = [f"gcp{k}" for k in range(7)]
    lines = _simulated_gcps(truth, names)
    # A point whose surveyed position is 15 m off (a typo in the survey), seen where gcp0 is seen: reported
    # and left out. gcp0 itself goes, so that no two labels share a pixel.
    x, y, _, px, py, image, _ = lines[0].split()
    lines = [line for line in lines if not line.endswith(" gcp0")] + [f"{float(x) + 15:.3f} {y} 0 {px} {py} {image} wrong"]
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1),
                        gcp=_write(tmp_path / "gcp_list.txt", lines))
    georeference = report["parts"][0]["georeference"]
    assert georeference["source"] == "gcp" and georeference["crs"] == "EPSG:32611"
    assert georeference["gcps"]["wrong"]["used"] is False and georeference["gcps"]["wrong"]["checkpoint_m"] > 10
    used = [p for p in georeference["gcps"].values() if p["used"]]
    assert len(used) == 6 and georeference["gcp_checkpoint_rms_m"] < 0.3
    assert georeference["pixel_size_m"] == pytest.approx(0.05, rel=0.05)
    assert (tmp_path / "map.pgw").is_file() and "UTM_Zone_11N" in (tmp_path / "map.prj").read_text()


def test_too_few_points_and_pixels_outside_the_frames_are_reported(tmp_path):
    gcps = read_gcp_file(_write(tmp_path / "g.txt", ["10 20 0 5000 10 a.jpg p1", "11 21 0 10 10 a.jpg p2", "30 40 0 10 10 missing.jpg p3"]))
    frames = {"a.jpg": ((320, 240), np.eye(3))}
    with pytest.raises(UdhError, match="only 1 ground-control point"):
        fit_gcps(gcps, frames)
    with pytest.raises(UdhError, match="outside a.jpg's 320x240 pixels"):
        fit_gcps(read_gcp_file(_write(tmp_path / "h.txt", ["10 20 0 5000 10 a.jpg p1"])), frames)


def test_two_labels_on_one_pixel_are_both_left_out(tmp_path):
    lines = ["0 0 0 100 100 a.jpg p0", "20 0 0 101 100 a.jpg p4", "0 10 0 100 150 a.jpg p1", "10 10 0 150 150 a.jpg p2",
             "10 0 0 150 100 a.jpg p3"]
    gcps = read_gcp_file(_write(tmp_path / "g.txt", lines))
    flip = np.diag([0.2, -0.2, 1.0])  # 0.2 m per pixel, y up on the map
    found = fit_gcps(gcps, {"a.jpg": ((320, 240), np.linalg.inv(flip) @ np.eye(3))})
    assert "p0" not in found.points and "p4" not in found.points
    assert any("same pixel" in line for line in found.skipped)


def test_observations_become_anchors_of_the_solve(tmp_path):
    """gcp_anchors: one anchor per usable observation, its pixel scaled to the frame, in the file's CRS; two
    labels on one pixel, images that are not frames, pixels outside the frame and a point left out on purpose
    are not anchors."""
    from udh_cli.mosaic.georef.gcp import gcp_anchors

    lines = ["0 0 0 100 100 a.jpg p0", "20 0 0 101 100 a.jpg p4", "5 6 0 600 400 a.jpg p1", "7 8 0 50 60 b.jpg p2",
             "9 9 0 9999 10 b.jpg p3", "1 2 0 10 10 other.jpg p5"]
    gcps = read_gcp_file(_write(tmp_path / "g.txt", lines))
    frames = {"a.jpg": (0, (320, 240)), "b.jpg": (3, (320, 240))}
    anchors = gcp_anchors(gcps, frames, 0.05, image_width=640)  # the marks were made on 640-px copies
    assert anchors.frames.tolist() == [0, 3]
    np.testing.assert_allclose(anchors.pixels, [[300.0, 200.0], [25.0, 30.0]])
    np.testing.assert_allclose(anchors.positions, [[5, 6], [7, 8]])
    assert anchors.sigma_m.tolist() == [0.05, 0.05]
    assert gcp_anchors(gcps, frames, 0.05, image_width=640, leave_out="p1").frames.tolist() == [3]
    assert gcp_anchors(gcps, {"c.jpg": (0, (320, 240))}, 0.05) is None


def test_ground_control_anchors_keep_a_simulated_flight_on_its_points(tmp_path):
    """--gcp-sigma: the observations join the solve; on a simulated flight with exact points the map stays
    within 0.3 m RMS at the checkpoints, as without them."""
    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    folder = tmp_path / "flight"
    folder.mkdir()
    make_flight(folder, SMALL, seed=8)
    truth = json.loads((folder / "ground_truth.json").read_text())
    gcp = _write(tmp_path / "gcp_list.txt", _simulated_gcps(truth, [f"gcp{k}" for k in range(7)]))
    results = [run_mosaic(folder, tmp_path / f"map{sigma}.png", MosaicConfig(method="sift", overlap_per_frame=1, gcp_sigma_m=sigma), gcp=gcp)
               for sigma in (0.0, 0.05)]
    rms = [r["parts"][0]["georeference"]["gcp_checkpoint_rms_m"] for r in results]
    assert rms[1] < 0.3 and rms[1] < rms[0] + 0.05
