"""Failing pairs: the fallback method, bridging a bad frame, splitting into parts; never a crash or a silent drop."""

from __future__ import annotations

import json

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.files import MANIFEST_NAME
from udh_cli.estimators import create_estimator
from udh_cli.mosaic import MosaicConfig, run_mosaic

from mosaic_flights import SMALL, FailOn, fingerprint, make_flight, work_fingerprints

FAST = MosaicConfig(overlap_per_frame=1, batch_size=4)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """8 frames: line one is frames 0-3, line two is frames 4-7."""
    folder = tmp_path_factory.mktemp("flight")
    paths = make_flight(folder, SMALL, seed=4)
    return folder, work_fingerprints(paths)


def test_fallback_rescues_a_failed_pair(flight, tmp_path):
    folder, prints = flight
    primary = FailOn(prints, lambda a, b: {a, b} == {2, 3})
    report = run_mosaic(folder, tmp_path / "m.png", FAST, estimator=primary, fallback=create_estimator("sift"))
    assert report["summary"]["placed"] == 8 and report["summary"]["parts"] == 1
    pair = next(p for p in report["pairs"] if (p["a"], p["b"]) == (2, 3))
    assert pair["status"] == "ok" and pair["method"] == "sift"
    assert [e["method"] for e in pair["estimates"]] == ["failing", "sift"]
    assert pair["estimates"][0]["failure"] == "made to fail by the test"
    others = [p for p in report["pairs"] if (p["a"], p["b"]) != (2, 3) and p["status"] == "ok"]
    assert all(p["method"] in ("failing", "chain+ecc") for p in others)  # the fallback only ran where it was needed
    assert max(primary.batches) > 1  # pairs reach the estimator in batches
    assert report["ground_truth_error"]["solved"]["max_corner_px"] < 3


def test_a_bad_frame_is_bridged_and_reported(flight, tmp_path):
    folder, prints = flight
    primary = FailOn(prints, lambda a, b: 5 in (a, b))
    report = run_mosaic(folder, tmp_path / "m.png", FAST, estimator=primary)
    frames = report["frames"]
    assert frames[5]["status"] == "unplaced" and "made to fail" in frames[5]["reason"]
    assert all(f["status"] == "placed" and f["part"] == 1 for i, f in enumerate(frames) if i != 5)
    bridge = next(p for p in report["pairs"] if (p["a"], p["b"]) == (4, 6))
    assert bridge["kind"] == "bridge" and bridge["status"] == "ok"
    assert any("frame_005.jpg is not in any mosaic" in w for w in report["warnings"])
    assert (tmp_path / "m.png").is_file() and not list(tmp_path.glob("m.part*"))


def test_unbridgeable_gap_splits_the_sequence(flight, tmp_path):
    folder, prints = flight
    across = lambda a, b: a is not None and b is not None and (a < 4) != (b < 4)  # noqa: E731
    primary, fallback = FailOn(prints, across), FailOn(prints, across)
    report = run_mosaic(folder, tmp_path / "m.png", FAST, estimator=primary, fallback=fallback)
    assert report["summary"]["parts"] == 2 and report["summary"]["placed"] == 8
    assert [f["part"] for f in report["frames"]] == [1, 1, 1, 1, 2, 2, 2, 2]
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != MANIFEST_NAME) == [
        "m.json", "m.part1.png", "m.part1.preview.jpg", "m.part2.png", "m.part2.preview.jpg", "m.report.html",
    ]
    failed = [p for p in report["pairs"] if p["status"] == "failed"]
    assert {(p["a"], p["b"]) for p in failed} == {(3, 4), (2, 4), (3, 5)}
    assert all(len(p["estimates"]) == 2 for p in failed)  # first method, then fallback
    assert any("split into 2 parts" in w for w in report["warnings"])
    sidecar = json.loads((tmp_path / "m.json").read_text())
    assert [p["frames"] for p in sidecar["parts"]] == [[0, 1, 2, 3], [4, 5, 6, 7]]
    assert [p["reference_frame"] for p in sidecar["parts"]] == [2, 6]


