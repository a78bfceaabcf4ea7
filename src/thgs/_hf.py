"""Loading Hugging Face models from a local folder or the cache, never from the network."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from thgs._open_clip import OPEN_CLIP_CONFIG
from thgs.errors import ThgsError

__all__ = ["is_hub_id", "load_local_model", "quietly"]

Model = TypeVar("Model")

_HUB_ID = re.compile(r"[A-Za-z0-9][\w.-]*/[A-Za-z0-9][\w.-]*")


def quietly(load: Callable[[], Model]) -> Model:
    """Run ``load()`` without transformers' weight-loading progress bar (only the CLI shows
    progress)."""
    try:
        from transformers.utils import logging as transformers_logging
    except ImportError:
        return load()
    enabled = transformers_logging.is_progress_bar_enabled()
    transformers_logging.disable_progress_bar()
    try:
        return load()
    finally:
        if enabled:
            transformers_logging.enable_progress_bar()


def is_hub_id(name: str) -> bool:
    """Whether ``name`` has the shape of a Hugging Face model id (``owner/name``) and is not a
    local path: only such names are worth an ``hf download`` hint."""
    return bool(_HUB_ID.fullmatch(name)) and not Path(name).expanduser().exists()


def load_local_model(
    load: Callable[[str], Model],
    model_id: str,
    model_path: str | os.PathLike[str] | None,
    *,
    what: str,
    hint: str,
) -> tuple[Model, str]:
    """Load a model with ``load(source)`` (which must pass ``local_files_only=True``).

    Args:
        load: reads the model from ``source``, a folder path or a model id.
        model_id: the Hugging Face model id, looked up in the cache without ``model_path``.
        model_path: a local folder in Hugging Face format, instead of the cache.
        what: the model's kind in messages, e.g. "CLIP" or "SAM".
        hint: the command-line flag that passes a folder, e.g. "--sam DIR".

    Returns:
        ``(model, source)``.

    Raises:
        ThgsError: ``model_path`` has no config.json (nor, for CLIP, OpenCLIP's
            open_clip_config.json), or the weights are not found (the message
            names the model, where it was looked for, the flag that passes a folder and, for a
            Hugging Face id, the command that fetches it).
    """
    if model_path is not None and not any(
        (Path(model_path) / name).is_file() for name in ("config.json", OPEN_CLIP_CONFIG)
    ):
        raise ThgsError(f"{model_path}: not a Hugging Face model folder (no config.json)")
    source = str(model_path) if model_path is not None else model_id
    try:
        return quietly(lambda: load(source)), source
    except OSError as error:
        if model_path is not None:
            raise ThgsError(
                f"{what} weights for {model_id!r} not found in {model_path}: the folder must hold "
                f"the whole model in Hugging Face format (config.json, weights; {hint})"
            ) from error
        if not is_hub_id(model_id):
            raise ThgsError(
                f"{what} weights for {model_id!r} not found: it is not a Hugging Face model id, "
                f"so pass the model's local folder ({hint})"
            ) from error
        raise ThgsError(
            f"{what} weights for {model_id!r} not found in the Hugging Face cache. On a machine "
            f"with internet run `hf download {model_id}` (it fills ~/.cache/huggingface, or "
            f"$HF_HOME) and copy that cache here, or pass a local folder with the model in "
            f"Hugging Face format ({hint})"
        ) from error
