"""Processes and temporary folders that never outlive the run that made them.

Workers: a worker process that udh starts (a pool's, live mode's refresh process) runs :func:`die_with_parent`
first, so that it ends when its parent does, SIGKILL included; otherwise it would wait on its queue for ever,
holding the terminal's output and the resource tracker with it.

Temporary folders: :func:`run_temp_folder` names a folder with the process that owns it (its pid and a tag of
this host, boot and pid namespace), so that :func:`remove_dead_runs_folders` can remove what a killed run left, and never a live run's.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import signal
import socket
import tempfile
import threading
from pathlib import Path

# Seconds between a worker's looks at its parent: a killed run's workers are gone within this.
PARENT_POLL_S = 0.5


def die_with_parent(parent_pid: int) -> None:
    """Pool initializer: end this process when ``parent_pid`` is no longer its parent (it died, even by SIGKILL),
    and leave Ctrl-C to the parent, which stops its workers itself (else each prints its own traceback).

    Why a watching thread and not Linux's ``PR_SET_PDEATHSIG``: that signal follows the parent *thread* that
    started the worker, and a pool may be started from a thread that ends long before the run does."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == parent_pid:
            threading.Event().wait(PARENT_POLL_S)
        os._exit(1)  # no clean-up to run: the parent that would read the results is gone

    threading.Thread(target=watch, name="udh-die-with-parent", daemon=True).start()


def _host_tag() -> str:
    """Eight hex digits naming where a pid means one process: the host name, its boot and its pid namespace (where
    the system says them, else the host name alone). Why all three: a folder on a shared disk is judged only where
    its pid means the same; two containers sharing a host name (Docker ``--network host``) do not share pids."""
    identity = [socket.gethostname(), _boot_id(), _pid_namespace()]
    return hashlib.sha256("\n".join(identity).encode(errors="replace")).hexdigest()[:8]


def _boot_id() -> str:
    """Linux's id of this boot; "" where there is none."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def _pid_namespace() -> str:
    """This process's pid namespace on Linux (``pid:[4026531836]``); "" where there is none."""
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:  # no /proc: not Linux
        return ""


def run_temp_folder(parent: Path, prefix: str, suffix: str = "") -> Path:
    """A new temporary folder in ``parent`` named ``PREFIX<pid>-<host tag>-<random>SUFFIX``: owned by this process."""
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-{_host_tag()}-", suffix=suffix, dir=parent))


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (one we may not signal, or cannot ask about, counts as
    alive: its folder is kept)."""
    if pid <= 0 or os.name == "nt":  # 0 and below name process groups; Windows' os.kill would end the process
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True
    return True


def remove_dead_runs_folders(parent: Path, prefix: str) -> list[Path]:
    """Remove the folders of :func:`run_temp_folder` in ``parent`` whose owner died on this host; returns them.
    A folder of a live process, of another host, or named otherwise is kept."""
    pattern = re.compile(re.escape(prefix) + r"(\d+)-([0-9a-f]{8})-")
    removed = []
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return removed
    here = _host_tag()
    for entry in entries:
        match = pattern.match(entry.name)
        if match is None or match.group(2) != here or not entry.is_dir(follow_symlinks=False):
            continue
        if not _alive(int(match.group(1))):
            shutil.rmtree(entry.path, ignore_errors=True)
            removed.append(Path(entry.path))
    return removed
