"""--resume: an interrupted run keeps its finished pair estimates, and a resumed run estimates only the rest."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import pytest

from udh_cli import cli
from udh_cli.estimators import Estimator
from udh_cli.mosaic import MosaicConfig, Reporter, run_mosaic
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.mosaic.pairs.cache import estimator_identity

from mosaic_flights import SMALL, FailOn, make_flight, work_fingerprints

# Batches of 3: the 7 consecutive pairs go as 3 + 3 + 1, then the loop-closure pairs, 3 at a time. Every loop pair
# runs the estimator (no confirming from the prediction), so that its calls count the pairs estimated.
CONFIG = MosaicConfig(batch_size=3, overlap_per_frame=2, confirm_loops=False)


class Interrupted(FailOn):
    """Real SIFT estimates, counted; after ``interrupt_after`` of them the next one raises KeyboardInterrupt
    (as Ctrl-C would). ``calls`` records (a, b) by frame index, ``None`` for a pre-warped image."""

    name: ClassVar[str] = "counted"

    def __init__(self, prints: list[str], interrupt_after: int | None = None) -> None:
        super().__init__(prints, lambda a, b: False)
        self.interrupt_after = interrupt_after

    def _estimate(self, pair):
        if self.interrupt_after is not None and len(self.calls) >= self.interrupt_after:
            raise KeyboardInterrupt
        return super()._estimate(pair)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    folder = tmp_path_factory.mktemp("flight")
    paths = make_flight(folder, SMALL, seed=4)
    return folder, work_fingerprints(paths)


@pytest.fixture(scope="module")
def uninterrupted(flight, tmp_path_factory):
    folder, prints = flight
    estimator = Interrupted(prints)
    report = run_mosaic(folder, tmp_path_factory.mktemp("whole") / "m.png", CONFIG, estimator=estimator)
    assert len(estimator.calls) == len(report["pairs"]) >= 10  # one estimate per pair: no fallback here
    return report


def cached_pairs(output) -> list[dict]:
    return json.loads(RunFiles(output).pair_cache.read_text())["pairs"]


def assert_same_geometry(report: dict, reference: dict) -> None:
    for frame, expected in zip(report["frames"], reference["frames"], strict=True):
        np.testing.assert_allclose(frame["mosaic_from_frame"], expected["mosaic_from_frame"], rtol=0, atol=1e-9)
    for pair, expected in zip(report["pairs"], reference["pairs"], strict=True):
        assert (pair["a"], pair["b"], pair["kind"], pair["status"]) == (expected["a"], expected["b"], expected["kind"], expected["status"])
        if expected["b_from_a"] is not None:
            np.testing.assert_allclose(pair["b_from_a"], expected["b_from_a"], rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("interrupt_after", "finished"),
    [(5, 3), (11, 10)],  # in the second batch of consecutive pairs; in the second batch of loop pairs (7 + 3 done)
)
def test_resume_estimates_only_the_pairs_the_interrupt_lost(flight, uninterrupted, tmp_path, interrupt_after, finished):
    folder, prints = flight
    out = tmp_path / "m.png"
    reporter = Reporter(quiet=True)
    with pytest.raises(KeyboardInterrupt):
        run_mosaic(folder, out, CONFIG, reporter, estimator=Interrupted(prints, interrupt_after), resume=True)
    assert [p.name for p in tmp_path.iterdir()] == ["m.pairs.json"]  # no mosaic, no sidecar
    assert len(cached_pairs(out)) == finished  # every finished batch, none of the interrupted one
    assert any("--resume" in w for w in reporter.warnings)

    counted = Interrupted(prints)
    report = run_mosaic(folder, out, CONFIG, estimator=counted, resume=True)
    total = len(uninterrupted["pairs"])
    assert len(counted.calls) == total - finished
    assert report["summary"]["pairs_from_cache"] == finished
    assert_same_geometry(report, uninterrupted)
    assert len(cached_pairs(out)) == total  # kept after a successful run, complete

    # Resuming a finished run estimates nothing; without --resume the cache is ignored and left as it is.
    again = Interrupted(prints)
    assert run_mosaic(folder, out, CONFIG, estimator=again, resume=True)["summary"]["pairs_from_cache"] == total
    assert again.calls == []
    fresh = Interrupted(prints)
    assert run_mosaic(folder, out, CONFIG, estimator=fresh)["summary"]["pairs_from_cache"] == 0
    assert len(fresh.calls) == total and len(cached_pairs(out)) == total


def test_a_second_interrupt_loses_nothing_either(flight, uninterrupted, tmp_path):
    folder, prints = flight
    out = tmp_path / "m.png"
    with pytest.raises(KeyboardInterrupt):
        run_mosaic(folder, out, CONFIG, estimator=Interrupted(prints, 5), resume=True)  # 3 pairs finished
    with pytest.raises(KeyboardInterrupt):
        run_mosaic(folder, out, CONFIG, estimator=Interrupted(prints, 6), resume=True)  # 3 + 1 consecutive, 2 of a loop batch
    assert len(cached_pairs(out)) == 7
    counted = Interrupted(prints)
    report = run_mosaic(folder, out, CONFIG, estimator=counted, resume=True)
    assert len(counted.calls) == len(uninterrupted["pairs"]) - 7
    assert_same_geometry(report, uninterrupted)


def test_pairs_that_no_longer_match_are_estimated_again(flight, uninterrupted, tmp_path):
    folder, prints = flight
    work = tmp_path / "frames"
    work.mkdir()
    for path in folder.iterdir():
        (work / path.name).write_bytes(path.read_bytes())
    out = tmp_path / "m.png"
    run_mosaic(work, out, CONFIG, estimator=Interrupted(prints), resume=True)

    # Another confidence threshold changes every key.
    counted = Interrupted(prints)
    report = run_mosaic(work, out, MosaicConfig(batch_size=3, overlap_per_frame=2, confirm_loops=False, min_confidence=0.25), estimator=counted, resume=True)
    # Every pair is estimated (loop closure's later rounds may estimate a pair once more, or add one).
    assert report["summary"]["pairs_from_cache"] == 0 and len(counted.calls) >= len(report["pairs"]) >= len(uninterrupted["pairs"]) - 1

    # A changed frame: its two consecutive pairs are estimated again, the other five come from the cache.
    frame = work / "frame_006.jpg"
    cv2.imwrite(str(frame), cv2.imread(str(frame)), [cv2.IMWRITE_JPEG_QUALITY, 80])
    new_prints = work_fingerprints(sorted(work.glob("frame_*.jpg")))
    assert new_prints[6] != prints[6] and new_prints[:6] == prints[:6]
    counted = Interrupted(new_prints)
    report = run_mosaic(work, out, MosaicConfig(batch_size=3, overlap_per_frame=2, confirm_loops=False, min_confidence=0.25), estimator=counted, resume=True)
    assert [c for c in counted.calls if None not in c] == [(5, 6), (6, 7)]
    assert report["summary"]["pairs_from_cache"] >= 5

    # Other acceptance rules (a new revision of what makes a pair accepted) change every key too.
    import udh_cli.mosaic.pairs.cache as pair_cache

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pair_cache, "ACCEPTANCE_REVISION", pair_cache.ACCEPTANCE_REVISION + 1)
        counted = Interrupted(new_prints)
        report = run_mosaic(work, out, MosaicConfig(batch_size=3, overlap_per_frame=2, confirm_loops=False, min_confidence=0.25), estimator=counted, resume=True)
        assert report["summary"]["pairs_from_cache"] == 0 and len(counted.calls) >= len(report["pairs"])


def test_resume_takes_the_loop_pairs_confirmed_from_the_prediction_as_they_were(flight, tmp_path):
    """The cache records which path answered a loop pair: a resumed run takes the cheap answers as they were,
    asks the estimator about nothing, and draws the same map."""
    folder, prints = flight
    out, config = tmp_path / "m.png", MosaicConfig(batch_size=3, overlap_per_frame=2)
    first = Interrupted(prints)
    report = run_mosaic(folder, out, config, estimator=first, resume=True)
    loops = [p for p in report["pairs"] if p["kind"] == "overlap"]
    confirmed = [p for p in loops if p["method"] == "chain+ecc"]
    assert len(confirmed) >= len(loops) - 1 >= 5 and all(p["status"] == "ok" for p in confirmed)
    assert len(first.calls) == len(report["pairs"]) - len(confirmed)  # the cascade ran only on the others
    assert sum(record["method"] == "chain+ecc" for record in cached_pairs(out)) == len(confirmed)
    again = Interrupted(prints)
    resumed = run_mosaic(folder, out, config, estimator=again, resume=True)
    assert again.calls == [] and resumed["summary"]["pairs_from_cache"] == len(report["pairs"])
    assert_same_geometry(resumed, report)
    assert [p["method"] for p in resumed["pairs"]] == [p["method"] for p in report["pairs"]]


@dataclass
class WithModel(Estimator):
    name: ClassVar[str] = "with-model"
    model: str = ""
    device: str = "cpu"

    def model_files(self) -> list[str]:
        return [self.model]


def test_estimator_identity_follows_settings_and_model_files(tmp_path):
    model = tmp_path / "net.onnx"
    model.write_bytes(b"first")
    before = estimator_identity(WithModel(str(model)))
    assert before["name"] == "with-model" and before["settings"] == {"model": str(model), "device": "cpu"}
    assert estimator_identity(WithModel(str(model))) == before
    assert estimator_identity(WithModel(str(model), device="cuda")) != before
    model.write_bytes(b"retrained")  # same path, new weights: a different method
    assert estimator_identity(WithModel(str(model))) != before


def test_the_shipped_networks_are_named_in_the_identity_of_every_method_that_runs_them():
    from udh_cli.estimators import create_estimator

    auto = estimator_identity(create_estimator("auto"))
    network = estimator_identity(create_estimator("unsupervised"))
    assert auto["name"] == "auto" and network["name"] == "unsupervised"
    shipped = {Path(f[0]).name for f in network["files"]}
    assert {"udh-unsupervised-int8.onnx", "udh-unsupervised-refine-int8.onnx", "udh-unsupervised-flight-int8.onnx",
            "udh-unsupervised-matcher.onnx"} <= shipped
    # auto runs the same networks but not the matcher (its network has no tile stage; ECC and SIFT settle its doubts)
    assert shipped - {"udh-unsupervised-matcher.onnx"} == {Path(f[0]).name for f in auto["files"]}
    assert auto["settings"]["opinions"][0]["method"] == "sift" and auto["settings"]["refiner"]["levels"] == 3
    assert auto["settings"]["start"]["method"] == "unsupervised" and auto["settings"]["start"]["precision"] == "int8"
    assert estimator_identity(create_estimator("sift"))["files"] == []


def test_cli_resume_with_the_output_inside_the_frames_folder(flight, tmp_path, monkeypatch, capfd):
    folder = tmp_path / "frames"
    shutil.copytree(flight[0], folder)
    out = folder / "m.png"
    args = ["udh", "mosaic", str(folder), "-o", str(out), "--overlap-pairs", "1", "--quiet", "--resume"]
    for extra in ([], []):  # a first run that keeps its pairs, then a run that takes them all
        monkeypatch.setattr(sys, "argv", args + extra)
        with pytest.raises(SystemExit) as stop:
            cli.main()
        assert stop.value.code == 0
    err = capfd.readouterr().err
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["summary"]["pairs_from_cache"] == len(sidecar["pairs"]) > 7
    assert sidecar["skipped_files"] == []  # the cache (and the other outputs) are never read as frames
    assert f"{len(sidecar['pairs'])} of {len(sidecar['pairs'])} pair estimates taken from" in err


def test_the_pair_key_covers_the_judges_thresholds(flight, monkeypatch, tmp_path):
    """A record holds verdicts (verified, which stage answered) that the judge's table decided: a retuned table
    must not reuse them."""
    from dataclasses import replace

    from udh_cli.mosaic.inputs.frames import open_frames
    from udh_cli.mosaic.pairs import cache as pair_cache
    from udh_cli.mosaic.pairs.types import Acceptance, PairRequest

    frames = open_frames(flight[0], 64).frames

    def key() -> str:
        cache = pair_cache.PairCache.open(tmp_path / "m.pairs.json", frames, [], Acceptance(), False, Reporter(quiet=True), keep=False)
        return cache.key(PairRequest(0, 1, "consecutive"))

    before = key()
    monkeypatch.setattr(pair_cache, "THRESHOLDS", replace(pair_cache.THRESHOLDS, min_matched_tile_levels=3))
    assert key() != before
