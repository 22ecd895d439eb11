"""Resumable pairwise estimation: every finished pair estimate is kept in ``<output stem>.pairs.json``.

Pairwise estimation is the expensive stage of a mosaic run. :class:`PairCache` records each finished pair
(its :class:`~udh_cli.mosaic.pairs.types.PairResult`) and rewrites the file atomically after every batch, so an
interrupted run loses at most the batch it was in. With ``resume`` a later run takes a pair from the file
only when its key matches exactly; anything else is estimated again.

A pair's key covers everything its estimate depends on:
- both frames: file name, full-resolution size, and a digest of the working copy the estimator sees (so the
  file's content, EXIF orientation and ``work_size`` are all in it);
- the opinions (the method, then the fallback): registry name, settings and the size and modification time
  of any model file among them, so a retrained model is a different method;
- the acceptance thresholds (they decide which estimates are accepted and when the next opinion is asked) and the
  judge's whole table (:data:`~udh_cli.estimators.thresholds.THRESHOLDS`: the verdicts inside the estimates);
- for pre-warped loop-closure pairs, the prior (the chained prediction B is warped with), exactly, and whether it
  was first confirmed as it is (:mod:`.confirm`; the record's ``method`` then says which path answered).

Each record also carries the SHA-256 of its key and content (``digest``): a record edited since udh wrote it, even
consistently (a homography shifted with its estimate), is estimated again with a warning, never reused unchecked.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from udh_cli import geometry
from udh_cli.estimators import Estimate, Estimator
from udh_cli.estimators.base import TYPED_FIELDS
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.errors import UdhError
from udh_cli.files import read_side_file
from udh_cli.version import __version__
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.inputs.frames import Frame
from udh_cli.mosaic.pairs.types import ACCEPTANCE_REVISION, Acceptance, PairRequest, PairResult, full_resolution, work_inputs
from udh_cli.mosaic.report import Reporter

CACHE_FORMAT = "udh-mosaic-pairs/1"
MAX_CACHE_BYTES = 256 * 2**20  # thousands of pairs take a few MB; a larger file is not a cache of ours
_MAX_RECORD_DEPTH = 64  # a pair record nests a few levels (estimates, details); deeper is damage, and could not be written back


def estimator_identity(estimator: Estimator | None) -> dict[str, Any] | None:
    """What makes an estimator's answers what they are: its registry name, its settings record
    (:meth:`~udh_cli.estimators.base.Estimator.settings`) and its model files, each named with its size and
    modification time, so that overwriting a model with a retrained one changes the identity."""
    if estimator is None:
        return None
    files = []
    for name in estimator.model_files():
        stat = Path(name).stat()
        files.append([str(Path(name).resolve()), stat.st_size, stat.st_mtime_ns])
    return {"name": estimator.name, "settings": estimator.settings(), "files": files}


def frame_identity(frame: Frame) -> dict[str, Any]:
    """A frame as its estimates see it: file name, full (w, h), and the SHA-1 of its working copy."""
    work = np.ascontiguousarray(frame.work)
    digest = hashlib.sha1(repr((work.shape, str(work.dtype))).encode() + work.tobytes()).hexdigest()
    return {"file": frame.name, "size": list(frame.size), "work": digest}


class PairCache:
    """Finished pair estimates of one run, looked up by key and saved to ``path`` after every batch.

    Attributes:
        path: the cache file.
        hits: pair estimates taken from the previous run's file in this run.
        requests: pair estimates asked for in this run, cached or not (a loop-closure pair asked again in a later
            round counts again, so ``hits`` may exceed the number of distinct pairs but never ``requests``).
        entries: key -> cache record of every pair finished (or taken from the file) in this run.
    """

    def __init__(self, path: Path, frames: Sequence[Frame], context: dict[str, Any], previous: dict[str, dict] | None = None,
                 reporter: Reporter | None = None, keep: bool = True) -> None:
        self.path = Path(path)
        self.keep = keep  # False: nothing is ever written (a run without --resume or a cache folder)
        self.frames = frames
        self.context = context
        self.previous = previous or {}
        self.reporter = reporter
        self.entries: dict[str, dict] = {}
        self.hits = 0
        self.requests = 0
        self.damaged = 0  # matching records that failed the checks and were estimated again
        self._frame_ids: dict[int, dict[str, Any]] = {}

    @classmethod
    def open(
        cls,
        path: str | Path,
        frames: Sequence[Frame],
        opinions: Sequence[Estimator],
        acceptance: Acceptance,
        resume: bool,
        reporter: Reporter,
        keep: bool = True,
    ) -> "PairCache":
        """The cache of a run; with ``resume`` the pairs of ``path`` (if it exists) can be reused.

        Without ``resume`` an existing file is ignored, and (``keep``) replaced after the first batch; with
        ``keep`` False nothing is written. An unreadable or foreign file is a warning, not an error: every
        pair is then estimated.
        """
        context = {
            "udh_version": __version__,  # a different release may estimate differently
            "opinions": [estimator_identity(opinion) for opinion in opinions],
            "acceptance": {"min_confidence": float(acceptance.min_confidence), "min_verified": float(acceptance.min_verified),
                           "revision": ACCEPTANCE_REVISION},
            "judge": dataclasses.asdict(THRESHOLDS),  # a retuned threshold changes the verdicts the records hold
        }
        previous: dict[str, dict] = {}
        path = Path(path)
        if resume:
            previous = _read(path, reporter)
            if previous:
                reporter.info(f"resuming: {len(previous)} pair estimates in {path}")
        return cls(path, frames, context, previous, reporter, keep)

    def key(self, request: PairRequest) -> str:
        """SHA-1 over the request's frames, prior, and the run's estimators and confidence threshold."""
        prior = None
        if request.prior is not None:
            prior = hashlib.sha1(np.ascontiguousarray(request.prior, dtype=np.float64).tobytes()).hexdigest()
        content = {**self.context, "a": self._frame(request.a), "b": self._frame(request.b), "prior": prior,
                   "from_prediction": request.from_prediction}
        return hashlib.sha1(json.dumps(content, sort_keys=True).encode()).hexdigest()

    def lookup(self, request: PairRequest) -> PairResult | None:
        """The previous run's result for ``request`` when its key matches, re-indexed to this run; else ``None``."""
        self.requests += 1
        key = self.key(request)
        record = self.previous.get(key)
        if record is None:
            return None
        try:
            if record.get("digest") != record_digest(key, record):
                raise ValueError("it is not as udh wrote it: its digest does not match its content (edited by hand?)")
            result = _result_from_record(record, request, self.frames)
        except Exception as exc:  # noqa: BLE001 - whatever the damage (NaN, wrong types or shapes), the pair is estimated again
            self.previous.pop(key, None)  # and never written back
            self.damaged += 1
            if self.reporter is not None:
                frames = self.frames
                self.reporter.warn(f"--resume: the cached estimate of {frames[request.a].name} -> {frames[request.b].name} in {self.path} "
                                   f"is damaged ({_describe(exc)}); estimating it again")
            return None
        self.entries[key] = record
        self.hits += 1
        return result

    def add(self, request: PairRequest, result: PairResult) -> None:
        """Record a finished pair (call :meth:`save` to write it)."""
        key = self.key(request)
        record = _record(result, self.frames)
        self.entries[key] = {**record, "digest": record_digest(key, record)}

    def save(self, prune: bool = False) -> None:
        """Write every pair of this run so far, atomically (an interrupt leaves the previous file whole).

        The previous file's pairs that this run has not reached yet are kept too, so a second interrupt
        loses nothing either; ``prune`` (once every pair of the run is known) drops the ones it did not use.
        """
        if not self.keep:
            return
        records = dict(self.entries) if prune else {**self.previous, **self.entries}
        pairs = [{"key": key, **_content(record), "digest": record["digest"]} for key, record in records.items()]  # as sealed
        text = json.dumps({"format": CACHE_FORMAT, "pairs": pairs}, indent=None, separators=(",", ":"))
        atomic_write_bytes(self.path, (text + "\n").encode())

    def _frame(self, index: int) -> dict[str, Any]:
        if index not in self._frame_ids:
            self._frame_ids[index] = frame_identity(self.frames[index])
        return self._frame_ids[index]


