"""Writing the files of a mosaic run so that they appear together or not at all (their names: :mod:`.files`).

A split run writes ``NAME.part1.png``, ``NAME.part2.png``... and a preview of each. Each is first written
under a hidden temporary name (:class:`StagedFiles`); only when every part has been written are they
renamed to their own names together with the sidecar, which comes last. A run that fails in its third part so
leaves the outputs of the previous run as they were, not a mix of both. Part files of this output name
that the new run does not produce (an earlier run had more parts) are removed (:func:`stale_part_files`).

What a run publishes is recorded as written by it (the folder's ``.udh-written.json``, :mod:`udh_cli.files`, with the
output's name as the run), and a run replaces or removes only files recorded as its own earlier run's and unchanged
since: never a user's file named like a part, nor another run's mosaic named ``NAME.part1.png``.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import time
from pathlib import Path
from typing import Iterable

from udh_cli.errors import UdhError
from udh_cli.files import SIDE_FILE_LIMIT, folder_locked, read_side_file, record_written, written_by_udh
from udh_cli.images import IMAGE_SUFFIXES
from udh_cli.mosaic.outputs.files import (CAMERAS_SUFFIX, COG_SUFFIX, GEOREFERENCE_SUFFIXES, LIVE_PICTURE_SUFFIX, PAM_SUFFIX, PREVIEW_SUFFIX,
                                         REPORT_PAGE_SUFFIX, MosaicFiles, RunFiles)
from udh_cli.mosaic.report import Reporter

SIDECAR_FORMAT = "udh-mosaic/1"  # the sidecar's "format", its first key as udh writes it


def _is_udh_json(path: Path, formats: tuple[str, ...]) -> bool:
    """Whether ``path`` is a JSON file udh wrote (its ``format`` starts with one of ``formats``)."""
    try:
        if path.stat().st_size > 256 * 2**20:  # no sidecar or pair cache of ours is this large: say so, not "not ours"
            raise UdhError(f"{path}: {path.stat().st_size >> 20} MiB, larger than any sidecar or pair cache udh writes; "
                           f"move it away or choose another output name")
        text = path.read_text(errors="replace")
    except OSError:
        return False
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        # Damaged further on (absurdly nested, cut short, edited): still ours if it opens as udh writes it.
        opening = re.match(r'\s*\{\s*"format"\s*:\s*"([^"\\]*)"', text[:1000])
        return opening is not None and opening.group(1).startswith(formats)
    return isinstance(data, dict) and isinstance(data.get("format"), str) and data["format"].startswith(formats)


def check_outputs_are_not_inputs(source: Path, files: dict[str, Path], sidecar: Path) -> None:
    """Refuse, before any work, outputs that would replace a user's file rather than an earlier run's.

    ``files`` names every file the run may write (``{"mosaic": path, "sidecar": path, ...}``). Refused: any
    of them that is the input video or an existing frame of ``source`` (unless an earlier run to the same
    mosaic recorded it as its own, whatever its extension), and a ``.json`` of ours that exists and was not
    written by udh.
    """
    sources = {source.resolve()} if source.is_file() else set()
    earlier_run = sidecar.is_file() and _is_udh_json(sidecar, ("udh-mosaic/",))
    for role, path in files.items():
        if not path.exists():
            continue
        resolved = path.resolve()
        is_frame = source.is_dir() and resolved.parent == source.resolve() and path.suffix.lower() in IMAGE_SUFFIXES
        ours = written_by_udh(path, files["mosaic"].name) if "mosaic" in files else earlier_run  # live mode's pictures: unrecorded
        if resolved in sources or (is_frame and not ours):
            raise UdhError(f"{path}: the {role} would replace an input file of {source}; choose another output name")
        owned_by_run = path.name.lower().endswith(GEOREFERENCE_SUFFIXES + (CAMERAS_SUFFIX, REPORT_PAGE_SUFFIX, PAM_SUFFIX))
        if (path.suffix.lower() == ".json" and not owned_by_run and not _is_udh_json(path, ("udh-mosaic",))) or (owned_by_run and not earlier_run):
            # JSON, world files and OpenSfM's cameras beside frames are often a flight's own records: never replaced
            raise UdhError(f"{path}: the {role} would replace a file udh did not write (even --overwrite keeps it); choose another output name")


def check_sidecar_is_this_outputs(files: RunFiles, overwrite: bool = False) -> None:
    """Refuse, before any work, a run whose sidecar ``NAME.json`` is an earlier run's to another mosaic (``NAME.png``
    when this one writes ``NAME.tif``): replacing it would orphan that run's files. ``overwrite`` allows it."""
    sidecar, output = files.sidecar, files.output
    if overwrite or not sidecar.is_file() or written_by_udh(sidecar, output.name):
        return
    mosaics = _sidecar_mosaics(sidecar)
    own = re.compile(rf"{re.escape(output.stem)}(?:\.part[1-9][0-9]*)?{re.escape(output.suffix)}")
    if written_by_udh(sidecar) or (mosaics and not any(own.fullmatch(name) for name in mosaics)):
        other = f" of the mosaic {mosaics[0]}" if mosaics else ""
        raise UdhError(f"{sidecar}: the sidecar{other}, written by another run than one to {output.name}; add --overwrite to "
                       f"replace it, or choose another output name")


