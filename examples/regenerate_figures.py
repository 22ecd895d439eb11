"""Regenerate the README's figures with udh's own library calls, and say which ones still hold.

    python examples/regenerate_figures.py [--only a,b] [--data ../shared/data] [--flights copr,brighton-beach]
        [--n 300] [--out figures/]

Groups: (a) the example flight's mosaic against its ground truth, (b) real-flight mosaics (needs ``--data``),
(c) the synthetic-pairs table, (d) flight motion, (e) speed. Each figure is compared with the README's current
value, found by row label, and marked ``reproduced`` (every compared number within its tolerance, below),
``differs`` (both values given), ``not run`` (why), ``no README value`` or ``reported`` (timings only: wall times
and speed ratios are never compared). ``--out`` receives ``figures-YYYY-MM-DD.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SIM_FLIGHT = ROOT / "examples" / "sim_flight"
REAL_FLIGHTS = ("copr", "brighton-beach", "seneca")
MOSAIC_METHODS = ("auto", "sift")  # the example flight's columns
REAL_METHODS = ("auto", "sift", "unsupervised")
SYNTHETIC_METHODS = ("sift", "orb", "ecc", "supervised", "unsupervised", "auto")
SYNTHETIC_RHOS = (32.0, 45.0)
README_SYNTHETIC_N = 300  # the README's pairs per rho
README_FLIGHT_N = 200  # the README's flight-motion pairs
FLIGHT_MOTION_LABELS = {"auto": "`auto`", "sift": "SIFT", "unsupervised": "`--method unsupervised`"}  # as the prose names them


@dataclass(frozen=True)
class Tolerance:
    """A measured number reproduces the README's when ``|measured - readme| <= max(absolute, relative * |readme|)``."""

    relative: float
    absolute: float

    def holds(self, measured: float, readme: float) -> bool:
        return abs(measured - readme) <= max(self.absolute, self.relative * abs(readme))


COUNT = Tolerance(0.0, 0.0)  # frames placed and parts are exact
PIXELS = Tolerance(0.10, 0.02)  # corner and loop errors: 10 %, and 0.02 px for the small ones
PERCENT = Tolerance(0.0, 1.0)  # failure rates, in percentage points
TOLERANCES = {"count": "exact", "pixels": "within 10 % or 0.02 px", "percent": "within 1 percentage point",
              "timings": "reported, never compared"}


@dataclass
class Figure:
    """One README cell, measured again.

    Attributes:
        row, column: the README table's row and column keys (:func:`row_key`, :func:`column_key`).
        values: the measured numbers, in the order the README cell gives them; empty when not run.
        compared: one tolerance per value, ``None`` for a number only reported (wall times, ratios of times).
        text: the measured cell as the README would read.
        details: more of the run for the docs' longer tables (e.g. loop consistency before and after), never compared.
    """

    group: str
    row: str
    column: str
    values: list[float | None] = field(default_factory=list)
    compared: tuple[Tolerance | None, ...] = ()
    text: str = ""
    status: str = "not run"
    readme: str | None = None
    note: str = ""
    details: dict = field(default_factory=dict)


# ---- the README, read by row label ----

def row_key(label: str) -> str:
    """``"**auto** (default)"`` -> ``"auto"``; ``"copr, 41 frames, 1600x1067"`` -> ``"copr"``."""
    plain = label.replace("*", "").replace("`", "").strip()
    return re.split(r",| \(", plain, maxsplit=1)[0].strip().lower()


def column_key(header: str) -> str:
    """``"`--method unsupervised` (networks only)"`` -> ``"unsupervised"``; ``"rho 32: median / p95 / fail"`` -> ``"rho 32"``."""
    plain = header.replace("*", "").replace("`", "").replace("--method ", "").strip()
    return re.split(r":| \(", plain, maxsplit=1)[0].strip().lower()


