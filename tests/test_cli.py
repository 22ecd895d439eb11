"""`udh estimate` end to end: output formats, and bad input that fails in one line with no leftovers."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from udh_cli.estimators import estimator_names
from udh_cli.estimators.flags import OPTION_FLAGS
from udh_cli import cli, geometry
from udh_cli.files import MANIFEST_NAME
from udh_cli.homography_files import format_homography
from udh_cli.models_catalog import licence_help
from udh_cli.onnx_model import RECORDED_SINCE

from conftest import run_main, warped_pair

WIDTH, HEIGHT = 320, 240
TRUTH = geometry.homography_from_offsets(np.random.default_rng(42).uniform(-12, 12, (4, 2)), WIDTH, HEIGHT)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """A textured pair related by TRUTH (A 8-bit grey, B as 16-bit and as colour), its truth file, and bad inputs."""
    folder = tmp_path_factory.mktemp("cli")
    image_a, image_b = warped_pair(TRUTH, WIDTH, HEIGHT, seed=3)
    paths = {name: folder / name for name in ("a.png", "b16.png", "b.jpg", "truth.txt", "flat.png", "one.png", "text.png", "bad_gt.txt")}
    cv2.imwrite(str(paths["a.png"]), image_a)
    cv2.imwrite(str(paths["b16.png"]), (image_b.astype(np.uint16) * 257).astype(np.uint16))
    cv2.imwrite(str(paths["b.jpg"]), cv2.applyColorMap(image_b, cv2.COLORMAP_BONE), [cv2.IMWRITE_JPEG_QUALITY, 95])
    paths["truth.txt"].write_text(format_homography(TRUTH))
    cv2.imwrite(str(paths["flat.png"]), np.full((HEIGHT, WIDTH), 128, np.uint8))
    cv2.imwrite(str(paths["one.png"]), np.zeros((1, 1), np.uint8))
    paths["text.png"].write_text("not an image\n")
    paths["bad_gt.txt"].write_text("1 0 0\n0 1 0\n")
    return paths


# ---------------------------------------------------------------------------------- good input


def test_json_output(files):
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b16.png"]), "--json", "--gt", str(files["truth.txt"])])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert {"method", "homography", "elapsed_ms", "confidence"} <= set(report)
    assert report["method"] == "auto" and report["ok"] is True  # the default method
    homography = np.asarray(report["homography"])
    assert homography.shape == (3, 3)
    assert float(geometry.mace(homography, TRUTH, WIDTH, HEIGHT)) < 0.2
    assert report["corner_error_px"] == pytest.approx(float(geometry.mace(homography, TRUTH, WIDTH, HEIGHT)))
    assert report["corner_error_px"] <= report["corner_rmse_px"] + 1e-12
    assert 0 < report["elapsed_ms"] < 10_000 and 0.5 < report["confidence"] <= 1
    assert report["size_a"] == [WIDTH, HEIGHT] and report["size_b"] == [WIDTH, HEIGHT]
    np.testing.assert_allclose(report["offsets_4pt"], geometry.offsets_from_homography(homography, WIDTH, HEIGHT))


@pytest.mark.parametrize("method", ["orb", "ecc", "identity"])
def test_other_methods_and_colour_jpeg(files, method):
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b.jpg"]), "-m", method, "--json"])
    # identity is a guess by definition (confidence 0): it is printed, and exits with the "unverified" code
    assert result.exit_code == (cli.UNVERIFIED if method == "identity" else 0), result.output
    report = json.loads(result.stdout)
    assert report["method"] == method and report["exit_code"] == result.exit_code
    assert report["verified"] is (method != "identity")
    error = float(geometry.mace(np.asarray(report["homography"]), TRUTH, WIDTH, HEIGHT))
    assert error < {"orb": 2.0, "ecc": 0.3, "identity": 30.0}[method]


def test_an_answer_its_method_does_not_verify_must_also_align(files, monkeypatch):
    """ECC converged far off with a high correlation (as on a large shift from the identity): not verified, exit 3."""
    from udh_cli.estimators.ecc import EccEstimator

    off = geometry.translation(150.0, 40.0) @ TRUTH
    monkeypatch.setattr(EccEstimator, "_estimate", lambda self, pair: (off, 0.9, {"correlation": 0.9}))
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b.jpg"]), "-m", "ecc", "--json"])
    report = json.loads(result.stdout)
    assert report["confidence"] == pytest.approx(0.9) and report["verified"] is False
    assert result.exit_code == report["exit_code"] == cli.UNVERIFIED
    monkeypatch.setattr(EccEstimator, "_estimate", lambda self, pair: (TRUTH, 0.9, {"correlation": 0.9}))
    right = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b.jpg"]), "-m", "ecc", "--json"])
    assert json.loads(right.stdout)["verified"] is True and right.exit_code == 0


def test_an_unverified_answer_is_printed_with_a_warning(files, tmp_path):
    """Two unrelated textured images: auto answers its best guess, says it is unconfirmed, and the JSON says so."""
    from conftest import textured_image

    other = tmp_path / "other.png"
    cv2.imwrite(str(other), textured_image(WIDTH, HEIGHT, seed=99))
    table = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(other)])
    as_json = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(other), "--json"])
    report = json.loads(as_json.stdout)
    # printed, but never as a success: the exit code says "unverified", the warning goes to stderr
    assert table.exit_code == as_json.exit_code == cli.UNVERIFIED
    assert "did not verify" in table.stderr and "did not verify" not in table.stdout and "did not verify" not in as_json.stdout
    assert report["ok"] and report["verified"] is False and report["confidence"] < 0.1
    assert report["exit_code"] == cli.UNVERIFIED
    right = json.loads(CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b16.png"]), "--json"]).stdout)
    assert right["verified"] is True and right["exit_code"] == 0


def test_json_reports_a_failure_as_one_object(files, tmp_path):
    missing = tmp_path / "missing.png"
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(missing), "--json"])
    assert result.exit_code != 0
    report = json.loads(result.stdout)
    assert report["ok"] is False and report["exit_code"] == 1 and "no such file" in report["failure"]


def test_large_images_are_estimated_at_the_work_size_and_answered_at_full_resolution(tmp_path):
    from conftest import warped_pair

    truth = np.array([[1.01, 0.02, 30.0], [-0.015, 0.99, -20.0], [0.0, 0.0, 1.0]])
    a, b = warped_pair(truth, width=2400, height=1800, seed=5, margin=60)
    cv2.imwrite(str(tmp_path / "a.png"), a)
    cv2.imwrite(str(tmp_path / "b.png"), b)
    result = CliRunner().invoke(cli.app, ["estimate", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-m", "sift", "--json", "--work-size", "800"])
    report = json.loads(result.stdout)
    assert result.exit_code == 0 and report["work_size_a"] == [800, 600] and report["size_a"] == [2400, 1800]
    assert float(geometry.mace(np.asarray(report["homography"]), truth, 2400, 1800)) < 3.0  # full-resolution pixels


def test_table_output_and_viz(files, tmp_path):
    picture = tmp_path / "result.png"
    result = CliRunner().invoke(
        cli.app, ["estimate", str(files["a.png"]), str(files["b16.png"]), "--gt", str(files["truth.txt"]), "--viz", str(picture), "-m", "sift", "--best-features", "200"]
    )
    assert result.exit_code == 0, result.output
    for text in ("pixels of A -> pixels of B", "top-left", "bottom-left", "corner error", "confidence", str(picture)):
        assert text in result.stdout
    drawn = cv2.imread(str(picture))
    assert drawn is not None and drawn.shape[1] == WIDTH + 12 + WIDTH and drawn.shape[0] > HEIGHT
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME, "result.png"]  # the picture, and that udh wrote it


# ----------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("case", "message"),
    [
        (["missing.png", "a.png"], "no such file"),
        (["a.png", "text.png"], "not a readable image"),
        (["one.png", "a.png"], "1x1 pixels"),
        (["flat.png", "flat.png", "-m", "sift"], "sift found no homography"),
        (["flat.png", "flat.png"], "auto found no homography: no answer aligns the images"),  # the default method
        (["flat.png", "a.png", "-m", "orb"], "orb found no homography"),
        (["flat.png", "a.png", "-m", "ecc"], "ecc found no homography"),
        (["a.png", "b16.png", "--gt", "bad_gt.txt"], "not a 3x3 homography"),
        (["a.png", "b16.png", "--gt", "missing.txt"], "no such homography file"),
        (["a.png", "b16.png", "-m", "surf"], "'surf' is not one of"),
        (["a.png", "b16.png", "-m", "ecc", "--best-features", "50"], "does not take"),
    ],
)
def test_bad_input_fails_in_one_line_without_leftovers(files, tmp_path, monkeypatch, capfd, case, message):
    args = [str(files[a]) if a in files else (str(tmp_path / a) if a.endswith((".png", ".txt")) else a) for a in case]
    picture = tmp_path / "viz.png"
    code, out, err = run_main(monkeypatch, capfd, "estimate", *args, "--viz", str(picture), "--json")
    assert code == (2 if "is not one of" in message else 1)  # an unknown choice is a usage error
    if out:  # errors the command itself meets are also one JSON object on stdout; usage errors come before it
        report = json.loads(out)
        assert report["ok"] is False and report["exit_code"] == 1 and message in report["failure"]
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], err
    assert "Traceback" not in err and "Value error" not in err  # pydantic's prefix is not shown
    assert not picture.exists() and not any(p.name.startswith(".viz") for p in tmp_path.iterdir())


def test_bad_viz_path_fails_before_estimating(files, tmp_path, monkeypatch, capfd):
    for viz, message in [(tmp_path / "no_folder" / "v.png", "does not exist"), (tmp_path / "v.gif", "unknown file type"), (files["a.png"], "one of the input images")]:
        code, out, err = run_main(monkeypatch, capfd, "estimate", str(files["a.png"]), str(files["b16.png"]), "--viz", str(viz))
        assert code == 1 and message in err and len(err.strip().splitlines()) == 1
    assert cv2.imread(str(files["a.png"])) is not None  # the input was not overwritten


def test_gt_is_checked_before_the_images(files, tmp_path, monkeypatch, capfd):
    # Both are wrong; the cheap check (the truth file) is the one reported, before any image is decoded.
    code, _, err = run_main(monkeypatch, capfd, "estimate", str(files["text.png"]), str(files["a.png"]), "--gt", str(files["bad_gt.txt"]))
    assert code == 1 and "bad_gt.txt" in err


def test_images_are_read_once(files, monkeypatch):
    from udh_cli import api, images

    calls = []
    original = images.read_image
    monkeypatch.setattr(images, "read_image", lambda path: calls.append(Path(path).name) or original(path))
    api.estimate_report(files["a.png"], files["b16.png"], "identity", gt=files["truth.txt"])
    assert calls == ["a.png", "b16.png"]


# ------------------------------------------------------------------------------- real processes


def udh(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "udh_cli", *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=120)


def test_process_exit_codes_and_clean_stderr(files, tmp_path):
    missing = udh("estimate", str(tmp_path / "missing.png"), str(files["a.png"]))
    assert missing.returncode == 1 and missing.stdout == ""
    assert missing.stderr.strip().startswith("error: ") and len(missing.stderr.strip().splitlines()) == 1
    assert "Traceback" not in missing.stderr

    textureless = udh("estimate", str(files["flat.png"]), str(files["flat.png"]), "--method", "sift", "--viz", str(tmp_path / "v.png"))
    assert textureless.returncode == 1 and "Traceback" not in textureless.stderr
    assert textureless.stderr.strip().splitlines() == [textureless.stderr.strip()]
    assert "texture" in textureless.stderr and not (tmp_path / "v.png").exists()


def test_process_json_and_debug_traceback(files, tmp_path):
    good = udh("estimate", str(files["a.png"]), str(files["b.jpg"]), "--json")
    assert good.returncode == 0, good.stderr
    assert good.stderr == ""
    assert np.asarray(json.loads(good.stdout)["homography"]).shape == (3, 3)

    debug = udh("--debug", "estimate", str(tmp_path / "missing.png"), str(files["a.png"]))
    assert debug.returncode != 0
    assert "Traceback" in debug.stderr and "UdhError" in debug.stderr and "no such file" in debug.stderr


# ----------------------------------------------------------------------------------- real data


def test_graf_pair_with_sift_is_within_3_px(shared_data):
    folder = shared_data / "pairs" / "opencv-samples"
    result = udh("estimate", "graf1.png", "graf3.png", "--method", "sift", "--gt", "H1to3p.xml", "--json", cwd=folder)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["corner_error_px"] < 3.0  # measured 1.33 px (RMSE 1.39)
    assert report["size_a"] == [800, 640]


def test_usage_errors_are_one_line_with_exit_code_2():
    import subprocess
    import sys

    for args in (["estimate", "only_one.png"], ["estimate", "a.png", "b.png", "--best-features", "abc"], ["bench", "synthetic", "--n", "x"]):
        result = subprocess.run([sys.executable, "-m", "udh_cli", *args], capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, args
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("error:") and "--help" in lines[0], result.stderr
        assert "Traceback" not in result.stderr


def test_error_messages_are_printed_as_text_not_markup(tmp_path):
    import subprocess
    import sys

    missing = tmp_path / "flight[train].png"
    result = subprocess.run([sys.executable, "-m", "udh_cli", "estimate", str(missing), str(missing)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 1
    assert "flight[train].png" in result.stderr


def test_method_names_are_case_insensitive_and_bool_flags_show_no_metavar(files):
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "SIFT", "--json"])
    assert result.exit_code == 0 and json.loads(result.stdout)["method"] == "sift"
    help_text = CliRunner().invoke(cli.app, ["estimate", "--help"], terminal_width=200).stdout
    flag_lines = [line for line in help_text.splitlines() if "--json" in line or "--full-resolution" in line]
    assert len(flag_lines) == 2 and not any("<bool>" in line for line in flag_lines) and "IMAGE_A" in help_text
    for name in estimator_names():  # the --method help is the registry's, every method described
        assert name in help_text


def test_simulate_writes_a_flight_with_ground_truth_and_never_into_a_used_folder(tmp_path):
    folder = tmp_path / "flight"
    result = CliRunner().invoke(cli.app, ["simulate", str(folder), "--strips", "2", "--frames-per-strip", "3", "--width", "320", "--height", "240"])
    assert result.exit_code == 0, result.output
    truth = json.loads((folder / "ground_truth.json").read_text())
    assert len(truth["frames"]) == 6 and len(list(folder.glob("frame_*.jpg"))) == 6
    assert cv2.imread(str(folder / "frame_000.jpg")).shape == (240, 320, 3)
    before = (folder / "frame_000.jpg").read_bytes()
    again = CliRunner().invoke(cli.app, ["simulate", str(folder)])
    assert again.exit_code == 1 and (folder / "frame_000.jpg").read_bytes() == before


def test_the_papers_single_pass_is_still_one_command(files):
    args = ["estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "unsupervised", "--iterations", "1", "--refine-rounds", "0",
            "--headings", "1", "--no-tiles", "--flight-model", "none", "--json"]
    result = CliRunner().invoke(cli.app, args)
    report = json.loads(result.stdout)
    assert report["ok"] and report["details"]["iterations"] == 1 and report["details"]["refine_rounds"] == 0
    assert "tile_levels" not in report["details"] and "tiles" not in report["details"]["stage_ms"]
    full = json.loads(CliRunner().invoke(cli.app, args[:5] + ["--json"]).stdout)
    assert full["details"]["tile_levels"] >= 0 and full["details"]["refine_rounds"] == 2


def test_estimate_takes_method_options_in_the_one_syntax(files):
    """-O [METHOD.]KEY=VALUE on estimate, as on mosaic and bench: it reaches the method, and a key the method does
    not take is a one-line error."""
    a, b = str(files["a.png"]), str(files["b16.png"])
    few = json.loads(CliRunner().invoke(cli.app, ["estimate", a, b, "-m", "sift", "-O", "best_features=40", "--json"]).stdout)
    assert few["ok"] and few["details"]["keypoints_a"] == 40
    also = json.loads(CliRunner().invoke(cli.app, ["estimate", a, b, "-m", "sift", "-O", "sift.best_features=40", "--json"]).stdout)
    assert also["homography"] == few["homography"]
    wrong = CliRunner().invoke(cli.app, ["estimate", a, b, "-m", "sift", "-O", "iterations=3"])
    assert wrong.exit_code == 1 and "no method here takes 'iterations'" in str(wrong.exception)


def test_a_bad_option_still_prints_one_json_object(files):
    result = CliRunner().invoke(cli.app, ["estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "sift", "-O", "iterations=3", "--json"])
    payload = json.loads(result.stdout)
    assert payload["ok"] is False and payload["exit_code"] == 1 and "iterations" in payload["failure"]


def test_help_at_80_columns_shows_every_option_name_whole(monkeypatch):
    """Rich shrinks the option-name column to fit the terminal; no command's option name may end in an ellipsis."""
    import typer

    def paths(command, path):
        yield path
        for name, sub in getattr(command, "commands", {}).items():
            yield from paths(sub, path + [name])

    for path in paths(typer.main.get_command(cli.app), []):
        out = CliRunner().invoke(cli.app, [*path, "--help"], env={"COLUMNS": "80"}).output
        assert max(len(line) for line in out.splitlines()) <= 80, path
        names = [line.strip("│ ").split("  ")[0] for line in out.splitlines() if line.strip("│ ").startswith("-")]
        assert names and not [n for n in names if "…" in n], (path, names)


