"""Benchmark output: the markdown table, CSV and JSON files (written atomically), with the scoring rules."""

from __future__ import annotations

import csv
import io
import json
import math
import os
import platform
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from udh_cli.bench import metrics
from udh_cli.bench.runner import WARMUP_PAIRS, MethodRun
from udh_cli.errors import UdhError
from udh_cli.files import check_replaceable, write_file_set

RULES = (
    "Errors in pixels at the four corners of image A (for synthetic pairs, the 128x128 patch), measured in B. "
    "MACE: mean corner distance; RMSE: the paper's 4-point RMSE; 0-30 / 30-60 / 60-100 %: mean MACE of the pairs "
    "in that percentile range, best first; p95: 95th percentile of MACE.",
    f"A pair with no answer is scored as 'no motion' (the identity) and stays in every statistic; "
    f"fail % counts pairs with no answer or MACE > {metrics.FAIL_PX:g} px, which also stay in the means.",
    "Input: patch = the two 128x128 patches; full = the full 320x240 frames (the paper's protocol for the "
    "classical methods), scored at the same patch corners; image = the real images as given.",
    f"ms/pair: median of the estimator's own time per pair after a warm-up on {WARMUP_PAIRS} pairs; x SIFT: ratio of that "
    "median to SIFT's on the same set and input (any SIFT row of the set when SIFT did not run with that input). "
    "Absolute times on a shared machine are noisy; the ratios come from one run.",
)


@dataclass
class BenchResult:
    """Everything one ``udh bench`` run produced.

    Attributes:
        kind: ``"synthetic"`` or ``"pairs"``.
        runs: one :class:`MethodRun` per (pair set, method, input).
        config: how the run was set up (command options, where the pairs came from), JSON-ready.
        notes: extra lines for the footer (e.g. that a CSV holds references, not ground truth).
    """

    kind: str
    runs: list[MethodRun]
    config: dict[str, Any]
    notes: list[str] = field(default_factory=list)


def _fmt_px(value: float) -> str:
    if not math.isfinite(value):
        return "inf" if value > 0 else "n/a"
    return f"{value:.2f}" if value < 100 else f"{value:.0f}"


def _fmt_ms(value: float) -> str:
    return f"{value:.2f}" if value < 10 else f"{value:.1f}" if value < 1000 else f"{value:.0f}"


def table_rows(result: BenchResult) -> list[dict[str, Any]]:
    """One flat dict per run: what the CSV holds and the JSON lists."""
    rows = []
    for run in result.runs:
        reasons = Counter(f for f in run.failures if f)
        rows.append({
            "set": run.set_name, "rho": run.rho, "method": run.method, "input": run.input,
            **run.summary.to_dict(), "wall_ms_per_pair": run.wall_ms_per_pair, "time_ratio_to_sift": run.sift_ratio,
            "top_no_answer_reasons": "; ".join(f"{n}x {r}" for r, n in reasons.most_common(3)),
        })
    return rows