def parse_tables(markdown: str) -> list[dict[str, dict[str, str]]]:
    """Every Markdown table as ``{row key: {column key: cell}}``; the first column's key is kept under ``""``."""
    tables, lines = [], markdown.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and re.match(r"^\|[\s:|-]+\|\s*$", lines[i + 1]):
            headers = [column_key(h) for h in _cells(lines[i])]
            table, i = {}, i + 2
            while i < len(lines) and lines[i].startswith("|"):
                cells = _cells(lines[i])
                table.setdefault(row_key(cells[0]), {"": headers[0], **dict(zip(headers[1:], cells[1:]))})
                i += 1
            tables.append(table)
        else:
            i += 1
    return tables


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def find_table(tables: list[dict[str, dict[str, str]]], first_column: str, column: str) -> dict[str, dict[str, str]]:
    """The first table whose first column is ``first_column`` and that has ``column``; empty when none."""
    for table in tables:
        rows = list(table.values())
        if rows and rows[0][""] == first_column and any(column in r for r in rows):
            return table
    return {}


def cell_numbers(cell: str) -> list[float]:
    """The numbers of a cell, without what is in parentheses (dates, remarks): ``"1.62 px, 18 s (trees)"`` -> [1.62, 18]."""
    return [float(v) for v in re.findall(r"\d+(?:\.\d+)?", re.sub(r"\([^)]*\)", "", cell))]


def flight_motion_cell(markdown: str, method: str) -> str | None:
    """The README's flight-motion prose for ``method`` as a cell, ``"0.28 / 3.5 %"`` (median px / failures)."""
    paragraph = markdown.split("**Flight motion**", 1)[-1].split("\n\n", 1)[0] if "**Flight motion**" in markdown else ""
    found = re.search(re.escape(FLIGHT_MOTION_LABELS.get(method, method)) + r"\s+([\d.]+) px(?: median)?, ([\d.]+) %", paragraph)
    return f"{found.group(1)} / {found.group(2)} %" if found else None


def readme_cell(markdown: str, figure: Figure) -> str | None:
    """The README's current value for ``figure``, or ``None`` where the README has none."""
    if figure.group == "d":
        return flight_motion_cell(markdown, figure.row)
    if figure.group == "e":
        return None
    first_column = "method" if figure.group == "c" else "flight"
    table = find_table(parse_tables(markdown), first_column, figure.column)
    cell = table.get(figure.row, {}).get(figure.column)
    return cell or None


def judge(figure: Figure, readme: str | None) -> Figure:
    """Set ``figure.status``, ``readme`` and ``note`` from the comparison with the README cell ``readme``."""
    figure.readme = readme
    if not figure.values:
        figure.status = "not run"
        return figure
    if not any(figure.compared):
        figure.status = "reported"
        return figure
    if readme is None:
        figure.status = "no README value"
        return figure
    expected = cell_numbers(readme)
    off = [i for i, tolerance in enumerate(figure.compared) if tolerance is not None and (
        i >= len(expected) or figure.values[i] is None or not tolerance.holds(figure.values[i], expected[i]))]
    figure.status = "differs" if off else "reproduced"
    if off:
        differences = "; ".join(f"number {i + 1}: measured {_number(figure.values[i])}, README "
                                f"{_number(expected[i]) if i < len(expected) else 'none'}" for i in off)
        figure.note = f"{figure.note}; {differences}" if figure.note else differences
    return figure


def _number(value: float | None) -> str:
    return "none" if value is None else f"{value:g}"


# ---- the figure groups ----

@dataclass
class Settings:
    """What a run measures: ``data`` the shared data folder (``None``: real flights not run), ``n`` synthetic pairs
    per rho, ``flight_n`` flight-motion pairs, ``work_size`` the mosaics' (``None``: the default)."""

    scratch: Path
    data: Path | None = None
    flights: tuple[str, ...] = REAL_FLIGHTS
    sim_methods: tuple[str, ...] = MOSAIC_METHODS
    real_methods: tuple[str, ...] = REAL_METHODS
    n: int = README_SYNTHETIC_N
    flight_n: int = README_FLIGHT_N
    speed_pairs: int = 5
    work_size: int | None = None