def test_nothing_matches_is_an_error_not_a_crash(flight, tmp_path):
    folder, prints = flight
    with pytest.raises(UdhError, match="no pair of frames could be matched"):
        run_mosaic(folder, tmp_path / "m.png", FAST, estimator=FailOn(prints, lambda a, b: True))
    assert [p.name for p in tmp_path.iterdir()] == []  # no mosaic (and no pair cache without --resume)


class PastTheHorizon(FailOn):
    """Real estimates, except pair 6 -> 7, whose (valid) homography has so much perspective that frame 7,
    chained back to the reference, falls past the horizon."""

    name = "past-the-horizon"

    def _estimate(self, pair):
        image_a, image_b = pair.a, pair.b
        a, b = self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))
        if (a, b) == (6, 7):
            return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.004, 0.0, 1.0]]), 0.9, {}
        return self.inner._estimate(pair)


def test_a_frame_chained_past_the_horizon_is_reported_not_fatal(flight, tmp_path):
    folder, prints = flight
    estimator = PastTheHorizon(prints, lambda a, b: False)
    # The alignment check would reject that pair before it is chained; this test is about the chaining.
    report = run_mosaic(folder, tmp_path / "m.png", MosaicConfig(overlap_per_frame=0, min_verified=0), estimator=estimator)
    frames = report["frames"]
    assert frames[7]["status"] == "unplaced" and "degenerate" in frames[7]["reason"]
    assert [f["status"] for f in frames[:7]] == ["placed"] * 7
    assert report["parts"][0]["frames"] == list(range(7)) and (tmp_path / "m.png").is_file()


class ZoomsIn(FailOn):
    """Real estimates, except pair 6 -> 7, which claims frame 7 is the same ground seen 4x closer: a wrong
    pair of the kind that blew seneca's canvas up (every check passes, the frame is drawn 4x too large)."""

    name = "zooms-in"

    def _estimate(self, pair):
        image_a, image_b = pair.a, pair.b
        a, b = self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))
        if (a, b) == (6, 7):
            h, confidence, details = self.inner._estimate(pair)
            return np.diag([0.25, 0.25, 1.0]) @ h, confidence, details  # B = A scaled down: A drawn 4x larger
        return self.inner._estimate(pair)


def test_a_frame_drawn_at_an_implausible_scale_is_reported_and_the_bound_is_a_setting(flight, tmp_path):
    folder, prints = flight
    config = MosaicConfig(overlap_per_frame=0, min_verified=0)
    report = run_mosaic(folder, tmp_path / "m.png", config, estimator=ZoomsIn(prints, lambda a, b: False))
    frames = report["frames"]
    assert frames[7]["status"] == "unplaced" and "scaled over 3x" in frames[7]["reason"]
    assert [f["status"] for f in frames[:7]] == ["placed"] * 7
    from dataclasses import replace

    loose = run_mosaic(folder, tmp_path / "loose.png", replace(config, max_frame_scale=5.0), estimator=ZoomsIn(prints, lambda a, b: False))
    assert [f["status"] for f in loose["frames"]] == ["placed"] * 8
    with pytest.raises(UdhError, match="max-frame-scale"):
        run_mosaic(folder, tmp_path / "bad.png", replace(config, max_frame_scale=1.0), estimator=ZoomsIn(prints, lambda a, b: False))


class Crashes(FailOn):
    """Breaks the never-raise contract on pair 2 -> 3 (as a buggy estimator would)."""

    name = "crashes"

    def _estimate(self, pair):
        image_a, image_b = pair.a, pair.b
        if (self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))) == (2, 3):
            raise RuntimeError("boom")
        return self.inner._estimate(pair)