def check_always_written_are_this_runs(files: RunFiles, overwrite: bool = False) -> None:
    """Refuse, before any work, a mosaic, sidecar or report page in the way that no earlier run to this output wrote
    (every run writes these; :meth:`StagedFiles.publish` checks the rest, parts among them, when they are known)."""
    for path in (files.output, files.sidecar, files.report_page):
        if not overwrite and (path.exists() or path.is_symlink()) and not written_by_udh(path, files.output.name):
            raise UdhError(f"{path}: exists and no earlier run to {files.output.name} wrote it (or it changed since); add "
                           f"--overwrite to replace it, or choose another output name")


def _sidecar_mosaics(sidecar: Path) -> list[str]:
    """The file names of the mosaics a udh sidecar lists (its parts' ``file``); empty when it lists none or is not one."""
    try:
        data = json.loads(sidecar.read_text(errors="replace"))
    except (OSError, ValueError, RecursionError):
        return []
    parts = data.get("parts") if isinstance(data, dict) and str(data.get("format", "")).startswith("udh-mosaic/") else None
    return [Path(p["file"]).name for p in parts if isinstance(p, dict) and isinstance(p.get("file"), str)] if isinstance(parts, list) else []


STALE_AFTER_S = 60.0  # a live quick look's temporary younger than this may be at work beside the refresh


def remove_stale_staged(output: Path, now: float | None = None) -> list[Path]:
    """Hidden temporary files of ``output``'s names (``.staged`` and ``.part``) that a run killed while
    writing left behind; removed. Only hidden files named after ``output``'s stem match. The live quick look's
    (``.NAME.live.jpg...part``) are left while younger than :data:`STALE_AFTER_S`: the quick look writes them
    beside the refresh that runs this."""
    pattern = re.compile(rf"\.+{re.escape(output.stem)}\..*(\.staged\.[A-Za-z0-9]+|\.part)")
    live = re.compile(rf"\.+{re.escape(output.stem)}\.live\.(jpg|json)\..*\.part")
    now = time.time() if now is None else now
    removed = []
    try:
        candidates = list(output.parent.iterdir())
    except OSError:
        return removed
    for path in candidates:
        if not (pattern.fullmatch(path.name) and path.is_file() and not path.is_symlink()):
            continue
        try:
            if live.fullmatch(path.name) and now - path.stat().st_mtime < STALE_AFTER_S:
                continue
        except OSError:  # gone meanwhile: its writer renamed it
            continue
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed


