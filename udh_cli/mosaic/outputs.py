"""The files of a mosaic run: their names, and writing them so that they appear together or not at all.

A split run writes ``NAME.part1.png``, ``NAME.part2.png``... and a preview of each. Each is first written
under a hidden temporary name (:class:`StagedFiles`); only when every part has been written are they
renamed to their own names, and the sidecar is written after them. A run that fails in its third part so
leaves the outputs of the previous run as they were, not a mix of both. Part files of this output name
that the new run does not produce (an earlier run had more parts) are removed (:func:`stale_part_files`).
"""

from __future__ import annotations

import os
import re
import secrets
from pathlib import Path

from udh_cli.errors import UdhError

PREVIEW_SUFFIX = ".preview.jpg"


def output_paths(output: Path, n_parts: int) -> list[Path]:
    """The mosaic file of each part: ``output`` itself for one part, ``stem.partK.suffix`` for several."""
    if n_parts == 1:
        return [output]
    return [output.with_name(f"{output.stem}.part{k}{output.suffix}") for k in range(1, n_parts + 1)]


def sidecar_path(output: Path) -> Path:
    return output.with_suffix(".json")


def preview_path(mosaic_file: Path) -> Path:
    return mosaic_file.with_name(f"{mosaic_file.stem}{PREVIEW_SUFFIX}")


def stale_part_files(output: Path, produced: list[Path]) -> list[Path]:
    """Files named as parts of ``output`` (``stem.partK.suffix`` and ``stem.partK.preview.jpg``, K >= 1)
    that are not in ``produced``: what an earlier run with more parts (or with previews) left behind.

    Only those two exact patterns match, with ``output``'s own stem and suffix; nothing else is returned.
    """
    part = rf"{re.escape(output.stem)}\.part[1-9][0-9]*"
    pattern = re.compile(rf"{part}{re.escape(output.suffix)}|{part}{re.escape(PREVIEW_SUFFIX)}")
    keep = {p.resolve() for p in produced}
    try:
        candidates = sorted(output.parent.iterdir())
    except OSError:
        return []
    return [p for p in candidates if pattern.fullmatch(p.name) and p.is_file() and not p.is_symlink() and p.resolve() not in keep]


class StagedFiles:
    """Files written under hidden temporary names in their own folder, then renamed together.

    ``path_for(final)`` gives the name to write to; :meth:`publish` renames every staged file to its
    final name (keeping the permissions of the file it replaces); :meth:`discard` deletes what is left.
    """

    def __init__(self) -> None:
        self.staged: list[tuple[Path, Path]] = []  # (temporary, final)

    def path_for(self, final: Path) -> Path:
        # Hidden (frames folders skip dot files) and with the final suffix, which picks the image encoder.
        temporary = final.with_name(f".{final.stem}.{secrets.token_hex(4)}.staged{final.suffix}")
        self.staged.append((temporary, final))
        return temporary

    def publish(self) -> None:
        """Rename every staged file to its final name. Raises :class:`UdhError` if a rename fails."""
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
