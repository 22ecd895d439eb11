"""The learned estimators (unsupervised UDH and supervised HomographyNet) on onnxruntime."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import ClassVar, Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.flight_motion import PREWARP_BORDER
from udh_cli.estimators.base import Estimate, Estimator
from udh_cli.estimators.hypotheses import HEADING_COUNT
from udh_cli.estimators.learned import Batch, StageClock, final_homography, first_answers, judged, packed, rescued
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.estimators.tiles import refine_pairs_with_tiles
from udh_cli.estimators.pair import PreparedPair
from udh_cli.onnx_model import PASSES_PER_CALL, OnnxHomographyModel
from udh_cli.estimators.matching import MatchSettings
from udh_cli.estimators.networks import LearnedNetworks, load_networks
from udh_cli.estimators.verify import Verifier


DEFAULT_ITERATIONS = 2  # coarse rounds
DEFAULT_REFINE_ROUNDS = 2  # measured on the held-out rho-32 bench (models/README.md)
PIPELINE_SEARCH = 2  # the search of the whole learned pipeline (unsupervised with its tile stage): 24 shifts
# B's turns the global match tries (matching.HEADINGS): half turns for a survey's alternating strips, then quarter
# turns for a strip's end, each only while no turn has found enough agreeing cells.
MATCH_HEADINGS = 4
# How the networks judge their own answers, on their S x S input (Verifier.score_grey, at the size given): the
# one Verifier, whole (a tile of a 4 x 4 grid at 128 px holds too few pixels to correlate); the search was tuned on it.
NETWORK_CHECK = Verifier(tiles=1, min_overlap=THRESHOLDS.min_network_overlap)


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
        iterations: rounds of the coarse network (at least 1). The second round took the held-out rho-45
            failures from 25 % to 17 % ahead of the refinement rounds.
        refine_model: path of the refinement network; ``None`` takes the shipped ``<name>-refine`` model.
        rounds_model: path of a network for the whole-frame refinement rounds only, e.g. one trained on what
            those rounds see (``udh train --residual``: A pre-warped at low overlap, with border fill); the
            tiles keep the refinement network, trained on tiles. ``None``: the refinement network runs both.
        tile_coarse_model: path of a network for the tile stage's coarse level only (its
            :attr:`TileRefinement.coarse_side` tiles), e.g. one trained on windows of frames at that scale
            (``udh train --source-side``); the whole-frame cascade keeps ``model``. ``None``: ``model`` runs both.
        refine_rounds: rounds of the refinement network after the coarse ones (0: no refinement stage).
            ``None``: :data:`DEFAULT_REFINE_ROUNDS` when a ``refine_model`` is given, or when ``model`` is
            the shipped one and a shipped refinement network exists; else 0 (a ``model`` given alone runs
            alone).
        search: large-motion search for pairs whose score is below ``search_below``: rerun the network
            from a (2 * search + 1)^2 grid of translations up to half the frame and keep the best-scoring
            answer (0: off; None: :data:`PIPELINE_SEARCH` when the tile stage runs, else off). For sequences
            that move further between frames than the network was trained for (it saw corners moved by up to
            45 px of 128).
        search_below: the score under which a pair is searched.
        precision: which shipped networks to load for those not given as ``model`` / ``refine_model`` files:
            "int8" (`udh quantize` copies: a network pass 1.7 -> 1.1 ms on one core, the same median accuracy
            on the bench, tails slightly worse), "fp32", or ``None``: int8 where shipped, else float32.
        flight_model: a second coarse network, trained for whole frames with real flight motion (``udh train
            --motion flight``); its cascade runs beside the first one's and the better-scoring answer is kept,
            so each serves the motion it was trained for. ``None`` takes the shipped ``<name>-flight`` network
            when there is one and ``model`` is not given; ``""`` turns it off.
        headings: 1 runs the network on B as given; 2 also on B turned half a turn, keeping the better-scoring
            answer. Why: a survey's strips alternate direction, and the flight network is trained for turns of
            up to 30 degrees; half a turn keeps the frame's shape (a quarter turn of a 4:3 frame would not).
        heading_search: for a doubted pair, B's small copy turned by this many angles over the circle, screened in
            one onnxruntime call, the best finishing the cascade (:mod:`~udh_cli.estimators.hypotheses`; 0: off). Why:
            other turns are beyond the networks' reach; this reaches them before the global match, at a few network
            passes instead of describing both frames (docs/estimators.md, "Any heading").
        judged: give every answer the verdict of :mod:`~udh_cli.estimators.judge` (``verified`` True or False);
            False leaves ``verified`` None, for a caller that judges the answer itself (auto's ECC and policy).
        matcher_model: a ``matcher`` network (``udh train --mode match``): for a doubted pair, its global match
            (every 4-px cell of A against every cell of B at ``match_side`` px, mutual nearest neighbours, a
            robust fit; :mod:`udh_cli.estimators.matching`) is tried before the search, and kept when the tile
            stage confirms it better than the cascade's answer. It reaches any displacement, where the
            regressing networks' whole-frame answer at 128 px is tens of px off on real flights with low
            overlap or little texture. ``None`` takes the shipped ``<name>-matcher`` network when there is one
            and the tile stage runs; ``""`` turns it off.
        match_side: the longer side, px, at which the matcher describes frames for the global match.
        match_escalate_side: the longer side, px, of a second global match for a pair whose first found fewer
            than :data:`~udh_cli.estimators.matching.CONFIDENT_INLIERS` agreeing cells (frames overlapping by a
            sliver); ``None``: none. It costs about four times the first, on the pairs that fail it only.
        match_refine_side: the longer side, px, at which the global match is refined by guided matching
            (:func:`~udh_cli.estimators.matching.guided_matches`); ``None``: not refined.
        polish_matches: a global match many cells support takes the tile stage's answer from it where the tiles
            agree on one (:mod:`~udh_cli.estimators.polish`). Off by default: a little better on turned and scaled
            pairs, but looser loops on a real flight's network-only mosaic (docs/benchmarks.md, "Turned and scaled
            pairs: the global match polished by the tiles").
        tiles: refine the answer on 128x128 tiles at finer levels up to full resolution with the last
            network of the cascade (:mod:`udh_cli.estimators.tiles`): the network alone is then sub-pixel
            at any frame size. None: on when the cascade has a refinement stage.
        batch_size: patches per onnxruntime call (:data:`~udh_cli.onnx_model.PASSES_PER_CALL`: larger runs cost more a pass).
        threads: onnxruntime intra-op threads (None: onnxruntime's default).

    Confidence is :meth:`score` (intensity and gradient NCC at S x S), halved when :mod:`~udh_cli.estimators.judge` doubts it.
    """

    name: ClassVar[str] = "deep"
    model: str | None = None
    device: str = "auto"
    iterations: int = DEFAULT_ITERATIONS
    refine_model: str | None = None
    rounds_model: str | None = None
    tile_coarse_model: str | None = None
    refine_rounds: int | None = None
    search: int | None = 0
    search_below: float = THRESHOLDS.network_search_below
    precision: str | None = None
    flight_model: str | None = None
    headings: int = 1
    heading_search: int = 0
    judged: bool = True
    tiles: bool | None = None
    matcher_model: str | None = None
    match_side: int = MatchSettings.side
    match_escalate_side: int | None = MatchSettings.escalate_side
    match_refine_side: int | None = MatchSettings.refine_side
    polish_matches: bool = False
    batch_size: int = PASSES_PER_CALL
    threads: int | None = None
    networks: LearnedNetworks = field(init=False, repr=False)  # every network loaded, by role
    match_settings: MatchSettings = field(init=False, repr=False)  # how the global match runs (the match_* options)

    def __post_init__(self) -> None:
        from udh_cli.models_catalog import PRECISIONS, check_precision, has_refinement_stage

        if self.iterations < 1 or self.batch_size < 1:  # 0 rounds would answer the identity as if estimated
            raise UdhError(f"method '{self.name}': iterations ({self.iterations}) and batch_size ({self.batch_size}) must be at least 1")
        if self.refine_rounds is None:
            has_stage = has_refinement_stage(self.name, self.model, self.refine_model)
            self.refine_rounds = DEFAULT_REFINE_ROUNDS if has_stage else 0
        if self.search is not None and self.search < 0:
            raise UdhError(f"method '{self.name}': search ({self.search}) must be 0 (off) or more")
        if self.refine_rounds < 0:
            raise UdhError(f"method '{self.name}': refine_rounds ({self.refine_rounds}) must be 0 or more")
        if self.headings not in (1, 2):
            raise UdhError(f"method '{self.name}': headings ({self.headings}) must be 1 (as given) or 2 (also half a turn)")
        if not (self.heading_search == 0 or 3 <= self.heading_search <= 72):
            raise UdhError(f"method '{self.name}': heading_search ({self.heading_search}) must be 0 (off) or 3 to 72 angles")
        check_precision(self.precision)
        self.match_settings = MatchSettings(self.match_side, MATCH_HEADINGS, self.match_refine_side, self.match_escalate_side).checked(self.name, "match_")
        if self.tiles is None:  # on with a refinement stage
            self.tiles = self.refine_rounds > 0
        if self.search is None:
            # Only with the tile stage: without it nothing but the 128-px score checks a searched answer, and a
            # translation alone can pass that (an untrained network on the example flight: 0.24 at 36 px off).
            self.search = PIPELINE_SEARCH if self.tiles else 0
        self.networks = load_networks(
            self.name, model=self.model, refine_model=self.refine_model, rounds_model=self.rounds_model,
            tile_coarse_model=self.tile_coarse_model, flight_model=self.flight_model, matcher_model=self.matcher_model,
            refine_rounds=self.refine_rounds, tiles=self.tiles, precision=self.precision, device=self.device, threads=self.threads)
        # Record what was chosen, so that settings (mosaic sidecars, the pair cache) say what ran: the shipped files
        # by path, and precision=None as the precision loaded (then None and "int8" name the same estimator).
        if self.flight_model is None and self.networks.flight is not None:
            self.flight_model = str(self.networks.flight.path)
        if self.matcher_model is None and self.networks.matcher is not None:
            self.matcher_model = str(self.networks.matcher.path)
        if self.precision is None and self.networks.precision() in PRECISIONS:
            self.precision = self.networks.precision()

    @property
    def network(self) -> OnnxHomographyModel:
        """The coarse network, the first of the cascade; its input side is S."""
        return self.networks.coarse

    @property
    def stages(self) -> list[tuple[OnnxHomographyModel, int]]:
        """The cascade as (network, rounds): the coarse network's, then the refinement network's if there is one."""
        refinement = [(self.networks.rounds, self.refine_rounds)] if self.networks.rounds is not None else []
        return [(self.networks.coarse, self.iterations), *refinement]

    def with_default_rounds(self) -> "DeepEstimator":
        """The same estimator and loaded networks with the default rounds (the refinement stage only if
        this one has it): a longer cascade without loading the models again."""
        twin = copy.copy(self)
        twin.iterations = DEFAULT_ITERATIONS
        twin.refine_rounds = DEFAULT_REFINE_ROUNDS if self.networks.rounds is not None else 0
        return twin

    def near_prior(self) -> "DeepEstimator":
        """These networks without the shift search, the global match at B's heading and first side only; the match
        and the heading search answer loop pairs the cascade cannot (docs/mosaic.md, "Loop-closure pairs ...")."""
        twin = copy.copy(self)
        twin.search, twin.match_settings = 0, self.match_settings.near_prior()
        twin.match_escalate_side = twin.match_settings.escalate_side
        return twin

    def loaded_precision(self) -> str:
        """What the cascade runs in: "int8", "fp32", or "mixed" (:meth:`LearnedNetworks.precision`)."""
        return self.networks.precision()

    def model_files(self) -> list[str]:
        return self.networks.files()

    def model_notes(self) -> list[str]:
        return self.networks.notes()

    def rounds(self) -> list[OnnxHomographyModel]:
        """The network of every round of the cascade, in order."""
        return [network for network, count in self.stages for _ in range(count)]

    def predict_small(self, small_a: np.ndarray, small_b: np.ndarray, rounds: Sequence[OnnxHomographyModel] | None = None,
                      start: np.ndarray | None = None) -> np.ndarray:
        """(N, S, S) x2 grey in [0, 1] -> (N, 3, 3) ``b_from_a`` in pixels of the S x S images.

        ``rounds``: the networks to run, in order (default: the whole cascade, :meth:`rounds`). ``start``:
        (N, 3, 3) estimates to continue from (default: the identity); A is warped by them first.
        """
        s = self.network.input_size
        b_from_a = np.repeat(np.eye(3)[None], len(small_a), 0) if start is None else np.array(start, np.float64)
        rounds = self.rounds() if rounds is None else list(rounds)
        for round_index, network in enumerate(rounds):
            current_a = small_a if start is None and round_index == 0 else np.stack([
                cv2.warpPerspective(a, h, (s, s), flags=cv2.INTER_LINEAR, borderMode=PREWARP_BORDER)
                if np.isfinite(h).all() else a
                for a, h in zip(small_a, b_from_a)
            ])
            offsets = network.predict_offsets(np.stack([current_a, small_b], 1), self.batch_size)
            try:
                step = geometry.homography_from_offsets(offsets, s, s)
            except np.linalg.LinAlgError:  # one degenerate output fails the batched solve: solve pair by pair
                step = np.stack([_safe_dlt(o, s) for o in offsets])
            b_from_a = step @ b_from_a
            b_from_a /= b_from_a[:, 2:3, 2:3]
        return b_from_a

    def score(self, small_a: np.ndarray, small_b: np.ndarray, b_from_a: np.ndarray) -> float:
        """Confidence of ``b_from_a`` between two S x S images: the lower of the intensity and gradient
        NCC over the overlap (0 for a degenerate H). Both must agree: intensity alone is fooled by smooth
        scenes under a wrong shift, gradients alone by noise and moving water."""
        s = self.network.input_size
        if not geometry.is_valid_homography(b_from_a, s, s):
            return 0.0
        return NETWORK_CHECK.score_grey(small_a, small_b, b_from_a)

    def estimate_pairs(self, pairs: Sequence[PreparedPair]) -> list[Estimate]:
        """The stages of :mod:`~udh_cli.estimators.learned`: prepare, network, tiles, the rescues of the doubted
        pairs (headings, match, search), verdict; each timed in ``details["stage_ms"]``."""
        if not pairs:
            return []
        clock = StageClock(len(pairs))
        batch = Batch.of(pairs, self.network.input_size)
        clock.lap("prepare")
        answers = rescued(self, batch, first_answers(self, batch, clock), clock)
        fulls = [final_homography(self, answer, pair) for answer, pair in zip(answers, pairs)]
        verdicts = judged(self, batch, answers, fulls)
        clock.lap("verdict", ran=self.judged)
        precision = self.loaded_precision()
        return [packed(self, pair, answer, full, verdict, clock.stage_ms, clock.per_pair_ms(), precision)
                for pair, answer, full, verdict in zip(pairs, answers, fulls, verdicts)]

    def full_resolution(self, small_h: np.ndarray, pair: PreparedPair) -> np.ndarray | None:
        """A ``b_from_a`` of the S x S images rescaled exactly to the pair's pixels; None when degenerate."""
        s = self.network.input_size
        if not geometry.is_valid_homography(small_h, s, s):
            return None
        return geometry.rescale_homography(small_h, (s, s), pair.a.size, (s, s), pair.b.size)

    def tile_stage(self, pairs: Sequence[PreparedPair], small_h: Sequence[np.ndarray]) -> list:
        """The tile stage (every pair's tiles of a level together) from S x S answers; None where one is degenerate."""
        fulls = [self.full_resolution(h, pair) for h, pair in zip(small_h, pairs)]
        valid = [i for i, full in enumerate(fulls) if full is not None]
        found = refine_pairs_with_tiles(self.networks.tile, [(pairs[i].a, pairs[i].b) for i in valid], [fulls[i] for i in valid],
                                        coarse_network=self.networks.tile_coarse) if valid else []
        by_index = dict(zip(valid, found))
        return [by_index.get(i) for i in range(len(pairs))]


