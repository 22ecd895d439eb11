"""udh bench speed: the structure and arithmetic of its results on the example flight, never its timings."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest
from typer.testing import CliRunner

from udh_cli import cli
from udh_cli.bench.speed import UNSTAGED, frame_files, stage_timings, time_reference
from udh_cli.errors import UdhError

SIM_FLIGHT = Path(__file__).resolve().parents[2] / "examples" / "sim_flight"


@pytest.fixture(scope="module")
def speed_run(tmp_path_factory):
    """One run on the 18-frame example flight with the network, and two single pairs timed for sift and identity."""
    out = tmp_path_factory.mktemp("speed")
    result = CliRunner().invoke(cli.app, ["bench", "speed", str(SIM_FLIGHT), "--method", "unsupervised", "--workers", "1",
                                          "--pairs", "2", "--methods", "identity,sift", "--keep-mosaic", "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out, json.loads((out / "results.json").read_text()), result.output


def test_stage_ratios_are_stage_over_reference(speed_run):
    _, results, _ = speed_run
    reference = results["reference"]["seconds"]
    assert results["reference"]["frames"] == 18 and results["reference"]["keypoints"] > 0
    for stage in results["stages"]:
        assert stage["ratio"] == pytest.approx(stage["seconds"] / reference)
    assert results["ratio"] == pytest.approx(results["wall_s"] / reference)


def test_stages_sum_to_the_wall_time(speed_run):
    _, results, _ = speed_run
    names = [stage["name"] for stage in results["stages"]]
    assert names[-1] == UNSTAGED and "total" not in names
    assert {"reading frames", "consecutive pairs", "compositing"} <= set(names)
    named = sum(stage["seconds"] for stage in results["stages"][:-1])
    assert named <= results["wall_s"]
    assert named + results["stages"][-1]["seconds"] == pytest.approx(results["wall_s"])


def test_the_run_says_what_it_measured(speed_run):
    out, results, stdout = speed_run
    assert results["method"] == "unsupervised" and results["workers"] == 1 and results["reference_side_px"] == 800
    assert results["summary"]["placed"] == 18
    assert results["peak_memory_mb"]["self"] > 0 and results["machine"]["cpu_count"] >= 1
    for stage in results["stages"]:
        assert f"| {stage['name']} |" in stdout
    assert (out / "results.md").read_text() in stdout
    assert (out / "mosaic.png").is_file()  # --keep-mosaic


def test_single_pairs_are_timed_against_sift(speed_run):
    _, results, _ = speed_run
    by_method = {pair["method"]: pair for pair in results["pairs"]}
    assert set(by_method) == {"identity", "sift"} and all(pair["pairs"] == 2 for pair in results["pairs"])
    assert by_method["sift"]["sift_ratio"] == pytest.approx(1.0)
    assert by_method["identity"]["sift_ratio"] == pytest.approx(by_method["identity"]["median_ms"] / by_method["sift"]["median_ms"])
    assert by_method["sift"]["answered"] == 2 == sum(by_method["sift"]["answered_by"].values())


def test_the_picture_decodes(speed_run):
    out, results, _ = speed_run
    picture = cv2.imread(str(out / "stages.png"))
    assert picture is not None and picture.ndim == 3 and picture.shape[1] > 400
    assert (picture < 250).any()  # something is drawn


def test_stage_timings_leave_out_the_total_and_name_the_rest():
    stages = stage_timings({"reading frames": 1.0, "compositing": 3.0, "total": 4.5}, wall_s=5.0, reference_s=2.0)
    assert [(s.name, s.seconds, s.ratio) for s in stages] == [("reading frames", 1.0, 0.5), ("compositing", 3.0, 1.5), (UNSTAGED, 1.0, 0.5)]
    assert stage_timings({"a": 2.0}, wall_s=1.9, reference_s=1.0)[-1].seconds == 0.0  # clock granularity, never negative


def test_the_reference_restores_opencv_threads():
    threads = cv2.getNumThreads()
    timing = time_reference(frame_files(SIM_FLIGHT)[:2])
    assert timing.frames == 2 and timing.seconds > 0
    assert cv2.getNumThreads() == threads


@pytest.mark.parametrize("args, message", [(["--pairs", "2", "--methods", "sift,nosuch"], "unknown method"),
                                           (["--pairs", "2", "-O", "sift.nosuch=1"], "nosuch")])
def test_bad_pair_methods_fail_before_any_work(tmp_path, monkeypatch, args, message):
    def forbidden(*_):
        raise AssertionError("the reference workload ran")

    monkeypatch.setattr("udh_cli.bench.speed.time_reference", forbidden)
    result = CliRunner().invoke(cli.app, ["bench", "speed", str(SIM_FLIGHT), "--out", str(tmp_path / "results"), *args])
    assert result.exit_code != 0 and isinstance(result.exception, UdhError) and message in str(result.exception)
    assert not (tmp_path / "results").exists()


def test_a_file_as_out_fails_before_any_work(tmp_path):
    (tmp_path / "taken").write_text("")
    result = CliRunner().invoke(cli.app, ["bench", "speed", str(SIM_FLIGHT), "--out", str(tmp_path / "taken")])
    assert isinstance(result.exception, UdhError) and "not a folder" in str(result.exception)


def test_a_folder_without_a_flight_fails_in_one_line_before_any_work(tmp_path):
    with pytest.raises(UdhError, match="at least two frames"):
        frame_files(tmp_path)
    (tmp_path / "frame.jpg").write_bytes((SIM_FLIGHT / "frame_000.jpg").read_bytes())
    out = tmp_path / "results"
    result = CliRunner().invoke(cli.app, ["bench", "speed", str(tmp_path), "--out", str(out)])
    assert result.exit_code != 0 and "at least two frames" in str(result.exception)
    assert not out.exists()
