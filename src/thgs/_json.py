"""JSON and text reading with errors that name the file and the key: camera formats, labels,
guidance, training configurations."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from thgs.errors import InputError


def read_text(path: str | os.PathLike[str]) -> str:
    """A UTF-8 text file's content; raise :class:`InputError` naming the file when it is missing
    or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not readable as text ({exc})") from exc


def load_json(path: str | os.PathLike[str]) -> Any:
    """Parse a JSON file; raise :class:`InputError` naming the file for every failure."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    text = path.read_bytes()
    if not text.strip():
        raise InputError(path, "the file is empty")
    try:
        return json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError, a 5000-digit integer
        raise InputError(path, f"not valid JSON ({exc})") from exc
    except RecursionError as exc:
        raise InputError(path, "not valid JSON (nested too deeply to read)") from exc


def get_number(entry: dict[str, Any], key: str, path: Path, where: str) -> float:
    """``entry[key]`` as a finite float, or an :class:`InputError` saying where it is missing."""
    if key not in entry:
        raise InputError(path, f"{where} has no {key!r}")
    value = entry[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(path, f"{where}: {key!r} is {value!r}, not a number")
    if value != value or value in (float("inf"), float("-inf")):
        raise InputError(path, f"{where}: {key!r} is {value}")
    return float(value)


def get_matrix(
    entry: dict[str, Any], key: str, shape: tuple[int, ...], path: Path, where: str
) -> list:
    """``entry[key]`` as a nested list of finite numbers with the given shape."""
    import numpy as np

    if key not in entry:
        raise InputError(path, f"{where} has no {key!r}")
    try:
        array = np.asarray(entry[key], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"{where}: {key!r} is not a numeric array") from exc
    if array.shape != shape:
        raise InputError(
            path, f"{where}: {key!r} has shape {list(array.shape)}, expected {list(shape)}"
        )
    if not np.isfinite(array).all():
        raise InputError(path, f"{where}: {key!r} has NaN or infinite values")
    return array
