"""The settings of a mosaic run (:class:`MosaicConfig`), their checks, and what they make: the estimators asked
about each pair and the pair-acceptance thresholds."""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field, replace
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.estimators import DEFAULT_METHOD, Estimator, create_estimator
from udh_cli.estimators.registry import with_option_default
from udh_cli.mosaic.inputs.frames import ORDERS
from udh_cli.mosaic.pairs.types import Acceptance
from udh_cli.mosaic.pairs.workers import EstimatorSpec, automatic_workers
from udh_cli.mosaic.render import composite as compositing
from udh_cli.mosaic.render.canvases import Drawing
from udh_cli.mosaic.render.gains import EXPOSURES
from udh_cli.mosaic.render.seams import SEAM_FINDERS
from udh_cli.mosaic.solve.global_solve import GlobalSolve
from udh_cli.mosaic.solve.loops import LoopClosure

@dataclass(frozen=True)
class MosaicConfig:
    """Every choice of a mosaic run; the CLI's options and defaults come from here.

    Attributes:
        method: registered estimator name for every pair.
        fallback: registered estimator name of the second opinion, asked about the pairs ``method`` fails or
            doubts (:func:`.pairs.workers.judge_opinions`); ``None`` for none.
        method_options: keyword options for ``create_estimator(method, ...)``, e.g. ``{"model": "x.onnx"}``.
        fallback_options: the same for ``fallback``.
        work_size: longest side, pixels, of the copies the estimators see.
        order: frame order in a folder: ``"name"`` or ``"time"`` (EXIF capture time).
        every: for a video, keep every N-th frame.
        min_confidence: estimates below this confidence count as failures (then fallback, then split).
        min_verified: estimates whose photometric alignment check (see
            :class:`~udh_cli.mosaic.pairs.types.Acceptance`) is below this count as failures too; 0: no check.
        overlap_min: non-consecutive frames whose chained footprints overlap by this share of the smaller
            frame are estimated too (loop closure).
        overlap_per_frame: at most this many loop-closure partners per frame (bounds the work).
        confirm_loops: each loop-closure pair is first confirmed from the chain's prediction by ECC (the cascade's pyramid) and
            the photometric check (:mod:`.pairs.confirm`); only the pairs that fail it run ``method``'s whole
            cascade. False: every loop pair runs the cascade.
        gps_pairs: when the frames carry GPS and the run splits, at most this many pairs between each two
            parts that GPS puts close together are estimated (:mod:`.solve.bridges`); 0: off. Off by default:
            joining a long flight's parts can chain homographies further than one plane per frame holds
            (measured in docs/mosaic.md).
        gps_sigma_m: with GPS in the frames, the fixes join the global solve as anchors of this standard
            error in metres (:class:`~udh_cli.mosaic.solve.homographies.Anchors`): they bound the projective drift of long
            chains that loop closures alone leave. 0: off, the solve uses the pairs alone.
        gcp_sigma_m: with ground-control points (``run_mosaic(gcp=...)``), their observations join the global
            solve as anchors of this standard error in metres, so that the mosaic bends to them instead of only
            being placed by them afterwards; 0: off.
        workers: local processes estimating pairs at once (:mod:`.pairs.workers`; 1: in this process; None: one per
            core, at most 4, for 30 frames or more, :func:`.pairs.workers.automatic_workers`, which is what the command
            line does). 1 by default here: a pool spawns processes that import the calling script again, so a
            script needs ``if __name__ == "__main__":`` first.
        scheduler: a Dask scheduler's address (``tcp://host:8786``): pairs are estimated on its workers.
        exposure: exposure compensation of each part (:mod:`.render.gains`: ``blocks``, ``channels``, ``gain``, ``none``).
        seams: where one frame gives way to the next (:mod:`.render.seams`: ``dp``, ``graphcut``, ``central``); with
            ``blend`` ``feather`` the frames are averaged and there are no seams.
        preview: also write a small JPEG preview beside the mosaic.
        solve: the global solve's model (:data:`SOLVES`): ``homography``, a free homography per frame
            (:mod:`.solve.homographies`), or ``camera``, a pinhole camera per frame over one flat ground, all sharing one
            focal length (:mod:`.solve.cameras`): the map is then drawn on that ground. The camera model starts from
            the homography solve's answer.
    """

    method: str = DEFAULT_METHOD
    fallback: str | None = None
    method_options: dict[str, Any] = field(default_factory=dict)
    fallback_options: dict[str, Any] = field(default_factory=dict)
    work_size: int = 800
    order: str = "name"
    every: int = 1
    min_confidence: float = Acceptance.min_confidence
    min_verified: float = Acceptance.min_verified
    overlap_min: float = 0.3
    overlap_per_frame: int = 3
    confirm_loops: bool = True
    gps_pairs: int = 0
    gps_sigma_m: float = 0.0
    gcp_sigma_m: float = 0.0
    workers: int | None = 1
    scheduler: str | None = None
    max_disagreement: float = 0.1
    huber_px: float = 2.0
    outlier_px: float = 5.0
    blend: str = "multiband"  # hard seams blended band by band: no ghosts where parallax defeats the homographies
    exposure: str = "channels"
    seams: str = "dp"
    max_frame_scale: float = 3.0
    # Without anchors, draw on the plane the frames look down on rather than in the reference frame's view
    # (rectify.py). Off by default: it helped simulated nadir surveys but put copr's ground-control checkpoints
    # 3.99 m from the map instead of 2.10 m (docs/mosaic.md).
    rectify: bool = False
    max_size: int | None = None
    max_canvas_bytes: int = compositing.DEFAULT_MAX_CANVAS_BYTES
    batch_size: int = 16
    preview: bool = True
    solve: str = "homography"

    def loop_closure(self) -> LoopClosure:
        return LoopClosure(self.overlap_min, self.overlap_per_frame, self.max_disagreement, self.huber_px, self.confirm_loops)

    def global_solve(self) -> GlobalSolve:
        return GlobalSolve(self.solve, self.huber_px, self.outlier_px, self.rectify, self.max_frame_scale)

    def drawing(self) -> Drawing:
        return Drawing(self.blend, self.exposure, self.seams, self.max_frame_scale, self.max_size, self.max_canvas_bytes, self.workers,
                       self.preview)


