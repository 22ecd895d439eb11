"""The run folder: a new run never mixes into an earlier one, one process writes it at a time, and the metrics
log survives a kill mid-line."""

from __future__ import annotations

import json
import math
from pathlib import Path

from udh_cli.errors import UdhError

def logged_step(line: str) -> float:
    """The step of a metrics.jsonl line; infinity (dropped on resume) for a blank or damaged one, such as the
    half-written last line of a killed run."""
    try:
        record = json.loads(line)
        step = record.get("step", 0)
        return float(step) if isinstance(step, (int, float)) and not isinstance(step, bool) else math.inf
    except (ValueError, RecursionError, AttributeError):
        return math.inf


def check_fresh_out(out: Path, overwrite: bool) -> None:
    """A new run never mixes into an earlier one: an ``--out`` that holds a run needs --resume or --overwrite,
    and a ``config.json`` that udh did not write (a data folder given as --out) needs --overwrite."""
    from udh_cli.files import check_replaceable

    check_replaceable(out / "config.json", overwrite)
    found = [name for name in ("checkpoint.pt", "best.pt", "metrics.jsonl") if (out / name).is_file()]
    if not found:
        return
    if not overwrite:
        raise UdhError(f"--out {out} holds a run ({', '.join(found)}); add --resume to continue it, --overwrite to replace it, "
                       f"or choose another --out")
    lock = lock_run_folder(out)  # never delete a run that another process is writing
    try:
        for name in found:
            (out / name).unlink()
    finally:
        lock.close()


def lock_run_folder(out: Path):
    """An exclusive lock on ``out/.lock`` for this process; a second run into the same folder is refused.

    The operating system drops the lock when the process ends, however it ends, so a killed run never
    leaves a stale lock. Where ``fcntl`` does not exist (Windows) there is no lock.
    """
    out.mkdir(parents=True, exist_ok=True)
    handle = open(out / ".lock", "a+")  # noqa: SIM115 - held open for the run's lifetime
    try:
        import fcntl
    except ImportError:
        return handle
    try:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise UdhError(f"--out {out}: another training is writing to this folder; wait for it or choose another --out") from None
    return handle
