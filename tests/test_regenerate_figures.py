"""examples/regenerate_figures.py: the README read by row label, the comparison, and group (a) run on the example flight."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "regenerate_figures.py"
_spec = importlib.util.spec_from_file_location("regenerate_figures", SCRIPT)
figures = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = figures  # dataclasses look their module up there
_spec.loader.exec_module(figures)

TABLES = """\
Some text.

| flight | `auto` (default) | `sift` | `--method unsupervised` (networks only) |
|---|---|---|---|
| simulated, 18 frames, ground truth | 0.041 px mean / 0.23 px largest corner error, 3.3 s (2026-11-25) | 0.10 / 0.63 px, 9.6 s | |
| copr, 41 frames, 1600x1067 | 41 placed, 1 part, 1.18 px, 21 s | 41 placed, 1 part, 1.11 px, 32 s | **41 placed, 1 part**, 1.65 px (dunes), 18 s |

| method | rho 32: median / p95 / fail | time, x SIFT (rho 32) |
|---|---|---:|
| orb * | 4.22 / 32.86 / 32.0 % | 0.21 |
| **auto** (default) | **0.06 / 0.56 / 0.3 %** | 1.4 |

**Flight motion** (200 pairs): `auto` 0.28 px median, 3.5 % failures; SIFT 0.77 px, 23.5 %; `--method unsupervised` 0.86 px, 5.5 %.
"""


def test_tables_are_read_by_row_and_column_label():
    tables = figures.parse_tables(TABLES)
    mosaics = figures.find_table(tables, "flight", "auto")
    synthetic = figures.find_table(tables, "method", "rho 32")
    assert set(mosaics) == {"simulated", "copr"}
    assert mosaics["copr"]["unsupervised"] == "**41 placed, 1 part**, 1.65 px (dunes), 18 s"
    assert set(synthetic) == {"orb", "auto"}
    assert synthetic["auto"]["time, x sift"] == "1.4"
    assert figures.find_table(tables, "flight", "rho 32") == {}


def test_cell_numbers_leave_out_parentheses():
    assert figures.cell_numbers("**41 placed, 1 part**, 1.65 px (dunes), 18 s") == [41, 1, 1.65, 18]
    assert figures.cell_numbers("0.041 px mean / 0.23 px largest, 3.3 s (2026-11-25)") == [0.041, 0.23, 3.3]
    assert figures.cell_numbers("**0.06 / 0.56 / 0.3 %**") == [0.06, 0.56, 0.3]


def test_flight_motion_prose_is_read_per_method():
    assert figures.flight_motion_cell(TABLES, "auto") == "0.28 / 3.5 %"
    assert figures.flight_motion_cell(TABLES, "sift") == "0.77 / 23.5 %"
    assert figures.flight_motion_cell(TABLES, "unsupervised") == "0.86 / 5.5 %"
    assert figures.flight_motion_cell("no such paragraph", "auto") is None


def _mosaic_figure(values):
    return figures.Figure("b", "copr", "auto", values, (figures.COUNT, figures.COUNT, figures.PIXELS, None))


def test_within_tolerance_is_reproduced_and_wall_time_is_never_compared():
    judged = figures.judge(_mosaic_figure([41, 1, 1.25, 900.0]), "41 placed, 1 part, 1.18 px, 21 s")
    assert judged.status == "reproduced"
    assert judged.note == ""


def test_outside_tolerance_differs_with_both_values():
    judged = figures.judge(_mosaic_figure([40, 1, 1.18, 21.0]), "41 placed, 1 part, 1.18 px, 21 s")
    assert judged.status == "differs"
    assert judged.note == "number 1: measured 40, README 41"
    judged = figures.judge(_mosaic_figure([41, 1, 1.31, 21.0]), "41 placed, 1 part, 1.18 px, 21 s")
    assert judged.note == "number 3: measured 1.31, README 1.18"


def test_not_run_no_readme_value_and_timings_only():
    assert figures.judge(figures.Figure("b", "copr", "auto", note="absent"), "41 placed").status == "not run"
    assert figures.judge(_mosaic_figure([41, 1, 1.18, 21.0]), None).status == "no README value"
    timing = figures.Figure("e", "pair: sift", "ms", [430.0, 1.0], (None, None))
    assert figures.judge(timing, "999 ms").status == "reported"


def test_tolerance_is_relative_or_absolute_whichever_is_larger():
    assert figures.PIXELS.holds(0.05, 0.041)  # 0.009 px off: under the 0.02 px floor
    assert not figures.PIXELS.holds(1.40, 1.18)  # 19 % off
    assert figures.PIXELS.holds(1.28, 1.18)  # 8 % off
    assert not figures.COUNT.holds(40, 41)


def test_real_flights_without_data_are_not_run(tmp_path):
    settings = figures.Settings(tmp_path, data=None, flights=("copr",), real_methods=("sift",))
    (figure,) = figures.real_flight_figures(settings)
    assert (figure.status, figure.note) == ("not run", "no --data folder given")
    settings = figures.Settings(tmp_path, data=tmp_path, flights=("copr",), real_methods=("sift",))
    (figure,) = figures.real_flight_figures(settings)
    assert figure.note.endswith("is absent")


def test_the_readme_has_the_figures_the_script_compares():
    readme = figures.README.read_text(encoding="utf-8")
    for row, column in [("simulated", "auto"), ("simulated", "sift"), ("copr", "unsupervised"), ("seneca", "auto")]:
        cell = figures.readme_cell(readme, figures.Figure("b", row, column))
        assert cell is not None and len(figures.cell_numbers(cell)) >= 3, (row, column)
    for method in figures.SYNTHETIC_METHODS:
        cell = figures.readme_cell(readme, figures.Figure("c", method, "rho 32"))
        assert cell is not None and len(figures.cell_numbers(cell)) == 3, method
    for method in figures.FLIGHT_MOTION_LABELS:
        assert figures.readme_cell(readme, figures.Figure("d", method, "flight motion")) is not None, method


@pytest.fixture(scope="module")
def sim_flight_run(tmp_path_factory):
    """Group (a) with sift alone on the example flight, judged against the README and written out."""
    scratch = tmp_path_factory.mktemp("figures")
    settings = figures.Settings(scratch, sim_methods=("sift",))
    judged = figures.regenerate(["a"], settings, figures.README.read_text(encoding="utf-8"))
    paths = figures.write_outputs(scratch / "out", judged, "2026-11-27", {"groups": "a"})
    return judged, paths


def test_group_a_measures_the_example_flight_against_its_truth(sim_flight_run):
    (figure,), _ = sim_flight_run
    assert (figure.group, figure.row, figure.column) == ("a", "simulated", "sift")
    mean_px, max_px, wall_s = figure.values
    assert 0 < mean_px <= max_px < 2.0  # sift places the 18 simulated frames within a couple of pixels
    assert wall_s > 0
    assert figure.compared[2] is None
    assert figure.readme is not None
    assert figure.status in ("reproduced", "differs")


def test_outputs_are_dated_markdown_and_json(sim_flight_run):
    judged, (markdown, record) = sim_flight_run
    assert (markdown.name, record.name) == ("figures-2026-11-27.md", "figures-2026-11-27.json")
    assert not list(markdown.parent.glob(".*partial"))
    loaded = json.loads(record.read_text())
    assert loaded["date"] == "2026-11-27"
    assert [f["status"] for f in loaded["figures"]] == [f.status for f in judged]
    assert loaded["figures"][0]["compared"] == [True, True, False]
    assert "| simulated | sift |" in markdown.read_text()


def test_a_differing_figure_keeps_its_earlier_note():
    figure = figures.Figure("c", "sift", "rho 32", [0.5, 7.58, 5.0], (figures.PIXELS, figures.PIXELS, figures.PERCENT),
                            note="20 pairs, the README's 300")
    judged = figures.judge(figure, "0.42 / 7.58 / 5.0 %")
    assert judged.note == "20 pairs, the README's 300; number 1: measured 0.5, README 0.42"
