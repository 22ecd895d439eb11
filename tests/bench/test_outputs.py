"""End-to-end `udh bench` runs on small made-up sets: the files and plots it writes, crash handling,
and bad input that fails in one clear line before any work."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from udh_cli import cli, geometry
from udh_cli.bench import run_pairs_bench, run_synthetic_bench, write_outputs
from udh_cli.bench import runner as bench_runner
from udh_cli.errors import UdhError
from udh_cli.estimators.identity import IdentityEstimator
from udh_cli.homography_files import format_homography

from conftest import textured_image, warped_pair

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("held_out")
    for seed in range(6):
        cv2.imwrite(str(folder / f"img{seed}.png"), textured_image(400, 300, seed=seed))
    return folder


@pytest.fixture(scope="module")
def small_run(image_folder, tmp_path_factory):
    result = run_synthetic_bench(images=image_folder, rhos=[16.0, 32.0], count=6, seed=0, methods=["identity", "orb"],
                                 mode="both", show_progress=False)
    out = tmp_path_factory.mktemp("out")
    return result, out, write_outputs(result, out)


def test_every_method_input_and_rho_gets_a_row(small_run):
    result, _, _ = small_run
    rows = {(r.set_name, r.method, r.input) for r in result.runs}
    assert rows == {(s, m, i) for s in ("rho 16", "rho 32") for m, i in
                    (("identity", "patch"), ("orb", "patch"), ("orb", "full"))}
    assert all(r.summary.pairs == 6 for r in result.runs)


def test_result_files_agree_with_the_runs(small_run):
    result, out, written = small_run
    assert {p.name for p in written} == {"results.md", "results.csv", "results.json", "per_pair.csv",
                                         "percentiles.png", "speed_accuracy.png"}
    data = json.loads((out / "results.json").read_text())
    assert len(data["results"]) == len(result.runs) and data["config"]["mode"] == "both"
    first = data["results"][0]
    assert first["mace_mean"] == pytest.approx(result.runs[0].summary.mace_mean)
    assert "| rho 16 | orb | full |" in (out / "results.md").read_text()
    assert len((out / "per_pair.csv").read_text().strip().splitlines()) == 1 + 6 * len(result.runs)
    assert not list(out.glob("*.part"))  # atomic writes leave no temporaries


@pytest.mark.parametrize("name", ["percentiles.png", "speed_accuracy.png"])
def test_plots_are_readable_pngs_of_sensible_size(small_run, name):
    _, out, _ = small_run
    path = out / name
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    assert 5_000 < path.stat().st_size < 200_000
    image = cv2.imread(str(path))
    assert image is not None and 400 <= image.shape[0] <= 1200 and 600 <= image.shape[1] <= 2000
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 20  # lines, text and colours, not a blank canvas


class _CrashesOnEveryOtherPair(IdentityEstimator):
    """Answers like identity, but raises on every second call after the warm-up."""

    calls = 0

    def estimate_many(self, pairs):
        results = []
        for a, b in pairs:
            type(self).calls += 1
            if type(self).calls > 3 and type(self).calls % 2 == 0:
                raise RuntimeError("boom")
            results.append(self.estimate(a, b))
        return results


def test_a_method_that_crashes_on_some_pairs_counts_them_as_failures(image_folder, monkeypatch):
    monkeypatch.setattr(bench_runner, "create_estimator", lambda name, **kw: _CrashesOnEveryOtherPair())
    result = run_synthetic_bench(images=image_folder, rhos=[16.0], count=10, methods=["crashy"], mode="patch",
                                 show_progress=False)
    (run,) = result.runs
    crashed = [f for f in run.failures if f.startswith("crashed: RuntimeError: boom")]
    assert 0 < len(crashed) < 10 and run.summary.no_answer_rate == pytest.approx(len(crashed) / 10)


def test_unknown_method_fails_before_any_work(tmp_path):
    with pytest.raises(UdhError, match="unknown method 'nope'"):
        run_synthetic_bench(images=tmp_path / "missing", methods=["sift", "nope"], show_progress=False)


def test_missing_model_fails_clearly(tmp_path):
    with pytest.raises(UdhError, match="no such model file"):
        run_synthetic_bench(images=tmp_path, methods=["unsupervised"], options={"unsupervised": {"model": str(tmp_path / "x.onnx")}},
                            show_progress=False)


def test_empty_and_too_small_image_folders(tmp_path):
    with pytest.raises(UdhError, match="no images found"):
        run_synthetic_bench(images=tmp_path, methods=["identity"], show_progress=False)
    cv2.imwrite(str(tmp_path / "one.png"), textured_image(320, 240))
    with pytest.raises(UdhError, match="need at least 5"):
        run_synthetic_bench(images=tmp_path, methods=["identity"], show_progress=False)


def test_pairs_csv_and_oxford_folder(tmp_path):
    truth = geometry.homography_from_offsets(np.random.default_rng(1).uniform(-10, 10, (4, 2)), 320, 240)
    image_a, image_b = warped_pair(truth, seed=4)
    cv2.imwrite(str(tmp_path / "img1.png"), image_a)
    cv2.imwrite(str(tmp_path / "img2.png"), image_b)
    (tmp_path / "H1to2p").write_text(format_homography(truth))
    numbers = " ".join(f"{v:.10g}" for v in truth.ravel())
    (tmp_path / "pairs.csv").write_text(f"img1,img2,H\nimg1.png,img2.png,{numbers}\n")
    for source in (tmp_path, tmp_path / "pairs.csv"):
        result = run_pairs_bench(source, methods=["sift"], show_progress=False)
        assert result.runs[0].input == "image" and result.runs[0].summary.mace_mean < 1.0


@pytest.mark.parametrize("content, message", [
    ("img1,img2,H\na.png,b.png,1 0 0 0 1 0 0 0\n", "line 2, column H: not a 3x3 homography"),
    ("img1,img2,H\na.png,b.png,1 2 3 2 4 6 0 0 1\n", "line 2, column H: the homography is singular"),
    ("img1,img2\na.png,b.png\n", "missing column"),
    ("img1,img2,H\n", "no pairs"),
])
def test_malformed_ground_truth_csv(tmp_path, content, message):
    (tmp_path / "bad.csv").write_text(content)
    with pytest.raises(UdhError, match=message):
        run_pairs_bench(tmp_path / "bad.csv", methods=["identity"], show_progress=False)


def test_malformed_oxford_homography_file(tmp_path):
    cv2.imwrite(str(tmp_path / "img1.png"), textured_image())
    cv2.imwrite(str(tmp_path / "img3.png"), textured_image(seed=1))
    (tmp_path / "H1to3p").write_text("1 0 0\n0 1\n")
    with pytest.raises(UdhError, match="not a 3x3 homography"):
        run_pairs_bench(tmp_path, methods=["identity"], show_progress=False)


def test_cli_prints_the_table_and_writes_the_files(image_folder, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(cli.app, ["bench", "synthetic", "--images", str(image_folder), "--rho", "16", "--n", "4",
                                          "-m", "identity", "--no-plots", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "| rho 16 | identity | patch |" in result.stdout
    assert (out / "results.csv").is_file() and not (out / "percentiles.png").exists()


def test_cli_refuses_a_bad_out_folder_before_running(image_folder, tmp_path, monkeypatch):
    (tmp_path / "taken").write_text("a file, not a folder")
    ran = []
    monkeypatch.setattr(bench_runner, "run_jobs", lambda *args, **kwargs: ran.append(1))
    for out in (tmp_path / "taken", tmp_path / "taken" / "sub"):
        result = CliRunner().invoke(cli.app, ["bench", "synthetic", "--images", str(image_folder), "--rho", "16", "--n", "2",
                                              "-m", "identity", "--out", str(out)])
        assert result.exit_code != 0 and isinstance(result.exception, UdhError)
        assert "is a file, not a folder" in str(result.exception)
    assert ran == []  # refused before any pair was estimated


def test_graf_pair_from_the_shared_data(shared_data, tmp_path):
    result = run_pairs_bench(shared_data / "pairs" / "opencv-samples", methods=["sift"], prefix="graf", show_progress=False)
    assert result.runs[0].summary.mace_mean < 3.0


def test_the_flight_motion_set_refuses_saved_pairs_instead_of_ignoring_them(tmp_path):
    for given in ({"save_pairs": tmp_path / "p.npz"}, {"load_pairs": tmp_path / "p.npz"}):
        with pytest.raises(UdhError, match="drawn again from --seed"):
            run_synthetic_bench(images=tmp_path, count=4, methods=["identity"], motion="flight", **given)
    assert list(tmp_path.iterdir()) == []
