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
from udh_cli.estimators.matching import CONFIDENT_INLIERS, MatchSettings
from udh_cli.onnx_model import OnnxMatcher


@dataclass
class MatcherEstimator(Estimator):
    """The global match of a matcher network between two images.

    Attributes:
        model: path of a matcher ONNX file; ``None`` takes the shipped ``unsupervised-matcher``.
        device, threads: onnxruntime's ("auto", "cpu" or "cuda"; None: onnxruntime's default threads).
        side, refine_side, escalate_side, headings: the global match's
            (:class:`~udh_cli.estimators.matching.MatchSettings`, which checks them).
        min_inliers: agreeing cells an answer needs (:data:`~udh_cli.estimators.matching.CONFIDENT_INLIERS`:
            pairs of frames from different flights reached at most 27).

    Confidence is the support, ``n / (n + min_inliers)`` for ``n`` agreeing cells.
    """

    name: ClassVar[str] = "matcher"
    verifies_itself: ClassVar[bool] = True  # an answer needs min_inliers cells that agree on it
    model: str | None = None
    device: str = "auto"
    threads: int | None = None
    side: int = MatchSettings.side
    refine_side: int | None = MatchSettings.refine_side
    escalate_side: int | None = MatchSettings.escalate_side
    headings: int = MatchSettings.headings
    min_inliers: int = CONFIDENT_INLIERS
    network: OnnxMatcher = field(init=False, repr=False)
    match_settings: MatchSettings = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from udh_cli.models_catalog import ShippedRoles, shipped_onnx

        if self.min_inliers < 4:
            raise UdhError(f"method 'matcher': min_inliers ({self.min_inliers}) must be at least 4")
        self.match_settings = MatchSettings(self.side, self.headings, self.refine_side, self.escalate_side).checked(self.name)
        path = self.model if self.model is not None else shipped_onnx(ShippedRoles.of("unsupervised").matcher, "fp32")
        self.network = OnnxMatcher.load(path, self.device, self.threads)

    def model_files(self) -> list[str]:
        return [str(self.network.path)]

    def model_notes(self) -> list[str]:
        return self.network.lacks()

    def near_prior(self) -> "MatcherEstimator":
        """The same matcher (its network not loaded again) at B's own heading and the first side only
        (:meth:`MatchSettings.near_prior`)."""
        twin = copy.copy(self)
        twin.match_settings = self.match_settings.near_prior()
        twin.headings, twin.escalate_side = twin.match_settings.headings, twin.match_settings.escalate_side
        return twin

    def _estimate(self, pair):
        found = self.match_settings.match(self.network, pair.a, pair.b)
        if found.b_from_a is None or found.inliers < self.min_inliers:
            raise EstimationFailed(f"{found.inliers} of {found.matches} matched cells agree (need {self.min_inliers}); "
                                   f"the frames may not overlap, or lack texture")
        details = {"inliers": found.inliers, "matches": found.matches, "heading": found.heading, "side": found.side,
                   "verified": True, "verified_by": "matches"}
        return found.b_from_a, found.inliers / (found.inliers + self.min_inliers), details
