"""A rich progress bar for training: step, loss, validation corner error, speed and ETA."""

from __future__ import annotations

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class TrainProgress:
    """Context manager; ``update(step, loss, val_median)`` after every step. Silent when disabled."""

    def __init__(self, total: int, start: int, enabled: bool = True):
        self.enabled = enabled
        self.progress = Progress(
            TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(), TextColumn("loss {task.fields[loss]}"),
            TextColumn("val MACE {task.fields[val]}"), TimeElapsedColumn(), TimeRemainingColumn(), disable=not enabled,
        )
        self.task = self.progress.add_task("train", total=total, completed=start, loss="-", val="-")

    def __enter__(self) -> "TrainProgress":
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def update(self, step: int, loss: float, val_median: float | None) -> None:
        fields = {"loss": f"{loss:.4g}"}
        if val_median is not None:
            fields["val"] = f"{val_median:.2f} px"
        self.progress.update(self.task, completed=step, **fields)
