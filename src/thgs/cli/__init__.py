"""The ``thgs`` command line: a thin layer over the library, and the only code that prints."""

from __future__ import annotations

import sys

import tyro
from rich.markup import escape

from thgs.cli._console import stderr
from thgs.cli.bench import bench
from thgs.cli.build import build, demo
from thgs.cli.evaluate import evaluate, evaluate_mean
from thgs.cli.preprocess import preprocess
from thgs.cli.query import export, pick, query
from thgs.cli.scene import info, synth
from thgs.cli.view import view
from thgs.errors import ThgsError

__all__ = [
    "bench",
    "build",
    "demo",
    "entrypoint",
    "evaluate",
    "evaluate_mean",
    "export",
    "info",
    "pick",
    "preprocess",
    "query",
    "synth",
    "view",
]


def entrypoint(argv: list[str] | None = None) -> None:
    """Run the CLI; bad input ends with one line on stderr and exit status 2."""
    try:
        tyro.extras.subcommand_cli_from_dict(
            {
                "demo": demo,
                "preprocess": preprocess,
                "build": build,
                "query": query,
                "pick": pick,
                "export": export,
                "view": view,
                "eval": evaluate,
                "eval-mean": evaluate_mean,
                "info": info,
                "bench": bench,
                "synth": synth,
            },
            prog="thgs",
            description="thgs: open-vocabulary, hierarchical understanding of Gaussian scenes.",
            args=argv,
        )
    except ThgsError as exc:
        # escaped: a message such as "pip install 'thgs[viewer]'" is text, not rich markup
        stderr.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False)
        sys.exit(2)
