"""The ``thgs`` command line: a thin layer over the library, and the only code that prints."""

from __future__ import annotations

import sys

import tyro

from thgs.cli._console import error
from thgs.cli.bench import bench
from thgs.cli.build import build, demo
from thgs.cli.evaluate import evaluate, evaluate_mean
from thgs.cli.preprocess import preprocess
from thgs.cli.query import export, pick, query
from thgs.cli.scene import info, synth
from thgs.cli.suite import bare_ray_flag, suite
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
    "suite",
    "synth",
    "view",
]


def entrypoint(argv: list[str] | None = None) -> None:
    """Run the CLI. Bad input ends with one `error:` line on stderr and exit status 2, an
    operating-system error (a full disk, a name too long) with one such line and status 1, Ctrl-C
    with `error: interrupted` and status 130; outputs are only ever whole or absent."""
    args = bare_ray_flag(sys.argv[1:] if argv is None else argv)
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
                "suite": suite,
                "synth": synth,
            },
            prog="thgs",
            description="thgs: open-vocabulary, hierarchical understanding of Gaussian scenes.",
            args=args,
            config=(tyro.conf.DisallowNone,),
        )
    except ThgsError as exc:
        error(str(exc))
        sys.exit(2)
    except MemoryError as exc:
        what = f" ({exc})" if str(exc) else ""
        error(
            f"out of memory{what}: a setting asks for more than this machine holds (a --set or "
            "--config value far from its default?), or the scene is too large for it"
        )
        sys.exit(2)
    except KeyboardInterrupt:
        # every output is written to a temporary name and renamed when whole (thgs._atomic),
        # so an interrupted command leaves nothing half-written behind
        error("interrupted")
        sys.exit(130)
    except OSError as exc:  # disk full, a name too long, no permission, …
        where = f"{exc.filename}: " if exc.filename else ""
        error(f"{where}{exc.strerror or exc}")
        sys.exit(1)
