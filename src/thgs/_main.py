"""The ``thgs`` command's entry point: imports the CLI (torch, numba …, seconds) where a Ctrl-C
is answered as an interruption, not a traceback."""

from __future__ import annotations

import sys


def main() -> None:
    """Run ``thgs`` with ``sys.argv``."""
    try:
        from thgs.cli import entrypoint
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        sys.exit(130)
    entrypoint()
