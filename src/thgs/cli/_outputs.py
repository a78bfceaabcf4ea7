"""Output paths checked before a command does any work (issue 26: a build that fails only after
computing everything because ``-o`` names a folder is the worst time to find out)."""

from __future__ import annotations

import os
from pathlib import Path

from thgs.errors import InputError


def check_output_file(path: Path, flag: str = "-o") -> Path:
    """Refuse ``path`` as a file to write: an existing folder, a parent that is a file or not
    writable, a name longer than the file system allows. Returns ``path``."""
    existing = _check_place(path, flag)
    if existing == Path(os.path.abspath(path)) and existing.is_dir():
        raise InputError(path, f"is a folder; {flag} names the file to write")
    return path


def check_output_folder(path: Path, flag: str = "-o") -> Path:
    """Refuse ``path`` as a folder to write into: an existing file, a parent that is a file or
    not writable, a name longer than the file system allows. Returns ``path``."""
    existing = _check_place(path, flag)
    if existing == Path(os.path.abspath(path)) and not existing.is_dir():
        raise InputError(path, f"is a file; {flag} names a folder to write into")
    return path


def _check_place(path: Path, flag: str) -> Path:
    """The deepest existing folder or file on the way to ``path`` (``path`` itself if it
    exists), after checking every name's length and that what must be created can be."""
    absolute = Path(os.path.abspath(path))
    existing = Path(absolute.anchor)
    parts = absolute.parts[1:]
    for depth, part in enumerate(parts):
        limit = os.pathconf(existing if existing.is_dir() else existing.parent, "PC_NAME_MAX")
        if len(os.fsencode(part)) > limit:
            raise InputError(path, f"has a name longer than {limit} bytes ({flag})")
        following = existing / part
        if not following.exists():
            break
        if not following.is_dir() and depth < len(parts) - 1:
            raise InputError(following, f"is a file, so {flag} {path} cannot be created under it")
        existing = following
    folder = existing if existing.is_dir() else existing.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(folder, f"is not writable ({flag} {path})")
    return existing