SOLVES = ("homography", "camera")  # the global solve's models (MosaicConfig.solve)


MOSAIC_SEARCH = 2  # the learned methods' large-motion search, on for mosaics unless the user sets it
MOSAIC_VIEWS: tuple[str, ...] = ()  # auto's mirrored, flipped and swapped looks at a pair, off for mosaics unless set


def check_config(config: MosaicConfig) -> None:
    """Fail before any work on a setting that could only fail later (a typo in --blend, a zero size)."""
    if config.blend not in compositing.BLENDS:
        raise UdhError(f"unknown blend '{config.blend}'; choose one of: {', '.join(compositing.BLENDS)}")
    if config.exposure not in EXPOSURES:
        raise UdhError(f"unknown exposure compensation '{config.exposure}'; choose one of: {', '.join(EXPOSURES)}")
    if config.seams not in SEAM_FINDERS:
        raise UdhError(f"unknown seam finder '{config.seams}'; choose one of: {', '.join(SEAM_FINDERS)}")
    if config.order not in ORDERS:
        raise UdhError(f"unknown order '{config.order}'; choose one of: {', '.join(ORDERS)}")
    if config.work_size < 32:
        raise UdhError(f"--work-size {config.work_size}: give at least 32 pixels")
    if config.max_size is not None and config.max_size < 16:
        raise UdhError(f"--max-size {config.max_size}: give at least 16 pixels")
    if not 0.0 <= config.min_confidence <= 1.0:
        raise UdhError(f"--min-confidence {config.min_confidence}: give a value in [0, 1]")
    if not 0.0 <= config.min_verified <= 1.0:
        raise UdhError(f"--min-verified {config.min_verified}: give a value in [0, 1]")
    if not config.max_frame_scale > 1.0:
        raise UdhError(f"--max-frame-scale {config.max_frame_scale}: give a factor above 1 (frames drawn that many times larger or smaller than the reference are reported)")
    if config.workers is not None and config.workers < 1:
        raise UdhError(f"--workers {config.workers}: give at least 1 (pairs estimated in this process)")
    if not (config.gps_sigma_m >= 0 and math.isfinite(config.gps_sigma_m)):
        raise UdhError(f"--gps-sigma {config.gps_sigma_m}: give the GPS fixes' error in metres (e.g. 3), or 0 for off")
    if not (config.gcp_sigma_m >= 0 and math.isfinite(config.gcp_sigma_m)):
        raise UdhError(f"--gcp-sigma {config.gcp_sigma_m}: give the ground-control points' error in metres (e.g. 0.05), or 0 for off")
    if config.gps_sigma_m > 0 and importlib.util.find_spec("pyproj") is None:  # fail before the pairs, not after
        raise UdhError("--gps-sigma needs pyproj to put the GPS fixes on a map: pip install pyproj (or pip install '.[geo]')")
    if config.solve not in SOLVES:
        raise UdhError(f"--solve {config.solve}: choose one of {', '.join(SOLVES)}")
    if config.every < 1 or config.overlap_per_frame < 0 or config.gps_pairs < 0:
        raise UdhError("--every must be at least 1, and --overlap-pairs and --gps-pairs at least 0")


