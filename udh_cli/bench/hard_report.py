"""``udh bench hard``'s output: the table per kind of motion, results.json with every pair, and the
reliability diagram, written atomically."""

from __future__ import annotations

import json
import math
from pathlib import Path

from udh_cli.bench import metrics
from udh_cli.bench.hard import HardResult
from udh_cli.bench.report import _png_bytes, check_output_folder, environment
from udh_cli.bench.verdicts import ALL_KINDS, VERIFIED_CONFIDENCE, right, verified
from udh_cli.errors import UdhError
from udh_cli.files import write_file_set

RULES = (
    f"failures: no answer, or a mean corner error (MACE, at A's four corners, in B's pixels at 800 px) over "
    f"{metrics.FAIL_PX:g} px. A pair without an answer is scored as 'no motion' in the median.",
    "verified: what udh reports as verified (the method's own verdict, Estimate.verified, where it gives one; else a "
    f"confidence of at least {VERIFIED_CONFIDENCE:g}, the mosaic's floor). verified but wrong: verified, yet a failure; "
    "as a share of all pairs, and of the verified answers (the aim: under 3 % of the verified answers wrong).",
)


def _percent(value: float) -> str:
    return "n/a" if not math.isfinite(value) else f"{100 * value:.1f} %"


def _px(value: float) -> str:
    return "inf" if not math.isfinite(value) else f"{value:.2f}" if value < 100 else f"{value:.0f}"


def markdown_table(result: HardResult) -> str:
    """Per kind, then over all kinds: each method's failures, verified but wrong and median error."""
    head = ["kind of motion", "method", "pairs", "failures", "verified", "verified but wrong", "wrong among verified",
            "median px"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|"]
    for s in result.scores:
        kind = f"**{s.kind}**" if s.kind == ALL_KINDS else s.kind
        lines.append("| " + " | ".join([
            kind, s.method, str(s.pairs), f"{s.failures} ({_percent(s.failure_rate)})", str(s.verified),
            f"{s.verified_wrong} ({_percent(s.verified_wrong_rate)})", _percent(s.wrong_among_verified), _px(s.median_px),
        ]) + " |")
    footer = list(RULES) + result.notes
    return "\n".join(lines) + "\n\n" + "\n".join(f"- {line}" for line in footer) + "\n"


def _per_pair(result: HardResult) -> list[dict]:
    rows = []
    for run in result.runs:
        is_right, is_verified = right(run), verified(run)
        for i, label in enumerate(result.labels[run.set_name]):
            rows.append({"kind": run.set_name, "pair": label, "method": run.method, "mace": _finite(run.mace[i]),
                         "answered": bool(run.answered[i]), "confidence": float(run.confidence[i]),
                         "verified": bool(is_verified[i]), "right": bool(is_right[i]), "no_answer_reason": run.failures[i]})
    return rows


def _finite(value: float) -> float | str:
    return float(value) if math.isfinite(value) else str(value)


def write_hard_outputs(result: HardResult, out_dir: str | Path, plots: bool = True, overwrite: bool = False) -> list[Path]:
    """Write ``results.md``, ``results.json`` and (with ``plots``) ``reliability.png`` into ``out_dir``, all or none,
    replacing only files udh wrote unless ``overwrite``."""
    from udh_cli.bench.reliability_plot import reliability_plot

    out_dir = check_output_folder(out_dir, overwrite)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UdhError(f"{out_dir}: cannot create the results folder ({exc.strerror}); choose another --out") from None
    payload = {
        "kind": "hard", "config": result.config, "rules": list(RULES), "notes": result.notes, "environment": environment(),
        "results": [{k: _finite(v) if isinstance(v, float) else v for k, v in s.to_dict().items()} for s in result.scores],
        "reliability": [c.to_dict() for c in result.curves], "pairs": _per_pair(result),
    }
    files = {"results.md": markdown_table(result).encode(), "results.json": json.dumps(payload, indent=2).encode()}
    if plots:
        files["reliability.png"] = _png_bytes(reliability_plot(result.curves, title="reliability: all kinds of motion"))
    return write_file_set(out_dir, files, overwrite)
