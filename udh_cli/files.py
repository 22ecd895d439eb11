"""What udh may read and replace: side files bounded before they are read, outputs replaced only when udh wrote them.

Reading: :func:`read_side_file` opens only regular files (a FIFO without a writer would block for ever, a device
never ends) and refuses one over its size limit before reading a byte.

Writing: a folder that udh writes into keeps a manifest, ``.udh-written.json``, of each file it wrote there with
its size and SHA-256 digest. :func:`check_replaceable` lets a run replace an existing file only when the manifest
proves udh wrote it and nobody changed it since; any other file needs ``--overwrite``. :func:`write_output`
checks, writes atomically and records in one step, under a lock on the folder, so two runs never interleave.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import stat
from pathlib import Path
from typing import Iterator

from udh_cli.errors import UdhError
from udh_cli.images import atomic_write_bytes, create_new, new_file_mode, temporary_name

MANIFEST_NAME = ".udh-written.json"
MANIFEST_FORMAT = "udh-written/1"
MAX_MANIFEST_BYTES = 16 * 2**20  # thousands of entries; a larger one is not ours
SIDE_FILE_LIMIT = 64 * 2**20  # JSON and text side files: far above any real one, far below memory trouble


def read_side_file(path: str | os.PathLike, option: str = "", limit: int = SIDE_FILE_LIMIT) -> bytes:
    """The bytes of the side file ``path`` given to ``option`` (e.g. ``--camera``; "" for a file named elsewhere),
    read only when it is a regular file of at most ``limit`` bytes. Raises :class:`UdhError` naming both otherwise."""
    path = Path(path)
    where = f"{option} {path}" if option else str(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer; a regular file ignores the flag.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise UdhError(f"{where}: no such file; check the path") from None
    except OSError as exc:
        raise UdhError(f"{where}: cannot read it ({exc.strerror or exc}); check the path and its permissions") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise UdhError(f"{where}: is a folder; give the file itself")
        if not stat.S_ISREG(info.st_mode):
            raise UdhError(f"{where}: not a regular file (a pipe, device or socket); save it to a file and give that")
        if info.st_size > limit:
            raise UdhError(f"{where}: {_amount(info.st_size)}, more than the {_amount(limit)} such a file can be; "
                           f"check that it is the right file")
        chunks, total = [], 0
        while True:  # the size may grow while we read: stop at the limit all the same
            chunk = os.read(fd, min(1 << 20, limit + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                raise UdhError(f"{where}: grew past {_amount(limit)} while being read; check that it is the right file")
        return b"".join(chunks)
    except OSError as exc:
        raise UdhError(f"{where}: cannot read it ({exc.strerror or exc}); check the file") from None
    finally:
        os.close(fd)


def _amount(size: int) -> str:
    """A byte count as people read it: ``"512 bytes"``, ``"3.2 MiB"``."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if size >= scale:
            return f"{size / scale:.1f} {unit}"
    return f"{size} bytes"


def read_side_text(path: str | os.PathLike, option: str = "", limit: int = SIDE_FILE_LIMIT) -> str:
    """:func:`read_side_file` as text: UTF-8, a leading byte-order mark dropped, undecodable bytes refused."""
    data = read_side_file(path, option, limit)
    where = f"{option} {path}" if option else str(path)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UdhError(f"{where}: not UTF-8 text (byte {exc.start}); give the text file itself") from None


def file_digest(path: Path) -> tuple[int, str]:
    """``(size in bytes, SHA-256 hex digest)`` of the regular file ``path``."""
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
            size += len(chunk)
    return size, digest.hexdigest()


def _manifest(folder: Path) -> dict[str, dict]:
    """The folder's manifest entries, ``{file name: {"size": bytes, "sha256": hex}}``; empty when missing or not ours."""
    path = folder / MANIFEST_NAME
    try:
        if not path.is_file() or path.stat().st_size > MAX_MANIFEST_BYTES:
            return {}
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return {}
    if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT or not isinstance(data.get("files"), dict):
        return {}
    return {name: entry for name, entry in data["files"].items() if isinstance(entry, dict)}


def written_by_udh(path: str | os.PathLike, run: str | None = None) -> bool:
    """Whether ``path`` is a file the manifest of its folder lists with its present size and digest; with ``run``,
    also recorded as written by that run (see :func:`record_written`)."""
    path = Path(path)
    entry = _manifest(path.parent).get(path.name)
    try:
        if entry is None or (run is not None and entry.get("run") != run) or not path.is_file() or path.is_symlink() or path.stat().st_size != entry.get("size"):
            return False
        return file_digest(path) == (entry.get("size"), entry.get("sha256"))
    except OSError:
        return False


