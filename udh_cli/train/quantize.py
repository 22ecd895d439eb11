"""``udh quantize``: a udh ONNX network to int8 (static, per-channel), calibrated on synthetic pairs.

Why: the network pass is most of a single-round estimate on a CPU, and there the convolutions were already
running near the core's float32 peak (the 16x16 layers at about 47 GMAC/s on one core). int8
convolutions ran about 1.8x faster on this AVX2 machine; the shipped coarse network's pass went from 1.7 to
1.1 ms on one core (models/README.md), with the cascade's median accuracy unchanged on the bench pairs (its
tails slightly worse).

What is quantized (measured on the ``corr`` networks, per-op onnxruntime profile, one core):

- every Conv (with its ReLU), Gemm and MaxPool, in QDQ format: weights int8 per output channel, activations uint8 per
  tensor, ranges from calibration (min/max);
- not a Conv with one input channel (the first layer): onnxruntime's int8 kernel took 258 us there
  against 43 us in float32;
- not the correlation MatMul: int8 saved nothing once the extra (de)quantisation was paid.

Needs the ``onnx`` package (the ``[train]`` extra) for onnxruntime's quantisation tools; no torch.
"""

from __future__ import annotations

import importlib.util
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.files import check_replaceable, write_output
from udh_cli.images import check_output_path
from udh_cli.onnx_model import OnnxHomographyModel, write_metadata
from udh_cli.flight_motion import MotionConfig, make_motion_pairs, source_size
from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs, split_holdout

# Calibration motions, as fractions of the rho the network was trained at: a cascade shows a network large
# motion in its first round and small residuals after, and both need their activation ranges covered.
CALIBRATION_MOTION = (1.0, 0.7, 0.35, 0.1)
QUANTIZED_OPS = ("Conv", "Relu", "Gemm", "MaxPool")  # a ReLU quantized with its Conv fuses into it
MAX_MEDIAN_DRIFT_PX = 0.5  # an int8 network further than this from its source (median over check pairs) is refused


def calibration_motions(model: OnnxHomographyModel) -> list[float]:
    """The rho values (px of the S x S input) to calibrate at: :data:`CALIBRATION_MOTION` of the model's
    training rho (metadata ``rho``; 32 px if absent), at least 1 px."""
    try:
        rho = float(model.metadata.get("rho", 32.0))
    except ValueError:
        rho = float("nan")
    if not 0.0 < rho < model.input_size:
        raise UdhError(f"{model.path}: its metadata gives an unusable training rho ({model.metadata.get('rho')!r}); re-export it with `udh export-onnx`")
    return [max(1.0, rho * fraction) for fraction in CALIBRATION_MOTION]


def calibration_patches(sources: list[np.ndarray], model: OnnxHomographyModel, pairs_per_motion: int, seed: int) -> np.ndarray:
    """(N, 2, S, S) synthetic pairs in [0, 1] (with illumination shifts), ``pairs_per_motion`` at each of
    :func:`calibration_motions`."""
    rng = np.random.default_rng(seed)
    batches = []
    flight = model.metadata.get("motion") == "flight"
    for fraction, rho in zip(CALIBRATION_MOTION, calibration_motions(model)):
        if flight:  # calibrate on the motion the network was trained for: its flight ranges, shrunk likewise
            pairs = make_motion_pairs(sources, pairs_per_motion, flight_motion_of(model).scaled(fraction), rng,
                                      patch=model.input_size, with_context=False)
        else:
            pairs = make_pairs(sources, pairs_per_motion, PairConfig(rho=rho, patch_size=model.input_size), rng, with_context=False)
        batches.append(np.stack([pairs.patch_a, pairs.patch_b], 1))
    return np.concatenate(batches)


