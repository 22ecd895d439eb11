"""int8 quantisation (udh_cli.train.quantize) and the choice of shipped precision (models_catalog)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import export_tiny_network, run_main, textured_image, warped_pair
from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator
from udh_cli.models_catalog import SHIPPED_INT8, models_dir, shipped_onnx
from udh_cli.onnx_model import OnnxHomographyModel


def _sources(count: int = 6) -> list[np.ndarray]:
    return [cv2.resize(textured_image(400, 300, seed=20 + i), (320, 240), interpolation=cv2.INTER_AREA) for i in range(count)]


@pytest.fixture(scope="module")
def tiny_float_and_int8(tmp_path_factory) -> tuple[Path, Path, dict]:
    pytest.importorskip("onnx")
    from udh_cli.train.quantize import quantize_model

    folder = tmp_path_factory.mktemp("quantize")
    source = export_tiny_network(folder, "corr", seed=0)  # the seed the estimator and fuzz tests export too
    result = quantize_model(source, folder / "tiny-int8.onnx", _sources(), pairs_per_motion=8, seed=0)
    return source, folder / "tiny-int8.onnx", result


def test_int8_copy_keeps_metadata_and_stays_close_to_float(tiny_float_and_int8):
    import onnx

    source, int8_path, result = tiny_float_and_int8
    float_model, int8_model = OnnxHomographyModel.load(source, "cpu"), OnnxHomographyModel.load(int8_path, "cpu")
    assert int8_model.metadata["precision"] == "int8" and "32 synthetic pairs" in int8_model.metadata["calibration"]
    assert json.loads(int8_model.metadata["quantized_from"])["file"] == source.name
    for key in ("arch", "input_size", "normalization_mean", "normalization_std", "rho", "steps"):
        assert int8_model.metadata[key] == float_model.metadata[key]

    # The reported drift is what the two models do on fresh pairs, and it is small against the motion.
    rng = np.random.default_rng(5)
    patches = rng.random((24, 2, 32, 32)).astype(np.float32)
    drift = np.abs(int8_model.predict_offsets(patches) - float_model.predict_offsets(patches))
    scale = np.abs(float_model.predict_offsets(patches)).mean()
    assert 0.0 < result["median_drift_px"] <= 0.5 and np.median(drift) < 0.1 * scale + 0.05

    # Every convolution's weights come through a DequantizeLinear (int8), except the single-channel first one's.
    graph = onnx.load(str(int8_path)).graph
    produced_by = {out: node.op_type for node in graph.node for out in node.output}
    shapes = {init.name: tuple(init.dims) for init in graph.initializer}
    convs = [node for node in graph.node if node.op_type == "Conv"]
    float_convs = [node for node in convs if produced_by.get(node.input[1]) != "DequantizeLinear"]
    assert len(convs) >= 6 and len(float_convs) == 1
    assert shapes[float_convs[0].input[1]][1] == 1  # its one input channel


def test_int8_model_runs_in_the_estimator(tiny_float_and_int8):
    source, int8_path, _ = tiny_float_and_int8
    truth = geometry.translation(1.5, -1.0)
    a, b = warped_pair(truth, 320, 240, seed=8)
    int8 = create_estimator("unsupervised", model=str(int8_path), device="cpu").estimate(a, b)
    fp32 = create_estimator("unsupervised", model=str(source), device="cpu").estimate(a, b)
    assert int8.details["precision"] == "int8" and fp32.details["precision"] == "fp32"
    # An untrained network: not accurate, but the int8 copy answers like its source.
    assert geometry.mace(int8.homography, fp32.homography, 320, 240) < 2.0


def test_quantizing_twice_over_itself_or_too_far_is_refused(tiny_float_and_int8, tmp_path, monkeypatch):
    from udh_cli.train import quantize

    source, int8_path, _ = tiny_float_and_int8
    with pytest.raises(UdhError, match="already an int8 model"):
        quantize.quantize_model(int8_path, tmp_path / "again.onnx", _sources(), pairs_per_motion=4)
    with pytest.raises(UdhError, match="would replace the float32 network"):
        quantize.quantize_model(source, source, _sources(), pairs_per_motion=4)
    with pytest.raises(UdhError, match=r"--seed \(-1\)"):
        quantize.quantize_model(source, tmp_path / "x.onnx", _sources(), seed=-1)
    broken = OnnxHomographyModel.load(source, "cpu")
    broken.metadata["rho"] = "lots"
    with pytest.raises(UdhError, match="unusable training rho"):
        quantize.calibration_motions(broken)
    monkeypatch.setattr(quantize, "MAX_MEDIAN_DRIFT_PX", -1.0)  # any drift is too much
    with pytest.raises(UdhError, match="drifts"):
        quantize.quantize_model(source, tmp_path / "refused.onnx", _sources(), pairs_per_motion=4)
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_quantize_command(tiny_float_and_int8, tmp_path, monkeypatch, capfd):
    source, _, _ = tiny_float_and_int8
    images = tmp_path / "images"
    images.mkdir()
    for i in range(4):  # one of them is held out
        cv2.imwrite(str(images / f"{i}.png"), textured_image(320, 240, seed=40 + i))
    copy = tmp_path / "tiny.onnx"
    copy.write_bytes(source.read_bytes())
    code, out, err = run_main(monkeypatch, capfd, "quantize", str(copy), "--data", str(images), "--pairs", "4")
    assert code == 0, err
    written = tmp_path / "tiny-int8.onnx"  # the default output: beside the model, named after it
    assert written.is_file() and "px median" in out
    metadata = OnnxHomographyModel.load(written, "cpu").metadata
    assert metadata["precision"] == "int8" and "from 3 images" in metadata["calibration"]

    # Bad data: one line, no traceback, nothing written.
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_main(monkeypatch, capfd, "quantize", str(copy), "--data", str(empty), "-o", str(tmp_path / "x.onnx"))
    assert code != 0 and "holds 0 image(s)" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    for name in ("a.png", "b.png"):  # two files to train on, neither readable
        (empty / name).write_bytes(b"not a png")
    code, _, err = run_main(monkeypatch, capfd, "quantize", str(copy), "--data", str(empty), "-o", str(tmp_path / "x.onnx"))
    assert code != 0 and "found 0 usable images" in err and not (tmp_path / "x.onnx").exists()


def test_shipped_int8_copies_exist_and_are_the_default():
    for name, stem in SHIPPED_INT8.items():
        assert (models_dir() / f"{stem}.onnx").is_file(), f"shipped int8 {name} model missing"
    assert shipped_onnx("unsupervised", None).name == "udh-unsupervised-int8.onnx"  # int8 where shipped
    assert shipped_onnx("unsupervised").name == "udh-unsupervised.onnx"  # the float32 default for --init etc.
    assert shipped_onnx("supervised", None).name == "udh-supervised.onnx"  # no int8 copy: float32
    with pytest.raises(UdhError, match="no int8 copy of the supervised"):
        shipped_onnx("supervised", "int8")
    with pytest.raises(UdhError, match="unknown precision 'int4'"):
        create_estimator("unsupervised", precision="int4")
    with pytest.raises(UdhError, match="unknown precision 'int4'"):  # checked with a model file too
        create_estimator("unsupervised", model=str(shipped_onnx("unsupervised")), precision="int4")


def test_shipped_int8_cascade_matches_float32_on_pairs_it_never_saw():
    """The default (int8) cascade against the float32 one on test-made pairs: the same median accuracy."""
    int8, fp32 = create_estimator("unsupervised", device="cpu"), create_estimator("unsupervised", device="cpu", precision="fp32")
    rng = np.random.default_rng(11)
    errors = {"int8": [], "fp32": []}
    for seed in range(8):
        small = geometry.homography_from_offsets(rng.uniform(-16, 16, (4, 2)), 128, 128)
        truth = geometry.rescale_homography(small, (128, 128), (320, 240))
        a, b = warped_pair(truth, 320, 240, seed=seed)
        for name, estimator in (("int8", int8), ("fp32", fp32)):
            estimate = estimator.estimate(a, b)
            assert estimate.details["precision"] == name  # what ran is reported
            errors[name].append(geometry.mace(estimate.homography, truth, 320, 240))
    assert np.median(errors["int8"]) < 2.5  # px at 320x240, corners moved by up to 40 px
    assert abs(np.median(errors["int8"]) - np.median(errors["fp32"])) < 0.5
    # A float32 model file followed by the shipped int8 refinement network is reported as such.
    mixed = create_estimator("unsupervised", model=str(shipped_onnx("unsupervised")), refine_rounds=1, device="cpu")
    assert mixed.loaded_precision() == "mixed"


def test_estimate_command_takes_a_precision(tmp_path, monkeypatch, capfd):
    truth = geometry.translation(3.0, 2.0)
    a, b = warped_pair(truth, 320, 240, seed=2)
    folder = tmp_path
    cv2.imwrite(str(folder / "a.png"), a)
    cv2.imwrite(str(folder / "b.png"), b)
    code, out, err = run_main(monkeypatch, capfd, "estimate", str(folder / "a.png"), str(folder / "b.png"), "-m", "unsupervised",
                              "--precision", "fp32", "--json")
    assert code == 0, err
    assert json.loads(out)["details"]["precision"] == "fp32"
    code, _, err = run_main(monkeypatch, capfd, "estimate", str(folder / "a.png"), str(folder / "b.png"), "-m", "unsupervised",
                            "--precision", "fp16")
    assert code != 0 and "unknown precision 'fp16'" in err
