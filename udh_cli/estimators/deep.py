"""The learned estimators (unsupervised UDH and supervised HomographyNet) on onnxruntime."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import ClassVar, Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators.base import Estimate, Estimator
from udh_cli.images import check_image, to_gray_float
from udh_cli.onnx_model import OnnxHomographyModel
from udh_cli.verify import alignment_ncc


DEFAULT_REFINE_ROUNDS = 2  # measured on the held-out rho-32 bench (models/README.md)


@dataclass
class DeepEstimator(Estimator):
    """Resize both images whole to the network's S x S input, predict the 4-point offsets, solve the DLT
    in numpy, and rescale ``b_from_a`` exactly to the original images' pixels.

    A cascade of rounds: ``iterations`` rounds of the coarse network, then ``refine_rounds`` rounds of the
    refinement network (a finer one trained on small motion). Every round after the first warps A by the
    current estimate and predicts the residual, which is composed onto it.

    Attributes:
        model: path of a udh ONNX model; ``None`` takes the shipped model of this estimator's name.
        device: "auto", "cpu" or "cuda" (onnxruntime providers).
        iterations: rounds of the coarse network (at least 1).
        refine_model: path of the refinement network; ``None`` takes the shipped ``<name>-refine`` model.
        refine_rounds: rounds of the refinement network after the coarse ones (0: no refinement stage).
            ``None``: :data:`DEFAULT_REFINE_ROUNDS` when both networks are the shipped ones and a shipped
            refinement network exists, else 0 (a ``model`` given alone runs alone).
        batch_size: pairs per onnxruntime call in :meth:`estimate_many`.
        threads: onnxruntime intra-op threads (None: onnxruntime's default).

    Confidence is the normalised cross-correlation of the aligned S x S images (0 when negative).
    """

    name: ClassVar[str] = "deep"
    model: str | None = None
    device: str = "auto"
    iterations: int = 1
    refine_model: str | None = None
    refine_rounds: int | None = None
    batch_size: int = 64
    threads: int | None = None
    network: OnnxHomographyModel = field(init=False, repr=False)
    stages: list[tuple[OnnxHomographyModel, int]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from udh_cli.models_catalog import has_shipped, shipped_onnx

        if self.iterations < 1 or self.batch_size < 1:  # 0 rounds would answer the identity as if estimated
            raise UdhError(f"method '{self.name}': iterations ({self.iterations}) and batch_size ({self.batch_size}) must be at least 1")
        if self.refine_rounds is None:
            shipped_pair = self.model is None and self.refine_model is None and has_shipped(f"{self.name}-refine")
            self.refine_rounds = DEFAULT_REFINE_ROUNDS if shipped_pair else 0
        if self.refine_rounds < 0:
            raise UdhError(f"method '{self.name}': refine_rounds ({self.refine_rounds}) must be 0 or more")

        path = self.model if self.model is not None else shipped_onnx(self.name)
        self.network = OnnxHomographyModel.load(path, self.device, self.threads)
        self.stages = [(self.network, self.iterations)]
        if self.refine_rounds:
            refine_path = self.refine_model if self.refine_model is not None else shipped_onnx(f"{self.name}-refine")
            refiner = OnnxHomographyModel.load(refine_path, self.device, self.threads)
            if refiner.input_size != self.network.input_size:
                raise UdhError(f"{refine_path}: the refinement network takes {refiner.input_size}px inputs but "
                               f"{path} takes {self.network.input_size}px; give two models of the same input size")
            self.stages.append((refiner, self.refine_rounds))

    def _small(self, image: np.ndarray) -> np.ndarray:
        s = self.network.input_size
        return cv2.resize(to_gray_float(image), (s, s), interpolation=cv2.INTER_AREA)

    def predict_small(self, small_a: np.ndarray, small_b: np.ndarray) -> np.ndarray:
        """(N, S, S) x2 grey in [0, 1] -> (N, 3, 3) ``b_from_a`` in pixels of the S x S images."""
        s = self.network.input_size
        b_from_a = np.repeat(np.eye(3)[None], len(small_a), 0)
        current_a = small_a
        rounds = [network for network, count in self.stages for _ in range(count)]
        for round_index, network in enumerate(rounds):
            offsets = network.predict_offsets(np.stack([current_a, small_b], 1), self.batch_size)
            try:
                step = geometry.homography_from_offsets(offsets, s, s)
            except np.linalg.LinAlgError:  # one degenerate output fails the batched solve: solve pair by pair
                step = np.stack([_safe_dlt(o, s) for o in offsets])
            b_from_a = step @ b_from_a
            b_from_a /= b_from_a[:, 2:3, 2:3]
            if round_index + 1 < len(rounds):
                current_a = np.stack([
                    cv2.warpPerspective(a, h, (s, s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                    if np.isfinite(h).all() else a
                    for a, h in zip(small_a, b_from_a)
                ])
        return b_from_a

    def estimate_many(self, pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> list[Estimate]:
        if not pairs:
            return []
        for a, b in pairs:
            check_image(a, "image A")
            check_image(b, "image B")
        start = time.perf_counter()
        small_a = np.stack([self._small(a) for a, _ in pairs])
        small_b = np.stack([self._small(b) for _, b in pairs])
        small_h = self.predict_small(small_a, small_b)
        s = self.network.input_size
        results = []
        for (a, b), h, sa, sb in zip(pairs, small_h, small_a, small_b):
            valid = geometry.is_valid_homography(h, s, s)
            confidence = max(0.0, alignment_ncc(sa, sb, h)) if valid else 0.0
            full = geometry.rescale_homography(h, (s, s), (a.shape[1], a.shape[0]), (s, s), (b.shape[1], b.shape[0])) if valid else None
            results.append((full, confidence))
        per_pair_ms = (time.perf_counter() - start) * 1e3 / len(pairs)
        out = []
        for (a, _), (full, confidence) in zip(pairs, results):
            failure = None if full is not None else "the network's 4-point output gives a degenerate homography"
            out.append(self._checked(full, confidence, per_pair_ms, failure,
                                     {"iterations": self.iterations, "refine_rounds": self.refine_rounds}, a.shape))
        return out

    def estimate(self, image_a: np.ndarray, image_b: np.ndarray) -> Estimate:
        return self.estimate_many([(image_a, image_b)])[0]


def _safe_dlt(offsets: np.ndarray, size: int) -> np.ndarray:
    """(4, 2) offsets -> (3, 3) ``b_from_a`` of the S x S input, NaN when the DLT is singular (then rejected)."""
    try:
        return geometry.homography_from_offsets(offsets, size, size)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.nan)


@dataclass
class UnsupervisedEstimator(DeepEstimator):
    """The paper's unsupervised network (photometric L1 training)."""

    name: ClassVar[str] = "unsupervised"


@dataclass
class SupervisedEstimator(DeepEstimator):
    """HomographyNet: the same kind of network trained with L2 on synthetic 4-point labels."""

    name: ClassVar[str] = "supervised"
