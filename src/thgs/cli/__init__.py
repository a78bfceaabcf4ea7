"""The ``thgs`` command line: a thin layer over the library, and the only code that prints."""

from __future__ import annotations

import sys
import typing
from collections.abc import Callable, Sequence

import tyro

from thgs.cli._console import error
from thgs.cli.bench import bench
from thgs.cli.build import build, demo
from thgs.cli.evaluate import evaluate, evaluate_mean
from thgs.cli.preprocess import preprocess
from thgs.cli.query import catalog, export, pick, query
from thgs.cli.scene import info, synth
from thgs.cli.suite import bare_ray_flag, suite
from thgs.cli.view import view
from thgs.errors import ThgsError

__all__ = [
    "bench",
    "build",
    "catalog",
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


COMMANDS: dict[str, Callable[..., None]] = {
    "demo": demo,
    "preprocess": preprocess,
    "build": build,
    "query": query,
    "pick": pick,
    "export": export,
    "catalog": catalog,
    "view": view,
    "eval": evaluate,
    "eval-mean": evaluate_mean,
    "info": info,
    "bench": bench,
    "suite": suite,
    "synth": synth,
}
"""Each ``thgs`` subcommand and the function that runs it."""


def list_options(command: Callable[..., None]) -> set[str]:
    """The options of ``command`` that take any number of values (``tuple[X, ...]``), as
    ``--name``."""
    names = set()
    for name, hint in typing.get_type_hints(command, include_extras=True).items():
        if typing.get_origin(hint) is typing.Annotated:
            hint = typing.get_args(hint)[0]
        arguments = typing.get_args(hint)
        if typing.get_origin(hint) is tuple and arguments[-1:] == (Ellipsis,):
            names.add("--" + name.replace("_", "-"))
    return names


def _starts_option(arg: str) -> bool:
    return arg.startswith("--") or arg in ("-o", "-h")


def joined_list_options(argv: Sequence[str]) -> list[str]:
    """Arguments with every repeated list option given once, all its values in order:
    ``--set a=1 --set b=2`` becomes ``--set a=1 b=2`` (the command line would otherwise keep
    only the last ``--set``). A list option's values are the arguments after it up to the
    next one that starts with ``--`` or is ``-o`` or ``-h``; ``--set=a=1`` is one value."""
    args = list(argv)
    command = COMMANDS.get(args[0]) if args else None
    if command is None:
        return args
    options = list_options(command)
    values: dict[str, list[str]] = {}
    kept: list[str] = []
    i = 0
    while i < len(args):
        name, equals, value = args[i].partition("=")
        if name not in options:
            kept.append(args[i])
            i += 1
            continue
        found = [value] if equals else []
        i += 1
        while not equals and i < len(args) and not _starts_option(args[i]):
            found.append(args[i])
            i += 1
        if name not in values:
            values[name] = []
            kept.append(name)
        values[name] += found
    joined: list[str] = []
    for arg in kept:
        joined.append(arg)
        if arg in values:
            joined += values.pop(arg)
    return joined


def entrypoint(argv: list[str] | None = None) -> None:
    """Run the CLI. Bad input ends with one `error:` line on stderr and exit status 2, an
    operating-system error (a full disk, a name too long) with one such line and status 1, Ctrl-C
    with `error: interrupted` and status 130; outputs are only ever whole or absent."""
    args = joined_list_options(bare_ray_flag(sys.argv[1:] if argv is None else argv))
    try:
        tyro.extras.subcommand_cli_from_dict(
            COMMANDS,
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