def stale_part_files(output: Path, produced: list[Path]) -> list[Path]:
    """Files named as parts of ``output`` (``stem.partK.suffix``, ``stem.partK.preview.jpg`` and a part's
    world, ``.prj``, ``.cog.tif`` and GDAL ``.aux.xml`` files, K >= 1) that are not in ``produced``: what an
    earlier run with more parts (or with previews) left behind.

    Only those exact patterns match, with ``output``'s own stem and suffix, and only files recorded as written
    by an earlier run to ``output`` and unchanged since; nothing else is returned.
    """
    part = rf"{re.escape(output.stem)}\.part[1-9][0-9]*"
    georeference = "|".join(re.escape(s) for s in GEOREFERENCE_SUFFIXES)
    pattern = re.compile(rf"{part}{re.escape(output.suffix)}(?:{re.escape(PAM_SUFFIX)})?|{part}{re.escape(PREVIEW_SUFFIX)}|{part}(?:{georeference})")
    keep = {p.resolve() for p in produced}
    try:
        candidates = sorted(output.parent.iterdir())
    except OSError:
        return []
    return [p for p in candidates if pattern.fullmatch(p.name) and p.is_file() and not p.is_symlink() and p.resolve() not in keep
            and written_by_udh(p, output.name)]


class StagedFiles:
    """Files written under hidden temporary names in their own folder, then renamed together.

    ``path_for(final)`` gives the name to write to; :meth:`publish` renames every staged file to its
    final name (keeping the permissions of the file it replaces); :meth:`discard` deletes what is left.
    With ``run`` (the mosaic's output path), :meth:`publish` replaces only files recorded as that run's (or any,
    with ``overwrite``) and records what it publishes as that run's.
    """

    def __init__(self, run: Path | None = None, overwrite: bool = False) -> None:
        self.staged: list[tuple[Path, Path]] = []  # (temporary, final)
        self.run, self.overwrite = run, overwrite

    def path_for(self, final: Path) -> Path:
        # Hidden (frames folders skip dot files) and with the final suffix, which picks the image encoder.
        temporary = final.with_name(f".{final.stem}.{secrets.token_hex(4)}.staged{final.suffix}")
        self.staged.append((temporary, final))
        return temporary

    def forget(self, final: Path) -> None:
        """Drop ``final`` from the files to publish and delete what was staged for it (a write that failed)."""
        for temporary, staged_final in [item for item in self.staged if item[1] == final]:
            temporary.unlink(missing_ok=True)
            self.staged.remove((temporary, staged_final))

    def temporary_of(self, final: Path) -> Path | None:
        """The temporary name ``final`` is staged under, or None."""
        return next((temporary for temporary, staged_final in self.staged if staged_final == final), None)

    def publish(self) -> list[Path]:
        """Rename every staged file to its final name; returns the final names. Raises :class:`UdhError` if a
        rename fails."""
        published = [final for _, final in self.staged]
        if self.run is None:
            self._rename()
            return published
        with folder_locked(self.run.parent):
            for final in published:
                if not self.overwrite and (final.exists() or final.is_symlink()) and not written_by_udh(final, self.run.name):
                    raise UdhError(f"{final}: exists and no earlier run to {self.run.name} wrote it (or it changed since); nothing "
                                   f"was written: add --overwrite to replace it, or choose another output name")
            self._rename()
            record_written(*published, run=self.run.name)
        return published

    def _rename(self) -> None:
        for temporary, final in self.staged:
            try:
                if final.exists():
                    os.chmod(temporary, final.stat().st_mode & 0o7777)
                os.replace(temporary, final)
            except OSError as exc:
                raise UdhError(f"{final}: cannot put the new file in place ({exc.strerror}); check the folder's permissions") from None
        self.staged = []

    def discard(self) -> None:
        """Delete the staged files that were not published (after a failure)."""
        for temporary, _ in self.staged:
            temporary.unlink(missing_ok=True)
        self.staged = []


