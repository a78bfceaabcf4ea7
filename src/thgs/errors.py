"""The project's exception types.

Every problem with user input (a file, a folder, an array handed to a public function) raises
:class:`InputError`. Its message starts with the source (a path, or the name of the object being
checked) and then says what is wrong, so a user can act on it without reading a traceback.
"""

from __future__ import annotations

import os

__all__ = ["InputError", "ThgsError"]


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
