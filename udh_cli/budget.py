"""How much memory one piece of work may take: the memory this machine has free, or ``UDH_MEMORY_BUDGET``.

Work whose size the user chooses (a simulated flight's frames, a benchmark's pairs, estimation at full
resolution) is sized from its options before it starts; :func:`check_memory` refuses what does not fit with a
one-line error that names the option to lower, instead of a MemoryError or the kernel's OOM killer later.
"""

from __future__ import annotations

import os

from udh_cli.errors import UdhError

MEMORY_BUDGET_ENV = "UDH_MEMORY_BUDGET"
_FALLBACK_BUDGET = 4 * 2**30  # where the free memory cannot be read


def memory_budget() -> int:
    """Bytes of memory one piece of work may take: ``UDH_MEMORY_BUDGET`` (bytes, e.g. ``8e9``) if set, else the
    memory available now (Linux's MemAvailable, else free physical pages, else 4 GiB)."""
    value = os.environ.get(MEMORY_BUDGET_ENV)
    if value is not None:
        try:
            budget = int(float(value))
        except (ValueError, OverflowError):
            raise UdhError(f"{MEMORY_BUDGET_ENV}={value!r}: give a number of bytes, e.g. 8e9") from None
        if budget <= 0:
            raise UdhError(f"{MEMORY_BUDGET_ENV}={value!r}: give a positive number of bytes")
        return budget
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return _FALLBACK_BUDGET


def gib(size: float) -> str:
    """Bytes as GiB for a message: ``"3.2 GiB"``."""
    return f"{size / 2**30:.1f} GiB"


def check_memory(needed: float, what: str, advice: str) -> None:
    """Raise :class:`UdhError` when ``needed`` bytes exceed :func:`memory_budget`.

    ``what`` says which work (e.g. ``"--width 8000 --height 6000 with 18 frames"``), ``advice`` which option to
    lower; the message also names ``UDH_MEMORY_BUDGET`` for a machine whose free memory is read wrongly.
    """
    budget = memory_budget()
    if needed > budget:
        raise UdhError(f"{what} needs about {gib(needed)} of memory, more than the {gib(budget)} free here; {advice} "
                       f"(or set {MEMORY_BUDGET_ENV} in bytes if more is free)")
