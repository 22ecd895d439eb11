"""`udh mosaic` on bad input: a one-line error or a warning, the right exit code, and nothing half-written."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from udh_cli import cli

from mosaic_flights import SMALL, make_flight

FAST = ["--overlap-pairs", "1", "--quiet"]


def run_main(monkeypatch, capfd, *args: str) -> tuple[int, str, str]:
    """Run the console entry point in-process; returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["udh", *args])
    code = 0
    try:
        cli.main()
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    captured = capfd.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("flight")
    make_flight(folder, SMALL, seed=4)
    return folder


def _copy(flight: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "frames"
    shutil.copytree(flight, folder)
    return folder


def test_main_command_prints_error_against_ground_truth(flight, tmp_path, monkeypatch, capfd):
    code, out, err = run_main(monkeypatch, capfd, "mosaic", str(flight), "-o", str(tmp_path / "m.png"), *FAST)
    assert code == 0, err
    assert "8 of 8" in out and "error vs ground truth" in out
    assert (tmp_path / "m.png").is_file() and (tmp_path / "m.json").is_file()


@pytest.mark.parametrize("case", ["empty", "single"])
def test_too_few_frames(case, flight, tmp_path, monkeypatch, capfd):
    folder = tmp_path / "in"
    folder.mkdir()
    if case == "single":
        shutil.copy(flight / "frame_000.jpg", folder)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(folder), "-o", str(out_dir / "m.png"), *FAST)
    assert code == 1
    assert ("no image files found" if case == "empty" else "only one readable image (frame_000.jpg)") in err
    assert "Traceback" not in err and list(out_dir.iterdir()) == []


def test_corrupt_frame_and_stray_file_are_skipped_with_warnings(flight, tmp_path, monkeypatch, capfd):
    folder = _copy(flight, tmp_path)
    (folder / "frame_003.jpg").write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    (folder / "notes.txt").write_text("flight log\n")
    code, out, err = run_main(monkeypatch, capfd, "mosaic", str(folder), "-o", str(tmp_path / "m.png"), *FAST)
    assert code == 0, err
    assert "skipping frame_003.jpg: cannot be decoded" in err and "skipping notes.txt: not an image file" in err
    report = json.loads((tmp_path / "m.json").read_text())
    assert {s["file"] for s in report["skipped_files"]} == {"frame_003.jpg", "notes.txt"}
    assert report["summary"]["frames"] == 7 and report["summary"]["placed"] == 7
    assert "frame_003.jpg" not in [f["file"] for f in report["frames"]]


def test_mixed_sizes_are_used_at_their_own_size(flight, tmp_path, monkeypatch, capfd):
    folder = _copy(flight, tmp_path)
    small = cv2.resize(cv2.imread(str(folder / "frame_007.jpg")), (240, 180), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(folder / "frame_007.jpg"), small)
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(folder), "-o", str(tmp_path / "m.png"), *FAST)
    assert code == 0, err
    assert "2 sizes: 320x240 (7), 240x180 (1)" in err
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["frames"][7]["status"] == "placed" and (report["frames"][7]["width"], report["frames"][7]["height"]) == (240, 180)
    # Frame 7 still lands where the truth says, once its 0.75 scale is undone.
    assert report["ground_truth_error"]["per_frame_solved"]["frame_006.jpg"]["max_corner_px"] < 3


@pytest.mark.parametrize("output", ["missing/m.png", "m.txt", "isdir"])
def test_unwritable_output_fails_before_any_work(output, flight, tmp_path, monkeypatch, capfd):
    (tmp_path / "isdir.png").mkdir()
    target = tmp_path / ("isdir.png" if output == "isdir" else output)
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(flight), "-o", str(target), *FAST)
    assert code == 1
    assert {"missing/m.png": "does not exist", "m.txt": "unknown image type", "isdir": "is a folder"}[output] in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["isdir.png"]


def test_video_input_and_undecodable_video(flight, tmp_path, monkeypatch, capfd):
    video = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5, SMALL.frame_size)
    for path in sorted(flight.glob("frame_*.jpg")):
        writer.write(cv2.imread(str(path)))
    writer.release()
    code, out, err = run_main(monkeypatch, capfd, "mosaic", str(video), "-o", str(tmp_path / "v.png"), "--every", "1", *FAST)
    assert code == 0, err
    report = json.loads((tmp_path / "v.json").read_text())
    assert [f["file"] for f in report["frames"]][:2] == ["flight.avi#0", "flight.avi#1"]
    assert report["summary"]["placed"] == 8
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video" * 100)
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(bad), "-o", str(tmp_path / "b.png"), *FAST)
    assert code == 1 and "cannot open this as a video" in err
    assert not (tmp_path / "b.png").exists() and not (tmp_path / "b.json").exists()


@pytest.mark.parametrize(("option", "message", "exit_code"), [(["--blend", "SMOOTH"], "'SMOOTH' is not one of", 2), (["--method", "nope"], "'nope' is not one of", 2),
                                                  (["--work-size", "0"], "--work-size 0", 1)])
def test_bad_options_fail_before_any_work(option, message, exit_code, flight, tmp_path, monkeypatch, capfd):
    """Unknown choices are usage errors (exit 2, the choices listed); impossible values are errors (exit 1)."""
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(flight), "-o", str(tmp_path / "m.png"), *option, *FAST)
    assert code == exit_code and message in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("damage", ["no_keys", "bad_matrix"])
def test_damaged_ground_truth_fails_before_any_work(damage, flight, tmp_path, monkeypatch, capfd):
    truth = json.loads((flight / "ground_truth.json").read_text())
    if damage == "no_keys":
        truth = {"format": truth["format"]}
    else:
        truth["frames"][0]["ground_from_frame"] = [[1.0, 0.0], [0.0, 1.0]]
    gt = tmp_path / "gt.json"
    gt.write_text(json.dumps(truth))
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(flight), "-o", str(out_dir / "m.png"), "--gt", str(gt), *FAST)
    assert code == 1 and "gt.json: the ground truth is damaged" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert list(out_dir.iterdir()) == []


def test_ground_truth_of_other_frames_is_reported_as_nothing_to_compare(flight, tmp_path, monkeypatch, capfd):
    truth = json.loads((flight / "ground_truth.json").read_text())
    for record in truth["frames"]:
        record["file"] = "other_" + record["file"]
    gt = tmp_path / "gt.json"
    gt.write_text(json.dumps(truth))
    code, out, err = run_main(monkeypatch, capfd, "mosaic", str(flight), "-o", str(tmp_path / "m.png"), "--gt", str(gt), *FAST)
    assert code == 0, err
    assert "names no placed frame" in out
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["ground_truth_error"]["solved"] == {"frames": 0, "mean_corner_px": None, "max_corner_px": None}