def _mosaic(folder: Path, output: Path, method: str, work_size: int | None) -> tuple[dict, float]:
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    config = MosaicConfig(method=method) if work_size is None else MosaicConfig(method=method, work_size=work_size)
    started = time.perf_counter()
    report = run_mosaic(folder, output, config)
    return report, time.perf_counter() - started


def sim_flight_figures(settings: Settings) -> list[Figure]:
    """(a) The example flight: mean / largest corner error of the solved frames against the simulator's truth, wall time."""
    figures = []
    for method in settings.sim_methods:
        def measure(method=method) -> Figure:
            report, wall = _mosaic(SIM_FLIGHT, settings.scratch / f"sim-{method}.png", method, settings.work_size)
            solved = report["ground_truth_error"]["solved"]
            return Figure("a", "simulated", method, [solved["mean_corner_px"], solved["max_corner_px"], wall], (PIXELS, PIXELS, None),
                          f"{solved['mean_corner_px']:.3f} px mean / {solved['max_corner_px']:.2f} px largest corner error, {wall:.1f} s")
        figures.append(_attempt("a", "simulated", method, measure))
    return figures


def flight_folder(data: Path, name: str) -> Path:
    """``DATA/flights/NAME/images`` (or without ``flights/`` or ``images/`` where the data is laid out so)."""
    for folder in (data / "flights" / name, data / name):
        if folder.is_dir():
            return folder / "images" if (folder / "images").is_dir() else folder
    return data / "flights" / name


def real_flight_figures(settings: Settings) -> list[Figure]:
    """(b) Real flights: frames placed, parts, mean loop consistency after the solve (px), wall time."""
    figures = []
    for name in settings.flights:
        for method in settings.real_methods:
            folder = None if settings.data is None else flight_folder(settings.data, name)
            if folder is None or not folder.is_dir():
                why = "no --data folder given" if folder is None else f"{folder} is absent"
                figures.append(Figure("b", name, method, note=why))
                continue

            def measure(folder=folder, name=name, method=method) -> Figure:
                report, wall = _mosaic(folder, settings.scratch / f"{name}-{method}.png", method, settings.work_size)
                summary, after = report["summary"], report["loop_consistency"]["loops_after"]
                parts = f"{summary['parts']} part{'s' if summary['parts'] != 1 else ''}"
                loops = f"{after['mean_px']:.2f} px" if after["count"] else "no loops"
                details = {"frames": summary["frames"], "pairs_rejected": summary["pairs_rejected"],
                           "loops_before": report["loop_consistency"]["loops_before"], "loops_after": after}
                return Figure("b", name, method, [summary["placed"], summary["parts"], after["mean_px"], wall], (COUNT, COUNT, PIXELS, None),
                              f"{summary['placed']} placed, {parts}, {loops}, {wall:.0f} s", details=details)
            figures.append(_attempt("b", name, method, measure))
    return figures


def synthetic_figures(settings: Settings) -> list[Figure]:
    """(c) The paper's protocol at rho 32 and 45: median / p95 corner error (px), failures (%), and the time ratio to SIFT."""
    from udh_cli.bench import run_synthetic_bench

    def measure() -> list[Figure]:
        result = run_synthetic_bench(rhos=list(SYNTHETIC_RHOS), count=settings.n, seed=0, methods=list(SYNTHETIC_METHODS),
                                     mode="patch", show_progress=False)
        figures = []
        for run in result.runs:
            s = run.summary
            figures.append(Figure("c", run.method, f"rho {run.rho:g}", [s.mace_median, s.mace_p95, 100 * s.failure_rate],
                                  (PIXELS, PIXELS, PERCENT), f"{s.mace_median:.2f} / {s.mace_p95:.2f} / {100 * s.failure_rate:.1f} %"))
            if run.rho == SYNTHETIC_RHOS[0]:
                ratio = run.sift_ratio
                figures.append(Figure("c", run.method, "time, x sift", [ratio], (None,), "" if ratio is None else f"{ratio:.2g}"))
        return figures
    return _attempt_many("c", "synthetic", measure, _n_note(settings.n, README_SYNTHETIC_N))


