"""``torch.load`` of checkpoints with tensors and plain containers only, and errors that say so."""

from __future__ import annotations

import pickle
import re
from pathlib import Path
from typing import Any

import torch

from thgs.errors import InputError

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_BOILERPLATE = ("Weights only load failed", "Check the documentation", "Please file an issue")


def _detail(error: BaseException) -> str:
    """What torch's error says went wrong, without its advice and escape codes."""
    lines = [line.strip() for line in _ANSI.sub("", str(error)).splitlines() if line.strip()]
    kept = []
    for line in lines:
        _, _, after = line.partition("WeightsUnpickler error:")
        if after.strip():
            kept.append(after.strip())
        elif not line.startswith(_BOILERPLATE):
            kept.append(line)
    return "; ".join(kept) or type(error).__name__


def load_tensors(path: Path, what: str = "PyTorch checkpoint") -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU.

    Raises:
        InputError: naming ``path``: it holds Python objects other than tensors and plain
            containers (refused, since unpickling them can run code; torch's advice to load it
            with ``weights_only=False`` is not relayed), or it cannot be read.
    """
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        detail = _detail(error)
        if "global" not in detail.lower():
            raise InputError(path, f"not a readable {what} ({detail})") from error
        raise InputError(
            path,
            f"holds Python objects besides tensors ({detail}); thgs loads only tensors and "
            "plain containers, so that a file cannot run code: save the weights alone "
            "(torch.save(model.state_dict(), …)) from code you trust",
        ) from error
    except Exception as error:  # torch raises RuntimeError, EOFError … on damaged files
        raise InputError(path, f"not a readable {what} ({_detail(error)})") from error
