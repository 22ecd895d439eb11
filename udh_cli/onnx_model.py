"""Loading a udh ONNX network for inference (onnxruntime only; no torch), with its metadata checked."""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.files import read_side_file

MODEL_FORMAT = "udh-onnx-1"
MAX_INPUT_SIZE = 512  # px: the largest patch training builds (udh_cli.train.checkpoint.MAX_PATCH_SIZE)
MAX_MODEL_BYTES = 2**31  # protobuf's own limit for one ONNX file


LICENCE_KEY = "licence"  # the metadata key of the weights' licence, e.g. "research use only" or "CC BY 4.0"
# Metadata that older udh exports lack, and what a file without it is taken to be.
RECORDED_SINCE = {
    LICENCE_KEY: "records no licence for its weights; check the terms of the images it was trained on before using "
                 "its answers (re-export it with `udh export-onnx --licence TEXT`)",
    "max_heading": "records no training headings; taken as trained without turns (the paper's motion)",
}
MATCHER_ARCH = "matcher"  # the metadata ``arch`` of a descriptor network (udh_cli.train.archs.DenseMatcher)


def _open_udh_model(path: str | Path, device: str, threads: int | None) -> tuple[Path, object, int, float, float, dict[str, str], str]:
    """Open a udh ONNX file in onnxruntime and check its metadata: (path, session, input size, mean, std, metadata,
    identity), the identity being a digest of the bytes the session was made from."""
    import onnxruntime as ort

    path = Path(path)
    if threads is not None and threads < 0:
        raise UdhError(f"threads {threads!r}: give a positive number of CPU threads (0 or none: onnxruntime's choice)")
    if not path.is_file():
        raise UdhError(f"{path}: no such model file")
    options = ort.SessionOptions()
    options.log_severity_level = 3
    if threads:
        options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    # Idle pool threads must sleep, not spin: an estimate interleaves each pass with NumPy and OpenCV
    # work, and on 2 cores a spinning worker took a core from it (default cascade on 2 threads: 19.6-24.2
    # ms spinning, 9.4-14.6 ms sleeping). Back-to-back passes alone lose a little (1.11 -> 1.23 ms).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        # QDQ propagation moves an int8 model's first quantize step above its first max-pool, which then
        # runs on uint8 in NCHW, a slow kernel: 0.5 ms of a 1.6 ms pass (`udh quantize`). Off, the pool
        # stays float32 and blocked (20 us). Float32 models have no QDQ nodes, so nothing changes for them.
        model_bytes = read_side_file(path, "", MAX_MODEL_BYTES)
        session = ort.InferenceSession(model_bytes, sess_options=options, providers=providers_for(device),
                                       disabled_optimizers=["QDQPropagationTransformer"])
    except UdhError:
        raise
    except Exception as exc:  # noqa: BLE001 - onnxruntime raises several private exception types
        raise UdhError(f"{path}: not a loadable ONNX model ({type(exc).__name__}); give a file written by `udh export-onnx`") from None
    metadata = dict(session.get_modelmeta().custom_metadata_map)
    if metadata.get("udh_format") != MODEL_FORMAT:
        raise UdhError(f"{path}: an ONNX model without udh metadata ({MODEL_FORMAT}); export it with `udh export-onnx`")
    try:
        size = int(metadata["input_size"])
        mean, std = float(metadata["normalization_mean"]), float(metadata["normalization_std"])
    except (KeyError, ValueError):
        raise UdhError(f"{path}: the model's udh metadata is incomplete or malformed") from None
    if not (math.isfinite(mean) and math.isfinite(std) and std > 0 and 16 <= size <= MAX_INPUT_SIZE):
        raise UdhError(f"{path}: unusable metadata (input size {size}, mean {mean}, std {std}; udh networks take 16 to "
                       f"{MAX_INPUT_SIZE} px)")
    return path, session, size, mean, std, metadata, hashlib.blake2b(model_bytes, digest_size=16).hexdigest()


