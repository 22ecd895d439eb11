"""The one table of acceptance thresholds: every reader takes its number from it, and no module restates one."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

from udh_cli.estimators import base, deep, judge, matching, tiles
from udh_cli.estimators.refined import Policy
from udh_cli.estimators.thresholds import THRESHOLDS, Thresholds
from udh_cli.mosaic.pairs import confirm
from udh_cli.mosaic.pairs.types import Acceptance

PACKAGE = Path(__file__).resolve().parents[2] / "udh_cli"
# The names that once held their own copy of a threshold: each now reads the table.
READERS = {"MIN_CONFIDENCE", "CONFIDENT_INLIERS", "CONFIRMING_LEVELS", "MIN_NETWORK_OVERLAP", "CONFIRM_MIN_SCORE",
           "CONFIRM_MIN_START", "CONFIRM_MAX_MOVE", "min_confidence", "min_verified", "min_score", "trusted_inliers", "search_below"}


def test_every_reader_takes_its_number_from_the_table():
    t = THRESHOLDS
    assert (base.MIN_CONFIDENCE, Acceptance().min_confidence) == (t.min_confidence, t.min_confidence)
    assert Acceptance().min_verified == t.min_alignment_supported
    assert (Policy().min_score, Policy().trusted_inliers) == (t.min_cascade_score, t.trusted_inliers)
    assert (confirm.CONFIRM_MIN_SCORE, confirm.CONFIRM_MIN_START, confirm.CONFIRM_MAX_MOVE) == (
        t.min_cascade_score, t.min_prediction_start, t.max_prediction_move)
    assert confirm.PREDICTION_CHECK.min_score == t.min_cascade_score and confirm.cascade_ecc().max_move == t.max_prediction_move
    assert (matching.CONFIDENT_INLIERS, tiles.CONFIRMING_LEVELS) == (t.confident_inliers, t.confirming_tile_levels)
    assert deep.DeepEstimator.search_below == t.network_search_below
    assert deep.NETWORK_CHECK.min_overlap == judge.MIN_NETWORK_OVERLAP == t.min_network_overlap
    assert judge.Thresholds is Thresholds and judge.THRESHOLDS is THRESHOLDS


def test_every_entry_has_its_reason():
    documented = Thresholds.__doc__
    missing = [f.name for f in dataclasses.fields(Thresholds) if f"{f.name}:" not in documented]
    assert not missing, missing


def test_no_module_restates_a_threshold_as_a_number():
    restated = []
    for path in PACKAGE.rglob("*.py"):
        if path.name == "thresholds.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
            value = getattr(node, "value", None)
            if isinstance(value, ast.Constant) and isinstance(value.value, (int, float)) and not isinstance(value.value, bool):
                restated += [f"{path.relative_to(PACKAGE)}:{node.lineno} {t.id}" for t in targets if isinstance(t, ast.Name) and t.id in READERS]
    assert not restated, restated
