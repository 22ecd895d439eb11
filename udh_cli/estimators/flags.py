"""The typed flags of ``udh estimate``: one table of the options common enough for a flag of their own.

Each flag is an estimator option by its key, forwarded where ``-O KEY=VALUE`` goes
(:func:`udh_cli.estimators.registry.nest_options`: ``--search 2`` is ``search`` for ``unsupervised`` and
``network.search`` for ``auto``), so an option is declared once, on its record, and described once, here. Free
of NumPy and of the estimators' modules, so that ``udh --help`` reads it without loading them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAX_ITERATIONS = 1000  # --iterations: ECC's own default (the paper's); network rounds need a handful
OFF = "none"  # the word that turns a network option off ("" to the estimator)


@dataclass(frozen=True)
class OptionFlag:
    """A flag of ``udh estimate`` for the estimator option ``key``.

    Attributes:
        key: the option (a field of the methods' records, :func:`~udh_cli.estimators.registry.option_path`).
        kind: the value's type on the command line (``Path`` values reach the estimator as text).
        help: what it does, for which methods.
        low, high: the least and most values the command line accepts (None: no bound).
        switch: a ``--KEY/--no-KEY`` pair instead of a value.
        off: the option also takes :data:`OFF`, which turns it off.
    """

    key: str
    kind: type
    help: str
    low: int | None = None
    high: int | None = None
    switch: bool = False
    off: bool = False

    @property
    def name(self) -> str:
        """The flag as typed: ``--refine-model``."""
        return "--" + self.key.replace("_", "-")

    def value(self, given: Any) -> Any:
        """``given`` on the command line as the estimator takes it: paths as text, :data:`OFF` as ""."""
        if self.off and isinstance(given, str) and given.lower() == OFF:
            return ""
        return str(given) if isinstance(given, Path) else given


_LEARNED = "Learned methods: "
OPTION_FLAGS: tuple[OptionFlag, ...] = (
    OptionFlag("best_features", int, "sift/orb: keep only the N strongest keypoints."),
    OptionFlag("model", Path, _LEARNED + "an ONNX file instead of the shipped model."),
    OptionFlag("device", str, _LEARNED + "auto (CUDA if onnxruntime has it), cpu or cuda."),
    OptionFlag("iterations", int, _LEARNED + f"rounds of the coarse network; ecc: ECC iterations (1-{MAX_ITERATIONS}).", 1, MAX_ITERATIONS),
    OptionFlag("refine_model", Path, _LEARNED + "an ONNX file for the refinement stage instead of the shipped one."),
    OptionFlag("refine_rounds", int, _LEARNED + "rounds of the refinement network after the coarse ones (0: none; at most 10).", 0, 10),
    OptionFlag("search", int, _LEARNED + "when the answer is doubted, retry from a (2N+1)^2 grid of shifts up to half the frame "
               "(0: off; at most 4; unsupervised: 2 with its tile stage).", 0, 4),
    OptionFlag("precision", str, _LEARNED + "which shipped networks, int8 (the default where shipped) or fp32."),
    OptionFlag("headings", int, _LEARNED + "2 also tries B turned half a turn (unsupervised's default), 1 only B as given.", 1, 2),
    OptionFlag("tiles", bool, _LEARNED + "refine on tiles up to full resolution (on when there is a refinement stage).", switch=True),
    OptionFlag("flight_model", str, _LEARNED + f"the flight-motion coarse network beside the first (default: the shipped one; "
               f"'{OFF}' for none).", off=True),
    OptionFlag("matcher_model", str, _LEARNED + f"the matcher whose global match a doubted answer gets (default: the shipped one "
               f"with the tile stage; '{OFF}' for none).", off=True),
)


def given_flags(values: dict[str, Any]) -> dict[str, Any]:
    """The flags given on a command line (``values``: each flag's key to its value, None when not given), as the
    estimator takes them."""
    return {flag.key: flag.value(values[flag.key]) for flag in OPTION_FLAGS if values.get(flag.key) is not None}