def test_an_estimator_that_raises_fails_only_its_pair(flight, tmp_path):
    folder, prints = flight
    report = run_mosaic(folder, tmp_path / "m.png", FAST, estimator=Crashes(prints, lambda a, b: False), fallback=create_estimator("sift"))
    pair = next(p for p in report["pairs"] if (p["a"], p["b"]) == (2, 3))
    assert "RuntimeError: boom" in pair["estimates"][0]["failure"] and pair["method"] == "sift"
    assert report["summary"]["placed"] == 8


class ConfidentlyWrong(FailOn):
    """Real estimates, except pair 3 -> 4, answered 40 px off with a confidence of 0.95."""

    name = "confidently-wrong"

    def _estimate(self, pair):
        image_a, image_b = pair.a, pair.b
        a, b = self.index.get(fingerprint(image_a)), self.index.get(fingerprint(image_b))
        h, confidence, details = self.inner._estimate(pair)
        if (a, b) == (3, 4):
            return geometry.translation(40.0, -25.0) @ h, 0.95, details
        return h, confidence, details


def test_a_confident_but_wrong_pair_fails_the_alignment_check(flight, tmp_path):
    folder, prints = flight
    report = run_mosaic(folder, tmp_path / "m.png", MosaicConfig(overlap_per_frame=0), estimator=ConfidentlyWrong(prints, lambda a, b: False))
    pairs = {(p["a"], p["b"]): p for p in report["pairs"]}
    assert pairs[(3, 4)]["status"] == "failed" and "alignment check" in pairs[(3, 4)]["reason"]
    assert pairs[(3, 4)]["verified"] < 0.3
    assert all(p["verified"] > 0.5 for key, p in pairs.items() if p["status"] == "ok")
    assert report["summary"]["placed"] == 8  # bridged over the doubted link (2 -> 4)


def test_an_answer_its_network_could_not_confirm_is_doubted_even_when_it_aligns():
    """A network's answer its tile levels did not confirm (``verified`` False) is not accepted, however well it
    aligns; an answer of a method that verifies itself (auto) is its method's to judge."""
    from conftest import warped_pair
    from udh_cli.estimators.base import Estimate
    from udh_cli.mosaic.pairs.types import Acceptance

    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=3)
    acceptance = Acceptance()
    confirmed = Estimate("unsupervised", truth, 0.9, 1.0)
    score, doubt = acceptance.judge(confirmed, a, b)
    assert doubt is None and score > 0.8  # it aligns: the photometric check alone would accept it
    unconfirmed = Estimate("unsupervised", truth, 0.9, 1.0, verified=False)
    score, doubt = acceptance.judge(unconfirmed, a, b)
    assert score is None and "unconfirmed" in doubt and "tile levels" in doubt
    assert acceptance.judge(Estimate("auto", truth, 0.9, 1.0, verified=False), a, b, verified_by_method=True) == (None, None)


def test_a_network_answer_its_global_match_verified_skips_the_photometric_check_as_sift_does():
    """Hundreds of agreeing cell matches verify an answer (``verified_by`` "matches") as RANSAC verifies SIFT's:
    brighton-beach's right answers score under the photometric floor. A wrong answer, so verified, would pass
    too, which is why the estimator gives that mark only above CONFIDENT_INLIERS."""
    from conftest import warped_pair
    from udh_cli.estimators.base import Estimate
    from udh_cli.mosaic.pairs.types import Acceptance

    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=3)
    wrong = geometry.translation(-30.0, 25.0)
    acceptance = Acceptance()
    score, doubt = acceptance.judge(Estimate("unsupervised", wrong, 0.9, 1.0), a, b)
    assert "alignment check" in doubt  # unverified, a wrong answer fails the photometric check
    matched = Estimate("unsupervised", wrong, 0.9, 1.0, verified=True, verified_by="matches", inliers=400)
    assert acceptance.judge(matched, a, b) == (None, None)
    low = Estimate("unsupervised", truth, 0.1, 1.0, verified=True, verified_by="matches", inliers=400)
    assert "confidence" in acceptance.judge(low, a, b)[1]  # the confidence floor still applies
