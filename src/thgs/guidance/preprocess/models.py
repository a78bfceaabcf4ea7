"""The preprocessing models from what a user names: a local folder or a Hugging Face model id.

One place decides how ``--sam`` / ``--clip`` values are read, for ``thgs preprocess``, ``thgs
suite`` and the workers of a distributed run, so that every path makes the same features.
"""

from __future__ import annotations

from pathlib import Path

import torch

from thgs.errors import InputError
from thgs.guidance.preprocess.clip_features import CLIPImageEncoder
from thgs.guidance.preprocess.sam import PointSegmenter

__all__ = ["load_preprocess_models", "local_model_folder"]


def local_model_folder(value: str) -> Path | None:
    """A model value that names an existing folder is a local model (its path); anything else is
    a model id read from the Hugging Face cache (None)."""
    path = Path(value).expanduser()
    return path if path.is_dir() else None


def load_preprocess_models(
    sam: str,
    clip: str,
    *,
    space: str | None = None,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
) -> tuple[PointSegmenter, CLIPImageEncoder]:
    """SAM (or SAM 2) and CLIP, ready for :func:`thgs.guidance.preprocess.preprocess_images`.

    Args:
        sam: a local folder or a model id (Hugging Face format; never downloaded).
        clip: likewise, for CLIP.
        space: the features' embedding space when ``clip`` is a folder (default: derived from
            the folder, :class:`CLIPImageEncoder`); must be left out for a model id, whose space
            is its id.
        device: the torch device; dtype: the models' precision.

    Raises:
        InputError: ``space`` given with a model id.
        ThgsError: a model cannot be read (not in the cache, not SAM/CLIP).
    """
    clip_path = local_model_folder(clip)
    if clip_path is None and space is not None and space != clip:
        raise InputError("--space", f"names the space of a --clip folder; {clip!r} is a model id")
    clip_space = clip if clip_path is None else space
    segmenter = PointSegmenter(sam, local_model_folder(sam), device=device, dtype=dtype)
    encoder = CLIPImageEncoder(clip_space, clip_path, device=device, dtype=dtype)
    return segmenter, encoder
