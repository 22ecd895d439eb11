"""Progress, warnings and stage timings of a mosaic run, shown with rich or kept quiet (for tests and APIs)."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Callable, Iterator

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn


class Reporter:
    """Collects warnings and per-stage wall times; draws a rich progress bar per stage when ``progress``.

    ``quiet`` prints nothing at all (the library's default): warnings are still collected for the sidecar.

    Attributes:
        warnings: every warning issued, in order (they also go to the sidecar).
        timings_s: stage name -> wall time in seconds, in the order the stages ran.
    """

    def __init__(self, console: Console | None = None, quiet: bool = False, progress: bool = True) -> None:
        self.console = console or Console(stderr=True)
        self.quiet = quiet
        self.progress = progress and not quiet
        self.warnings: list[str] = []
        self.timings_s: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str, total: int | None = None, label: str | None = None) -> Iterator[Callable[[int], None]]:
        """Time a stage and show its progress; yields ``advance(n=1)``. Repeated names add up (e.g. the
        compositing of every part); ``label`` names the progress bar when it should say more than ``name``."""
        start = time.perf_counter()
        if not self.progress:
            yield lambda n=1: None
        else:
            columns = (TextColumn(f"{label or name:<22}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            with Progress(*columns, console=self.console, transient=False) as progress:
                task = progress.add_task(name, total=total)
                yield lambda n=1: progress.advance(task, n)
                progress.update(task, completed=total if total is not None else 1, total=total or 1)
        self.timings_s[name] = self.timings_s.get(name, 0.0) + time.perf_counter() - start

    def warn(self, message: str) -> None:
        """Record a warning and print it (one line)."""
        self.warnings.append(message)
        if not self.quiet:
            # Escaped: a message quotes file names and commands ('.[geo]', 'notes[draft].txt') that rich would read as markup.
            self.console.print(f"[yellow]warning:[/yellow] {escape(message)}", highlight=False, soft_wrap=True)

    def info(self, message: str) -> None:
        if not self.quiet:
            self.console.print(escape(message), highlight=False, soft_wrap=True)
