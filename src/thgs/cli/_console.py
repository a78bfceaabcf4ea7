"""Shared pieces of the command line: the consoles, logging set-up and progress bars."""

from __future__ import annotations

import logging
from typing import ClassVar

from rich.console import Console
from rich.markup import escape

# soft_wrap: rich never breaks a line itself (the terminal wraps it), so a path in a message stays
# one word to copy, however long, and a log reads the message on one line
stdout = Console(soft_wrap=True)
stderr = Console(stderr=True, soft_wrap=True)


def warn(message: str) -> None:
    """Print one ``warning:`` line on stderr."""
    stderr.print("[yellow]warning:[/] " + escape(message), highlight=False)


def error(message: str) -> None:
    """Print one ``error:`` line on stderr."""
    stderr.print("[bold red]error:[/] " + escape(message), highlight=False)


class _ConsoleHandler(logging.Handler):
    """Log records on stderr as the CLI's own messages: ``error:`` and ``warning:`` lines, the
    same spelling as the error that ends a command; other records (``--verbose``) as they are."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = self.format(record)
            if record.levelno >= logging.ERROR:
                error(message)
            elif record.levelno >= logging.WARNING:
                warn(message)
            else:
                stderr.print(escape(message), highlight=False)
        except Exception:  # logging must never end the command
            self.handleError(record)


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[_ConsoleHandler()],
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
