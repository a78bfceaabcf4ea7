"""Atomic output: write into a hidden sibling of the target, then rename it into place.

One writer for files (:func:`atomic_output`), one for a set of files that belong together
(:func:`atomic_files`) and one for folders (:func:`atomic_folder`); a reader never sees a
half-written result, and a failure (an exception, Ctrl-C) leaves the target
as it was and removes the temporary. The temporaries are created with the default modes
(0o666 for files, 0o777 for folders), which the kernel reduces by the process's umask exactly
as for a file or folder created plainly; the umask is never read, so no ``os.umask`` call
changes it process-wide under a concurrent thread (the viewer writes exports from its own).

A temporary is named ``.<name>.<host>-<pid>-<random>.tmp``: ``<host>`` is a short hash of the
machine's name and ``<pid>`` the writing process. A process killed outright (kill -9, a power
cut) cannot remove its temporaries, so every writer first removes the stale temporaries of its
own target: those of this machine whose process no longer runs (``os.kill(pid, 0)``), or whose
process is this one but which it no longer has open (a recycled pid, as in a container). Those
of a process still running, or of another machine sharing the folder, are left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
import secrets
import shutil
import socket
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, TypeVar

from thgs.errors import InputError

__all__ = [
    "atomic_files",
    "atomic_folder",
    "atomic_output",
    "remove_stale_temporaries",
    "staging_folder",
]

T = TypeVar("T")

logger = logging.getLogger(__name__)

_ATTEMPTS = 100
"""Random temporary names tried before giving up (a collision needs 2⁴⁸ bad luck)."""

_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
"""This machine in temporary names: a process id means something only on its own machine."""

_OWNER = re.compile(r"(?P<host>[0-9a-f]{8})-(?P<pid>[0-9]+)-[0-9a-f]{12}")
"""The middle of a temporary's name, ``.<name>.<host>-<pid>-<random>.tmp``."""

_OPEN: set[str] = set()
"""This process's temporaries that are still being written (by any of its threads), as
absolute paths."""


def _key(path: Path) -> str:
    return os.path.abspath(path)


def _running(pid: int) -> bool:
    """Whether a process ``pid`` exists on this machine (someone else's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(target: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporaries of ``target`` left by writers that were killed outright.

    A temporary is stale when it was made on this machine by a process that no longer runs,
    or by this process but is not one it is writing now (its pid was recycled). Temporaries
    of running processes and of other machines are kept: they may be writing right now.

    Returns:
        The removed paths (files or folders), each logged as a warning.
    """
    target = Path(target)
    prefix, removed = f".{target.name}.", []
    try:
        entries = list(os.scandir(target.parent))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for entry in entries:
        if not (entry.name.startswith(prefix) and entry.name.endswith(".tmp")):
            continue
        owner = _OWNER.fullmatch(entry.name[len(prefix) : -len(".tmp")])
        if owner is None or owner["host"] != _HOST:
            continue
        pid, path = int(owner["pid"]), Path(entry.path)
        in_use = _key(path) in _OPEN if pid == os.getpid() else _running(pid)
        if in_use:
            continue
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        logger.warning("removed %s, left by an interrupted writer (process %d)", path, pid)
        removed.append(path)
    return removed


@contextlib.contextmanager
def _sibling(target: Path, create: Callable[[Path], T]) -> Iterator[tuple[Path, T]]:
    """A new hidden temporary beside ``target``, made by ``create`` after the stale ones of
    ``target`` are removed; known to this process as open until the block ends."""
    remove_stale_temporaries(target)
    owner = f"{_HOST}-{os.getpid()}"
    for _ in range(_ATTEMPTS):
        candidate = target.parent / f".{target.name}.{owner}-{secrets.token_hex(6)}.tmp"
        key = _key(candidate)
        _OPEN.add(key)
        try:
            made = create(candidate)
        except FileExistsError:
            _OPEN.discard(key)
            continue
        except BaseException:
            _OPEN.discard(key)
            raise
        try:
            yield candidate, made
        finally:
            _OPEN.discard(key)
        return
    raise FileExistsError(f"no free temporary name beside {target}")


def _new_file(path: Path) -> int:
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)


def _named_after(error: OSError, target: Path, staging: Path) -> OSError:
    """``error`` naming ``target`` when it names no file (a full disk) or ``staging`` (the hidden
    file or folder being filled) or a file inside it, given in the message; a short write
    (NumPy's ``N requested and M written``) is called the full disk it almost always is. An
    error naming another file is returned as it is."""
    inside = ""
    if error.filename:
        try:
            relative = Path(error.filename).relative_to(staging)
        except ValueError:
            return error
        if relative != Path("."):
            inside = f" (writing {relative})"
    reason = error.strerror or str(error)
    if error.errno is None and "requested and" in reason:
        reason = f"No space left on device? ({reason})"
    return OSError(error.errno, f"{reason}{inside}", str(target))


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success flush, fsync and rename it to ``path``.

    If the body raises, the temporary file is removed and ``path`` is left as it was (absent, or
    its previous content). The parent folders are created. A system error that names no file
    (a full disk) or names the temporary file (a folder in ``path``'s place) is raised again
    naming ``path``.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with _sibling(target, _new_file) as (tmp, fd):
        try:
            encoding = None if "b" in mode else "utf-8"
            try:
                with os.fdopen(fd, mode, encoding=encoding) as handle:
                    yield handle
                    handle.flush()
                    os.fsync(handle.fileno())
                os.replace(tmp, target)
            except OSError as error:
                named = _named_after(error, target, tmp)
                if named is error:
                    raise
                raise named from error
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
    with _sibling(target, lambda candidate: os.mkdir(candidate, 0o777)) as (tmp, _):
        try:
            yield tmp
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def atomic_files(paths: Sequence[str | os.PathLike[str]]) -> Iterator[tuple[Path, ...]]:
    """Yield a hidden path to write for each of ``paths`` (files of one folder); on success move
    them all into place, in order: all of them or none.

    If the body raises, nothing is moved and the folder is left as it was; if the moves are
    interrupted (Ctrl-C, a full disk), the files already moved are removed again. The files
    are staged in a hidden folder inside their folder (created if missing).

    Raises:
        ValueError: ``paths`` is empty, not all in one folder, or names a file twice.
    """
    targets = [Path(path) for path in paths]
    if not targets or len({target.parent for target in targets}) != 1:
        raise ValueError(f"atomic_files needs files of one folder, got {targets}")
    if len({target.name for target in targets}) != len(targets):
        raise ValueError(f"atomic_files got a file twice: {targets}")
    folder = targets[0].parent
    with staging_folder(folder / f"{targets[0].name}.files") as stage:
        staged = tuple(stage / target.name for target in targets)
        yield staged
        moved: list[Path] = []
        try:
            for source, target in zip(staged, targets):
                os.replace(source, target)
                moved.append(target)
        except BaseException:
            for target in moved:
                target.unlink(missing_ok=True)
            raise


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
        try:
            yield tmp
        except OSError as error:  # named after the folder, not the hidden one being filled
            named = _named_after(error, target, tmp)
            if named is error:
                raise
            raise named from error
        if replace and target.is_dir():
            with _sibling(target, lambda candidate: os.replace(target, candidate)) as (old, _):
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
