"""The networks of a learned estimator, loaded once into one record by role (:class:`LearnedNetworks`), from the
user's files or the shipped ones (:class:`~udh_cli.models_catalog.ShippedRoles`)."""

from __future__ import annotations

from dataclasses import dataclass

from udh_cli.errors import UdhError
from udh_cli.models_catalog import ShippedRoles, has_shipped, shipped_onnx
from udh_cli.onnx_model import OnnxHomographyModel, OnnxMatcher


@dataclass(frozen=True)
class LearnedNetworks:
    """The loaded networks of a learned estimator, each in its role; every homography network takes S x S inputs
    of the same S.

    Attributes:
        coarse: the first network of the cascade (``model``).
        rounds: the network of the refinement rounds (``rounds_model``, else the refinement network); None: the
            cascade has no refinement stage.
        tile: the tile stage's network: the refinement network, or ``coarse`` without one.
        tile_coarse: the network of the tile stage's coarse level (``tile_coarse_model``, else ``coarse``); None
            without a refinement stage.
        flight: a second coarse network whose cascade competes with ``coarse``'s; None: none.
        matcher: the descriptors of the global match of doubted pairs; None: no global match.
    """

    coarse: OnnxHomographyModel
    rounds: OnnxHomographyModel | None
    tile: OnnxHomographyModel
    tile_coarse: OnnxHomographyModel | None
    flight: OnnxHomographyModel | None
    matcher: OnnxMatcher | None

    @property
    def side(self) -> int:
        """S, the side of every homography network's input, px."""
        return self.coarse.input_size

    @property
    def first(self) -> list[OnnxHomographyModel]:
        """The coarse networks whose cascades compete, in order."""
        return [self.coarse] + ([self.flight] if self.flight is not None else [])

    def homography_networks(self) -> list[OnnxHomographyModel]:
        """Every homography network loaded (some in more than one role); the matcher is not one."""
        return [network for network in (self.coarse, self.rounds, self.tile, self.tile_coarse, self.flight) if network is not None]

    def precision(self) -> str:
        """What the homography networks run in: "int8", "fp32", or "mixed" (networks of both, e.g. a float32
        ``model`` file followed by the shipped int8 refinement network)."""
        found = {network.metadata.get("precision", "fp32") for network in self.homography_networks()}
        return found.pop() if len(found) == 1 else "mixed"

    def notes(self) -> list[str]:
        """What each loaded file's metadata lacks (:meth:`~udh_cli.onnx_model.OnnxHomographyModel.lacks`), each
        line once, in the order of :meth:`homography_networks` then the matcher."""
        loaded = self.homography_networks() + ([self.matcher] if self.matcher is not None else [])
        return list(dict.fromkeys(line for network in loaded for line in network.lacks()))

    def files(self) -> list[str]:
        """The model files the answers depend on, sorted, each once."""
        matcher = [str(self.matcher.path)] if self.matcher is not None else []
        return sorted({str(network.path) for network in self.homography_networks()} | set(matcher))


def load_networks(method: str, *, model: str | None, refine_model: str | None, rounds_model: str | None,
                  tile_coarse_model: str | None, flight_model: str | None, matcher_model: str | None, refine_rounds: int,
                  tiles: bool, precision: str | None, device: str, threads: int | None) -> LearnedNetworks:
    """Load the networks of the learned method ``method`` from the options of the same names of
    :class:`~udh_cli.estimators.deep.DeepEstimator`, checked there (``precision`` too), with ``refine_rounds`` and
    ``tiles`` resolved. A file ``None`` takes the shipped network of its role where the estimator's docstring says
    so; ``""`` turns a flight network or matcher off. Raises :class:`UdhError` for a file that is missing, not a udh
    network, or of another input size than ``model``'s."""
    shipped = ShippedRoles.of(method)
    path = model if model is not None else shipped_onnx(shipped.coarse, precision)
    coarse = OnnxHomographyModel.load(path, device, threads)
    rounds, tile, tile_coarse = None, coarse, None
    if refine_rounds:
        refine_path = refine_model if refine_model is not None else shipped_onnx(shipped.refine, precision)
        tile = rounds = OnnxHomographyModel.load(refine_path, device, threads)
        if rounds.input_size != coarse.input_size:
            raise UdhError(f"{refine_path}: the refinement network takes {rounds.input_size}px inputs but "
                           f"{path} takes {coarse.input_size}px; give two models of the same input size")
        if rounds_model:
            rounds = _same_side(OnnxHomographyModel.load(rounds_model, device, threads), coarse, rounds_model, path, "the rounds' network")
        tile_coarse = coarse
    if tile_coarse_model and tile_coarse is None:
        raise UdhError(f"method '{method}': tile_coarse_model runs in the tile stage, which needs a refinement stage "
                       f"(refine_rounds is 0 or no refinement network is given)")
    if tile_coarse_model:
        tile_coarse = _same_side(OnnxHomographyModel.load(tile_coarse_model, device, threads), coarse, tile_coarse_model, path,
                                 "the tiles' coarse network")
    if flight_model is None and model is None and has_shipped(shipped.flight, precision=None):
        flight_model = str(shipped_onnx(shipped.flight, precision))
    flight = _same_side(OnnxHomographyModel.load(flight_model, device, threads), coarse, flight_model, path,
                        "the flight network") if flight_model else None
    if matcher_model is None and model is None and tiles and has_shipped(shipped.matcher, precision=None):
        matcher_model = str(shipped_onnx(shipped.matcher, "fp32"))  # float32 only: 0.57 MB, run on doubted pairs
    matcher = OnnxMatcher.load(matcher_model, device, threads) if matcher_model else None
    return LearnedNetworks(coarse, rounds, tile, tile_coarse, flight, matcher)


def _same_side(network: OnnxHomographyModel, coarse: OnnxHomographyModel, path, coarse_path, role: str) -> OnnxHomographyModel:
    """``network`` (loaded from ``path``) when it takes the coarse network's input size; else a :class:`UdhError`."""
    if network.input_size != coarse.input_size:
        raise UdhError(f"{path}: {role} takes {network.input_size}px inputs, {coarse_path} {coarse.input_size}px")
    return network