def flight_motion_of(model: OnnxHomographyModel) -> MotionConfig:
    """The flight-motion ranges in a model's metadata (``udh export-onnx`` writes them)."""
    meta = model.metadata
    try:
        scale = float(meta["max_scale"])
        return MotionConfig(max_heading=float(meta["max_heading"]), scale_range=(1.0 / scale, scale),
                            max_shift=float(meta["max_shift"]), perspective=float(meta.get("rho", 12.0)),
                            residual=float(meta.get("residual", 0.0)))
    except (KeyError, ValueError, ZeroDivisionError):
        raise UdhError(f"{model.path}: its metadata says flight motion but not its ranges; re-export it with `udh export-onnx`") from None


def _nodes_to_quantize(model_proto: Any) -> list[str]:
    """Names of the nodes worth int8 (see the module docstring): Conv/Gemm/MaxPool, less single-channel Convs."""
    weights = {init.name: tuple(init.dims) for init in model_proto.graph.initializer}
    chosen, float_outputs = [], set()
    for node in model_proto.graph.node:
        single_channel = node.op_type == "Conv" and len(weights.get(node.input[1], ())) == 4 and weights[node.input[1]][1] == 1
        if single_channel or (node.op_type == "Relu" and node.input[0] in float_outputs):
            float_outputs.update(node.output)  # its ReLU stays float32 with it
        elif node.op_type in QUANTIZED_OPS:
            chosen.append(node.name)
    return chosen


def quantize_from_folders(source: str | Path, output: str | Path | None, folders: list[Path], images: int = 200,
                          pairs_per_motion: int = 64, seed: int = 0, overwrite: bool = False) -> dict[str, Any]:
    """What ``udh quantize`` does: :func:`quantize_model` calibrated on up to ``images`` images drawn (by
    ``seed``) from the training part of ``folders`` (every tenth image, the benchmarks' held-out split, is
    left out). ``output`` ``None`` writes ``<source stem>-int8.onnx`` beside ``source``; an existing file there is
    replaced only when udh wrote it, or with ``overwrite``."""
    source = Path(source)
    output = source.with_name(f"{source.stem}-int8.onnx") if output is None else Path(output)
    _check_request(source, output, pairs_per_motion, seed, overwrite)
    if images < 1:
        raise UdhError(f"--images ({images}) must be at least 1")
    found = list_images(folders)
    train_paths, _ = split_holdout(found)
    if not train_paths:
        raise UdhError(f"--data holds {len(found)} image(s), all held out for benchmarks (every 10th); give a folder of 2 or more")
    rng = np.random.default_rng(seed)
    chosen = sorted(rng.choice(len(train_paths), min(images, len(train_paths)), replace=False))
    flight = OnnxHomographyModel.load(source).metadata.get("motion") == "flight"
    sources = load_sources([train_paths[i] for i in chosen], min_count=1, size_for=source_size if flight else None)
    return quantize_model(source, output, sources, pairs_per_motion, seed, overwrite)


def _check_request(source: Path, output: Path, pairs_per_motion: int, seed: int, overwrite: bool) -> Path:
    """Fail before any work on a missing onnx package or source, a bad output path, an output that would
    replace the source or a file udh did not write (without ``overwrite``), or bad numbers."""
    if importlib.util.find_spec("onnx") is None:  # onnxruntime's quantisation tools need it
        raise UdhError("quantisation needs the onnx package: pip install onnx (it comes with the udh checkout's train extra: pip install '.[train]')")
    if not Path(source).is_file():
        raise UdhError(f"{source}: no such model file")
    output = check_output_path(output, (".onnx",))
    if output.resolve() == Path(source).resolve():
        raise UdhError(f"{output}: the int8 copy would replace the float32 network it is made from; give another --output")
    check_replaceable(output, overwrite)
    if pairs_per_motion < 1:
        raise UdhError(f"--pairs ({pairs_per_motion}) must be at least 1: calibration pairs per motion level")
    if seed < 0:
        raise UdhError(f"--seed ({seed}) must be 0 or more")
    return output


