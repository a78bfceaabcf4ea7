"""The project's exception types.

Every problem with user input (a file, a folder, an array handed to a public function) raises
:class:`InputError`. Its message starts with the source (a path, or the name of the object being
checked) and then says what is wrong, so a user can act on it without reading a traceback.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

__all__ = ["InputError", "ThgsError", "settings_as_flags"]


class ThgsError(Exception):
    """Base class of every error raised by thgs on purpose."""


class InputError(ThgsError, ValueError):
    """Bad input: a file, folder or array that thgs cannot use.

    Attributes:
        source: the file or folder (or, for in-memory data, the object's name) at fault.
        problem: what is wrong with it, in words.
    """

    def __init__(self, source: str | os.PathLike[str], problem: str):
        self.source = os.fspath(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")

    def __reduce__(self):
        # pickled with its source and problem, so that it survives a trip between processes
        # (a Ray worker's error re-raised in the driver) as the same type and message
        return type(self), (self.source, self.problem)


@contextlib.contextmanager
def settings_as_flags(*names: str, **renamed: str) -> Iterator[None]:
    """Name a library setting the user gave as a command-line flag by that flag: an
    :class:`InputError` about ``QueryConfig.top`` or ``pred_iou_threshold`` (a name in ``names``)
    is raised again about ``--top`` or ``--pred-iou-threshold``; a setting in ``renamed`` is
    named by the flag it maps to (``min_relevancy="threshold"``: ``--threshold``)."""
    try:
        yield
    except InputError as error:
        setting = error.source.rpartition(".")[2]
        if setting not in names and setting not in renamed:
            raise
        flag = renamed.get(setting, setting)
        raise InputError("--" + flag.replace("_", "-"), error.problem) from error
