"""int8 quantisation (udh_cli.train.quantize) and the choice of shipped precision (models_catalog)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import export_tiny_network, run_main, textured_image, warped_pair
from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator
from udh_cli.models_catalog import has_shipped, shipped_variant
from udh_cli.onnx_model import OnnxHomographyModel


def _sources(count: int = 6) -> list[np.ndarray]:
    return [cv2.resize(textured_image(400, 300, seed=20 + i), (320, 240), interpolation=cv2.INTER_AREA) for i in range(count)]


@pytest.fixture(scope="module")
def tiny_float_and_int8(tmp_path_factory) -> tuple[Path, Path, dict]:
    pytest.importorskip("onnx")
    from udh_cli.train.quantize import quantize_model

    folder = tmp_path_factory.mktemp("quantize")
    source = export_tiny_network(folder, "corr", seed=3)
    result = quantize_model(source, folder / "tiny-int8.onnx", _sources(), pairs_per_motion=8, seed=0)
    return source, folder / "tiny-int8.onnx", result


def test_int8_copy_keeps_metadata_and_stays_close_to_float(tiny_float_and_int8):
    import onnx

    source, int8_path, result = tiny_float_and_int8
    float_model, int8_model = OnnxHomographyModel.load(source, "cpu"), OnnxHomographyModel.load(int8_path, "cpu")
    assert int8_model.metadata["precision"] == "int8" and "32 synthetic pairs" in int8_model.metadata["calibration"]
    for key in ("arch", "input_size", "normalization_mean", "normalization_std", "rho", "steps"):
        assert int8_model.metadata[key] == float_model.metadata[key]

    # The reported drift is what the two models do on fresh pairs, and it is small against the motion.
    rng = np.random.default_rng(5)
    patches = rng.random((24, 2, 32, 32)).astype(np.float32)
    drift = np.abs(int8_model.predict_offsets(patches) - float_model.predict_offsets(patches))
    scale = np.abs(float_model.predict_offsets(patches)).mean()
    assert 0.0 < result["median_drift_px"] <= 0.5 and np.median(drift) < 0.1 * scale + 0.05

    # Weights are int8 except the single-channel first convolution's, which stays float32 (with its ReLU).
    graph = onnx.load(str(int8_path)).graph
    int8_weights = [init for init in graph.initializer if init.data_type == onnx.TensorProto.INT8 and len(init.dims) == 4]
    float_convs = [node for node in graph.node if node.op_type == "Conv" and not any("DequantizeLinear" in i for i in node.input[1:2])]
    assert len(int8_weights) == 6  # encoder 3 + regressor 3 at 32 px (first conv excluded)
    assert len(float_convs) == 1 and all(dim == 1 for dim in [next(i.dims[1] for i in graph.initializer if i.name == float_convs[0].input[1])])


def test_int8_model_runs_in_the_estimator(tiny_float_and_int8):
    _, int8_path, _ = tiny_float_and_int8
    a, b = textured_image(320, 240, seed=8), textured_image(320, 240, seed=9)
    estimate = create_estimator("unsupervised", model=str(int8_path), device="cpu").estimate(a, b)
    assert estimate.homography is None or np.isfinite(estimate.homography).all()
    assert 0.0 <= estimate.confidence <= 1.0


def test_quantizing_twice_and_drifting_too_far_are_refused(tiny_float_and_int8, tmp_path, monkeypatch):
    from udh_cli.train import quantize

    source, int8_path, _ = tiny_float_and_int8
    with pytest.raises(UdhError, match="already an int8 model"):
        quantize.quantize_model(int8_path, tmp_path / "again.onnx", _sources(), pairs_per_motion=4)
    monkeypatch.setattr(quantize, "MAX_MEDIAN_DRIFT_PX", -1.0)  # any drift is too much
    with pytest.raises(UdhError, match="drifts"):
        quantize.quantize_model(source, tmp_path / "refused.onnx", _sources(), pairs_per_motion=4)
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_quantize_command_reports_a_bad_data_folder(tiny_float_and_int8, tmp_path, monkeypatch, capfd):
    source, _, _ = tiny_float_and_int8
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_main(monkeypatch, capfd, "quantize", str(source), "--data", str(empty), "-o", str(tmp_path / "x.onnx"))
    assert code != 0 and not (tmp_path / "x.onnx").exists()
    assert "holds 0 image(s)" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    for name in ("a.png", "b.png"):  # two files to train on, neither readable
        (empty / name).write_bytes(b"not a png")
    code, _, err = run_main(monkeypatch, capfd, "quantize", str(source), "--data", str(empty), "-o", str(tmp_path / "x.onnx"))
    assert code != 0 and "found 0 usable images" in err and not (tmp_path / "x.onnx").exists()


def test_shipped_precision_choice():
    if not has_shipped("unsupervised-int8"):
        pytest.skip("shipped int8 model not built yet")
    assert shipped_variant("unsupervised", None) == "unsupervised-int8"  # int8 where shipped
    assert shipped_variant("unsupervised", "fp32") == "unsupervised"
    assert shipped_variant("supervised", None) == "supervised"  # no int8 copy: float32
    with pytest.raises(UdhError, match="no int8 copy of the supervised"):
        shipped_variant("supervised", "int8")
    with pytest.raises(UdhError, match="unknown precision 'int4'"):
        create_estimator("unsupervised", precision="int4")


def test_shipped_int8_cascade_matches_float32_on_pairs_it_never_saw():
    """The default (int8) cascade against the float32 one on test-made pairs: the same accuracy."""
    if not has_shipped("unsupervised-int8"):
        pytest.skip("shipped int8 model not built yet")
    int8, fp32 = create_estimator("unsupervised", device="cpu"), create_estimator("unsupervised", device="cpu", precision="fp32")
    assert int8.network.metadata["precision"] == "int8" and "precision" not in fp32.network.metadata
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