def _safe_dlt(offsets: np.ndarray, size: int) -> np.ndarray:
    """(4, 2) offsets -> (3, 3) ``b_from_a`` of the S x S input, NaN when the DLT is singular (then rejected)."""
    try:
        return geometry.homography_from_offsets(offsets, size, size)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.nan)


@dataclass
class UnsupervisedEstimator(DeepEstimator):
    """The paper's unsupervised network (photometric L1 training), as a whole learned pipeline: the coarse
    and refinement cascade on the whole frames from both headings, then the tile stage to full resolution,
    and the large-motion search for the pairs that stage doubts.
    ``iterations=1, refine_rounds=0, headings=1, tiles=False, search=0`` is the paper's single 128x128 pass.

    Why the search by default: between whole frames of a flight the failures follow the shift, not the turn,
    and the search recovers shifts up to half the frame; with it the flight-motion benchmark fails on 27.5 %
    of pairs instead of 47.5 % (SIFT: 23.5 %), while the paper's patches, which have no room for tiles, are
    searched only when they score low. Only doubted pairs pay for it (docs/estimators.md).
    """

    name: ClassVar[str] = "unsupervised"
    headings: int = 2
    heading_search: int = HEADING_COUNT
    search: int | None = None  # PIPELINE_SEARCH with the tile stage (the shipped networks), else off


@dataclass
class SupervisedEstimator(DeepEstimator):
    """HomographyNet: the same kind of network trained with L2 on synthetic 4-point labels."""

    name: ClassVar[str] = "supervised"