def flight_motion_figures(settings: Settings) -> list[Figure]:
    """(d) Flight motion: median corner error (px) and failures (%) on whole 320x240 frames."""
    from udh_cli.bench import run_synthetic_bench

    def measure() -> list[Figure]:
        result = run_synthetic_bench(count=settings.flight_n, seed=0, methods=list(FLIGHT_MOTION_LABELS), motion="flight",
                                     show_progress=False)
        return [Figure("d", run.method, "flight motion", [run.summary.mace_median, 100 * run.summary.failure_rate], (PIXELS, PERCENT),
                       f"{run.summary.mace_median:.2f} / {100 * run.summary.failure_rate:.1f} %") for run in result.runs]
    return _attempt_many("d", "flight motion", measure, _n_note(settings.flight_n, README_FLIGHT_N))


def speed_figures(settings: Settings) -> list[Figure]:
    """(e) Speed on the example flight: the reference workload, each stage as a multiple of it, and single pairs."""
    from udh_cli.bench.speed import run_speed_bench

    def measure() -> list[Figure]:
        result = run_speed_bench(SIM_FLIGHT, pairs=settings.speed_pairs)
        ref = result.reference
        figures = [Figure("e", "reference workload", "seconds", [ref.seconds], (None,), f"{ref.frames} frames through SIFT in {ref.seconds:.2f} s"),
                   Figure("e", "mosaic", "x reference", [result.wall_s / ref.seconds], (None,),
                          f"{result.wall_s:.1f} s, {result.wall_s / ref.seconds:.2f} x the reference")]
        figures += [Figure("e", f"stage: {stage.name}", "x reference", [stage.ratio], (None,), f"{stage.seconds:.2f} s, {stage.ratio:.2f} x")
                    for stage in result.stages]
        figures += [Figure("e", f"pair: {pair.method}", "ms", [pair.median_ms, pair.sift_ratio], (None, None),
                           f"{pair.median_ms:.0f} ms" + ("" if pair.sift_ratio is None else f", {pair.sift_ratio:.2f} x SIFT"))
                    for pair in result.pairs]
        return figures
    return _attempt_many("e", "speed", measure, "")


def _n_note(n: int, readme_n: int) -> str:
    return "" if n == readme_n else f"{n} pairs, the README's {readme_n}: a smaller draw differs by chance"


def _attempt(group: str, row: str, column: str, measure: Callable[[], Figure]) -> Figure:
    """``measure()``, or a ``not run`` figure saying why it failed."""
    try:
        return measure()
    except Exception as error:  # a figure that cannot be made is reported, and the others still run
        return Figure(group, row, column, note=f"failed: {type(error).__name__}: {error}")


def _attempt_many(group: str, row: str, measure: Callable[[], list[Figure]], note: str) -> list[Figure]:
    try:
        figures = measure()
    except Exception as error:  # as in _attempt
        return [Figure(group, row, "", note=f"failed: {type(error).__name__}: {error}")]
    for figure in figures:
        figure.note = note
    return figures


GROUPS: dict[str, tuple[str, Callable[[Settings], list[Figure]]]] = {
    "a": ("the example flight's mosaic (README: Mosaics, simulated row)", sim_flight_figures),
    "b": ("real-flight mosaics (README: Mosaics)", real_flight_figures),
    "c": ("synthetic pairs (README: Synthetic pairs)", synthetic_figures),
    "d": ("flight motion (README: Flight motion)", flight_motion_figures),
    "e": ("speed on the example flight (README: Speed; timings are reported, not compared)", speed_figures),
}


