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


def _assignments():
    """(module path relative to udh_cli, line, assigned name, value node) of every plain or annotated assignment to
    a name in udh_cli, thresholds.py left out."""
    for path in PACKAGE.rglob("*.py"):
        if path.name == "thresholds.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
            for target in targets:
                if isinstance(target, ast.Name):
                    yield str(path.relative_to(PACKAGE)), node.lineno, target.id, getattr(node, "value", None)


def test_no_module_restates_a_threshold_as_a_number():
    restated = [f"{module}:{line} {name}" for module, line, name, value in _assignments()
                if name in READERS and isinstance(value, ast.Constant) and isinstance(value.value, (int, float))
                and not isinstance(value.value, bool)]
    assert not restated, restated


# Each reader by module and name, and the entry of the table it must read: equal numbers (0.2, 0.5) cannot show
# a reader taking the wrong entry, the source can.
EXPECTED_ENTRIES = {
    ("estimators/base.py", "MIN_CONFIDENCE"): "min_confidence",
    ("estimators/matching.py", "CONFIDENT_INLIERS"): "confident_inliers",
    ("estimators/tiles.py", "CONFIRMING_LEVELS"): "confirming_tile_levels",
    ("estimators/judge.py", "MIN_NETWORK_OVERLAP"): "min_network_overlap",
    ("mosaic/pairs/confirm.py", "CONFIRM_MIN_SCORE"): "min_cascade_score",
    ("mosaic/pairs/confirm.py", "CONFIRM_MIN_START"): "min_prediction_start",
    ("mosaic/pairs/confirm.py", "CONFIRM_MAX_MOVE"): "max_prediction_move",
    ("mosaic/pairs/types.py", "min_confidence"): "min_confidence",
    ("mosaic/pairs/types.py", "min_verified"): "min_alignment_supported",
    ("estimators/refined.py", "min_score"): "min_cascade_score",
    ("estimators/refined.py", "trusted_inliers"): "trusted_inliers",
    ("estimators/deep.py", "search_below"): "network_search_below",
}


def test_every_reader_names_its_own_entry_of_the_table():
    read = {(module, name): value.attr for module, _, name, value in _assignments()
            if (module, name) in EXPECTED_ENTRIES and isinstance(value, ast.Attribute)
            and isinstance(value.value, ast.Name) and value.value.id == "THRESHOLDS"}
    assert read == EXPECTED_ENTRIES
