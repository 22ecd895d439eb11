"""``--method matcher``: the learned matcher alone, as a feature method (no regression, no tiles, no ECC).

The ``matcher`` network (``udh train --mode match``) describes every 4-px cell of both images; their global match
(:func:`udh_cli.estimators.matching.global_match`: mutual nearest cells, a robust fit, guided refinement) is
the answer. Like SIFT's, the answer is verified by its matches. Inside ``--method unsupervised`` the same
match rescues the doubted pairs of the regressing cascade (:class:`~udh_cli.estimators.deep.DeepEstimator`).
"""

from __future__ import annotations

import copy

from dataclasses import dataclass, field
from typing import ClassVar

from udh_cli.errors import EstimationFailed, UdhError
from udh_cli.estimators.base import Estimator
from udh_cli.estimators.matching import CONFIDENT_INLIERS, HEADINGS, MATCH_REFINE_SIDE, MATCH_SIDE, MAX_MATCH_SIDE, global_match
from udh_cli.onnx_model import OnnxMatcher


@dataclass
class MatcherEstimator(Estimator):
    """The global match of a matcher network between two images.

    Attributes:
        model: path of a matcher ONNX file; ``None`` takes the shipped ``unsupervised-matcher``.
        device, threads: onnxruntime's ("auto", "cpu" or "cuda"; None: onnxruntime's default threads).
        side, refine_side: the longer side, px, of the global match and of its guided refinement (None: none).
        escalate_side: the longer side, px, of a second global match when the first finds fewer than
            ``min_inliers`` (:func:`~udh_cli.estimators.matching.global_match`; None: none).
        headings: B's turns tried (1: as given; 2: also half a turn; 4: also quarter turns), each only while
            fewer than :data:`~udh_cli.estimators.matching.CONFIDENT_INLIERS` cells agree.
        min_inliers: agreeing cells an answer needs (:data:`~udh_cli.estimators.matching.CONFIDENT_INLIERS`:
            pairs of frames from different flights reached at most 27).

    Confidence is the support, ``n / (n + min_inliers)`` for ``n`` agreeing cells.
    """

    name: ClassVar[str] = "matcher"
    verifies_itself: ClassVar[bool] = True  # an answer needs min_inliers cells that agree on it
    model: str | None = None
    device: str = "auto"
    threads: int | None = None
    side: int = MATCH_SIDE
    refine_side: int | None = MATCH_REFINE_SIDE
    escalate_side: int | None = MAX_MATCH_SIDE
    headings: int = 4
    min_inliers: int = CONFIDENT_INLIERS
    network: OnnxMatcher = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from udh_cli.models_catalog import shipped_onnx

        if self.headings not in HEADINGS:
            raise UdhError(f"method 'matcher': headings ({self.headings}) must be one of {', '.join(map(str, HEADINGS))}")
        if not 64 <= self.side <= MAX_MATCH_SIDE or not (self.refine_side is None or 64 <= self.refine_side <= 4096) or self.min_inliers < 4 \
                or not (self.escalate_side is None or 64 <= self.escalate_side <= MAX_MATCH_SIDE):
            raise UdhError(f"method 'matcher': side ({self.side}) and escalate_side ({self.escalate_side}, or none) must be 64 to "
                           f"{MAX_MATCH_SIDE} px, refine_side ({self.refine_side}) 64 to 4096 px or none, and min_inliers "
                           f"({self.min_inliers}) at least 4")
        path = self.model if self.model is not None else shipped_onnx("unsupervised-matcher", "fp32")
        self.network = OnnxMatcher.load(path, self.device, self.threads)

    def model_files(self) -> list[str]:
        return [str(self.network.path)]

    def near_prior(self) -> "MatcherEstimator":
        """The same matcher (its network not loaded again) at B's own heading and the first side only: the other
        turns and the second look search for what a pre-warped pair's prediction settled."""
        twin = copy.copy(self)
        twin.headings, twin.escalate_side = 1, None
        return twin

    def _estimate(self, pair):
        found = global_match(self.network, pair.a, pair.b, self.side, self.headings, self.refine_side, self.escalate_side)
        if found.b_from_a is None or found.inliers < self.min_inliers:
            raise EstimationFailed(f"{found.inliers} of {found.matches} matched cells agree (need {self.min_inliers}); "
                                   f"the frames may not overlap, or lack texture")
        details = {"inliers": found.inliers, "matches": found.matches, "heading": found.heading, "side": found.side,
                   "verified": True, "verified_by": "matches"}
        return found.b_from_a, found.inliers / (found.inliers + self.min_inliers), details