def _content(record: dict[str, Any]) -> dict[str, Any]:
    """The record without its key and digest: what the digest covers, beside the key."""
    return {name: value for name, value in record.items() if name not in ("key", "digest")}


def record_digest(key: str, record: dict[str, Any]) -> str:
    """SHA-256 of a pair's key and record content, as JSON with sorted keys (floats round-trip exactly; the record is
    first passed through JSON so that a record about to be written and the same record read back agree)."""
    as_read = json.loads(json.dumps([key, _content(record)]))
    text = json.dumps(as_read, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _read(path: Path, reporter: Reporter) -> dict[str, dict]:
    if not path.is_file():
        reporter.info(f"--resume: no pair cache at {path}; estimating every pair")
        return {}
    try:
        data = json.loads(read_side_file(path, "--resume", MAX_CACHE_BYTES))
        if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT:
            raise ValueError(f"format {data.get('format') if isinstance(data, dict) else type(data).__name__!r}")
        if not isinstance(data.get("pairs"), list):
            raise ValueError("no list of pairs")
    except (OSError, ValueError, RecursionError, MemoryError) as exc:  # RecursionError: absurdly nested JSON
        reporter.warn(f"--resume: cannot use the pair cache {path} ({_describe(exc)}); estimating every pair")
        return {}
    except UdhError as exc:  # not a regular file, or too large to be one of ours
        reporter.warn(f"cannot use the pair cache: {exc}; estimating every pair")
        return {}
    # Records are checked one by one: a damaged one costs its own pair, not the whole cache.
    records = {record["key"]: record for record in data["pairs"]
               if isinstance(record, dict) and isinstance(record.get("key"), str) and _depth(record) <= _MAX_RECORD_DEPTH}
    if len(records) < len(data["pairs"]):
        reporter.warn(f"--resume: {len(data['pairs']) - len(records)} entries of the pair cache {path} are damaged; their pairs are estimated again")
    unsealed = [key for key, record in records.items() if "digest" not in record]
    if unsealed:  # records without a digest cannot be checked: estimated again, with one warning for them all
        reporter.warn(f"--resume: {len(unsealed)} entries of the pair cache {path} have no digest to check them by; "
                      f"their pairs are estimated again")
        for key in unsealed:
            del records[key]
    return records


def _depth(value: Any) -> int:
    """How deeply lists and dicts nest in ``value`` (iteratively: a hostile file must not exhaust the stack)."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (list, dict)):
            deepest = max(deepest, depth)
            if deepest > _MAX_RECORD_DEPTH:
                break
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return deepest


def _describe(exc: BaseException) -> str:
    """``Type: message`` of an exception, on one line and not too long (a record's repr can be huge)."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:200]}{'...' if len(text) > 200 else ''}"


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


def _result_from_record(record: dict[str, Any], request: PairRequest, frames: Sequence[Frame]) -> PairResult:
    """The record as a PairResult, after the checks a fresh estimate passes; ValueError (or another
    exception) when it is damaged.

    Every estimate's homography must be a valid one (:func:`udh_cli.geometry.is_valid_homography`) for the
    working image A the estimator saw, as :class:`~udh_cli.estimators.Estimator` demands of a fresh one;
    an ``ok`` pair's ``b_from_a`` must be the one its accepted estimate gives, so a NaN or singular matrix
    never reaches the chaining (where it would silently unplace frames).
    """
    if not isinstance(record.get("estimates"), list) or not record["estimates"]:
        raise ValueError("no estimates")
    image_a, _, undo = work_inputs(request, frames)  # what the estimator saw (cropped when pre-warped)
    size_a = (image_a.shape[1], image_a.shape[0])
    estimates = []
    for e in record["estimates"]:
        homography = None if e["homography"] is None else _matrix(e["homography"])
        if homography is not None and not geometry.is_valid_homography(homography, *size_a):
            raise ValueError("an estimate's homography is degenerate (non-finite, singular or folded)")
        confidence, elapsed_ms = float(e["confidence"]), float(e["elapsed_ms"])
        if not (0.0 <= confidence <= 1.0 and math.isfinite(elapsed_ms)):
            raise ValueError(f"confidence {confidence} or time {elapsed_ms} out of range")
        estimates.append(Estimate(_text(e["method"]), homography, confidence, elapsed_ms, _text(e["failure"], True), dict(e["details"]),
                                  **_typed_fields(e)))
    b_from_a = None if record["b_from_a"] is None else _matrix(record["b_from_a"])
    status = record["status"]
    if status not in ("ok", "failed") or (status == "ok") != (b_from_a is not None):
        raise ValueError(f"inconsistent cached pair (status {status!r})")
    method = _text(record["method"], optional=status != "ok")
    if b_from_a is not None:
        accepted = estimates[-1]  # attempts stop at the accepted one
        if not accepted.ok or accepted.method != method:
            raise ValueError(f"its last estimate is not an answer of its method {method!r}")
        expected = full_resolution(accepted, request, frames, undo)
        if not (np.all(np.isfinite(b_from_a)) and np.allclose(b_from_a, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())):
            raise ValueError("its homography is not the one its estimate gives (NaN or altered)")
    verified = record.get("verified")
    if verified is not None and not math.isfinite(float(verified)):
        raise ValueError(f"alignment check {verified!r}")
    result = PairResult(request.a, request.b, request.kind, estimates, b_from_a, status, _text(record["reason"], True), method, request.prior)
    result.verified = None if verified is None else float(verified)
    return result


_TYPED_CHECKS = {  # Estimate's typed fields (TYPED_FIELDS), as to_json writes them; absent (older caches): None
    "inliers": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    "verification_score": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
    "verified": lambda v: isinstance(v, bool),
    "verified_by": lambda v: isinstance(v, str),
    "stage": lambda v: isinstance(v, str),
}


def _typed_fields(record: dict[str, Any]) -> dict[str, Any]:
    typed = {key: record.get(key) for key in TYPED_FIELDS}
    for key, value in typed.items():
        if value is not None and not _TYPED_CHECKS.get(key, lambda v: True)(value):
            raise ValueError(f"an estimate's {key} is {type(value).__name__} {str(value)[:20]}")
    return typed


def _text(value: Any, optional: bool = False) -> str | None:
    if value is None and optional:
        return None
    if not isinstance(value, str):
        raise ValueError(f"{type(value).__name__} where text was expected")
    return value


def _matrix(values: Any) -> np.ndarray:
    matrix = np.asarray(values, dtype=np.float64)
    if matrix.shape != (3, 3):
        raise ValueError(f"a {matrix.shape} matrix where 3x3 was expected")
    return matrix