def regenerate(groups: list[str], settings: Settings, readme: str) -> list[Figure]:
    """Run ``groups`` (keys of :data:`GROUPS`) and judge every figure against ``readme``'s text."""
    figures = []
    for group in groups:
        for figure in GROUPS[group][1](settings):
            figures.append(judge(figure, readme_cell(readme, figure)))
    return figures


# ---- writing ----

def to_markdown(figures: list[Figure], day: str, settings: dict) -> str:
    lines = [f"# udh figures regenerated on {day}", "",
             "Settings: " + ", ".join(f"{k} {v}" for k, v in settings.items()) + ".",
             "Tolerances: " + "; ".join(f"{k} {v}" for k, v in TOLERANCES.items()) + ".", ""]
    for group, (title, _) in GROUPS.items():
        rows = [f for f in figures if f.group == group]
        if not rows:
            continue
        lines += [f"## ({group}) {title}", "", "| row | column | measured | README | status | note |", "|---|---|---|---|---|---|"]
        lines += [f"| {f.row} | {f.column} | {f.text} | {f.readme or ''} | {f.status} | {f.note} |" for f in rows]
        lines.append("")
    return "\n".join(lines)


def write_outputs(out: Path, figures: list[Figure], day: str, settings: dict) -> tuple[Path, Path]:
    """``out/figures-DAY.md`` and ``.json``, each written beside itself first and renamed into place."""
    out.mkdir(parents=True, exist_ok=True)
    record = {"date": day, "settings": settings, "tolerances": TOLERANCES,
              "figures": [{**asdict(f), "compared": [t is not None for t in f.compared]} for f in figures]}
    written = []
    for suffix, text in ((".md", to_markdown(figures, day, settings)), (".json", json.dumps(record, indent=1))):
        target = out / f"figures-{day}{suffix}"
        staged = target.with_name(f".{target.name}.partial")
        staged.write_text(text + "\n", encoding="utf-8")
        os.replace(staged, target)
        written.append(target)
    return written[0], written[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(GROUPS), help="groups to run, comma-separated: " + ", ".join(GROUPS))
    parser.add_argument("--data", type=Path, default=None, help="the shared data folder (holding flights/); without it (b) is not run")
    parser.add_argument("--flights", default=",".join(REAL_FLIGHTS), help="real flights for (b)")
    parser.add_argument("--n", type=int, default=None, help=f"synthetic pairs: per rho in (c) (default {README_SYNTHETIC_N}) and in (d) "
                                                            f"(default {README_FLIGHT_N})")
    parser.add_argument("--out", type=Path, default=Path("figures"))
    args = parser.parse_args()
    groups = [g.strip() for g in args.only.split(",") if g.strip()]
    unknown = [g for g in groups if g not in GROUPS]
    if unknown or not groups:
        parser.error(f"--only {args.only!r}: choose among {', '.join(GROUPS)}, e.g. --only a,b")
    if args.n is not None and args.n < 1:
        parser.error(f"--n {args.n}: give at least one pair")
    if args.data is not None and not args.data.is_dir():
        parser.error(f"--data {args.data}: not a folder; give the shared data folder that holds flights/")
    day = datetime.date.today().isoformat()
    with tempfile.TemporaryDirectory(prefix="udh-figures-") as scratch:
        settings = Settings(Path(scratch), args.data, tuple(f.strip() for f in args.flights.split(",") if f.strip()),
                            n=args.n or README_SYNTHETIC_N, flight_n=args.n or README_FLIGHT_N)
        figures = regenerate(groups, settings, README.read_text(encoding="utf-8"))
    shown = {"groups": ",".join(groups), "data": str(args.data), "flights": ",".join(settings.flights), "n": settings.n,
             "flight_n": settings.flight_n, "cpu_count": os.cpu_count()}
    markdown, _ = write_outputs(args.out, figures, day, shown)
    print(markdown.read_text(encoding="utf-8"))


if __name__ == "__main__":
    main()
