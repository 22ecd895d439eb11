"""Resumable pairwise estimation: every finished pair estimate is kept in ``<output stem>.pairs.json``.

Pairwise estimation is the expensive stage of a mosaic run. :class:`PairCache` records each finished pair
(its :class:`~udh_cli.mosaic.pairwise.PairResult`) and rewrites the file atomically after every batch, so an
interrupted run loses at most the batch it was in. With ``resume`` a later run takes a pair from the file
only when its key matches exactly; anything else is estimated again.

A pair's key covers everything its estimate depends on:
- both frames: file name, full-resolution size, and a digest of the working copy the estimator sees (so the
  file's content, EXIF orientation and ``work_size`` are all in it);
- the method and the fallback: registry name, settings (dataclass fields) and the size and modification
  time of any model file among them, so a retrained model is a different method;
- the acceptance thresholds (they decide which estimates are accepted and when the fallback runs);
- for pre-warped loop-closure pairs, the prior (the chained prediction B is warped with), exactly.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from udh_cli import __version__
from udh_cli.estimators import Estimate, Estimator
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.frames import Frame
from udh_cli.mosaic.pairwise import Acceptance, PairRequest, PairResult
from udh_cli.mosaic.report import Reporter

CACHE_FORMAT = "udh-mosaic-pairs/1"
_MAX_DEPTH = 6  # how deep estimator settings are searched for model files (auto -> its network -> stages -> model -> path)


def cache_path(output: str | Path) -> Path:
    """The pair cache of a mosaic output: ``mosaic.png`` -> ``mosaic.pairs.json``."""
    output = Path(output)
    return output.with_name(f"{output.stem}.pairs.json")


def estimator_identity(estimator: Estimator | None) -> dict[str, Any] | None:
    """What makes an estimator's answers what they are: its name, its settings and its model files.

    Settings are the dataclass fields shown in its repr (none for an estimator that is not a dataclass).
    Model files are found among the dataclass fields (repr or not, nested estimators and model wrappers
    included); each is named with its size and modification time, so that overwriting a model with a
    retrained one changes the identity. Values that cannot be written as JSON are named by their repr.
    """
    if estimator is None:
        return None
    settings = {}
    if dataclasses.is_dataclass(estimator):
        settings = {f.name: _plain(getattr(estimator, f.name, None)) for f in dataclasses.fields(estimator) if f.repr}
    files = sorted(_model_files(estimator, _MAX_DEPTH))
    return {"name": estimator.name, "settings": settings, "files": [list(f) for f in files]}


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name, None)) for f in dataclasses.fields(value) if f.repr}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)


def _model_files(value: Any, depth: int) -> set[tuple[str, int, int]]:
    """(resolved path, size, mtime_ns) of every existing file named by a str/Path within the dataclass fields."""
    if isinstance(value, (str, os.PathLike)):
        try:
            path = Path(value)
            if path.is_file():
                stat = path.stat()
                return {(str(path.resolve()), stat.st_size, stat.st_mtime_ns)}
        except (OSError, ValueError):  # not a path at all (too long, NUL...)
            pass
        return set()
    if depth <= 0:
        return set()
    found: set[tuple[str, int, int]] = set()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            found |= _model_files(getattr(value, f.name, None), depth - 1)
    elif isinstance(value, (list, tuple)):
        for item in value:
            found |= _model_files(item, depth - 1)
    elif isinstance(value, dict):
        for item in value.values():
            found |= _model_files(item, depth - 1)
    return found


def frame_identity(frame: Frame) -> dict[str, Any]:
    """A frame as its estimates see it: file name, full (w, h), and the SHA-1 of its working copy."""
    work = np.ascontiguousarray(frame.work)
    digest = hashlib.sha1(repr((work.shape, str(work.dtype))).encode() + work.tobytes()).hexdigest()
    return {"file": frame.name, "size": list(frame.size), "work": digest}


class PairCache:
    """Finished pair estimates of one run, looked up by key and saved to ``path`` after every batch.

    Attributes:
        path: the cache file.
        hits: pairs taken from the previous run's file in this run.
        entries: key -> cache record of every pair finished (or taken from the file) in this run.
    """

    def __init__(self, path: Path, frames: Sequence[Frame], context: dict[str, Any], previous: dict[str, dict] | None = None) -> None:
        self.path = Path(path)
        self.frames = frames
        self.context = context
        self.previous = previous or {}
        self.entries: dict[str, dict] = {}
        self.hits = 0
        self._frame_ids: dict[int, dict[str, Any]] = {}

    @classmethod
    def open(
        cls,
        path: str | Path,
        frames: Sequence[Frame],
        estimator: Estimator,
        fallback: Estimator | None,
        acceptance: Acceptance,
        resume: bool,
        reporter: Reporter,
    ) -> "PairCache":
        """The cache of a run; with ``resume`` the pairs of ``path`` (if it exists) can be reused.

        Without ``resume`` an existing file is ignored, and replaced after the first batch. An unreadable
        or foreign file is a warning, not an error: every pair is then estimated.
        """
        context = {
            "udh_version": __version__,  # a different release may estimate differently
            "method": estimator_identity(estimator),
            "fallback": estimator_identity(fallback),
            "acceptance": {"min_confidence": float(acceptance.min_confidence), "min_verified": float(acceptance.min_verified)},
        }
        previous: dict[str, dict] = {}
        path = Path(path)
        if resume:
            previous = _read(path, reporter)
            if previous:
                reporter.info(f"resuming: {len(previous)} pair estimates in {path}")
        return cls(path, frames, context, previous)

    def key(self, request: PairRequest) -> str:
        """SHA-1 over the request's frames, prior, and the run's estimators and confidence threshold."""
        prior = None
        if request.prior is not None:
            prior = hashlib.sha1(np.ascontiguousarray(request.prior, dtype=np.float64).tobytes()).hexdigest()
        content = {**self.context, "a": self._frame(request.a), "b": self._frame(request.b), "prior": prior}
        return hashlib.sha1(json.dumps(content, sort_keys=True).encode()).hexdigest()

    def lookup(self, request: PairRequest) -> PairResult | None:
        """The previous run's result for ``request`` when its key matches, re-indexed to this run; else ``None``."""
        key = self.key(request)
        record = self.previous.get(key)
        if record is None:
            return None
        try:
            result = _result_from_record(record, request)
        except (KeyError, TypeError, ValueError):  # a damaged record is estimated again
            return None
        self.entries[key] = record
        self.hits += 1
        return result

    def add(self, request: PairRequest, result: PairResult) -> None:
        """Record a finished pair (call :meth:`save` to write it)."""
        self.entries[self.key(request)] = _record(result, self.frames)

    def save(self, prune: bool = False) -> None:
        """Write every pair of this run so far, atomically (an interrupt leaves the previous file whole).

        The previous file's pairs that this run has not reached yet are kept too, so a second interrupt
        loses nothing either; ``prune`` (once every pair of the run is known) drops the ones it did not use.
        """
        records = dict(self.entries) if prune else {**self.previous, **self.entries}
        pairs = [{"key": key, **record} for key, record in records.items()]
        text = json.dumps({"format": CACHE_FORMAT, "pairs": pairs}, indent=None, separators=(",", ":"))
        atomic_write_bytes(self.path, (text + "\n").encode())

    def _frame(self, index: int) -> dict[str, Any]:
        if index not in self._frame_ids:
            self._frame_ids[index] = frame_identity(self.frames[index])
        return self._frame_ids[index]


