"""Loop-closure pairs confirmed from the chain's prediction: the cascade's ECC pyramid, then the photometric check.

A loop pair's B arrives pre-warped into A's frame by the chained prediction (:func:`.types.work_inputs`), so the
prediction is the identity between the two working images. When ECC started there aligns them as well as
:data:`CONFIRM_MIN_SCORE` asks, that answer is the pair's; otherwise the pair goes to the mosaic's opinions (the
whole cascade) as if it had never been tried. Why: the chain already puts most loop pairs within a few pixels,
where the cascade's network and tile stages add time and nothing else. The refinement is the cascade's own
(``auto``'s :class:`~udh_cli.estimators.refine.PyramidEcc`), its finest level always at the full working side:
from the prediction it lands where the cascade lands, where cheaper ECC levels loosened the loops
(docs/mosaic.md, "Loop-closure pairs from the chain's prediction", has the measurements).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from udh_cli.errors import EstimationFailed
from udh_cli.estimators import Estimator
from udh_cli.estimators.pair import PreparedPair
from udh_cli.estimators.refine import PyramidEcc
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.estimators.verify import VERIFIER

# The score auto's cascade asks of its own answers (Policy.min_score): the loop's disagreement test cannot stand
# in, since the answer starts at the prediction it is tested against.
CONFIRM_MIN_SCORE = THRESHOLDS.min_cascade_score
CONFIRM_MIN_START = THRESHOLDS.min_prediction_start  # below it the cascade decides at once
CONFIRM_MAX_MOVE = THRESHOLDS.max_prediction_move  # further and ECC left the prediction's basin: the cascade decides


def cascade_ecc() -> PyramidEcc:
    """The refinement that confirms a prediction: the cascade's ECC pyramid, held near its start, its finest level
    always at the full working side, because loop pairs hold the map together (docs/benchmarks.md, Speed)."""
    return PyramidEcc(max_move=CONFIRM_MAX_MOVE, clean_side=None)


@dataclass
class PredictionCheck(Estimator):
    """Confirms that a pre-warped pair's prediction (the identity between its images) is right, refining it by
    ``refiner``; raises :class:`EstimationFailed` (the pair then runs the whole cascade) when the prediction
    scores below ``min_start``, when ECC diverges, or when the aligned images score below ``min_score``
    (:data:`~udh_cli.estimators.verify.VERIFIER`).

    Its answers are ``verified`` by "alignment" with the score as their confidence, so the mosaic's
    :class:`~udh_cli.mosaic.pairs.types.Acceptance` still judges them as it judges any other."""

    name: ClassVar[str] = "chain+ecc"
    refiner: PyramidEcc = field(default_factory=cascade_ecc)
    min_score: float = CONFIRM_MIN_SCORE
    min_start: float = CONFIRM_MIN_START

    def _estimate(self, pair: PreparedPair) -> tuple[np.ndarray, float, dict]:
        start = VERIFIER.score(pair.a, pair.b, np.eye(3))
        if start < self.min_start:
            raise EstimationFailed(f"the chained prediction aligns too little to refine (alignment {start:.2f} < {self.min_start})")
        refined, correlation = self.refiner.refine(pair.a, pair.b, np.eye(3))
        score = VERIFIER.score(pair.a, pair.b, refined)
        if score < self.min_score:
            raise EstimationFailed(f"the chained prediction did not confirm (alignment {score:.2f} < {self.min_score})")
        details = {"correlation": correlation, "verification_score": score, "verified": True, "verified_by": "alignment",
                   "stage": "prediction"}
        return refined, score, details


PREDICTION_CHECK = PredictionCheck()
