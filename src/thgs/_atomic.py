"""Atomic output: write into a hidden sibling of the target, then rename it into place.

One writer for files (:func:`atomic_output`) and one for folders (:func:`atomic_folder`); a
reader never sees a half-written result, and a failure (an exception, Ctrl-C) leaves the target
as it was and removes the temporary. The temporaries are created with the default modes
(0o666 for files, 0o777 for folders), which the kernel reduces by the process's umask exactly
as for a file or folder created plainly; the umask is never read, so no ``os.umask`` call
changes it process-wide under a concurrent thread (the viewer writes exports from its own).
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, TypeVar

from thgs.errors import InputError

__all__ = ["atomic_folder", "atomic_output", "staging_folder"]

T = TypeVar("T")

_ATTEMPTS = 100
"""Random temporary names tried before giving up (a collision needs 2⁴⁸ bad luck)."""


def _sibling(target: Path, create: Callable[[Path], T]) -> tuple[Path, T]:
    """A new hidden ``.<name>.<random>.tmp`` beside ``target``, made by ``create``."""
    for _ in range(_ATTEMPTS):
        candidate = target.parent / f".{target.name}.{secrets.token_hex(6)}.tmp"
        try:
            return candidate, create(candidate)
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {target}")


def _new_file(path: Path) -> int:
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success flush, fsync and rename it to ``path``.

    If the body raises, the temporary file is removed and ``path`` is left as it was (absent, or
    its previous content). The parent folders are created.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp, fd = _sibling(target, _new_file)
    try:
        encoding = None if "b" in mode else "utf-8"
        with os.fdopen(fd, mode, encoding=encoding) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def staging_folder(beside: str | os.PathLike[str]) -> Iterator[Path]:
    """A new empty hidden folder next to ``beside``, removed with its content afterwards,
    whatever happens (for writers that move its files elsewhere one by one)."""
    target = Path(beside)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp, _ = _sibling(target, lambda candidate: os.mkdir(candidate, 0o777))
    try:
        yield tmp
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike[str], *, replace: bool = False) -> Iterator[Path]:
    """Yield a new empty folder next to ``path`` to fill; on success rename it to ``path``.

    ``path`` must be absent or an empty folder, unless ``replace``: then an existing folder is
    first renamed aside, the new one renamed into place, and only then the old one deleted (it
    is restored if the new one cannot be moved in). If the body raises, the new folder is
    deleted and ``path`` is left as it was.

    Raises:
        InputError: the new folder could not be moved into place (e.g. someone else created a
            non-empty ``path`` meanwhile); the new folder is deleted.
    """
    target = Path(path)
    with staging_folder(target) as tmp:
        yield tmp
        if replace and target.is_dir():
            old, _ = _sibling(target, lambda candidate: os.replace(target, candidate))
            try:
                os.replace(tmp, target)
            except OSError as error:
                os.replace(old, target)
                raise InputError(
                    target, f"could not move the new folder into place ({error})"
                ) from error
            shutil.rmtree(old, ignore_errors=True)
            return
        try:
            os.replace(tmp, target)
        except OSError as error:
            raise InputError(
                target, f"could not move the new folder into place ({error})"
            ) from error