def earlier_outputs(files: Iterable[Path]) -> dict[Path, str]:
    """The images among ``files`` that an earlier ``udh mosaic`` wrote beside its sidecar (``NAME.json`` of
    :data:`SIDECAR_FORMAT`): ``NAME.png``, ``NAME.preview.jpg``, ``NAME.part2.png``, ``NAME.cog.tif`` and the
    like, each mapped to its sidecar's file name.

    Why: a mosaic written into its frames' folder under another name than this run's would otherwise be stitched
    in as a frame by the next run (its own outputs, :meth:`.files.RunFiles.own_files`, are left out by name)."""
    files = list(files)
    found: dict[Path, str] = {}
    for sidecar in (path for path in files if path.suffix.lower() == ".json" and _is_sidecar(path)):
        # The mosaics it lists by name, and the files named after them; never merely a file that shares its stem,
        # which may be a frame (a mosaic "frame_003.png" beside the frame "frame_003.jpg").
        listed = set(_sidecar_mosaics(sidecar))
        derived = re.compile(rf"{re.escape(sidecar.stem)}(\.part[1-9][0-9]*)?({re.escape(PREVIEW_SUFFIX)}|{re.escape(COG_SUFFIX)}|"
                             rf"{re.escape(LIVE_PICTURE_SUFFIX)})|{re.escape(sidecar.stem)}\.part[1-9][0-9]*\.[A-Za-z]+")
        for path in files:
            if path.suffix.lower() in IMAGE_SUFFIXES and (path.name in listed or derived.fullmatch(path.name)):
                found[path] = sidecar.name
    return found


def _is_sidecar(path: Path) -> bool:
    """Whether ``path`` holds a udh mosaic sidecar: a JSON object whose ``"format"`` is :data:`SIDECAR_FORMAT`,
    wherever the key stands (a sidecar re-saved with sorted keys or reformatted is still one).

    The first 200 bytes answer for a sidecar as udh writes it; any other JSON file is parsed whole."""
    try:
        with open(path, "rb") as file:
            head = file.read(200)
    except OSError:
        return False
    if re.search(rb'"format"\s*:\s*"' + re.escape(SIDECAR_FORMAT.encode()) + rb'"', head) is not None:
        return True
    if SIDECAR_FORMAT.encode() not in head and not _mentions(path, SIDECAR_FORMAT.encode()):
        return False  # most JSON files beside frames (GPS logs, cameras) end here without being parsed
    try:
        data = json.loads(read_side_file(path))
    except (UdhError, ValueError, RecursionError):
        return False
    return isinstance(data, dict) and data.get("format") == SIDECAR_FORMAT


def _mentions(path: Path, text: bytes, limit: int = SIDE_FILE_LIMIT) -> bool:
    """Whether the first ``limit`` bytes of ``path`` contain ``text`` (read in chunks, never whole)."""
    try:
        with open(path, "rb") as file:
            carried = b""
            for _ in range(limit // (1 << 20) + 1):
                chunk = file.read(1 << 20)
                if not chunk:
                    return False
                if text in carried + chunk:
                    return True
                carried = chunk[-len(text):]
    except OSError:
        return False
    return False


def remove_stale_files(files: RunFiles, published: list[Path], mosaics: list[Path], reporter: Reporter) -> None:
    """Remove part files of this output name (an earlier run with more parts) that this run did not write
    (``published``), and the georeference files (world, .prj, GeoTIFF, .aux.xml) beside ``mosaics`` that this run did not
    write again: an old world file beside a new mosaic would put it on the map in the wrong place. Only files an
    earlier run to this output recorded as its own, unchanged since, are removed."""
    produced = {f.resolve() for f in published}
    stale = stale_part_files(files.output, published)
    for mosaic in mosaics:
        stale += [f for f in MosaicFiles(mosaic).georeference if f.is_file() and f.resolve() not in produced and f not in stale
                  and written_by_udh(f, files.output.name)]
    for path in stale:
        try:
            path.unlink()
        except OSError as exc:
            reporter.warn(f"{path.name} is left from an earlier run and could not be removed ({exc.strerror})")
    if stale:
        reporter.info(f"removed {len(stale)} part files of an earlier run: {', '.join(p.name for p in stale)}")