def _read(path: Path, reporter: Reporter) -> dict[str, dict]:
    if not path.is_file():
        reporter.info(f"--resume: no pair cache at {path}; estimating every pair")
        return {}
    try:
        data = json.loads(path.read_text())
        if data.get("format") != CACHE_FORMAT:
            raise ValueError(f"format {data.get('format')!r}")
        return {record["key"]: record for record in data["pairs"]}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        reporter.warn(f"--resume: cannot use the pair cache {path} ({type(exc).__name__}: {exc}); estimating every pair")
        return {}


def _record(result: PairResult, frames: Sequence[Frame]) -> dict[str, Any]:
    """A PairResult as JSON; floats keep every bit through json (repr round-trips float64 exactly)."""
    return {
        "a": result.a,
        "b": result.b,
        "a_file": frames[result.a].name,
        "b_file": frames[result.b].name,
        "kind": result.kind,
        "status": result.status,
        "reason": result.reason,
        "method": result.method,
        "confidence": result.confidence,
        "verified": result.verified,
        "b_from_a": None if result.b_from_a is None else result.b_from_a.tolist(),
        "estimates": [e.to_json() for e in result.estimates],
    }


def _result_from_record(record: dict[str, Any], request: PairRequest) -> PairResult:
    estimates = [
        Estimate(
            e["method"],
            None if e["homography"] is None else _matrix(e["homography"]),
            float(e["confidence"]),
            float(e["elapsed_ms"]),
            e["failure"],
            dict(e["details"]),
        )
        for e in record["estimates"]
    ]
    b_from_a = None if record["b_from_a"] is None else _matrix(record["b_from_a"])
    status = record["status"]
    if status not in ("ok", "failed") or (status == "ok") != (b_from_a is not None):
        raise ValueError(f"inconsistent cached pair (status {status!r})")
    verified = record.get("verified")
    result = PairResult(request.a, request.b, request.kind, estimates, b_from_a, status, record["reason"], record["method"], request.prior)
    result.verified = None if verified is None else float(verified)
    return result


def _matrix(values: Any) -> np.ndarray:
    matrix = np.asarray(values, dtype=np.float64)
    if matrix.shape != (3, 3):
        raise ValueError(f"a {matrix.shape} matrix where 3x3 was expected")
    return matrix
