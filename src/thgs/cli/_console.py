"""Shared pieces of the command line: the consoles, logging set-up and progress bars."""

from __future__ import annotations

import logging
from typing import ClassVar

from rich.console import Console
from rich.logging import RichHandler

stdout = Console()
stderr = Console(stderr=True)


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=stderr, show_path=False, show_time=False)],
        force=True,
    )


class StageBars:
    """A rich progress display for ``progress(stage, done, total)`` callbacks: one bar per stage,
    each finished bar showing its time."""

    _LABELS: ClassVar[dict[str, str]] = {
        "generate": "generating the synthetic scene",
        "lift": "lifting masks onto Gaussians",
        "partition": "KNN graph, reweighting, cut pursuit",
        "merge": "merging levels 1–3",
        "features": "region features",
    }

    def __init__(self, bar) -> None:
        self._bar = bar
        self._tasks: dict[str, int] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self._tasks:
            label = self._LABELS.get(stage, stage)
            self._tasks[stage] = self._bar.add_task(label, total=total)
        self._bar.update(self._tasks[stage], completed=done, total=total)


def stage_progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stderr,
    )