def mosaic_method_options(method: str, given: dict[str, Any]) -> dict[str, Any]:
    """``given`` plus the mosaic's defaults for ``method``: the learned methods search for large motion, and
    ``auto`` asks no second opinion of mirrored, flipped or swapped copies of a pair (``views``).

    Why: consecutive frames of real flights move further than the synthetic pairs the networks were trained
    on (docs/mosaic.md, "Stages": the learned methods' large-motion search). The views rescue small patches
    moved far, not whole frames, which the escalated network already matches at four headings; in a mosaic they
    only made failed pairs dearer (docs/benchmarks.md, "A mosaic's pairs without the views").
    """
    options = with_option_default(method, given, "search", MOSAIC_SEARCH)
    return with_option_default(method, options, "views", MOSAIC_VIEWS)


def acceptance(config: MosaicConfig) -> Acceptance:
    """The run's pair-acceptance thresholds."""
    return Acceptance(config.min_confidence, config.min_verified)


def run_estimators(config: MosaicConfig, estimator: Estimator | None = None, fallback: Estimator | None = None
                   ) -> tuple[tuple[Estimator, ...], EstimatorSpec | None]:
    """The opinions every pair is asked of, in order, while the answers are doubted (the method, then the
    fallback), and the spec that worker processes build them from; ``estimator`` / ``fallback`` are ready
    instances that override ``config.method`` / ``config.fallback`` and run in this process (no spec)."""
    method_options = mosaic_method_options(config.method, config.method_options)
    named = [(config.method, method_options)] + ([(config.fallback, dict(config.fallback_options))] if config.fallback else [])
    spec = None if estimator is not None or fallback is not None else EstimatorSpec(tuple(named), acceptance(config))
    estimator = estimator or create_estimator(config.method, **method_options)
    fallback = fallback or (create_estimator(config.fallback, **config.fallback_options) if config.fallback else None)
    return ((estimator,) if fallback is None else (estimator, fallback)), spec


def with_workers(config: MosaicConfig, n_frames: int) -> MosaicConfig:
    """``config`` with ``workers`` decided when it was left to the run (None): a cluster's workers estimate the
    pairs and the local ones still blend the tiles."""
    if config.workers is not None:
        return config
    return replace(config, workers=automatic_workers(n_frames) if config.scheduler is None else 1)