def providers_for(device: str) -> list[str]:
    """onnxruntime execution providers for ``device``: auto (CUDA when present, else CPU), cpu or cuda."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    if device == "cpu":
        return ["CPUExecutionProvider"]
    if device == "cuda":
        if "CUDAExecutionProvider" not in available:
            raise UdhError("--device cuda: this onnxruntime has no CUDA provider; replace it with the GPU build "
                           "(pip uninstall onnxruntime && pip install onnxruntime-gpu) or use --device cpu")
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    if device == "auto":
        return (["CUDAExecutionProvider"] if "CUDAExecutionProvider" in available else []) + ["CPUExecutionProvider"]
    raise UdhError(f"unknown --device '{device}'; choose auto, cpu or cuda")


# Patches per onnxruntime run: on a 2-core CPU a pass costs 15-40 % more in runs of 32-96 patches than of 4-16
# (the activations outgrow the caches; docs/benchmarks.md), and a run's own overhead is about 0.1 ms.
PASSES_PER_CALL = 8


@functools.cache
def _quiet_run():
    """Run options under which onnxruntime prints nothing itself: udh reports a failed run in one line."""
    import onnxruntime as ort

    options = ort.RunOptions()
    options.log_severity_level = 4  # fatal only
    return options


@dataclass
class _UdhOnnxModel:
    """What every loaded udh network has: its file, its onnxruntime session, the input standardisation it was
    trained with, and the metadata the exporter embedded (arch, mode, rho, steps, training data...)."""

    path: Path
    session: object
    mean: float
    std: float
    metadata: dict[str, str]
    # A digest of the model's bytes as loaded: what a result computed by this network is keyed by, since a file
    # rewritten under the same name in a long-lived process (a Dask worker, a notebook) is another network.
    identity: str

    @property
    def provider(self) -> str:
        """The execution provider that runs this network ("CUDAExecutionProvider", "CPUExecutionProvider"...):
        what actually ran, which ``--device auto`` or a CPU-only onnxruntime may make differ from the request."""
        providers = self.session.get_providers()
        return providers[0] if providers else "unknown"

    def run(self, batch: np.ndarray) -> np.ndarray:
        """The network's one output for the standardised ``batch``; a failure inside onnxruntime (a graph that
        loads but cannot run) is a one-line :class:`UdhError`, not an internal error."""
        name = self.session.get_inputs()[0].name  # load() checked there is one
        try:
            return self.session.run(None, {name: batch}, _quiet_run())[0]
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises several private exception types
            detail = " ".join(str(exc).split())[-120:]  # the end names the node's complaint; the start, source paths
            raise UdhError(f"{self.path}: the network failed inside onnxruntime ({type(exc).__name__}: {detail}); "
                           f"give a network written by `udh export-onnx`") from None

    def standardise(self, grey: np.ndarray) -> np.ndarray:
        """Grey values in [0, 1] (patches or images, any shape) -> the float32 network input, standardised as in
        training."""
        return ((grey - self.mean) / self.std).astype(np.float32)

    @property
    def licence(self) -> str | None:
        """The licence of the weights as exported (``udh export-onnx --licence``); None: the file records none."""
        return self.metadata.get(LICENCE_KEY) or None

    def lacks(self) -> list[str]:
        """One line per piece of metadata this file lacks that later exports record (:data:`RECORDED_SINCE`); the
        network loads and runs all the same, with what the line says assumed."""
        return [f"{self.path.name}: {what}" for key, what in RECORDED_SINCE.items() if key not in self.metadata]


@dataclass
class OnnxHomographyModel(_UdhOnnxModel):
    """A network mapping ``(N, 2, S, S)`` patches to ``(N, 4, 2)`` 4-point offsets (see geometry).

    Attributes:
        input_size: S (the rest: :class:`_UdhOnnxModel`).
    """

    input_size: int

    @classmethod
    def load(cls, path: str | Path, device: str = "auto", threads: int | None = None) -> "OnnxHomographyModel":
        """Open and check a udh ONNX model; raises :class:`UdhError` for a missing, corrupt or foreign file."""
        path, session, size, mean, std, metadata, identity = _open_udh_model(path, device, threads)
        if metadata.get("arch") == MATCHER_ARCH:
            raise UdhError(f"{path}: is a matcher (descriptors for global matching), not a homography network; "
                           f"a matcher runs beside the networks: --matcher-model FILE (-O matcher_model=FILE in mosaic and bench)")
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if (len(inputs) != 1 or list(inputs[0].shape[1:]) != [2, size, size] or len(outputs) != 1
                or list(outputs[0].shape[1:]) != [4, 2]):
            raise UdhError(f"{path}: the graph's shapes do not fit its metadata (want (N,2,{size},{size}) -> (N,4,2))")
        return cls(path=path, session=session, mean=mean, std=std, metadata=metadata, identity=identity, input_size=size)

    def predict_offsets(self, patches: np.ndarray, batch_size: int = PASSES_PER_CALL) -> np.ndarray:
        """``patches`` (N, 2, S, S) grey in [0, 1] -> (N, 4, 2) float64 offsets in pixels of the S x S input."""
        if patches.ndim != 4 or patches.shape[1:] != (2, self.input_size, self.input_size):
            raise UdhError(f"expected patches of shape (N, 2, {self.input_size}, {self.input_size}), got {patches.shape}")
        standardised = self.standardise(patches)
        outputs = [self.run(standardised[i : i + batch_size]) for i in range(0, len(patches), batch_size)]
        return np.concatenate(outputs).astype(np.float64)

@dataclass
class OnnxMatcher(_UdhOnnxModel):
    """A ``matcher`` network: ``(N, 1, H, W)`` grey images -> ``(N, C, H/4, W/4)`` unit descriptors, any size
    with H and W multiples of 4 (:mod:`udh_cli.estimators.matching` matches them)."""

    @classmethod
    def load(cls, path: str | Path, device: str = "auto", threads: int | None = None) -> "OnnxMatcher":
        """Open and check a matcher; raises :class:`UdhError` for a missing, corrupt or foreign file, or a
        homography network given as a matcher."""
        path, session, _, mean, std, metadata, identity = _open_udh_model(path, device, threads)
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if metadata.get("arch") != MATCHER_ARCH or len(inputs) != 1 or len(inputs[0].shape) != 4 or inputs[0].shape[1] != 1 \
                or len(outputs) != 1 or len(outputs[0].shape) != 4:
            raise UdhError(f"{path}: not a matcher (want arch '{MATCHER_ARCH}' and (N,1,H,W) -> (N,C,H/4,W/4)); "
                           f"train one with `udh train --mode match`")
        return cls(path=path, session=session, mean=mean, std=std, metadata=metadata, identity=identity)

    def describe(self, grey: np.ndarray) -> np.ndarray:
        """(H, W) grey in [0, 1], H and W multiples of 4 -> (C, H/4, W/4) float32 unit descriptors."""
        if grey.ndim != 2 or grey.shape[0] % 4 or grey.shape[1] % 4 or min(grey.shape) < 32:
            raise UdhError(f"the matcher takes one grey image with sides multiples of 4 and at least 32 px, got {grey.shape}")
        return self.run(self.standardise(grey)[None, None])[0]


def write_metadata(proto, metadata: dict[str, str]) -> None:
    """Replace an ONNX ``ModelProto``'s metadata with ``metadata`` (all strings): the keys `load` checks."""
    del proto.metadata_props[:]
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