def quantize_model(source: str | Path, output: str | Path, sources: list[np.ndarray], pairs_per_motion: int = 64,
                   seed: int = 0, overwrite: bool = False) -> dict[str, Any]:
    """Write an int8 copy of the udh ONNX network ``source`` to ``output`` (atomically), calibrated on
    synthetic pairs from ``sources`` (320x240 grey uint8 images, see :func:`udh_cli.synthetic.load_sources`;
    give training images, never the held-out ones).

    The copy keeps the source's metadata and adds ``precision`` ("int8"), ``calibration`` and
    ``quantized_from``. It is checked against the source on fresh pairs (another seed, the same images): the
    median and largest |offset difference| in pixels of the S x S input are returned, and a median above
    :data:`MAX_MEDIAN_DRIFT_PX` is refused.

    Returns ``{"path", "median_drift_px", "max_drift_px", "check_pairs", "metadata"}``.
    """
    output = _check_request(Path(source), Path(output), pairs_per_motion, seed, overwrite)
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    model = OnnxHomographyModel.load(source, device="cpu")
    if model.metadata.get("precision") == "int8":
        raise UdhError(f"{source}: already an int8 model; quantize the float32 network it came from")
    standardised = model.standardise(calibration_patches(sources, model, pairs_per_motion, seed))
    # A network whose own answers are NaN or infinite has no ranges to calibrate (onnxruntime fails deep inside).
    if not np.isfinite(model.session.run(None, {model.session.get_inputs()[0].name: standardised[:8]})[0]).all():
        raise UdhError(f"{source}: the float32 network gives NaN or infinite offsets, so it cannot be quantized; "
                       f"export it again from a good checkpoint (`udh export-onnx`)")
    input_name = model.session.get_inputs()[0].name

    class _Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._items = iter(standardised[i : i + 1] for i in range(len(standardised)))

        def get_next(self) -> dict[str, np.ndarray] | None:
            batch = next(self._items, None)
            return None if batch is None else {input_name: batch}

    with tempfile.TemporaryDirectory(prefix="udh-quantize-") as scratch:
        prepared, quantized = Path(scratch) / "prepared.onnx", Path(scratch) / "int8.onnx"
        # Folds BatchNorm into the convolutions and infers shapes, as onnxruntime recommends before quantizing.
        quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
        quantize_static(
            str(prepared), str(quantized), _Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, calibrate_method=CalibrationMethod.MinMax,
            nodes_to_quantize=_nodes_to_quantize(onnx.load(str(prepared))),
            extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
        )
        proto = onnx.load(str(quantized))
    metadata = dict(model.metadata)
    motions = "/".join(f"{rho:.0f}" for rho in calibration_motions(model))
    metadata["precision"] = "int8"
    metadata["calibration"] = (f"{len(standardised)} synthetic pairs (rho {motions}, illumination shifts) "
                               f"from {len(sources)} images, seed {seed}; static per-channel QDQ, min/max ranges")
    metadata["quantized_from"] = json.dumps({"file": Path(source).name, "steps": metadata.get("steps")})
    write_metadata(proto, metadata)
    onnx.checker.check_model(proto)

    with tempfile.TemporaryDirectory(prefix="udh-quantize-") as scratch:
        candidate = Path(scratch) / "candidate.onnx"
        candidate.write_bytes(proto.SerializeToString())
        int8 = OnnxHomographyModel.load(candidate, device="cpu")
        check = calibration_patches(sources, model, 16, seed + 1)
        drift = np.abs(int8.predict_offsets(check) - model.predict_offsets(check))
    if not np.isfinite(drift).all():
        raise UdhError(f"{source}: the int8 network gives non-finite offsets; it cannot be used")
    median_drift, max_drift = float(np.median(drift)), float(drift.max())
    if median_drift > MAX_MEDIAN_DRIFT_PX:
        raise UdhError(f"{source}: the int8 network drifts {median_drift:.2f} px (median) from the float32 one, more "
                       f"than {MAX_MEDIAN_DRIFT_PX} px; calibrate on more, or more typical, images (--data)")
    write_output(output, proto.SerializeToString(), overwrite)
    return {"path": output, "median_drift_px": median_drift, "max_drift_px": max_drift, "check_pairs": len(check),
            "metadata": metadata}