def check_replaceable(path: str | os.PathLike, overwrite: bool = False, option: str = "--overwrite") -> Path:
    """Raise :class:`UdhError` unless writing ``path`` loses nothing: it does not exist, udh wrote it (see
    :func:`written_by_udh`), or ``overwrite`` was asked for. ``option`` names the flag that allows it."""
    path = Path(path)
    try:
        exists = path.exists() or path.is_symlink()
    except OSError:
        return path  # an unusable name: the write itself reports it
    if exists and not overwrite:
        if path.is_dir():
            raise UdhError(f"{path}: is a folder; give a file name")
        if not written_by_udh(path):
            raise UdhError(f"{path}: exists and udh did not write it (or it changed since); add {option} to replace it, "
                           f"or choose another name")
    return path


@contextlib.contextmanager
def folder_locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on ``folder`` itself (no lock file is left); a no-op where ``fcntl`` is missing."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing drops the lock


def record_written(*paths: str | os.PathLike, run: str | None = None) -> None:
    """Add each file's size and digest to the manifest of its folder (call it with the lock held, or alone);
    ``run`` names the run that wrote them (a mosaic's output file name), so that a run removes only its own."""
    by_folder: dict[Path, list[Path]] = {}
    for path in map(Path, paths):
        by_folder.setdefault(path.parent, []).append(path)
    for folder, files in by_folder.items():
        entries = _manifest(folder)
        for path in files:
            size, digest = file_digest(path)
            entries[path.name] = {"size": size, "sha256": digest, **({"run": run} if run is not None else {})}
        entries = {name: entry for name, entry in entries.items() if (folder / name).is_file()}  # forget removed files
        atomic_write_bytes(folder / MANIFEST_NAME, (json.dumps({"format": MANIFEST_FORMAT, "files": entries}, indent=1, sort_keys=True)
                                                    + "\n").encode())


def write_file_set(folder: str | os.PathLike, files: dict[str, bytes], overwrite: bool = False) -> list[Path]:
    """Write a set of files into ``folder`` all or none: each is staged beside its name first, and only when
    every one is staged are they renamed into place (a full disk leaves the earlier set, not half of each).
    Each must pass :func:`check_replaceable`; they are recorded as udh's. Returns their paths, in order."""
    folder = Path(folder)
    staged: dict[Path, Path] = {}
    with folder_locked(folder):
        targets = [check_replaceable(folder / name, overwrite) for name in files]
        try:
            for target, data in zip(targets, files.values()):
                staged[target] = temporary = temporary_name(target)  # named before it exists: an interrupt can remove it
                with os.fdopen(create_new(temporary), "wb") as handle:
                    handle.write(data)
                    handle.flush()
                    os.fsync(handle.fileno())
                os.chmod(temporary, new_file_mode(target))
        except BaseException as exc:
            for temporary in staged.values():
                temporary.unlink(missing_ok=True)
            if not isinstance(exc, OSError):
                raise
            raise UdhError(f"{folder}: writing the results failed ({exc.strerror or exc}); nothing was replaced: check the "
                           f"free space and permissions") from None
        for target, temporary in staged.items():
            os.replace(temporary, target)
        record_written(*targets)
    return targets


@contextlib.contextmanager
def staged_folder(folder: str | os.PathLike) -> Iterator[Path]:
    """A new folder written all or none: yields a hidden staging folder beside ``folder`` to write into, renamed
    to ``folder`` (which must be new or empty) when the block ends, and removed with its contents when it fails.
    The staging folder names its process, so that the next run removes one a killed run left."""
    from udh_cli.processes import remove_dead_runs_folders, run_temp_folder

    folder = Path(folder)
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
        remove_dead_runs_folders(folder.parent, f".{folder.name}.")  # what a killed run left of its own staging
        staging = run_temp_folder(folder.parent, f".{folder.name}.", ".staged")
    except OSError as exc:
        raise UdhError(f"{folder}: cannot create a folder beside it ({exc.strerror or exc}); choose another place") from None
    try:
        yield staging
        umask = os.umask(0o022)
        os.umask(umask)
        os.chmod(staging, 0o777 & ~umask)  # mkdtemp's folder is owner-only
        os.replace(staging, folder)
    except BaseException as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, OSError):  # e.g. something was written into the folder meanwhile
            raise UdhError(f"{folder}: cannot put the finished folder in place ({exc.strerror or exc}); nothing was written") from None
        raise


def write_output(path: str | os.PathLike, data: bytes, overwrite: bool = False, option: str = "--overwrite") -> Path:
    """Write ``data`` to ``path`` atomically, if :func:`check_replaceable` allows it, and record it as udh's."""
    path = Path(path)
    folder = path.parent
    if not folder.is_dir():
        return atomic_write_bytes(path, data)  # the one-line error for a missing folder is atomic_write_bytes'
    with folder_locked(folder):
        check_replaceable(path, overwrite, option)
        atomic_write_bytes(path, data)
        record_written(path)
    return path