def test_the_map_shape_line_hints_at_the_ground_plane_only_when_it_is_off():
    from udh_cli.cli_mosaic import _plane_hint

    assert "--rectify or --solve camera" in _plane_hint(6.165, 0.041, {"rectify": False, "solve": "homography"})
    assert _plane_hint(0.5, 0.041, {}) == "" and _plane_hint(6.0, 0.04, {"solve": "camera"}) == ""


# ------------------------------------------------------------------------------------ start-up

# Modules a command that needs none of them must not load: the networks' runtime, torch, SciPy (the solves), the
# mosaic package and the estimators that do real work.
HEAVY_MODULES = ("onnxruntime", "torch", "scipy", "udh_cli.mosaic", "udh_cli.onnx_model", "udh_cli.bench", "udh_cli.estimators.features",
                 "udh_cli.estimators.ecc", "udh_cli.estimators.deep", "udh_cli.estimators.refined", "udh_cli.estimators.tiles",
                 "udh_cli.estimators.matching")


def modules_loaded_by(*args: str) -> set[str]:
    """The modules loaded by ``udh ARGS`` (no args: by importing udh_cli.cli alone), read in a fresh process."""
    code = ("import sys\nimport udh_cli.cli as cli\nsys.argv = ['udh', *sys.argv[1:]]\n"
            "try:\n    cli.main() if len(sys.argv) > 1 else None\nexcept SystemExit:\n    pass\n"
            "sys.stderr.write('MODULES ' + ' '.join(sys.modules))\n")
    result = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)
    return set(result.stderr.split("MODULES ", 1)[1].split())


