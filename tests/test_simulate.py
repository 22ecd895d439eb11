"""The simulated flight: deterministic, exact ground truth, the overlap it promises, and the shipped example."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.simulate import FlightConfig, load_ground_truth, make_ground, simulate_flight, write_flight

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "sim_flight"
TINY = FlightConfig(frame_size=(160, 120), strips=2, frames_per_strip=3, focal_px=150.0, noise_sigma=0.0)


def test_ground_is_deterministic_and_textured():
    a, b = make_ground((400, 300), seed=5), make_ground((400, 300), seed=5)
    assert a.shape == (300, 400, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert not np.array_equal(a, make_ground((400, 300), seed=6))
    # Texture everywhere: every 50x50 tile has local contrast and SIFT finds keypoints across the image.
    grey = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    assert min(grey[y : y + 50, x : x + 50].std() for y in range(0, 300, 50) for x in range(0, 400, 50)) > 3
    assert len(cv2.SIFT_create().detect(grey, None)) > 300


def test_frames_are_exact_views_of_the_ground():
    frames, ground = simulate_flight(TINY, seed=2)
    assert len(frames) == 6
    for frame in frames:
        # Re-render the ground through the true homography: only gain, vignetting and rounding differ.
        rendered = cv2.warpPerspective(ground, geometry.invert(frame.ground_from_frame), TINY.frame_size).astype(np.float32)
        observed = frame.image.astype(np.float32)
        ratio = observed[20:-20, 20:-20].mean() / rendered[20:-20, 20:-20].mean()
        assert 0.6 < ratio < 1.25
        correlation = np.corrcoef(rendered[20:-20, 20:-20].ravel(), observed[20:-20, 20:-20].ravel())[0, 1]
        assert correlation > 0.97


def test_ground_truth_file_and_overlap(tmp_path):
    write_flight(tmp_path, TINY, seed=2)
    truth = load_ground_truth(tmp_path / "ground_truth.json")
    assert sorted(p.name for p in tmp_path.glob("*.jpg")) == sorted(truth["ground_from_frame"])
    w, h = TINY.frame_size
    for a, b, b_from_a in truth["consecutive_pairs"]:
        expected = geometry.invert(truth["ground_from_frame"][b]) @ truth["ground_from_frame"][a]
        assert float(geometry.mace(b_from_a, expected / expected[2, 2], w, h)) < 1e-9
    # Consecutive frames on a line overlap by about the configured forward overlap (75 %).
    a, b, b_from_a = truth["consecutive_pairs"][0]
    quad = geometry.transform_points(b_from_a, geometry.image_corners(w, h)).astype(np.float32)
    area, _ = cv2.intersectConvexConvex(quad, geometry.image_corners(w, h).astype(np.float32))
    assert 0.6 < area / ((w - 1) * (h - 1)) < 0.9


def test_shipped_example_is_small_and_complete():
    files = sorted(EXAMPLE.glob("frame_*.jpg"))
    assert 12 <= len(files) <= 20
    assert sum(f.stat().st_size for f in EXAMPLE.iterdir()) < 5 * 2**20
    truth = json.loads((EXAMPLE / "ground_truth.json").read_text())
    assert [r["file"] for r in truth["frames"]] == [f.name for f in files]
    assert len(truth["consecutive_pairs"]) == len(files) - 1


def test_a_full_disk_leaves_no_half_flight_and_the_rerun_works(tmp_path, monkeypatch, capfd):
    from conftest import run_main

    from udh_cli import simulate

    written = []
    real_write = simulate.atomic_write_bytes

    def full_disk_at_the_third(path, data):
        written.append(path)
        if len(written) == 3:
            raise UdhError(f"{path}: writing it failed (No space left on device); check the free space and permissions")
        return real_write(path, data)

    monkeypatch.setattr(simulate, "atomic_write_bytes", full_disk_at_the_third)
    args = ["simulate", str(tmp_path / "s"), "--width", "160", "--height", "120", "--strips", "1", "--frames-per-strip", "4"]
    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 1 and "No space left on device" in err
    assert list(tmp_path.iterdir()) == []  # no folder, no staging folder
    monkeypatch.setattr(simulate, "atomic_write_bytes", real_write)
    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "s").iterdir())[-1] == "ground_truth.json" and len(list((tmp_path / "s").iterdir())) == 5