def markdown_table(result: BenchResult) -> str:
    """The table printed on stdout and quoted in the README, with the scoring rules as a footer."""
    head = ["set", "method", "input", "MACE mean", "MACE median", "RMSE mean", "0-30 %", "30-60 %", "60-100 %",
            "p95", "fail %", "ms/pair", "x SIFT"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    for run in result.runs:
        s = run.summary
        cells = [run.set_name, run.method, run.input, _fmt_px(s.mace_mean), _fmt_px(s.mace_median), _fmt_px(s.rmse_mean),
                 _fmt_px(s.bucket_0_30), _fmt_px(s.bucket_30_60), _fmt_px(s.bucket_60_100), _fmt_px(s.mace_p95),
                 f"{100 * s.failure_rate:.1f}", _fmt_ms(s.time_median_ms),
                 "" if run.sift_ratio is None else f"{run.sift_ratio:.2g}"]
        lines.append("| " + " | ".join(cells) + " |")
    pairs = sorted({(r.set_name, r.summary.pairs) for r in result.runs}, key=lambda p: p[0])
    footer = [f"Pairs per set: {', '.join(f'{name}: {n}' for name, n in pairs)}."] + list(RULES) + result.notes
    return "\n".join(lines) + "\n\n" + "\n".join(f"- {line}" for line in footer) + "\n"


def environment() -> dict[str, Any]:
    """Where the times were measured."""
    import cv2
    import numpy as np

    return {
        "machine": platform.machine(), "python": platform.python_version(), "cpu_count": os.cpu_count(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "opencv": cv2.__version__, "numpy": np.__version__,
        "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


RESULT_FILES = ("results.md", "results.csv", "results.json", "per_pair.csv")
PLOT_FILES = ("percentiles.png", "speed_accuracy.png")


def check_output_folder(out_dir: str | Path, overwrite: bool = False) -> Path:
    """Raise :class:`UdhError` unless ``out_dir`` is a folder, or can be created as one, that udh may write
    into, and its result files are udh's own or ``overwrite`` is given (:func:`udh_cli.files.check_replaceable`).
    Call it before the benchmark runs, so that a bad ``--out`` fails at once, not after the work."""
    out_dir = Path(out_dir)
    existing = out_dir
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "" if existing == out_dir else f" {existing}"
        raise UdhError(f"{out_dir}:{where} is a file, not a folder; give --out a folder for the results")
    if not os.access(existing, os.W_OK):
        raise UdhError(f"{out_dir}: the folder {existing} is not writable; choose another --out")
    if existing == out_dir:
        for name in RESULT_FILES + PLOT_FILES:
            check_replaceable(out_dir / name, overwrite)
    return out_dir


def write_outputs(result: BenchResult, out_dir: str | Path, plots: bool = True, overwrite: bool = False) -> list[Path]:
    """Write ``results.md``, ``results.csv``, ``results.json``, ``per_pair.csv`` and (with ``plots``)
    ``percentiles.png`` and ``speed_accuracy.png`` into ``out_dir`` (created if needed); returns the paths.
    Existing files are replaced only when udh wrote them, or with ``overwrite``; the set is written all or none."""
    out_dir = check_output_folder(out_dir, overwrite)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UdhError(f"{out_dir}: cannot create the results folder ({exc.strerror}); choose another --out") from None
    rows = table_rows(result)
    files = {
        "results.md": markdown_table(result).encode(),
        "results.csv": _csv_bytes(rows),
        "results.json": json.dumps({
            "kind": result.kind, "config": result.config, "rules": list(RULES), "notes": result.notes,
            "environment": environment(), "results": [_json_safe(r) for r in rows],
        }, indent=2).encode(),
        "per_pair.csv": _csv_bytes(_per_pair_rows(result)),
    }
    if plots:
        from udh_cli.bench.plots import percentile_plot, speed_accuracy_plot

        files["percentiles.png"] = _png_bytes(percentile_plot(result.runs))
        files["speed_accuracy.png"] = _png_bytes(speed_accuracy_plot(result.runs))
    return write_file_set(out_dir, files, overwrite)  # all or none: a full disk leaves no half-replaced set


def _png_bytes(image) -> bytes:
    """PNG at the strongest compression: the plots are flat colours, and the README keeps copies."""
    import cv2

    ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError("OpenCV could not encode a plot as PNG")
    return encoded.tobytes()


def _per_pair_rows(result: BenchResult) -> list[dict[str, Any]]:
    rows = []
    for run in result.runs:
        for i in range(len(run.mace)):
            rows.append({"set": run.set_name, "method": run.method, "input": run.input, "pair": i,
                         "mace": f"{run.mace[i]:.6g}", "rmse": f"{run.rmse[i]:.6g}", "answered": int(run.answered[i]),
                         "elapsed_ms": f"{run.elapsed_ms[i]:.4g}", "no_answer_reason": run.failures[i]})
    return rows


def _csv_bytes(rows: list[dict[str, Any]]) -> bytes:
    buffer = io.StringIO()
    if rows:
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return buffer.getvalue().encode()


def _json_safe(row: dict[str, Any]) -> dict[str, Any]:
    """JSON has no inf/NaN: write them as strings."""
    return {k: (str(v) if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