def heavy(modules: set[str]) -> set[str]:
    return {m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY_MODULES)}


@pytest.mark.parametrize("args", [(), ("--help",), ("estimate", "--help"), ("bench", "speed", "--help")])
def test_start_up_imports_nothing_heavy(args):
    assert heavy(modules_loaded_by(*args)) == set()


@pytest.mark.parametrize("args", [(), ("--help",), ("estimate", "--help"), ("simulate", "--help"), ("train", "--help")])
def test_start_up_needs_no_numpy(args):
    # NumPy is a tenth of a second of `udh --help`: the commands' defaults and the estimator names are read without it.
    assert not {"numpy", "cv2"} & modules_loaded_by(*args)


def test_the_public_names_load_on_first_use():
    code = ("import sys, udh_cli\nloaded = 'numpy' in sys.modules\n"
            "from udh_cli import Estimate, Estimator, create_estimator\nfrom udh_cli.estimators import require_ok\n"
            "print(loaded, Estimate.__module__, Estimator.__name__, require_ok.__module__, type(create_estimator('identity')).__name__)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.stdout.split() == ["False", "udh_cli.estimators.base", "Estimator", "udh_cli.estimators.base", "IdentityEstimator"]


def test_the_mosaic_command_loads_when_invoked():
    loaded = modules_loaded_by("mosaic", "--help")
    assert "udh_cli.mosaic.config" in loaded and "udh_cli.cli_mosaic" in loaded
    assert not {"onnxruntime", "torch"} & loaded


def test_estimate_help_states_the_licence_of_the_shipped_weights(monkeypatch, capfd):
    code, out, _ = run_main(monkeypatch, capfd, "estimate", "--help")
    assert code == 0 and licence_help() in " ".join(out.split()) and "models/README.md" in out


def test_estimate_flags_go_where_dash_o_goes_and_may_not_contradict_it(files, monkeypatch):
    from udh_cli import api

    seen = {}
    monkeypatch.setattr(api, "estimate_report", lambda *args, **kwargs: seen.update(kwargs) or {"verified": True})
    args = ["estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "auto", "-O", "network.iterations=1", "-O", "min_score=0.6", "--search", "2"]
    assert CliRunner().invoke(cli.app, [*args, "--flight-model", "none", "--json"]).exit_code == 0
    assert seen["network"] == {"iterations": 1, "search": 2, "flight_model": ""} and seen["min_score"] == 0.6
    contradicted = CliRunner().invoke(cli.app, [*args, "-O", "network.search=1"])
    assert contradicted.exit_code == 1  # main() prints the error as one line; the runner keeps it as the exception
    assert "network.search is given twice, as --search 2 and -O network.search=1" in str(contradicted.exception)
    help_text = CliRunner().invoke(cli.app, ["estimate", "--help"], env={"COLUMNS": "400"}).stdout
    for flag in OPTION_FLAGS:  # every flag, its help from the one table
        assert flag.name in help_text and flag.help[:40] in " ".join(help_text.split())
    too_far = CliRunner().invoke(cli.app, [*args[:-1], "5"])
    assert too_far.exit_code == 2 and "less than or equal to 4" in too_far.output


def test_estimate_notes_what_a_model_file_lacks_on_stderr_and_in_the_json(files, tmp_path, monkeypatch, capfd):
    from conftest import export_tiny_network

    tiny = export_tiny_network(tmp_path, "corr", seed=0)  # exported without --licence
    code, out, err = run_main(monkeypatch, capfd, "estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "unsupervised",
                              "-O", f"model={tiny}", "--json")
    report = json.loads(out)
    assert code in (0, 3) and report["notes"] == [f"corr.onnx: {line}" for line in [RECORDED_SINCE["licence"]]]
    assert "note: corr.onnx: records no licence for its weights" in " ".join(err.split())
    code, out, _ = run_main(monkeypatch, capfd, "estimate", str(files["a.png"]), str(files["b16.png"]), "-m", "sift", "--json")
    assert "notes" not in json.loads(out)  # classical methods have no model files
