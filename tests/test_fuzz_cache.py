"""Fuzzing the pair cache: a consistent hand edit (a homography shifted together with its estimate) is never reused."""

from __future__ import annotations

import json

import numpy as np

from conftest import run_main
from mosaic_flights import SMALL, make_flight
from udh_cli import geometry


def test_a_pair_cache_edited_consistently_by_hand_is_estimated_again(tmp_path, monkeypatch, capfd):
    frames = tmp_path / "frames"
    make_flight(frames, SMALL, seed=3)  # 320x240 frames: the working copies are the frames themselves
    out = tmp_path / "out"
    out.mkdir()
    args = ["mosaic", str(frames), "-o", str(out / "m.png"), "-m", "sift", "--quiet", "--overlap-pairs", "1", "--resume"]
    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 0, err
    honest = json.loads((out / "m.json").read_text())
    cache = json.loads((out / "m.pairs.json").read_text())
    edited = next(p for p in cache["pairs"] if p["status"] == "ok" and p["kind"] == "consecutive")
    shift = geometry.translation(40.0, 0.0)  # the estimate and the pair's homography moved together: every other check holds
    edited["estimates"][-1]["homography"] = (shift @ np.array(edited["estimates"][-1]["homography"])).tolist()
    edited["b_from_a"] = (shift @ np.array(edited["b_from_a"])).tolist()
    (out / "m.pairs.json").write_text(json.dumps(cache))

    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 0, err
    assert f"the cached estimate of {edited['a_file']} -> {edited['b_file']}" in err and "digest does not match" in err
    resumed = json.loads((out / "m.json").read_text())
    assert resumed["summary"]["pairs_from_cache"] == len(honest["pairs"]) - 1
    again = next(p for p in resumed["pairs"] if (p["a"], p["b"]) == (edited["a"], edited["b"]))
    reference = next(p for p in honest["pairs"] if (p["a"], p["b"]) == (edited["a"], edited["b"]))
    np.testing.assert_allclose(again["b_from_a"], reference["b_from_a"], atol=1e-9)  # estimated again, not shifted
    for mine, expected in zip(resumed["frames"], honest["frames"], strict=True):
        np.testing.assert_allclose(mine["mosaic_from_frame"], expected["mosaic_from_frame"], atol=1e-6)


def test_a_cache_without_digests_is_one_warning_and_its_pairs_are_estimated_again(tmp_path, monkeypatch, capfd):
    frames = tmp_path / "frames"
    make_flight(frames, SMALL, seed=3)
    args = ["mosaic", str(frames), "-o", str(tmp_path / "m.png"), "-m", "sift", "--quiet", "--overlap-pairs", "1", "--resume"]
    assert run_main(monkeypatch, capfd, *args)[0] == 0
    cache = json.loads((tmp_path / "m.pairs.json").read_text())
    for pair in cache["pairs"]:
        del pair["digest"]
    (tmp_path / "m.pairs.json").write_text(json.dumps(cache))
    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 0, err
    assert err.count("warning:") == 1 and f"{len(cache['pairs'])} entries of the pair cache" in err and "no digest" in err
    assert json.loads((tmp_path / "m.json").read_text())["summary"]["pairs_from_cache"] == 0
