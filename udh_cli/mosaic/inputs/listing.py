"""Which entries of a frame folder can be frames, in what order, and where the frames may be instead."""

from __future__ import annotations

import errno
import os
import re
import stat
from pathlib import Path

from udh_cli.images import IMAGE_SUFFIXES


def natural_key(name: str) -> list:
    """Sort key that puts frame_2 before frame_10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def not_a_file(path: Path) -> str | None:
    """None when the folder entry ``path`` is a regular file or a link to one; "" for a folder; else why it cannot
    be a frame: a link to nothing, a loop of links, a pipe, device or socket (a FIFO would block its reader)."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "a loop of symbolic links; point the link at the frame itself"
        if path.is_symlink():
            try:
                target = os.readlink(path)
            except OSError:  # the link itself went away meanwhile
                return "a symbolic link to a missing file; copy the frame there or remove the link"
            return f"a symbolic link to {target}, which does not exist; copy the frame there or remove the link"
        return f"cannot be read ({exc.strerror or exc}); check its permissions"
    if stat.S_ISDIR(mode):
        return ""
    if not stat.S_ISREG(mode):
        return "not a regular file (a pipe, device or socket); copy the frame into a file"
    return None


def subfolder_hint(folder: Path) -> str:
    """' (did you mean F/images?)' when a subfolder holds images: flight folders often keep them there."""
    for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
        try:
            if any(f.suffix.lower() in IMAGE_SUFFIXES for f in sub.iterdir()):
                return f" (did you mean {sub}?)"
        except OSError:  # an unreadable subfolder is no hint; the error being reported is about the folder
            continue
    return ""
